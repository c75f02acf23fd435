"""The ERLS damping on the strain rate: the joint damping the global-rate law added, and the filter's figures before
and after; writes ``docs/damping.md``.

    python benchmarks/damping.py [--models NAME,...] [--acceptance BEFORE.json[,...] AFTER.json[,...]]
                                 [--acceptance-labels BEFORE AFTER] [--long BEFORE.json[,...] AFTER.json[,...]]
                                 [--long-labels BEFORE AFTER] [--md docs/damping.md]

Turned deflection: for every model (the gallery and ``benchmarks/models/``), at ``q_ref`` with the first free
elastic mode's shape scaled to a largest nodal translation of 1 mm, every coordinate ``q_j`` turned at 1 rad/s with
every link's deflection held in its frame as far as the joints allow (``T u'`` nearest ``Y q'`` in the damping's own
metric, :meth:`~exuflex.erls.model.ErlsModel.turned_rates`: the turn with the least strain rate; exact where the
coordinate turns the links it moves rigidly together): the damping torque per unit rate ``v^T C v``
of the global-rate law (``diag(0, alpha M_e + beta K_uu)`` on ``u'``, the law before) and of the strain-rate law
(:meth:`~exuflex.erls.model.ErlsModel.damping`), each over the coordinate's rigid inertia ``M_qq[j, j]`` (a decay
rate, 1/s; quadratic in the deflection). ``--acceptance`` / ``--long``: the acceptance JSONs of
``benchmarks/gallery.py --acceptance`` before and after (per model and truth, per quantity the mean over the seeds of
RMS / bound, and the NIS / channels; :func:`held_elastic._acceptance`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import scipy.linalg as sla

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))

GALLERY = ("fivebar", "fourbar", "l_arm", "serial_arm", "single_link", "sixbar", "slider_crank", "three_link_arm")
EXTRA = ("vertical_link", "three_link_reach", "long_two_link")


def _path(name: str) -> Path:
    p = ROOT / "models" / f"{name}.toml"
    return p if p.exists() else ROOT / "benchmarks" / "models" / f"{name}.toml"


def turned_deflection(name: str, amplitude: float = 1e-3) -> dict:
    """The joint damping of a rigid turn of the first mode's deflection under both laws (module docstring)."""
    from exuflex.erls.model import ErlsModel
    from exuflex.mechanism import load_mechanism

    mech = load_mechanism(_path(name))
    m = ErlsModel(mech)
    q = np.asarray(mech.q_ref, float)
    cfg = m.configuration(q)
    nq = m.nq
    K_uu = m.T.T @ cfg.K_N @ m.T
    w2, phi = sla.eigh(K_uu, m.elastic_mass(cfg), subset_by_index=[0, 0])
    d = (m.T @ phi[:, 0]).reshape(-1, 3)
    u = phi[:, 0] * amplitude / np.abs(d[:, :2]).max()
    x = np.concatenate([q, u])
    C_old, C_new = m.damping(cfg), m.damping(cfg, x)
    M_qq = m.mass(cfg)[:nq, :nq]
    Y = m.turned_rates(cfg, x)
    old, new = [], []
    Z_uu = C_old[nq:, nq:]  # T^T (alpha P + beta K_N) T
    for j in range(nq):
        # the elastic rates of the turn with the least strain: T u' nearest Y e_j in the damping's own metric
        ud = np.linalg.solve(Z_uu, m.T.T @ m.damping_products(cfg, Y[:, j]))
        v = np.concatenate([np.eye(nq)[j], ud])
        old.append(max(float(v @ C_old @ v), 0.0) / M_qq[j, j])
        new.append(max(float(v @ C_new @ v), 0.0) / M_qq[j, j])
    return {"model": name, "f1_hz": float(np.sqrt(w2[0]) / (2 * np.pi)), "old": old, "new": new,
            "names": list(mech.coordinate_names)}


def page(models: list, acceptance: list | None, long: list | None, labels: dict, md: str) -> None:
    from held_elastic import _acceptance, comparison_tables

    L = ["# Damping on the strain rate", "",
         ("Written by `python benchmarks/damping.py` (its docstring has the options; the figures below come from "
          "the runs named in each section)."), "",
         ("The model file's `alpha`, `beta` are the Rayleigh damping of the free elastic modes. The ERLS model's "
          "elastic coordinates `u` are global, so their rate `u'` holds the deflection turned with its link "
          "(`d/dt (R e) = R e' + R' e`). A stiffness-proportional damping on `u'` therefore brakes a bent link that "
          "merely turns: a joint damping that material damping (a strain-rate law, invariant under rigid rotation) "
          "and Exudyn's beams (`bendingDamping`, `axialDamping` on the curvature and axial strain rates) do not "
          "have. The ERLS model now damps the strain rate `s = T u' - Y(u) q'` (`Y q'`: every node's displacement "
          "turned at its link's rate) with the dissipation function `D = beta/2 s^T K_N s + alpha/2 min_a |S a + "
          "s|^2_{M_N} = v^T C(x) v / 2`, `C(x) = L^T (alpha P + beta K_N) L`, `L = [-Y, T]`; the generalized "
          "damping force `-C(x) v` acts on the joints too. At rest `L = [0, T]`: the free modes keep the ratios "
          "`alpha/(2 w) + beta w/2`. The reduced model's damping is its projection `J^T C(H p) J`, and the held "
          "step's elastic forms take `A_k - E_k` for `A_k` (`exuflex.erls.model` and "
          "`ReducedModel.elastic_forms` state the equations). `tests/test_damping_strain.py` checks the law against "
          "element-frame rates by differences (polarisation, entry by entry), a rigid turn of a bent link (no "
          "dissipation; the global-rate law's was positive), positive semidefiniteness at random states, the "
          "position Jacobian by differences and the reduced projection; `tests/test_damping.py` the free modes' "
          "ratios."), ""]
    rows = [turned_deflection(n) for n in models]
    L += ["## The joint damping of a turned deflection", "",
          ("`python benchmarks/damping.py`: each model at `q_ref` with its first free elastic mode's shape scaled to "
          "1 mm (largest nodal translation), every coordinate turned at 1 rad/s with the links' deflections held: "
          "the damping torque per unit rate over the coordinate's rigid inertia (1/s, the decay rate it gives the "
          "joint; it grows with the square of the deflection), under the global-rate law (before) and the "
          "strain-rate law (after). Where a coordinate turns links against each other (a relative joint, a closed "
          "loop), a joint node's shared translation cannot turn with both links: the turn with the least strain "
          "rate is used (`T u'` nearest `Y q'` in the damping's own metric), and what the strain-rate law damps there "
          "is that strain."), "",
          "| model | first mode (Hz) | coordinate | global-rate law (1/s) | strain-rate law (1/s) |",
          "|---|---|---|---|---|"]
    for r in rows:
        for j, q in enumerate(r["names"]):
            L.append(f"| {r['model'] if j == 0 else ''} | {r['f1_hz']:.1f} | {q} | {r['old'][j]:.3g} | "
                     f"{r['new'][j]:.3g} |")
    L.append("")
    for title, pair, lab in (("The gallery", acceptance, labels["acceptance"]), ("The long arms", long,
                                                                                 labels["long"])):
        if not pair:
            continue
        before, after = (_acceptance(p) for p in pair)
        models_run = sorted({Path(m).stem for _, m in after})
        L += [f"## {title}: the filter's figures", "",
              (f"`python benchmarks/gallery.py --acceptance --truth-dir DIR --models MODELS --seeds 1-10` "
               f"({', '.join(f'`{m}`' for m in models_run)}); before: {lab[0]}; after: {lab[1]} (the JSONs "
               f"{pair[0]} and {pair[1]}): per quantity the mean over the seeds of RMS / bound, and the NIS / channels. The Exudyn "
               "truths are the same runs before and after (Exudyn's damping is its own); the ERLS and the reduced "
               "truths carry each code's damping and were made by it."), ""]
        L += comparison_tables(before, after, ("before", "after"))
    Path(md).write_text("\n".join(L).rstrip() + "\n")
    print(f"wrote {md}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default=",".join(GALLERY + EXTRA))
    ap.add_argument("--acceptance", nargs=2, metavar=("BEFORE", "AFTER"), default=None)
    ap.add_argument("--long", nargs=2, metavar=("BEFORE", "AFTER"), default=None)
    ap.add_argument("--acceptance-labels", nargs=2, default=("global-rate law", "strain-rate law"))
    ap.add_argument("--long-labels", nargs=2, default=("global-rate law", "strain-rate law"))
    ap.add_argument("--md", default=str(ROOT / "docs" / "damping.md"))
    a = ap.parse_args(argv)
    page(a.models.split(","), a.acceptance, a.long, {"acceptance": a.acceptance_labels, "long": a.long_labels}, a.md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The measurement rows about a held configuration: their error against the re-evaluated rows, first order and
with their exact first-order change with q.

    python benchmarks/measurement_rows.py [--models a,b,...] [--extra benchmarks/models/three_link_reach.toml]
                                          [--directions 6] [--md docs/measurement_rows.md]

For each model (default: the gallery, ``models/*.toml`` with a manoeuvre, and the fresh mechanism
``benchmarks/models/three_link_reach.toml``) the observer's model with default settings holds the undeformed
configuration at ``q*`` (the reduction's reference). At ``q = q* + dl`` for ``|dl|`` = 0.01, 0.02, 0.04 rad (the
measurement radius reaches 0.06 rad) in several random directions it compares, with the rows of ``q``'s own
configuration evaluated anew:

- the elastic rows ``E_i = U_i H_u`` of every channel the observer uses, relative to their size at ``q*``
  (``|E_i(q) - approx| / |E_i(q*)|``, largest over channels and directions): the rows at ``q*`` alone (what the
  rows were before the expansion, off the secant's line) and with ``sum_k dl_k D_k``;
- the rigid part of an undeformed state, in units of the channel's noise: the first-order rows and with the
  second-order term.

And the cost: the expansion's terms (``D_k``, ``G``) against the held configuration's evaluation, CPU time per
configuration, medians of repeats in one process.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXTRA = ROOT / "benchmarks" / "models" / "three_link_reach.toml"
STEPS = (0.01, 0.02, 0.04)

HEAD = """# The measurement rows about a held configuration

Written by `python benchmarks/measurement_rows.py{args}` (do not edit: rerun the script).

The observer's cached step holds the reduced model at a configuration `q0` and takes the measurement rows there
(`exuflex.observer.reduced.ReducedObserverModel.measure`); the filter's states lie up to the measurement radius
(1.5 refresh radii, at most 0.06 rad) from it. Every channel is `y(q, p) = rigid(q) + U(q) H_u(q) p`: the rigid
part a link angle or a point's coordinate, `U` the channel's row on the elastic displacements (a gauge's Hermite
curvature row turned into the global frame by its element's rotation, a point's displacement rows, an encoder's
nodal rotations), `H_u` the basis's elastic-displacement rows (zero in the q-columns).

## The expansion

With `dl = q - q0`, to first order in `dl`

    U(q) H_u(q) = U H_u + sum_k dl_k D_k,   D_k = dU/dq_k H_u + U dH_u/dq_k

at `q0`. The u rows depend on q only through the angle `theta_l` of their link: element rotations turn as
`dR_e/dtheta = R_e W` (`W` the 90-degree generator on each node's translations), so a gauge row `c R_e^T` turns at
`(W c) R_e^T`, a point's rows `r N R^T` at `r (w N - N W) R^T`, and `dU/dq_k = (dU/dtheta_l) dtheta_l/dq_k`
(`exuflex.observer.rows.ChannelRows.rates`); an encoder's rows (nodal rotations) do not turn. `dH_u/dq_k` is the
basis derivative (`CraigBampton.basis_derivative`: the Guyan shapes' change with the element stiffness matrices'
rotation and the interior modes turning with their nodes). The rigid part gains `1/2 dl^T G dl` with
`G = d^2 rigid/dq^2`, from the pose's second derivatives (`Kinematics.coordinate_rates` at the links' origins and
at the sensed points). The measurement is then

    y = c0 + (Hm + sum_k dl_k D_k) x + 1/2 dl^T G dl

(`c0 + Hm x` the rows at `q0`, rigid parts to first order), and its exact Jacobian in `x`

    H = Hm + sum_k dl_k D_k,   q-column j  +=  D_j x + G dl .

Its error is `O(dl^2 |p_e|) + O(dl^3)` in `y` (the rows at `q0` alone: `O(dl |p_e|) + O(dl^2)`), `O(dl^2)` in
`H`'s elastic columns and `O(dl |p_e|) + O(dl^2)` in its q-columns (the change of `D_k` with q is left out);
`tests/test_measurement_rows.py` checks y and H entry by entry against the re-evaluated measurement (halving `dl`
quarters every entry's error) on the three-link arm, the six-bar and the slider-crank. `D_k` and `G` are computed
once per held configuration and kept with it; a measurement adds `m r nq` products.

The secant the rows used before (the change of the rows from the previous held configuration, along the one
direction joining the two) gave the same first order along that line only; a three-joint arm moves off it, and
its hand gauge's row changes with the elbow angle at about the size of the row itself per radian.

## The rows' error at the distance from the held configuration

Per model, at `|dl|` = 0.01 / 0.02 / 0.04 rad from `q*` in {n_dir} random directions: the elastic rows' largest
relative error over the observer's channels (`|E_i(q) - approx| / |E_i(q*)|`, over the channels with an elastic
row), first order (the rows at `q*`) and with the expansion; the elastic part's error in units of the channel's
noise for an elastic state whose largest reading is a tenth of its channel's full scale (random, one per
direction: the rows' size says little alone, a gauge reads its state with a signal-to-noise ratio of 100 or more);
the rigid part's largest error on an undeformed state in units of the channel's noise at 0.04 rad; the expansion's
cost per held configuration against the held evaluation's (CPU, median of {n_rep}).

| model | channels | rows at q*, relative | expansion, relative | rows at q*, elastic / noise | expansion, elastic / noise | rigid / noise, first order | with G | cost / held evaluation |
|---|---|---|---|---|---|---|---|---|
"""


def gallery() -> list[Path]:
    return sorted(p for p in (ROOT / "models").glob("*.toml") if "manoeuvre" in tomllib.loads(p.read_text()))


def _cpu(f, n: int) -> float:
    ts = []
    for _ in range(n):
        t = time.process_time()
        f()
        ts.append(time.process_time() - t)
    return float(np.median(ts))


def measure(path: Path, n_dir: int, n_rep: int) -> dict:
    """The figures of one model (see the module docstring)."""
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.session import ObserverConfig, make_observer

    mech = load_mechanism(path)
    obs = make_observer(mech, ObserverConfig())
    m, channels = obs.model, tuple(obs.channels)
    nq, r = m.nq, m.r
    noise = np.array([m.sensors[c].noise_std for c in channels])
    q0 = np.asarray(m.rm.cb.q_star, float)
    iv = m._configuration(m.initial_state(q0), held=True)
    c0, Hm, D, G = m._expansion(iv, channels)
    E0 = np.linalg.norm(Hm[:, nq:r], axis=1)
    el = E0 > 1e-12 * E0.max()  # the channels with an elastic row (not a clamped joint's encoder)
    rng = np.random.default_rng(1)
    dirs = rng.standard_normal((n_dir, nq))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    first, expanded = np.zeros(len(STEPS)), np.zeros(len(STEPS))
    y_first, y_expanded = np.zeros(len(STEPS)), np.zeros(len(STEPS))
    rigid1 = rigid2 = 0.0
    scale = np.array([m.sensors[c].full_scale or np.inf for c in channels])
    for u in dirs:
        pe = rng.standard_normal(r - nq)  # an elastic state reading at most a tenth of a channel's full scale
        pe *= 0.1 / np.max(np.abs(Hm[:, nq:r] @ pe) / scale)
        for s, h in enumerate(STEPS):
            dl = h * u
            x = m.initial_state(q0 + dl)
            c, H = m._affine(m._configuration(x), channels)
            E = H[:, nq:r]
            approx = Hm[:, nq:r] + np.tensordot(dl, D[:, :, nq:], axes=1)
            first[s] = max(first[s], float(np.max(np.linalg.norm(E - Hm[:, nq:r], axis=1)[el] / E0[el])))
            expanded[s] = max(expanded[s], float(np.max(np.linalg.norm(E - approx, axis=1)[el] / E0[el])))
            y_first[s] = max(y_first[s], float(np.max(np.abs((E - Hm[:, nq:r]) @ pe) / noise)))
            y_expanded[s] = max(y_expanded[s], float(np.max(np.abs((E - approx) @ pe) / noise)))
            if h == STEPS[-1]:
                y = c + H @ x
                y1 = c0 + Hm @ x
                y2 = y1 + 0.5 * np.einsum("ijk,j,k->i", G, dl, dl)
                rigid1 = max(rigid1, float(np.max(np.abs(y1 - y) / noise)))
                rigid2 = max(rigid2, float(np.max(np.abs(y2 - y) / noise)))
    z = m.initial_state(q0)
    t_held = _cpu(lambda: m._configuration(z, held=True), n_rep)
    t_rows = _cpu(lambda: m._expansion(iv, channels), n_rep)
    t_affine = _cpu(lambda: m._affine(iv, channels), n_rep)
    return {"model": mech.name, "channels": ", ".join(channels), "first": first.tolist(),
            "expanded": expanded.tolist(), "y_first": y_first.tolist(), "y_expanded": y_expanded.tolist(), "rigid_first": rigid1, "rigid_second": rigid2,
            "cost": (t_rows - t_affine) / t_held}


def _row(f: dict) -> str:
    def trio(v):
        return " / ".join(f"{a:.1e}" for a in v)

    def trio2(v):
        return " / ".join(f"{a:.2g}" for a in v)

    return (f"| {f['model']} | {f['channels']} | {trio(f['first'])} | {trio(f['expanded'])} | "
            f"{trio2(f['y_first'])} | {trio2(f['y_expanded'])} | "
            f"{f['rigid_first']:.2g} | {f['rigid_second']:.2g} | {f['cost']:.2f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default=None, help="comma-separated model files (default: the gallery)")
    ap.add_argument("--extra", default=str(EXTRA.relative_to(ROOT)), help="a further model file ('' for none)")
    ap.add_argument("--directions", type=int, default=6, help="random directions of dl per distance")
    ap.add_argument("--repeats", type=int, default=21, help="repeats of the cost's timing")
    ap.add_argument("--md", default=str(ROOT / "docs" / "measurement_rows.md"), help="markdown page ('' for none)")
    a = ap.parse_args(argv)
    paths = [Path(p) for p in a.models.split(",")] if a.models else gallery()
    if a.extra:
        paths.append(ROOT / a.extra if not Path(a.extra).is_absolute() else Path(a.extra))
    rows = []
    for p in paths:
        f = measure(p, a.directions, a.repeats)
        rows.append(_row(f))
        print(rows[-1], flush=True)
    args = "".join(f" --{k} {v}" for k, v in (("models", a.models), ("directions", a.directions if a.directions != 6
                                                                         else None)) if v)
    text = HEAD.format(args=args, n_dir=a.directions, n_rep=a.repeats) + "\n".join(rows) + "\n"
    text += (f"\nVersions: numpy {np.__version__}, python {platform.python_version()}.\n")
    if a.md:
        Path(a.md).write_text(text)
        print(f"wrote {a.md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The observer against the Exudyn (ANCF) truth on long, slender arms: where the two truths part (docs/long_arms.md).

Three measurements, each a subcommand; ``page`` writes the page from their JSONs.

``modes``: every elastic mode below ``--fmax`` at ``q_ref`` (motors free): the frequency and damping ratio of the
full-order ERLS model (:func:`exuflex.erls.modal.damping_ratios`), of the observer's reduced model (its ``M_r``,
``K_r``, ``C_r`` at rest) and of the Exudyn truth's own linearised system on the truth's mesh
(:func:`exuflex.groundtruth.modal_damping`), beside the model file's Rayleigh ratio ``alpha / (2 w) + beta w / 2``.

``pairs``: the ERLS truth and the Exudyn truth under the same drive (the manoeuvre's rigid computed torque) and
their difference after the start-up (``t >= 0.3 s``) per gauge and joint rate, as a fraction of the Exudyn
signal's ringing (its part above 10 Hz), for controlled variants: as the acceptance runs them; undamped (``alpha =
beta = 0`` in both); the torques scaled by 0.1 and 0.01 (a discrepancy linear in the motion keeps its fraction,
one of second order falls with the scale); the Exudyn mesh refined to 10 elements per link; the ERLS truth
without the geometric stiffness of the motion's loads; the ERLS truth with the elements' axial forces taken from
their own axial strain (``N_e = EA/L (e_2 - e_1)``: every load the link carries, the elastic motion's inertia
included, instead of the rigid motion's loads; an experiment defined here, not a model of the package).

``truths``: ERLS truth runs of such a variant (``--variant nokg`` or ``strain``) in a gallery truth folder, for
``benchmarks/gallery.py --acceptance --engine erls --truth-dir DIR`` (which reuses runs already there).

Usage:
    python benchmarks/long_arms.py modes --models M1,M2 --json OUT
    python benchmarks/long_arms.py pairs --models M1,M2 --json OUT
    python benchmarks/long_arms.py truths --variant strain --models M1,M2 --truth-dir DIR
    python benchmarks/long_arms.py page --modes JSON --pairs JSON --acceptance LABEL=ENGINE:JSON ... --md docs/long_arms.md
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

START = 0.3  # s: the acceptance's start-up, left out of the differences
RINGING_HZ = 10.0  # the Exudyn signal's part above this is its ringing (the yardstick of the differences)


def model_path(name: str) -> Path:
    p = Path(name)
    if p.suffix == ".toml":
        return p
    return ROOT / "models" / f"{name}.toml"


# ---------------------------------------------------------------------------------------------- ERLS variants
def _strain_model():
    """ErlsModel whose geometric stiffness takes each element's axial force from its own axial strain."""
    from exuflex.erls.model import ErlsModel

    class StrainAxial(ErlsModel):
        def element_axial(self, cfg, u):
            de = (self.T @ u)[self.el_dofs]
            R = cfg.R
            return self.el_axial * (R[:, 0, 0] * (de[:, 3] - de[:, 0]) + R[:, 1, 0] * (de[:, 4] - de[:, 1]))

        def net_forces(self, cfg, x, v, tau, qdd=None):
            nq = self.nq
            rhs = self.generalized_forces(cfg, tau) - self.velocity_forces(cfg, x, v)
            rhs[nq:] -= self.T.T @ (cfg.K_N @ (self.T @ x[nq:]))
            rhs[nq:] += self.geometric_forces(cfg, self.element_axial(cfg, x[nq:]), x[nq:])
            if self.alpha or self.beta:
                rhs -= self.damping_forces(cfg, x, v)
            return rhs

    return StrainAxial


def _nokg_model():
    from exuflex.erls.model import ErlsModel

    class NoKG(ErlsModel):
        def __init__(self, mech, form="lagrange", geometric=True):
            super().__init__(mech, form=form, geometric=False)

    return NoKG


VARIANTS = {"nokg": _nokg_model, "strain": _strain_model}


@contextlib.contextmanager
def erls_variant(name: str | None):
    """The ERLS truth engine builds the variant's model while inside (it looks the class up at call time)."""
    import exuflex.erls.model as em

    if name is None:
        yield
        return
    keep = em.ErlsModel
    em.ErlsModel = VARIANTS[name]()
    try:
        yield
    finally:
        em.ErlsModel = keep


# ---------------------------------------------------------------------------------------------- modes
def _reduced_ratios(mech, q):
    from exuflex.erls.model import ErlsModel
    from exuflex.erls.modal import _oscillating
    from exuflex.observer.session import ObserverConfig
    from exuflex.reduction import CraigBampton, ReducedModel

    cfg = ObserverConfig.for_model(mech)
    cb = CraigBampton(ErlsModel(mech), masters=cfg.masters, q_star=cfg.q_star, n_interior=cfg.n_interior,
                      ranking=cfg.ranking, channels=cfg.channels)
    rm = ReducedModel(cb)
    p = rm.rest_state(q)[: cb.r]
    mats = rm.matrices(p, np.zeros(cb.r))
    r = cb.r
    MK = np.linalg.solve(mats.Mr, np.hstack([mats.Kr, mats.Cr]))
    A = np.block([[np.zeros((r, r)), np.eye(r)], [-MK[:, :r], -MK[:, r:]]])
    return _oscillating(np.linalg.eigvals(A))


def modes(models, fmax: float) -> list[dict]:
    from exuflex.erls.modal import aligned_ratios, damping_ratios, modal_analysis
    from exuflex.erls.model import ErlsModel
    from exuflex.groundtruth import modal_damping
    from exuflex.mechanism import load_mechanism
    from exuflex.truth.engines import exudyn_mesh

    out = []
    for name in models:
        mech = load_mechanism(model_path(name))
        q = np.asarray(mech.q_ref, float)
        model = ErlsModel(mech)
        f = modal_analysis(model, q).below(fmax)
        z_full = aligned_ratios(f, *damping_ratios(model, q))
        fr, zr = _reduced_ratios(mech, q)
        z_red = aligned_ratios(f, fr, zr)
        fe, ze = modal_damping(mech, q, elements_per_link=exudyn_mesh(mech), fmax=fmax * 1.05)
        w = 2 * np.pi * f
        rows = []
        for i, fi in enumerate(f):
            j = int(np.argmin(np.abs(fe - fi))) if len(fe) else None
            k = int(np.argmin(np.abs(fr - fi))) if len(fr) else None
            rows.append({"f_erls": float(fi), "f_reduced": float(fr[k]) if k is not None else None,
                         "f_exudyn": float(fe[j]) if j is not None else None,
                         "zeta_rayleigh": float(mech.damping.alpha / (2 * w[i]) + mech.damping.beta * w[i] / 2),
                         "zeta_erls": float(z_full[i]), "zeta_reduced": float(z_red[i]),
                         "zeta_exudyn": float(ze[j]) if j is not None else None})
        out.append({"model": Path(name).stem, "q": q.tolist(), "exudyn_elements_per_link": exudyn_mesh(mech),
                    "modes": rows})
        print(f"{Path(name).stem}: {len(rows)} modes", flush=True)
    return out


# ---------------------------------------------------------------------------------------------- pairs
PAIR_VARIANTS = (
    ("as-run", {}),
    ("undamped", {"undamped": True}),
    ("torques-x0.1", {"scale": 0.1}),
    ("torques-x0.01", {"scale": 0.01}),
    ("exudyn-10-per-link", {"exudyn_mesh": 10}),
    ("erls-no-KG", {"erls": "nokg"}),
    ("erls-KG-of-strain", {"erls": "strain"}),
)


def _signals(rec) -> dict:
    out = {}
    for arr in (rec.truth, rec.clean):
        for i, c in enumerate(arr.names):
            out[c] = np.asarray(arr.data)[:, i]
    return out, np.asarray(rec.truth.t)


def _ringing(y: np.ndarray, fs: float) -> np.ndarray:
    from scipy.signal import butter, sosfiltfilt

    return sosfiltfilt(butter(4, RINGING_HZ, btype="high", fs=fs, output="sos"), y)


def pairs(models, variants=PAIR_VARIANTS) -> list[dict]:
    from exuflex.mechanism import load_mechanism
    from exuflex.truth.engines import exudyn_mesh, plan_drive, simulate

    out = []
    for name in models:
        base = load_mechanism(model_path(name))
        gauges = [s.name for s in base.sensors if s.kind == "curvature"]
        rates = [f"d{c}" for c in base.coordinate_names]
        for label, v in variants:
            mech = base
            if v.get("undamped"):
                mech = replace(base, damping=replace(base.damping, alpha=0.0, beta=0.0))
            drive = plan_drive(mech, mech.manoeuvre.duration, 1e-4)
            drive.tau = drive.tau * v.get("scale", 1.0)
            t0 = time.perf_counter()
            with erls_variant(v.get("erls")):
                a, t = _signals(simulate(mech, drive, "erls"))
            b, _ = _signals(simulate(mech, drive, "exudyn", elements_per_link=v.get("exudyn_mesh",
                                                                                    exudyn_mesh(mech))))
            fs = 1.0 / (t[1] - t[0])
            sel = t >= START
            fig = {}
            for c in gauges + rates:
                ring = _ringing(b[c], fs)[sel]
                fig[c] = float(np.sqrt(np.mean((a[c] - b[c])[sel] ** 2)) / np.sqrt(np.mean(ring**2)))
            out.append({"model": Path(name).stem, "variant": label, "difference_over_ringing": fig,
                        "seconds": time.perf_counter() - t0})
            print(f"{Path(name).stem} {label}: " + ", ".join(f"{k} {x:.3f}" for k, x in fig.items()), flush=True)
    return out


# ---------------------------------------------------------------------------------------------- truths
def truths(models, variant: str, truth_dir: Path, seeds) -> None:
    from exuflex.truth import simulate_runs

    for name in models:
        base = Path(truth_dir) / "erls" / Path(name).stem
        base.mkdir(parents=True, exist_ok=True)
        missing = {s: base / f"s{s}" for s in seeds if not (base / f"s{s}" / "meta.json").exists()}
        if missing:
            with erls_variant(variant):
                simulate_runs(model_path(name), missing, engine="erls")
        print(f"{Path(name).stem}: {len(missing)} runs written to {base}", flush=True)


# ---------------------------------------------------------------------------------------------- page
def _acceptance_means(path: str, engine: str) -> dict:
    d = json.loads(Path(path).read_text())
    by = {}
    for r in d["runs"]:
        if r["engine"] != engine:
            continue
        m = by.setdefault(r["model"], {"ratios": {}, "nis": []})
        for k, x in r["ratio_to_bound"].items():
            m["ratios"].setdefault(k, []).append(x)
        m["nis"].append(r["nis_mean"] / r["nis_expected"])
    return {mod: {**{k: float(np.mean(v)) for k, v in m["ratios"].items()}, "NIS / channels": float(np.mean(m["nis"])),
                  "N": len(m["nis"])} for mod, m in by.items()}


def page(modes_json: str | None, pairs_json: str | None, acceptance: list[str], commands: list[str]) -> str:
    lines = ["# Long, slender arms: the ERLS and Exudyn truths", "",
             "Written by `python benchmarks/long_arms.py page` (its docstring has the subcommands; each section "
             "names the command that measured it).",
             "", *[x for para in FINDING.split("\n\n") for x in (para, "")]]
    if modes_json:
        lines += ["## The modes at rest", "", f"`{commands[0]}`" if commands else "", "",
                  "Every elastic mode at `q_ref` (motors free): frequency (Hz) of the full-order ERLS model, the "
                  "observer's reduced model and the Exudyn truth's own linearised system (on the truth's mesh), and "
                  "the damping ratio (%) the model file states (Rayleigh), and each model's.", ""]
        for m in json.loads(Path(modes_json).read_text()):
            lines += [f"### {m['model']} (Exudyn: {m['exudyn_elements_per_link']} elements per link)", "",
                      "| mode | f ERLS | f reduced | f Exudyn | zeta stated | zeta ERLS | zeta reduced | zeta Exudyn |",
                      "|---|---|---|---|---|---|---|---|"]
            for i, r in enumerate(m["modes"], 1):
                def pct(x):
                    return "-" if x is None or not np.isfinite(x) else f"{100 * x:.3f}"

                def hz(x):
                    return "-" if x is None else f"{x:.2f}"
                lines.append(f"| {i} | {hz(r['f_erls'])} | {hz(r['f_reduced'])} | {hz(r['f_exudyn'])} | "
                             f"{pct(r['zeta_rayleigh'])} | {pct(r['zeta_erls'])} | {pct(r['zeta_reduced'])} | "
                             f"{pct(r['zeta_exudyn'])} |")
            lines.append("")
    if pairs_json:
        rows = json.loads(Path(pairs_json).read_text())
        lines += ["## The two truths under the same drive", "", f"`{commands[1]}`" if len(commands) > 1 else "", "",
                  PAIRS_TEXT, ""]
        for model in dict.fromkeys(r["model"] for r in rows):
            rs = [r for r in rows if r["model"] == model]
            chans = list(rs[0]["difference_over_ringing"])
            lines += [f"### {model}", "", "| variant | " + " | ".join(chans) + " |",
                      "|---|" + "---|" * len(chans)]
            for r in rs:
                lines.append(f"| {r['variant']} | " + " | ".join(f"{r['difference_over_ringing'][c]:.3f}"
                                                              for c in chans) + " |")
            lines.append("")
    if acceptance:
        lines += ["## The filter's figures", "", ACCEPTANCE_TEXT, ""]
        tables = []
        for spec in acceptance:
            label, rest = spec.split("=", 1)
            engine, path = rest.split(":", 1)
            tables.append((label, _acceptance_means(path, engine)))
        models = list(dict.fromkeys(m for _, t in tables for m in t))
        for model in models:
            qs = list(dict.fromkeys(k for _, t in tables if model in t for k in t[model] if k != "N"))
            lines += [f"### {model}", "", "| truth | N | " + " | ".join(qs) + " |", "|---|---|" + "---|" * len(qs)]
            for label, t in tables:
                if model in t:
                    r = t[model]
                    lines.append(f"| {label} | {r['N']} | " + " | ".join(
                        f"{r[q]:.2f}" if q in r else "-" for q in qs) + " |")
            lines.append("")
    return "\n".join(lines) + "\n"


FINDING = (
    "What the tables say. At rest the Exudyn truth and the ERLS truth are the same linear system: every mode below "
    "the band has the same frequency and the same damping ratio, the model file's Rayleigh ratio, in the full-order "
    "ERLS model, in the observer's reduced model and in Exudyn's own linearised system (the first table). Under the "
    "manoeuvre the two truths part (the second table) by a part of second order in the motion (it falls with the "
    "torques faster than the ringing does), a coupling of the links' motion and their bending that the ERLS "
    "formulation carries to first order only.\n\n"
    "Every link's ERLS frame is its own tangent at its coordinate's joint, for a relative coordinate too "
    "(`exuflex/mechanism/dofs.py` fixes that node's elastic rotation whether the coordinate is absolute or relative). "
    "With the frame of a relative coordinate's link as the other link's rigid frame turned by q (the two nodes' "
    "elastic rotations at the joint tied, so that q was the relative encoder's reading) the proximal link's elastic "
    "rotation at the joint turned the whole distal link, payload included, as part of the distal link's elastic "
    "field, which the linear elastic field carries to first order only: on the long relative arms that was the "
    "dominant part of the truths' difference, and the observer failed on the Exudyn truth (long_two_link q2 2.53x the "
    "bound, three_link_reach q1 2.22x, over 10 seeds), while their absolute twins (`long_two_link_abs`, "
    "`three_link_reach_abs`: the same arms declared with absolute coordinates) passed. A relative and an absolute "
    "declaration of an arm are now one model in other coordinates (`tests/test_relative_frames.py`: the same elastic "
    "dofs and clamped modes; on a stiff arm the same estimates, within the filters' parametrisation of the prior and "
    "of the held matrices' refresh radius), without the user changing the model file.\n\n"
    "What q is. For a relative coordinate the model's q is the difference of the two links' ERLS frames; the relative "
    "encoder reads q + G u, G u the difference of the two links' elastic rotations at the joint "
    "(`ErlsModel.coordinate_reading_rows`: minus the other link's, the coordinate link's own being zero). The truths "
    "(ERLS and Exudyn alike: the links' slopes at the joint, `exuflex.sensors.true_states`), the logs (the encoder's "
    "channel) and the observer's estimates report, and the acceptance scores, the reading: `Observer.physical` adds "
    "R(q) p = G H_u(q) p to the state's q and its rate to q', and takes the tip's elastic displacement from the rigid "
    "tip at the reading (to second order, `ReducedObserverModel._tip_from_reading`); the bound and the estimates' "
    "standard deviations go through the same rows (`exuflex.scoring.physical.physical_covariance`). `truth.csv`'s and "
    "`estimates.csv`'s q columns keep their meaning, the encoder's reading (`docs/run_format.md`). Motors locked "
    "(`exuflex modes --locked`) holds the readings, as Exudyn's locked system does. The drive keeps its meaning, a "
    "motor's torque between two links: it acts on the two nodes at the joint, and its reaction on the proximal link "
    "now loads that link's elastic rotation there, which the reduction's static corrections carry "
    "(`exuflex.reduction.static`: each motor's own elastic load, scaled by its largest planned torque; without it the "
    "filter requirement's q1 on `benchmarks/models/steel_arm.toml` was 0.119 of the bound's variance, over its 0.1, "
    "with it 8e-7). The reduction's truncation and filter requirements stay on the model's own coordinates: the "
    "reading is a channel, which the truncation requirement covers (with the readings as the filter requirement's "
    "quantities the automatic count fell from 9 to 7 interior modes on long_two_link and its NIS per channel rose "
    "to 1.07 on the ERLS truth, 3 seeds; with the frames' q, 1.00).\n\n"
    "What remains. "
    "Over 10 seeds every quantity's mean is within its limit on both truths (long_two_link: q2 1.09 on the ERLS "
    "truth, 1.27 on the Exudyn truth; three_link_reach: q3 1.17 and dq2 1.46, the NIS per channel 1.00-1.05), but not "
    "every run: the relative readings' ratios scatter widely (90th percentiles 1.38-1.62), and 25 of the 40 runs pass "
    "(long_two_link 3 of 10 on the ERLS truth, its worst q1 1.48, 8 of 10 on the Exudyn truth; three_link_reach 7 and "
    "7). Three_link_reach's Exudyn dq2 (1.46) and dq3 (1.35) are the truths' difference, not the filter (1.00 and "
    "1.03 on the ERLS truth). The consistent truth (the observer's own reduced model generating the data) showed the "
    "relative readings above 1 with the earlier frames (long_two_link q2 1.24, three_link_reach q2 1.47, 10 seeds) and "
    "not the absolute twins' angles; it was not rerun here. The relative "
    "arm written fresh for this page (`benchmarks/models/folding_arm.toml`: a stiff steel upper arm, a long "
    "aluminium forearm, a heavy elbow motor and payload, the elbow folding while the shoulder turns back, tip sensors "
    "so that the tip is scored) passes on both truths, as serial_arm and three_link_arm do. The closed chains "
    "(fourbar, fivebar, sixbar) and l_arm declare absolute coordinates only: their elastic dofs and rows are "
    "unchanged (`tests/test_relative_frames.py`) and so are their reduced models (no motor of theirs loads an "
    "elastic coordinate but the sixbar's T3, whose interior count the file sets), so their figures are those of "
    "docs/acceptance.md."
    "\n\n"
    "The Exudyn truth is converged in mesh, step and Newton tolerance, damped as the model file states, and right to "
    "differ.")

PAIRS_TEXT = (
    "Each variant runs both truths under one drive (the ERLS truth on the model file's mesh, the Exudyn truth on "
    "its default mesh unless the variant refines it); the figure is the RMS of the ERLS truth minus the Exudyn truth "
    "after the start-up (t >= 0.3 s), over the RMS of the Exudyn signal's ringing (its part above 10 Hz): 0.1 means "
    "the two truths' ringing differs by a tenth of its size.")

ACCEPTANCE_TEXT = (
    "`python benchmarks/gallery.py --acceptance --truth-dir DIR --models MODELS --seeds 1-10` (the variant ERLS "
    "truths written first by `python benchmarks/long_arms.py truths --variant V --models MODELS --truth-dir DIR`; "
    "the gallery reuses runs already in DIR): per quantity the mean over the seeds of RMS error / bound, and the "
    "NIS / channels, of the observer with default settings on each truth.")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for c in ("modes", "pairs", "truths"):
        p = sub.add_parser(c)
        p.add_argument("--models", required=True, help="comma-separated gallery names or model files")
        if c == "modes":
            p.add_argument("--fmax", type=float, default=180.0)
        if c in ("modes", "pairs"):
            p.add_argument("--json", required=True)
        if c == "pairs":
            p.add_argument("--variants", default="", help="comma-separated keys of the variants (default all): "
                           + ", ".join(k for k, _ in PAIR_VARIANTS))
        if c == "truths":
            p.add_argument("--variant", choices=sorted(VARIANTS), required=True)
            p.add_argument("--truth-dir", required=True)
            p.add_argument("--seeds", default="1-10")
    p = sub.add_parser("page")
    p.add_argument("--modes")
    p.add_argument("--pairs")
    p.add_argument("--acceptance", action="append", default=[], help="LABEL=ENGINE:JSON of a gallery acceptance run")
    p.add_argument("--command", action="append", default=[], help="the commands that measured --modes, --pairs")
    p.add_argument("--md", default="")
    a = ap.parse_args(argv)
    if a.cmd == "page":
        from _pages import publish

        publish(page(a.modes, a.pairs, a.acceptance, a.command), a.md)
        return 0
    models = [m for m in a.models.split(",") if m]
    if a.cmd == "modes":
        Path(a.json).write_text(json.dumps(modes(models, a.fmax), indent=1))
    elif a.cmd == "pairs":
        keys = [k for k in a.variants.split(",") if k]
        chosen = tuple(v for v in PAIR_VARIANTS if not keys or v[0] in keys)
        Path(a.json).write_text(json.dumps(pairs(models, chosen), indent=1))
    else:
        lo, _, hi = a.seeds.partition("-")
        seeds = range(int(lo), int(hi or lo) + 1)
        truths(models, a.variant, Path(a.truth_dir), seeds)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

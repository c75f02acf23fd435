"""The flexible slider-crank (``models/slider_crank.toml``): the issue's three acceptance figures, written to
``docs/slider_crank.md``.

1. Modes: the converged ERLS model (every element split in 4) against Exudyn (ANCF, 8 elements per link), motors
   free, every mode below 1 kHz at four crank angles.
2. The 1 s manoeuvre (one crank turn): both engines under the same rigid computed-torque table (h = 0.1 ms; the
   ERLS engine implicit generalized-alpha on the file's mesh, Exudyn ANCF with 4 elements per link); the crank
   angle and the rod's midspan deflection transverse to the rod (the tip's elastic displacement projected on the
   rod's normal at the ERLS rod angle), normalised RMS of the difference.
3. The observer: ``exuflex simulate`` (Exudyn truth, seed 1) then ``exuflex observe --bound --json`` on its run:
   RMS estimation error over the filter's own bound per true state.

Usage: python benchmarks/slider_crank.py [--out docs/slider_crank.md] [--no-observer]
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _pages import publish  # (a script: its folder is on the path)

from exuflex.erls.kinematics import Kinematics
from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import ErlsModel
from exuflex.groundtruth import exudyn_frequencies
from exuflex.groundtruth.simulate import simulate_truth
from exuflex.mechanism import load_mechanism, refine_mechanism
from exuflex.sensors import monotonic_record, true_states, truth_names
from exuflex.truth import erls_truth, manoeuvre_table

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "slider_crank.toml"
ANGLES = (math.pi / 2, 0.3, 2.5, 4.0)
BAND = 1000.0
H = 1e-4


def modes_table(mech) -> tuple[list[str], float]:
    fine = ErlsModel(refine_mechanism(mech, 4))
    lines = ["| crank angle (rad) | mode | ERLS converged (Hz) | Exudyn (Hz) | deviation (%) |", "|---|---|---|---|---|"]
    worst = 0.0
    for q in ANGLES:
        fe = modal_analysis(fine, [q]).below(BAND)
        fx = exudyn_frequencies(mech, [q], elements_per_link=8)[: len(fe)]
        for i, (a, b) in enumerate(zip(fe, fx, strict=True)):
            d = 100 * (b / a - 1)
            worst = max(worst, abs(d))
            lines.append(f"| {q:.4f} | {i + 1} | {a:.3f} | {b:.3f} | {d:+.4f} |")
    return lines, worst


def transverse(mech, sig) -> np.ndarray:
    """The tip's elastic displacement projected on the rod's normal at the ERLS rod angle."""
    kin = Kinematics(mech)
    ex, ey = truth_names(mech)[2 : 2 + 2]
    rod = [lk.name for lk in mech.links].index("rod")
    out = np.empty(len(sig.t))
    z = None
    for k in range(len(sig.t)):
        pose = kin.pose([sig["q1"][k]], z)
        z = pose.z
        th = pose.z[3 * rod + 2]
        out[k] = -math.sin(th) * sig[ex][k] + math.cos(th) * sig[ey][k]
    return out


def manoeuvre_comparison(mech) -> dict:
    duration = mech.manoeuvre.duration
    t, tau, q0, qd0 = manoeuvre_table(mech, duration, H)
    out_dt = 1.0 / mech.sample_rate_hz
    c0 = time.perf_counter()
    exu = true_states(mech, monotonic_record(simulate_truth(mech, t, tau, duration, h=H, output_dt=out_dt, q0=q0)))
    c1 = time.perf_counter()
    erl = true_states(mech, monotonic_record(erls_truth(mech, t, tau, duration, H, out_dt, q0, qd0, None)))
    c2 = time.perf_counter()
    a, b = transverse(mech, exu), transverse(mech, erl)
    return {
        "q1_max_abs_rad": float(np.max(np.abs(exu["q1"] - erl["q1"]))),
        "midspan_transverse_nrms": float(np.sqrt(np.mean((a - b) ** 2) / np.mean(b**2))),
        "midspan_transverse_rms_erls_m": float(np.sqrt(np.mean(b**2))),
        "midspan_transverse_max_erls_m": float(np.max(np.abs(b))),
        "exudyn_s": c1 - c0,
        "erls_s": c2 - c1,
    }


def observer_figures() -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        subprocess.run([sys.executable, "-m", "exuflex", "simulate", str(MODEL), "--out", str(run), "--seed", "1",
                        "--no-progress"], check=True, capture_output=True)
        res = subprocess.run([sys.executable, "-m", "exuflex", "observe", str(MODEL), str(run), "--bound", "--json"],
                             check=True, capture_output=True, text=True)
    return json.loads(res.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "slider_crank.md"))
    ap.add_argument("--no-observer", action="store_true")
    args = ap.parse_args()
    mech = load_mechanism(MODEL)
    lines, worst = modes_table(mech)
    cmp = manoeuvre_comparison(mech)
    doc = [
        "# The flexible slider-crank: ERLS against Exudyn, and the observer",
        "",
        "Written by `python benchmarks/slider_crank.py` (model `models/slider_crank.toml`).",
        "",
        f"## Modes (motors free, below {BAND:g} Hz)",
        "",
        *lines,
        "",
        f"Worst deviation: {worst:.4f} %.",
        "",
        "## The 1 s manoeuvre (one crank turn, trapezoid law)",
        "",
        "Both engines under the same rigid computed-torque table (h = 0.1 ms); ERLS: implicit generalized-alpha on "
        "the file's mesh; Exudyn: ANCF, 4 elements per link.",
        "",
        f"- crank angle: max |Exudyn - ERLS| = {cmp['q1_max_abs_rad']:.3e} rad",
        f"- rod midspan deflection transverse to the rod: NRMS of the difference = "
        f"{100 * cmp['midspan_transverse_nrms']:.2f} % (ERLS RMS {1e6 * cmp['midspan_transverse_rms_erls_m']:.2f} um,"
        f" max {1e6 * cmp['midspan_transverse_max_erls_m']:.2f} um)",
        "",
    ]
    if not args.no_observer:
        obs = observer_figures()
        doc += [
            "## Observer (`exuflex simulate` Exudyn truth, seed 1; `exuflex observe --bound`)",
            "",
            f"Channels {', '.join(obs['channels'])}; reduced model {obs['reduced_ndof']} dofs; mean NIS "
            f"{obs['nis_mean']:.2f} (expected {obs['nis_expected']:.2f}); diverged: {obs['diverged']}; metrics from "
            f"{obs['metrics_from_s']:g} s.",
            "",
            "| state | RMS error | bound (RMS) | ratio |",
            "|---|---|---|---|",
        ]
        for name, ratio in obs["ratio_to_bound"].items():
            doc.append(f"| {name} | {obs['rms_error'][name]:.3g} | {obs['bound_rms'][name]:.3g} | {ratio:.2f} |")
        doc.append("")
    publish("\n".join(doc) + "\n", args.out)


if __name__ == "__main__":
    main()

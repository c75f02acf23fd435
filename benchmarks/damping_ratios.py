"""Modal damping as stated: every free elastic mode's ratio against the model file's Rayleigh formula.

For every model in ``models/`` (and any given), at ``q_ref`` with the motors free: the damping ratio of each mode
below ``--fmax`` from the damped eigenvalues of the ERLS state matrix (both forms,
:func:`exuflex.erls.modal.damping_ratios`) and of Exudyn's linearised system on the same mesh
(:func:`exuflex.groundtruth.modal_damping`: ``ComputeLinearizedSystem``, its own damper), each divided by
``alpha / (2 w) + beta w / 2`` at the mode's frequency. This is what ``exuflex modes MODEL --json --exudyn``
reports as ``full.damping_ratio`` and ``exudyn.damping_ratio``.

    python benchmarks/damping_ratios.py [MODEL ...] [--fmax 180] [--docs docs/validity.md]

``--docs`` rewrites the page's block between its ``damping_ratios.py`` markers.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from _pages import rewrite_block  # (a script: its folder is on the path)

from exuflex.erls.modal import aligned_ratios, damping_ratios, modal_analysis
from exuflex.erls.model import FORMS, ErlsModel
from exuflex.groundtruth import exudyn_frequencies, modal_damping
from exuflex.mechanism import load_mechanism

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- damping_ratios.py: begin -->", "<!-- damping_ratios.py: end -->"


def measure(path: Path, fmax: float) -> dict:
    mech = load_mechanism(path)
    a, b = mech.damping.alpha, mech.damping.beta
    out = {"model": mech.name, "alpha": a, "beta": b}
    f0 = modal_analysis(ErlsModel(mech)).below(fmax)
    w = 2 * np.pi * f0
    out["frequencies_hz"] = f0.tolist()
    out["stated"] = (a / (2 * w) + b * w / 2).tolist()
    for form in FORMS:
        out[form] = aligned_ratios(f0, *damping_ratios(ErlsModel(mech, form=form))).tolist()
    fx = exudyn_frequencies(mech, elements_per_link="file")
    fx = fx[fx <= fmax]
    out["exudyn_frequencies_hz"] = fx.tolist()
    wx = 2 * np.pi * fx
    out["exudyn"] = aligned_ratios(fx, *modal_damping(mech, elements_per_link="file")).tolist()
    out["exudyn_stated"] = (a / (2 * wx) + b * wx / 2).tolist()
    return out


def block(rows: list[dict], fmax: float, cmd: str) -> str:
    lines = [BEGIN, (f"Measured by `{cmd}` (q_ref, motors free, modes below {fmax:g} Hz; ratio / stated: the mode's "
                     "damping ratio from the damped eigenvalues over `alpha / (2 w) + beta w / 2` at its frequency)."),
             "",
             "| model | mode (Hz) | stated (%) | ERLS `lagrange` / stated | ERLS `eq2` / stated | Exudyn / stated |",
             "|---|---|---|---|---|---|"]
    worst = 0.0
    for r in rows:
        for i, f in enumerate(r["frequencies_hz"]):
            s = r["stated"][i]
            lg, e2 = r["lagrange"][i] / s, r["eq2"][i] / s
            ex = r["exudyn"][i] / r["exudyn_stated"][i] if i < len(r["exudyn"]) else float("nan")
            worst = max(worst, *(abs(v - 1) for v in (lg, e2, ex) if np.isfinite(v)))
            lines.append(f"| {r['model']} | {f:.2f} | {100 * s:.3f} | {lg:.4f} | {e2:.4f} | {ex:.4f} |")
    lines += ["", f"- largest departure from the stated ratio, any model, mode or model kind: {100 * worst:.2g} %", END]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="*", help="model files (default: every file in models/)")
    ap.add_argument("--fmax", type=float, default=180.0)
    ap.add_argument("--docs", default=None, help="page whose damping_ratios.py block is rewritten")
    args = ap.parse_args()
    paths = [Path(p) for p in args.models] or sorted((ROOT / "models").glob("*.toml"))
    rows = []
    for p in paths:
        d = load_mechanism(p).damping
        if not (d.alpha or d.beta):
            continue  # undamped (the spin-up beam): nothing stated
        r = measure(p, args.fmax)
        if r["frequencies_hz"]:
            rows.append(r)
    text = block(rows, args.fmax, " ".join(["python benchmarks/damping_ratios.py", *sys.argv[1:]]))
    print(text)
    if args.docs:
        rewrite_block(args.docs, BEGIN, END, text)


if __name__ == "__main__":
    main()

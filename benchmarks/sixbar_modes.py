"""Six-bar natural frequencies at q* against the paper's Table 2, per mode and RMS.

Usage::

    python benchmarks/sixbar_modes.py [--refine K] [--exudyn] [--json]

Prints the full-order ERLS frequencies below 180 Hz (motors free), the paper's Table 2 values and the
deviation of each, with the RMS deviation; ``--exudyn`` adds the independent Exudyn model.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from exuflex.cli.modes import modes_report
from exuflex.data import paper_reference

MODEL = Path(__file__).resolve().parents[1] / "models" / "sixbar.toml"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--refine", type=int, default=1, help="split every element into K (default 1: the paper's mesh)")
    p.add_argument("--exudyn", action="store_true", help="add the Exudyn model's frequencies")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)

    table2 = np.array(paper_reference()["table2_reduced_model_accuracy"]["frequencies_hz"])
    rep = modes_report(str(MODEL), refine=args.refine, exudyn=args.exudyn)
    f = np.array(rep["full"]["frequencies_hz"])
    n = min(len(f), len(table2))
    dev = 100 * (f[:n] / table2[:n] - 1)
    rms = float(np.sqrt(np.mean(dev**2)))
    if args.json:
        rep["table2_hz"] = table2.tolist()
        rep["deviation_pct"] = dev.tolist()
        rep["rms_deviation_pct"] = rms
        print(json.dumps(rep))
        return 0
    exu = rep.get("exudyn", {}).get("frequencies_hz")
    print(f"six-bar at q* = {rep['q']}: {rep['full']['ndof']} dofs ({rep['full']['n_elastic']} elastic), "
          f"{len(f)} modes below 180 Hz (motors free), mesh refined x{args.refine}")
    print(f"{'mode':>4} {'Table 2 (Hz)':>12} {'ERLS (Hz)':>10} {'dev %':>7}" + (f" {'Exudyn (Hz)':>11}" if exu else ""))
    for i in range(max(len(f), n)):
        t2 = f"{table2[i]:>12.2f}" if i < n else f"{'-':>12}"
        d = f"{dev[i]:>+7.2f}" if i < n else f"{'':>7}"
        row = f"{i + 1:>4} {t2} {f[i]:>10.2f} {d}"
        if exu:
            row += f" {exu[i]:>11.2f}" if i < len(exu) else ""
        print(row)
    print(f"RMS deviation from Table 2: {rms:.2f} % over {n} modes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

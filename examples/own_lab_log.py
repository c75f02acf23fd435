"""
Observe your own lab log
========================

Observe your own lab log: a CSV file with your column names and a time column in milliseconds.

    python examples/own_lab_log.py [LOG.csv] [--out DIR]

Without arguments it first writes a small example log (``examples/data/lab_sixbar.csv``, made from the test
run shipped with the repository: the six-bar's sensor log with renamed columns, time in ms) and observes that.
The same from the command line:

    exuflex observe models/sixbar.toml examples/data/lab_sixbar.csv \\
        --map T1=motor1_Nm,T2=motor2_Nm,T3=motor3_Nm,q1=enc1_rad,q2=enc2_rad,q3=enc3_rad,c1=gauge1,c2=gauge2,c4=gauge4 \\
        --time-column Time_ms --time-scale 1e-3 --out obs_lab
"""

from __future__ import annotations

import argparse
from pathlib import Path

import exuflex as xf

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
# exuflex channel (model file name) -> your column
MAP = {"T1": "motor1_Nm", "T2": "motor2_Nm", "T3": "motor3_Nm", "q1": "enc1_rad", "q2": "enc2_rad",
       "q3": "enc3_rad", "c1": "gauge1", "c2": "gauge2", "c4": "gauge4"}


def example_log(path: Path, run_dir: Path = ROOT / "tests" / "data" / "sixbar_erls_3s") -> Path:
    """A lab-style CSV from a six-bar run folder (default: the shipped test run; ``--from-run`` for one of
    yours, e.g. ``exuflex simulate models/sixbar.toml --out runs/mine``): renamed columns, time in
    milliseconds, a comment line."""
    run = xf.read_run(run_dir)
    S = run.sensors
    path.parent.mkdir(parents=True, exist_ok=True)
    cols = list(MAP)
    with open(path, "w") as f:
        f.write("# six-bar rig, logger v2\n")
        f.write(",".join(["Time_ms"] + [MAP[c] for c in cols]) + "\n")
        for k in range(len(S.t)):
            f.write(",".join([f"{S.t[k] * 1e3:.3f}"] + [repr(float(S[c][k])) for c in cols]) + "\n")
    return path


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.strip().split("\n")[3])
    ap.add_argument("log", nargs="?", help="your CSV log (default: an example made from a run folder)")
    ap.add_argument("--from-run", type=Path, default=None, help="the run folder the example log is made from "
                    "(default: the test run shipped with the repository)")
    ap.add_argument("--model", default=str(ROOT / "models" / "sixbar.toml"))
    ap.add_argument("--out", default=None, help="write estimates.csv, result.json and figures here")
    a = ap.parse_args(argv)
    if a.log:
        log_path = Path(a.log)
    elif a.from_run:
        log_path = example_log(HERE / "data" / "lab_sixbar.csv", a.from_run)
    else:
        log_path = example_log(HERE / "data" / "lab_sixbar.csv")

    mech = xf.load_mechanism(a.model)
    run = xf.read_lab_run(log_path, mech, MAP, time_column="Time_ms", time_scale=1e-3)  # ms -> s
    out = xf.observe_run(mech, run, report=print)  # checks the log, prints its channels, rates and the bound
    if a.out:
        from exuflex.scoring.output import write_outcome
        from exuflex.plots import observer_figures

        write_outcome(a.out, mech, run, out)
        observer_figures(a.out, mech, run, out)
    est = out.estimate.physical
    print(f"{len(est.t)} estimates; last q = {est.data[-1, :3].round(4).tolist()} rad")
    return out.summary


if __name__ == "__main__":
    main()

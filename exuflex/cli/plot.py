"""``exuflex plot MODEL LOG --out DIR``: figures of a log without running the observer.

``LOG`` is a run folder (``sensors.csv``, ``meta.json``, optional ``truth.csv``) or a lab CSV log (read as
``exuflex observe`` reads it: ``--map``, ``--time-column``, ``--time-scale``, ``--delimiter``, ``--decimal``). Written: ``fig_torques.png``
(the measured torques), ``fig_measurements.png`` (one panel per sensor channel), and with a truth
``fig_trajectory.png`` and ``fig_joint_states.png`` (the true states); with ``--estimates`` (an
``estimates.csv`` that ``exuflex observe --out`` wrote) the estimate beside the truth in those and the tip
figures.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .args import out_path, positive_float
from .observe import add_dialect_arguments

__all__ = ["add_parser", "run"]


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("plot", help="figures of a run folder or a lab log (no observer)",
                       description=__doc__.split("\n")[0])
    p.add_argument("model", help="mechanism model file (TOML)")
    p.add_argument("run_dir", help="run folder, or a CSV log file (then see --map)")
    p.add_argument("--out", type=out_path, default=None, help="folder for the figures (default: the run folder, "
                   "or beside the CSV log)")
    p.add_argument("--estimates", help="an estimates.csv written by exuflex observe --out")
    p.add_argument("--map", help="for a CSV log: channel=column pairs, e.g. T1=motor1_Nm,q1=enc1_rad")
    p.add_argument("--time-column", default="time", help="for a CSV log: the time column (default time)")
    p.add_argument("--time-scale", type=positive_float, default=1.0, help="for a CSV log: multiplies the time "
                   "column, e.g. 1e-3 for milliseconds")
    p.add_argument("--truth", help="for a CSV log: a truth CSV")
    add_dialect_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..mechanism import load_mechanism
    from ..runs import check_csv_dialect, output_folder, read_run
    from .observe import _read_log

    mech = load_mechanism(args.model)
    check_csv_dialect(args.delimiter, args.decimal)
    path = Path(args.run_dir)
    log = _read_log(args, mech) if path.is_file() else read_run(path)
    if args.out:
        out = Path(args.out)
    elif path.is_file():
        out = path.parent / f"{path.stem}_figures"
    else:  # the run folder itself if exuflex wrote it; beside it otherwise (a lab's folder is left as it is)
        out = path if _exuflex_folder(path) else path.parent / f"{path.name}_figures"
    with output_folder(out, "plot", mode="add") as out:
        return _draw(args, mech, log, out)


def _exuflex_folder(path: Path) -> bool:
    from ..runs import check_not_foreign

    try:
        check_not_foreign(path)
    except ValueError:
        return False
    return True


def _draw(args, mech, log, out: Path) -> int:
    from .. import plots
    from ..runs import read_signals_csv

    est = read_signals_csv(args.estimates) if args.estimates else None
    paper = mech.name in plots.PAPER_MODELS
    motors = tuple(log.motors or mech.motor_names)
    channels = [c for c in log.sensor_names if c not in motors]
    written = [plots.torques_figure(log.sensors, motors, out / "fig_torques.png", paper=paper),
               plots.measurements_figure(log.sensors, channels, out / "fig_measurements.png", paper=paper)]
    truth = log.truth
    if truth is not None or est is not None:
        written.append(plots.trajectory_figure(mech, truth, est, out / "fig_trajectory.png", sensors=log.sensors))
        written.append(plots.joint_states_figure(mech, truth, est if est is not None else truth,
                                                 out / "fig_joint_states.png"))
        if plots.tip_point(mech) is not None:
            written.append(plots.tip_displacement_figure(mech, truth, est if est is not None else truth,
                                                         out / "fig_tip_displacement.png"))
    for f in written:
        print(f"wrote {f}")
    print(f"exuflex plot: {len(written)} figures in {out}", file=sys.stderr)
    return 0

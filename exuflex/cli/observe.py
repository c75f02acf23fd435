"""``exuflex observe MODEL RUN_DIR``: run the reduced-order EKF on a logged run and score it."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["add_parser", "run"]


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("observe", help="estimate the states of a logged run with the reduced-order EKF")
    p.add_argument("model", help="mechanism model file (TOML)")
    p.add_argument("run_dir", help="run folder (sensors.csv, meta.json, optional truth.csv), or a CSV log file "
                   "(then see --map)")
    p.add_argument("--map", help="for a CSV log: channel=column pairs, e.g. T1=motor1_Nm,q1=enc1_rad (default: "
                   "columns named like the model's motors and sensors)")
    p.add_argument("--time-column", default="time", help="for a CSV log: the time column (default time)")
    p.add_argument("--time-scale", type=float, default=1.0, help="for a CSV log: multiplies the time column, "
                   "e.g. 1e-3 for milliseconds")
    p.add_argument("--truth", help="for a CSV log: a truth CSV (time + columns named like the truth states)")
    p.add_argument("--out", help="write estimates.csv, result.json and plots here")
    p.add_argument("--json", action="store_true", help="print one JSON object with the metrics")
    p.add_argument("--channels", help="comma-separated sensor channels (default: the paper's set for the model)")
    p.add_argument("--masters", help="comma-separated elastic master dofs (default: the model file's)")
    p.add_argument("--n-interior", default=None, help="interior modes: a number or 'auto'")
    p.add_argument(
        "--method",
        choices=("cached", "rk4"),
        default="cached",
        help="step map: cached (default), rk4 (the configuration at every RK4 stage: the exact reference)",
    )
    p.add_argument("--estimator", choices=("ekf", "ukf", "ekf-payload", "ekf-input"), default="ekf",
                   help="ekf (default), ukf, ekf-payload (payload scale as a state), ekf-input (torque disturbances "
                        "as states)")
    p.add_argument("--smooth", action="store_true", help="RTS-smoothed estimates of the whole log (EKF variants)")
    p.add_argument("--bound", action="store_true", help="also print the steady-state RMS bound (always in --json)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures in --out")
    p.set_defaults(func=run)
    return p


def _config(args):
    from ..observer.session import ObserverConfig

    ni = args.n_interior
    if ni is not None and ni != "auto":
        ni = int(ni)
    return ObserverConfig(
        channels=tuple(args.channels.split(",")) if args.channels else None,
        masters=tuple(args.masters.split(",")) if args.masters else None,
        n_interior=ni,
        method=args.method,
        estimator=args.estimator,
    )


def _read_log(args, mech):
    """A CSV log (a lab's, or Exudyn's sensor output converted to CSV) as a run: channels mapped by name."""
    from ..errors import LogFormatError
    from ..runs import Run, read_csv_log

    names = list(mech.motor_names) + [s.name for s in mech.sensors]
    if args.map:
        mapping = {}
        for pair in args.map.split(","):
            if "=" not in pair:
                raise LogFormatError(f"--map: expected channel=column pairs separated by commas, got {pair!r}")
            ours, theirs = (x.strip() for x in pair.split("=", 1))
            if ours not in names:
                raise LogFormatError(f"--map: {ours!r} is not a motor or sensor of {mech.name}; expected one of {names}")
            mapping[ours] = theirs
        for m in mech.motor_names:
            mapping.setdefault(m, m)
    else:
        mapping = None
    sig = read_csv_log(args.run_dir, mapping, time_column=args.time_column, time_scale=args.time_scale)
    motors = [m for m in mech.motor_names if m in sig]
    if len(motors) != len(mech.motor_names):
        raise LogFormatError(f"{args.run_dir}: the observer needs the measured torques {list(mech.motor_names)}; "
                             f"the log has {list(sig.names)} (use --map)")
    truth = read_csv_log(args.truth, time_column="time") if args.truth else None
    sensors = [n for n in sig.names if n not in motors]
    meta = {"engine": "csv", "source": str(args.run_dir), "motors": motors, "sensors": sensors}
    return Run(Path(args.run_dir), sig, truth, meta)


def run_manoeuvre(mech, log):
    """``mech`` with the manoeuvre the run was made with, when ``exuflex simulate --manoeuvre FILE`` replaced the
    model's (recorded in its meta.json): the observer starts where that manoeuvre starts."""
    from ..mechanism import load_manoeuvre

    src = ((log.meta or {}).get("settings") or {}).get("manoeuvre", {}).get("source", "model")
    if src in (None, "model"):
        return mech
    if not Path(src).is_file():
        print(f"exuflex observe: warning: the run's manoeuvre file {src} is gone; using the model's", file=sys.stderr)
        return mech
    return mech.replace(manoeuvre=load_manoeuvre(src, mech))


def run(args) -> int:
    from ..mechanism import load_mechanism
    from ..observer.session import observe_run
    from ..runs import read_run

    mech = load_mechanism(args.model)
    from ..validate import check_configurations

    check_configurations(mech)  # loops close, away from singularities
    log = _read_log(args, mech) if Path(args.run_dir).is_file() else read_run(args.run_dir)
    mech = run_manoeuvre(mech, log)
    if args.smooth and args.estimator == "ukf":
        print("exuflex observe: error: --smooth needs an EKF estimator (ekf, ekf-payload, ekf-input), not ukf",
              file=sys.stderr)
        return 2
    out = observe_run(mech, log, _config(args), smooth=args.smooth)
    s = out.summary
    if s["diverged"]:
        print(f"exuflex observe: warning: the filter diverged at t = {s['diverged_at']} s (NIS test)", file=sys.stderr)
    if args.out:
        from ..observer.output import write_outcome

        write_outcome(args.out, mech, log, out, plots=not args.no_plots)
    if args.json:
        print(json.dumps(s, indent=1, default=float))
        return 0
    print(f"{mech.name}: {len(out.estimate.result.t)} samples, reduced model {s['reduced_ndof']} dofs, "
          f"channels {' '.join(s['channels'])}")
    print(f"wall {s['wall_s']:.2f} s, real-time factor {s['real_time_factor']:.2f}, mean NIS {s['nis_mean']:.2f} "
          f"(expected {s['nis_expected']:.1f})")
    if "parameters" in s:
        print(f"payload scale {s['parameters']['payload_scale']:.4g} +- {s['parameters']['payload_scale_std']:.2g}")
    if "inputs" in s:
        print("torque disturbance (N m): " + ", ".join(f"{k} {v['value']:.3g} +- {v['std']:.2g}"
                                                     for k, v in s["inputs"].items()))
    if out.metrics:
        print(f"{'quantity':10s} {'RMS error':>11s} {'max error':>11s} {'bound':>11s} {'ratio':>6s}")
        for k, v in out.metrics["rms_error"].items():
            b = (out.bound or {}).get(k)
            ratio = f"{v / b:6.2f}" if b else "     -"
            bs = f"{b:11.3g}" if b else "          -"
            print(f"{k:10s} {v:11.3g} {out.metrics['max_error'][k]:11.3g} {bs} {ratio}")
    elif args.bound and out.bound:
        for k, b in out.bound.items():
            print(f"{k:10s} bound {b:.3g}")
    if args.out:
        print(f"wrote {Path(args.out)}")
    return 0

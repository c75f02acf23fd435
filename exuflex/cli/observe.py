"""``exuflex observe MODEL LOG``: run the reduced-order EKF on a logged run (a run folder or a lab CSV log),
report the log's channels and rates, and score it against a truth if any, with the estimation bound for that log
(without a truth the bound along the plan with ``--bound``).

Stage messages go to stderr (``exuflex observe: ...``); the result table to stdout. Tuning (see
``docs/tuning.md``): the prior (``--q0``, ``--qd0`` and the ``--*-std`` flags), the noise of any motor or sensor
(``--noise T1=0.02,c1=5e-5``: the filter's R and the torque process noise Q), a process-noise scale
(``--q-scale``), unmodelled elastic-rate noise (``--q-extra``) and the RK4 sub-step (``--substep``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..runs import dump_json
from .args import (
    add_overwrite,
    channel_list,
    finite_float,
    n_interior,
    name_list,
    nonneg_float,
    out_path,
    positive_float,
    probability,
    unit_probability,
)

__all__ = ["FULL_P_BYTES", "add_parser", "run"]

FULL_P_BYTES = 256e6
"""With ``--out --smooth`` (the whole record in memory), the filter keeps its full covariance per sample (for the
standard deviations of the tip columns) while it takes at most this many bytes; longer logs get the joint angles'
and rates' only. Without ``--smooth`` the log is filtered in chunks and ``estimates.csv`` written as it runs: the
full covariance of one chunk at a time, for any length."""


def _floats(text: str) -> tuple[float, ...]:
    vals = [v.strip() for v in text.split(",")]
    if not text.strip() or any(not v for v in vals):
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers such as 1.08,2.64,4.71, got {text!r}")
    return tuple(finite_float(v) for v in vals)


def _noise(text: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for pair in text.split(","):
        if pair.count("=") != 1 or not pair.split("=")[0].strip():
            raise argparse.ArgumentTypeError(f"expected NAME=STD pairs separated by commas (e.g. T1=0.02,c1=5e-5), "
                                             f"got {pair!r}")
        name, v = (x.strip() for x in pair.split("="))
        if name in out:
            raise argparse.ArgumentTypeError(f"{name!r} given twice")
        out[name] = positive_float(v)
    return out


def _delimiter(text: str) -> str:
    """A delimiter flag: one character, or a name such as ``tab`` (:data:`exuflex.runs.DELIMITER_NAMES`);
    checked with the decimal mark by :func:`exuflex.runs.check_csv_dialect`."""
    from ..runs import DELIMITER_NAMES

    return DELIMITER_NAMES.get(text.lower() if len(text) > 1 else text, text)


def add_dialect_arguments(g) -> None:
    """``--delimiter`` and ``--decimal`` of a lab CSV log (and its ``--truth``), for ``observe`` and ``plot``."""
    g.add_argument("--delimiter", type=_delimiter, default=",",
                   help="field separator of a CSV log and --truth: one character, or tab, semicolon, pipe, "
                        "space (default ,)")
    g.add_argument("--decimal", default=".", help="decimal mark of a CSV log and --truth: . (default) or , "
                   "(with another --delimiter, e.g. ';')")


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("observe", help="estimate the states of a logged run with the reduced-order EKF",
                       description=__doc__.split("\n")[0])
    p.add_argument("model", help="mechanism model file (TOML)")
    p.add_argument("run_dir", help="run folder (sensors.csv, meta.json, optional truth.csv), or a CSV log file "
                   "(then see --map)")
    g = p.add_argument_group("lab CSV logs")
    g.add_argument("--map", help="channel=column pairs, e.g. T1=motor1_Nm,q1=enc1_rad (default: columns named "
                   "like the model's motors and sensors)")
    g.add_argument("--time-column", default="time", help="the time column (default time)")
    g.add_argument("--time-scale", type=positive_float, default=1.0,
                   help="multiplies the time column, e.g. 1e-3 for milliseconds")
    add_dialect_arguments(g)
    g.add_argument("--truth", help="a truth CSV (time + columns named like the truth states)")
    p.add_argument("--accept-other-model", action="store_true",
                   help="observe a run folder whose meta.json names another mechanism (refused otherwise)")
    p.add_argument("--out", type=out_path, help="write estimates.csv, result.json and plots here")
    add_overwrite(p)
    p.add_argument("--json", action="store_true", help="print one JSON object with the metrics")
    p.add_argument("--channels", type=channel_list,
                   help="comma-separated sensor channels (default: the paper's set for the model)")
    r = p.add_argument_group("reduced model")
    r.add_argument("--masters", type=name_list("master dofs"),
                   help="comma-separated elastic master dofs (default: the model file's)")
    r.add_argument("--n-interior", type=n_interior, default=None, help="interior modes: a number or 'auto'")
    r.add_argument("--method", choices=("cached", "rk4"), default=None,
                   help="step map: cached (default), rk4 (the configuration at every RK4 stage: the exact reference)")
    r.add_argument("--substep", type=positive_float, default=None,
                   help="RK4 sub-step of the filter's prediction (s, default 1e-4)")
    t = p.add_argument_group("tuning (docs/tuning.md)")
    t.add_argument("--q0", type=_floats, help="initial joint angles Q1,Q2,... (rad; default: the manoeuvre's "
                   "start, else the model's q_ref); elastic coordinates at rest")
    t.add_argument("--qd0", type=_floats, help="initial joint rates (rad/s, default 0)")
    t.add_argument("--q0-std", type=positive_float, help="prior std of the joint angles (rad, default 0.05)")
    t.add_argument("--qd0-std", type=positive_float, help="prior std of the joint rates (rad/s, default 0.1)")
    t.add_argument("--elastic0-std", type=positive_float, help="prior std of the elastic coordinates (m or rad, "
                   "default 1e-3)")
    t.add_argument("--elastic-rate0-std", type=positive_float, help="prior std of the elastic rates (default 0.01)")
    t.add_argument("--noise", type=_noise, default={}, help="noise std overrides NAME=STD,... for motors (N m: "
                   "process noise) and sensors (their unit: R); default the model file's noise_std")
    t.add_argument("--q-scale", type=positive_float,
                   help="multiplies the torque process-noise covariance (default 1: the stated noise)")
    t.add_argument("--q-extra", type=nonneg_float,
                   help="extra white noise on the elastic rates per interval (std, unmodelled dynamics; default 0)")
    t.add_argument("--jump-p", type=probability, help="false-alarm probability per interval of the torque-jump "
                   "test (a torque step between two samples gets its effect at an unknown instant of the interval; "
                   "default: no test; helps logs whose torque steps fall between samples, e.g. a drifting clock)")
    t.add_argument("--start-up", type=nonneg_float,
                   help="seconds left out of the error metrics (default 0.3)")
    p.add_argument("--estimator", choices=("ekf", "ukf", "ekf-payload", "ekf-input", "imm"), default=None,
                   help="ekf (default), ukf, ekf-payload (payload scale as a state), ekf-input (torque disturbances "
                        "as states), imm (interacting multiple models: the plain EKF and ekf-payload's filter)")
    p.add_argument("--payload-nominal-p", type=unit_probability, metavar="P",
                   help="ekf-payload: prior probability that the payload is the model file's; the estimates are "
                        "the model average of the nominal payload and the estimated one (default 0.5; 0: the "
                        "filter's own posterior); imm: the nominal mode's prior probability")
    p.add_argument("--imm-dwell", type=positive_float, metavar="S",
                   help="imm: expected dwell time in each mode (s), its transition matrix (default: 100 "
                        "manoeuvre durations)")
    p.add_argument("--smooth", action="store_true", help="smoothed estimates of the whole log (EKF variants and the IMM)")
    p.add_argument("--isolate-faults", action="store_true", default=None,
                   help="leave a channel with a detected offset or stuck fault out of the updates until it clears "
                        "(off by default: a model error looks like a sensor offset; faults are always reported)")
    p.add_argument("--bound", action="store_true",
                   help="the bound for a log without a truth too (along the manoeuvre's plan; it takes about as long "
                        "as the filter). With a truth it is always computed: the errors are scored against it")
    p.add_argument("--no-plots", action="store_true", help="skip the figures in --out")
    p.add_argument("--allow-undersampled", action="store_true",
                   help="run on a log sampled too slowly for the reduced model's in-band modes (refused otherwise) "
                   "and flag the result ('sampling': undersampled)")
    p.set_defaults(func=run)
    return p


def _config(args, mech):
    """The observer's settings: the defaults, the model file's ``[observer]`` table, then the options given."""
    from ..observer.session import ObserverConfig

    given = {
        "channels": args.channels,
        "masters": args.masters,
        "n_interior": args.n_interior,
        "method": args.method,
        "h": args.substep,
        "q0_std": args.q0_std,
        "qd0_std": args.qd0_std,
        "elastic0_std": args.elastic0_std,
        "elastic_rate0_std": args.elastic_rate0_std,
        "q_scale": args.q_scale,
        "fault_isolation": args.isolate_faults,
        "q_extra_std": args.q_extra,
        "estimator": args.estimator,
        "start_up": args.start_up,
        "jump_p": args.jump_p,
        "payload_nominal_p": args.payload_nominal_p,
        "imm_dwell_s": args.imm_dwell,
    }
    return ObserverConfig.for_model(mech, **{k: v for k, v in given.items() if v is not None})


def _csv_options_unused(args) -> None:
    """A run folder has its own clock, columns and truth: the lab-CSV options are refused there, not ignored."""
    from ..errors import UsageError

    given = [flag for flag, v, default in (("--map", args.map, None), ("--time-column", args.time_column, "time"),
                                           ("--time-scale", args.time_scale, 1.0), ("--truth", args.truth, None),
                                           ("--delimiter", args.delimiter, ","), ("--decimal", args.decimal, "."))
             if v != default]
    if given:
        raise UsageError(f"{' '.join(given)}: options of a lab CSV log, but {args.run_dir} is a run folder (its "
                         "meta.json names the columns, its truth is its truth.csv); expected them only with a CSV file")


def _read_log(args, mech):
    """A CSV log (a lab's, or Exudyn's sensor output converted to CSV) as a run: channels mapped by name
    (:func:`exuflex.runs.read_lab_run`)."""
    from ..errors import LogFormatError
    from ..runs import read_lab_run

    mapping = None
    if args.map:
        mapping = {}
        for pair in args.map.split(","):
            if pair.count("=") != 1:
                raise LogFormatError(f"--map: expected channel=column pairs separated by commas, got {pair!r}")
            ours, theirs = (x.strip() for x in pair.split("=", 1))
            if ours in mapping:
                raise LogFormatError(f"--map: channel {ours!r} mapped twice")
            mapping[ours] = theirs
    return read_lab_run(args.run_dir, mech, mapping, time_column=args.time_column, time_scale=args.time_scale,
                        delimiter=args.delimiter, decimal=args.decimal, truth=args.truth, columns_name="--map")


def _say(msg: str) -> None:
    print(f"exuflex observe: {msg}", file=sys.stderr, flush=True)


def run_manoeuvre(mech, log):
    """``mech`` with the manoeuvre the run was made with, when ``exuflex simulate --manoeuvre FILE`` replaced the
    model's (recorded in its meta.json): the observer starts where that manoeuvre starts."""
    from ..mechanism import load_manoeuvre

    man = ((log.meta or {}).get("settings") or {}).get("manoeuvre", {})
    src = man.get("source", "model")
    if src in (None, "model"):
        return mech
    if man.get("copy") and getattr(log, "path", None) is not None and (Path(log.path) / man["copy"]).is_file():
        src = Path(log.path) / man["copy"]
    if not Path(src).is_file():
        print(f"exuflex observe: warning: the run's manoeuvre file {src} is gone; using the model's", file=sys.stderr)
        return mech
    return mech.replace(manoeuvre=load_manoeuvre(src, mech))


def _check_smoother_memory(obs, n_samples: int) -> None:
    """``--smooth`` keeps the whole filtered record in memory: per sample about three n x n matrices for the RTS
    pass (the predicted and filtered covariances and the step Jacobian), about four per mode for the IMM's.
    Refused with a :class:`~exuflex.errors.UsageError` where that exceeds :func:`~exuflex.validate.memory_limit_bytes`
    (without ``--smooth`` the log is filtered in chunks, for any length)."""
    from ..errors import UsageError
    from ..validate import _bytes, memory_limit_bytes

    ekf = obs.ekf
    per_sample = 8 * ekf.nx**2 * (4 * len(ekf.models) if hasattr(ekf, "dims") else 3)
    need, limit = n_samples * per_sample, memory_limit_bytes()
    if need > limit:
        raise UsageError(f"--smooth: {n_samples} samples of a {ekf.nx}-state filter need about {_bytes(need)} in "
                         f"memory, more than the {_bytes(limit)} allowed (half this machine's memory); expected a "
                         "shorter log, or no --smooth (the filter alone runs in chunks for any length)")


def _check_sampling(mech, obs, log, log_check, *, allow: bool, source: str) -> dict:
    """Sampling adequate for the model: the fastest used channel and the torques sampled at least at twice the
    reduced model's highest frequency within its band (``reduction.band_hz``) at ``q*`` (Nyquist: a mode above half
    the sampling rate aliases onto a slower one, and the update cannot tell them apart; a torque held over an
    interval longer than the mode's half period drives it with an input the log does not show). Refused with a
    :class:`~exuflex.errors.UsageError` naming the rates, unless ``allow`` (then flagged in the result)."""
    import numpy as np

    from ..errors import UsageError
    from ..reduction import reduced_modes

    cb = getattr(getattr(obs.model, "rm", None), "cb", None)
    band = float(mech.reduction.band_hz)
    if cb is not None:
        f = np.asarray(reduced_modes(cb, cb.q_star)[0], float)
        f = f[(f > 0) & (f <= band)]
        f_need = float(f.max()) if f.size else 0.0
    else:
        f_need = band
    rates = {c: r for c, r in log_check.channel_rate_hz.items() if r > 0}
    t = log.sensors.t
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    torque_rate = (len(t) - 1 - log_check.held_torques) / span if span > 0 else 0.0
    need = 2.0 * f_need
    why = []
    if rates and max(rates.values()) < need:
        c = max(rates, key=rates.get)
        why.append(f"its fastest channel ({c}, {rates[c]:.4g} Hz) samples below twice the reduced model's highest "
                   f"in-band frequency ({f_need:.4g} Hz)")
    if need and torque_rate < need:
        why.append(f"its torques are sampled at {torque_rate:.4g} Hz, below twice the reduced model's highest "
                   f"in-band frequency ({f_need:.4g} Hz)")
    text = f"{source}: the log cannot support the estimate: " + "; ".join(why) if why else ""
    if why and not allow:
        raise UsageError(f"{text}; expected rates of at least {need:.4g} Hz (a faster log, a model with a lower "
                         "reduction.band_hz, or --allow-undersampled to run and flag the result)")
    return {"undersampled": bool(why), "needed_hz": need, "highest_in_band_hz": f_need,
            "channel_rate_hz": rates, "torque_rate_hz": torque_rate, "why": "; ".join(why) or None}


def _check_substeps(mech, config, n_samples: int) -> None:
    """Bounds before work on ``--substep``: the RK4 sub-steps over the log (each about 4 evaluations of the reduced
    model and the propagation of its Jacobian, 4 nx^3 flop) within the time one setting may ask for."""
    import math

    from ..validate import check_work, state_size_estimate

    dt = config.dt or 1.0 / mech.sample_rate_hz
    per_sample = max(1, math.ceil(dt / config.h * (1 - 1e-9)))
    nx = state_size_estimate(mech)
    check_work(f"{config.h:g} s", float(n_samples) * per_sample, param="h", flag="--substep",
               what=f"RK4 sub-steps ({per_sample:.3g} a sample over {n_samples} samples)", flops_each=4 * nx**3)


def run(args) -> int:
    if not args.out:
        return _run(args)
    from ..runs import output_folder

    with output_folder(args.out, "observe", overwrite=args.overwrite, inputs=[args.run_dir]):
        return _run(args)


def _run(args) -> int:
    from . import setting_up

    with setting_up():  # the observer's modules (and SciPy, numba) imported
        from .. import _compile
        from ..errors import UsageError
        from ..mechanism import load_mechanism
        from ..observer.session import AUGMENTED_ESTIMATORS, make_observer
        from ..runs import check_csv_dialect, read_run
        from ..scoring.run import observe_run
        from ..sensors import default_channels
        from ..validate import check_configurations, check_observer_settings, check_provenance, check_run, with_noise

    mech = load_mechanism(args.model)
    if args.noise:
        mech = with_noise(mech, args.noise)
    config = _config(args, mech)
    if args.smooth and config.estimator == "ukf":
        raise UsageError("--smooth: the smoother needs an EKF estimator (ekf, ekf-payload, ekf-input or imm), not ukf")
    check_observer_settings(mech, config)  # before anything is built or read
    if Path(args.run_dir).is_dir():
        _csv_options_unused(args)
    check_csv_dialect(args.delimiter, args.decimal)
    for flag, v in (("--q0", args.q0), ("--qd0", args.qd0)):
        if v is not None and len(v) != len(mech.coordinates):
            raise UsageError(f"{flag}: expected {len(mech.coordinates)} values ({', '.join(mech.coordinate_names)}), "
                             f"got {len(v)}")
    # the first run: the kernels start compiling in the other processes while this one checks the model and the
    # log (compiling the closure's kernels as it does); prepare() below compiles the rest of its share and waits
    _compile.start(progress=_say, augmented=config.estimator in AUGMENTED_ESTIMATORS)
    with setting_up():  # (numba's set-up: the first compiled kernel)
        check_configurations(mech)  # loops close, away from singularities
    path = Path(args.run_dir)
    log = _read_log(args, mech) if path.is_file() else read_run(path)
    log, notes = check_provenance(mech, log, accept_other_model=args.accept_other_model)
    for note in notes:
        _say(f"note: {note}")
    _say(f"read {path}: {len(log.sensors.t)} rows, {float(log.sensors.t[-1] - log.sensors.t[0]):.4g} s")
    mech = run_manoeuvre(mech, log)
    _check_substeps(mech, config, len(log.sensors.t))
    # the log checked before the model is built: a bad log fails at once, and the check's working arrays (a
    # few floats a row, all rows at once) are freed before the observer's own memory is taken
    log_check = check_run(mech, log, tuple(config.channels) if config.channels else default_channels(mech),
                          dt=config.dt or 1.0 / mech.sample_rate_hz)
    _compile.prepare(progress=_say, augmented=config.estimator in AUGMENTED_ESTIMATORS)
    _say("building the reduced model")
    with setting_up():  # the kernels loaded, the model built
        obs = make_observer(mech, config)
        if args.q0 is not None or args.qd0 is not None:
            from ..manoeuvre import start_configuration

            q0 = args.q0 if args.q0 is not None else start_configuration(mech)
            x0 = obs.model.initial_state(q0, args.qd0)
            obs = make_observer(mech, config, x0=x0, cb=obs.model.rm.cb)
    sampling = _check_sampling(mech, obs, log, log_check, allow=args.allow_undersampled, source=str(path))
    if args.smooth:
        _check_smoother_memory(obs, len(log.sensors.t))
    if args.out and (not args.smooth or len(log.sensors.t) * obs.ekf.nx**2 * 8 <= FULL_P_BYTES):
        obs.ekf.store_P = "full"  # the standard deviations of the tip columns in estimates.csv need it
    elif not args.out and not args.smooth and obs.ekf.model is obs.model:
        obs.ekf.store_P = "none"  # nothing printed reads the per-sample covariance (8 nx bytes a sample)
    # what is kept of the filtered record: the physical estimates for the figures (and a truth's errors), else
    # only what the summary needs; estimates.csv is written as the filter runs (observe_run's memory notes)
    keep = "all" if args.smooth else "physical" if args.out and not args.no_plots else "summary"
    # the bound scores the errors against a truth; without one it is the plan's, asked for with --bound
    with_bound = True if args.bound else "truth"
    if log.truth is None and not args.bound:
        _say("no truth: no bound (--bound: the bound along the manoeuvre's plan for this log's sampling)")
    if args.out:
        from ..scoring.output import EstimatesWriter

        with EstimatesWriter(args.out, mech, observer=obs) as writer:
            out = observe_run(mech, log, config, observer=obs, report=_say, smooth=args.smooth, keep=keep,
                              sink=writer, log_check=log_check, with_bound=with_bound)
    else:
        out = observe_run(mech, log, config, observer=obs, report=_say, smooth=args.smooth, keep=keep,
                          log_check=log_check, with_bound=with_bound)
    s = out.summary
    s["sampling"] = sampling
    if sampling["undersampled"]:
        _say(f"warning: {sampling['why']}: the estimates are not supported by the log (--allow-undersampled)")
    if s["diverged"]:
        _say(f"warning: the filter diverged (estimates non-finite) at t = {s['diverged_at']} s")
    elif s["nis_inconsistent"]:
        when = (f"from t = {s['nis_flagged_at']:.4g} s" if s.get("nis_flagged_at") is not None else
                f"over the whole log (mean NIS {s['nis_mean']:.3g} against {s['nis_expected']:.3g})")
        _say(f"warning: NIS inconsistent {when} (innovations larger than the filter's "
             "covariance explains: model mismatch, wrong noise settings or units; estimates finite)")
    if args.out:
        from ..scoring.output import write_outcome

        _say(f"writing {args.out}")
        write_outcome(args.out, mech, log, out, observer=obs, estimates=False)
        if not args.no_plots:
            from ..plots import observer_figures

            observer_figures(args.out, mech, log, out)
    if args.json:
        print(dump_json(s, default=float))
        return 0
    from ..scoring.output import summary_table

    print(summary_table(mech, out, bound=True))
    if "parameters" in s:
        par = s["parameters"]
        nominal = par.get("payload_nominal_p")
        print(f"payload scale {par['payload_scale']:.4g} +- {par['payload_scale_std']:.2g}"
              + (f" (nominal payload: probability {nominal:.3g})" if nominal is not None else ""))
    if "inputs" in s:
        print("torque disturbance (N m): " + ", ".join(f"{k} {v['value']:.3g} +- {v['std']:.2g}"
                                                     for k, v in s["inputs"].items()))
    if args.out:
        print(f"wrote {Path(args.out)}")
    return 0

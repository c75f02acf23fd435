"""An observer run on a log, scored: the log checked, the bound for it, the filter, the errors against the truth
and the summary a result file records (:func:`observe_run`); the error metrics (:func:`metrics`) and the
whole-log NIS test (:func:`nis_whole_log_flag`)."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..mechanism import Mechanism
from ..observer.session import (Estimate, EstimateChunk, Observer, ObserverConfig, check_arguments, estimate,
                                estimate_chunks, make_observer, physical_names, physical_units)
from ..runs import LogColumns, input_hold_of
from ..sensors import Signals
from .bound import UnobservableError, _Sampled, bound_track, check_observable

__all__ = ["KEEP", "NIS_GROSS_FACTOR", "NIS_WHOLE_LOG_P", "Outcome", "extra_states", "held_error_summary",
           "last_state", "metrics", "nis_whole_log_flag", "observe_run"]

log = logging.getLogger(__name__)


NIS_WHOLE_LOG_P = 1e-6
"""False-alarm probability of the whole-log NIS test (:func:`nis_whole_log_flag`)."""

NIS_GROSS_FACTOR = 3.0
"""How far above a consistent filter's bound the whole log's mean NIS must lie to be flagged whatever the window:
the windowed test judges mild mismatch; this one a gross inconsistency (several times the innovations' stated
covariance: a log that cannot support the model, wrong units or noise)."""


def last_state(est: Estimate) -> tuple[np.ndarray, np.ndarray | None, float | None]:
    """The last sample's state, variances (None without a stored covariance) and nominal payload probability
    (None where not reported) of a whole record, smoothed where smoothing ran."""
    src = est.smoothed if est.smoothed is not None else est.result
    return (src.x_hat[-1], src.P_diag[-1] if src.P_diag is not None else None,
            None if src.nominal_p is None else float(src.nominal_p[-1]))


def extra_states(fmodel, x: np.ndarray, var: np.ndarray | None, nominal_p: float | None = None) -> dict:
    """The augmented states' estimates ``x`` and variances ``var`` at the end of the record (smoothed where
    smoothing ran; NaN standard deviations without ``var``): ``{"parameters": {"payload_scale": ...,
    "payload_scale_std": ..., "payload_nominal_p": ...}}`` (the last where reported, :func:`exuflex.observer.session.reported`) and
    ``{"inputs": {motor: {"value", "std"}}}``; empty for a plain model."""
    out: dict = {}
    it, ii = getattr(fmodel, "i_theta", None), getattr(fmodel, "i_inputs", None)
    if it is None and ii is None:
        return out
    var = np.full(len(x), np.nan) if var is None else var
    if it is not None:
        out["parameters"] = {"payload_scale": float(x[it]), "payload_scale_std": float(np.sqrt(var[it]))}
        if nominal_p is not None:
            out["parameters"]["payload_nominal_p"] = nominal_p
    if ii is not None:
        names = fmodel.inner.mech.motor_names
        out["inputs"] = {m: {"value": float(v), "std": float(np.sqrt(s))}
                         for m, v, s in zip(names, x[ii], var[ii], strict=True)}
    return out


def held_error_summary(model) -> dict:
    """What a reduced model's cached step recorded since its last reset (``result.json``'s ``held_model_error``): the
    held model's error ratios (:meth:`exuflex.observer.reduced.ReducedObserverModel._held_error`: count, median and largest) and the
    replaced step maps' errors (:func:`exuflex.observer.expansion.map_error`: count, median, largest, the last map
    radius)."""
    out = {"n": len(model.held_errors)}
    if model.held_errors:
        a = model.held_errors.asarray()
        out.update(vs_std_median=float(np.median(a[:, 0])), vs_std_max=float(a[:, 0].max()),
                   vs_process_noise_median=float(np.nanmedian(a[:, 1])),
                   vs_process_noise_max=float(np.nanmax(a[:, 1])))
    out["map_n"] = len(model.map_errors)
    if model.map_errors:
        e = np.asarray(model.map_errors)
        out.update(map_error_median=float(np.median(e)), map_error_max=float(e.max()), map_radius=model.map_rad)
    return out


def nis_whole_log_flag(nis_mean: float, nis_expected: float, n_updates: int, p: float = NIS_WHOLE_LOG_P,
                       factor: float = NIS_GROSS_FACTOR) -> bool:
    """The NIS test over the whole log, beside the filter's windowed one. With a consistent filter the sum of the
    ``n`` updates' NIS is chi-square with ``k = n d`` degrees of freedom (``d`` the mean channels per update); the
    log is flagged where the mean NIS exceeds ``factor`` times that sum's ``1 - p`` quantile over ``n``, so that a
    mean NIS far above its expectation is flagged even where no window of the windowed test fills (a short log, a
    slow one). The quantile ``chi2_{1-p}(k) = 2 Q^{-1}(k / 2, p)``, the inverse of the regularised upper incomplete
    gamma function."""
    if not (n_updates > 0 and math.isfinite(nis_mean) and math.isfinite(nis_expected) and nis_expected > 0):
        return False
    from scipy.special import gammainccinv

    q = 2.0 * float(gammainccinv(n_updates * nis_expected / 2.0, p))
    return bool(nis_mean * n_updates > factor * q)


def _scored(t: np.ndarray, start_up: float, truth_t: np.ndarray | None = None) -> np.ndarray:
    """The samples of a record of times ``t`` that :func:`metrics` scores: from ``t[0] + start_up`` on, within the
    truth's span (half a median interval's tolerance) where a truth's times are given."""
    t = np.asarray(t, float)
    sel = t >= t[0] + start_up
    if truth_t is not None and len(truth_t):
        tol = 0.5 * float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        sel &= (t >= float(truth_t[0]) - tol) & (t <= float(truth_t[-1]) + tol)
    return sel


def _bound_kind(along: str, smooth: bool) -> str:
    """What the bound of a summary is, in words (``bound_kind``)."""
    return (("smoothed " if smooth else "") + "posterior Cramer-Rao bound along the "
            + {"truth": "truth", "plan": "plan (no truth)", "q_ref": "reference pose at rest (no manoeuvre)"}[along])


def metrics(est: Signals, truth: Signals, start_up: float = 0.3, names: Sequence[str] | None = None, *,
            min_coverage: float = 0.9) -> dict:
    """RMS and max absolute error per quantity after ``start_up`` s (truth interpolated onto the estimate's times).

    The truth must cover the scored interval ``[t_0 + start_up, t_end]`` of the estimate: interpolation holds a
    truth's end values, so a truth cut short or on another clock would be scored silently against constants.
    Only the estimate's samples within the truth's span (half a sample's tolerance) are scored; if they are less
    than ``min_coverage`` of the scored interval it is an error (``ValueError`` naming both spans), else a
    partial cover is a warning. ``truth_coverage`` in the result is the covered fraction.
    """
    names = [n for n in (names or est.names) if n in truth]
    sel = est.t >= est.t[0] + start_up
    if not np.any(sel):
        raise ValueError(
            f"the log is {est.t[-1] - est.t[0]:.3g} s long, not longer than the start-up period left out of the "
            f"error metrics ({start_up:g} s); use a longer log or a shorter start_up"
        )
    ts = est.t[sel]
    tol = 0.5 * float(np.median(np.diff(est.t))) if len(est.t) > 1 else 0.0
    t0, t1 = (float(truth.t[0]), float(truth.t[-1])) if len(truth.t) else (math.nan, math.nan)
    inside = (ts >= t0 - tol) & (ts <= t1 + tol)
    coverage = float(inside.mean())
    span = f"the truth spans {t0:.6g} to {t1:.6g} s, the scored estimate {ts[0]:.6g} to {ts[-1]:.6g} s"
    if coverage < min_coverage:
        raise ValueError(f"the truth covers {coverage:.0%} of the scored interval ({span}): not the same run or "
                         f"clock? (at least {min_coverage:.0%} needed)")
    if coverage < 1.0:
        log.warning("the truth covers %.1f%% of the scored interval (%s); scoring the covered part only",
                    100 * coverage, span)
    ts = ts[inside]
    rms, mx = {}, {}
    for n in names:
        tr = np.interp(ts, truth.t, truth[n])
        e = est[n][sel][inside] - tr
        e = e[np.isfinite(e)]
        rms[n] = float(np.sqrt(np.mean(e**2))) if e.size else float("nan")
        mx[n] = float(np.max(np.abs(e))) if e.size else float("nan")
    return {"rms_error": rms, "max_error": mx, "truth_coverage": coverage}


# ------------------------------------------------------------------------------------------ runs
@dataclass
class Outcome:
    """The observer run on one log, with everything a result file records."""

    estimate: Estimate
    metrics: dict | None
    bound: dict | None
    summary: dict


#: what :func:`observe_run` keeps of the filtered record (``keep``)
KEEP = ("all", "physical", "summary")


def observe_run(mech: Mechanism, run, config: ObserverConfig | None = None, *, with_bound: bool | str = True,
                observer: Observer | None = None, report=None, smooth: bool = False, keep: str = "all",
                sink=None, log_check=None) -> Outcome:
    """Run the observer on a run folder's log (:class:`exuflex.runs.Run`) and score it against its truth
    (``smooth``: the RTS-smoothed estimates; the filter's errors are then in ``filtered_rms_error``).

    The log is checked first (:func:`exuflex.validate.check_run`): its clock, per-channel availability and rates.
    The filter steps by each sample's own time stamp (jitter and drift within the documented tolerance need no
    grid). The bound is the one for this log (:func:`bound_track`: the posterior Cramer-Rao bound along its truth,
    else along the plan, on its times, torques and sampled channels; with ``smooth`` the smoothed bound), its RMS
    over the samples :func:`metrics` scores (``bound_rms``, ``ratio_to_bound``; with ``smooth`` also
    ``filtered_bound_rms`` and ``filtered_ratio_to_bound`` for the filter's errors); it is computed before
    filtering, and an unobservable channel set is reported at once. ``with_bound``: True (default) the bound along
    the truth or the plan; ``"truth"`` only along a truth (a log without one: the observability test alone, no
    bound: along the plan the recursion costs about as much as the filter and scores nothing); False neither.
    ``report``: a callable taking one-line stage messages (the CLI prints them on stderr). ``log_check``: the
    log's check if the caller made it already (:func:`exuflex.validate.check_run` with the observer's channels and
    sample interval; the command line checks a log before it builds the model).

    Memory: besides the log, ``keep`` says what the outcome holds of the filtered record, per sample:

    - ``"all"`` (default): the filter's whole record (:class:`~exuflex.observer.ekf.EstimationResult`: estimates, covariances as
      the filter's ``store_P`` says, innovations, NIS) and the physical estimates;
    - ``"physical"``: the physical estimates (8 bytes a column) and the NIS sequence (10 bytes);
    - ``"summary"``: the NIS sequence, and the physical estimates only where a truth is scored.

    Except with ``"all"`` or ``smooth`` (the smoother needs the whole record) the log is filtered
    :data:`exuflex.observer.session.CHUNK_ROWS` rows at a time (:func:`exuflex.observer.session.estimate_chunks`, the same numbers) and nothing else grows with it.
    ``sink``: called with each :class:`exuflex.observer.session.EstimateChunk` as it is filtered (the smoothed run: once, with the smoothed
    physical estimates), e.g. :class:`.output.EstimatesWriter` streaming ``estimates.csv``.
    """
    from ..validate import check_mechanism_argument, check_run

    if keep not in KEEP:
        raise ValueError(f"keep must be one of {', '.join(KEEP)}, got {keep!r}")
    if with_bound not in (True, False, "truth"):
        raise ValueError(f"with_bound must be True, False or 'truth', got {with_bound!r}")
    check_mechanism_argument(mech)
    check_arguments(config=config, observer=observer)
    if not hasattr(run, "sensors") or not hasattr(run, "meta"):
        from ..errors import UsageError

        hint = " (a path: read it with exuflex.runs.read_run(path) first)" if isinstance(run, (str, bytes)) or \
            hasattr(run, "__fspath__") else ""
        raise UsageError(f"run: expected an exuflex.runs.Run, got {type(run).__name__}{hint}")
    say = report or (lambda msg: log.info("%s", msg))
    config = config or ObserverConfig.for_model(mech)
    obs = observer or make_observer(mech, config)
    obs.use_input_hold(*input_hold_of(run.meta, str(run.path)))  # the log's torques between two samples
    if log_check is None:
        log_check = check_run(mech, run, obs.channels, dt=obs.ekf.dt)
    elif set(log_check.channel_rate_hz) != set(obs.channels) or log_check.dt != obs.ekf.dt:
        raise ValueError(f"log_check: made for channels {sorted(log_check.channel_rate_hz)} at {log_check.dt} s, "
                         f"the observer has {sorted(obs.channels)} at {obs.ekf.dt} s")
    say(f"channels: {log_check.availability()}; log interval {log_check.interval_s * 1e3:.4g} ms"
        + (f", clock {log_check.clock_drift_ppm:+.1f} ppm, jitter up to {log_check.jitter_max_s * 1e6:.3g} us"
           if log_check.jitter_max_s > 1e-6 * log_check.dt else ""))
    for w in log_check.warnings:
        say(f"note: {w}")
    S = run.sensors
    motors = run.motors or mech.motor_names
    # a torque not sampled at a time: hold the last value (documented in docs/run_format.md)
    U = LogColumns.of(S, motors, hold=True)
    Y = LogColumns.of(S, obs.channels)
    bnd, unobservable, track = None, None, None
    if with_bound:  # before filtering: an unobservable channel set is reported at once
        try:
            check_observable(obs, log_check)
        except UnobservableError as exc:
            unobservable = str(exc)
            say(f"warning: no bound: {exc}")
    span = float(S.t[-1] - S.t[0]) if len(S.t) > 1 else 0.0
    start_up = config.start_up if span > config.start_up else 0.5 * span
    if start_up != config.start_up:
        log.warning("log is %.3g s long: error metrics from %.3g s instead of the %.3g s start-up", span, start_up,
                    config.start_up)
    if run.truth is not None:  # before filtering: a truth of another run or clock is refused at once
        try:
            metrics(Signals(S.t, (), np.empty((len(S.t), 0))), run.truth, start_up)
        except ValueError as exc:
            from ..errors import LogFormatError

            raise LogFormatError(f"{Path(run.path) / 'truth.csv'}: {exc}") from None
    if with_bound and unobservable is None and (with_bound is True or run.truth is not None):
        track, along = bound_track(obs, S.t, U, _Sampled(S, obs.channels), truth=run.truth, smooth=smooth)
        scored = _scored(S.t, start_up, None if run.truth is None else run.truth.t)
        names = physical_names(mech)
        bnd = dict(zip(names, map(float, track.rms(scored, smoothed=smooth)), strict=True))
        say(f"bound for this log ({_bound_kind(along, smooth)}): " + ", ".join(f"{k} {v:.3g}" for k, v in bnd.items()))
    say(f"filtering {len(S.t)} samples" + (" (and smoothing)" if smooth else ""))
    if keep == "all" or smooth:
        est = estimate(obs, S.t, U[:], Y[:], smooth=smooth)
        last = last_state(est)
        if sink is not None:
            sink(EstimateChunk(0, est.result, est.physical, est.wall_s))
    else:
        est, last = _estimate_kept(obs, S.t, U, Y, keep == "physical" or run.truth is not None, sink)
    met = metrics(est.physical, run.truth, start_up) if run.truth is not None else None
    res = est.result
    summary = {
        "model": mech.name,
        "model_file": mech.source,
        "run": str(run.path),
        "channels": list(obs.channels),
        "channels_used": [c for c in obs.channels if log_check.channel_rate_hz.get(c, 0) > 0],
        "reduced_ndof": obs.info["reduced_ndof"],
        "config": config.as_dict(),
        "nis_mean": res.mean_nis()[0],
        "nis_expected": res.mean_nis()[1],
        "n_updates": res.n_updates,
        "n_missing": res.n_missing,
        # diverged: the estimates became non-finite (the filter's covariance test can only flag inconsistency)
        "diverged": bool(res.nonfinite),
        "diverged_at": res.diverged_at if res.nonfinite else None,
        # (an estimator that reports its NIS test through ``diverged`` without non-finite values: the UKF)
        "nis_inconsistent": bool(res.nis_flagged or (res.diverged and not res.nonfinite)
                                 or nis_whole_log_flag(*res.mean_nis(), res.n_updates)),
        "nis_whole_log_flag": nis_whole_log_flag(*res.mean_nis(), res.n_updates),
        "nis_flagged_at": res.nis_flagged_at if res.nis_flagged else (
            res.diverged_at if res.diverged and not res.nonfinite else None),
        "flagged_intervals": [list(iv) for iv in res.flagged_intervals],
        "channel_faults": [dict(f) for f in res.channel_faults],
        "n_rejected": dict(res.n_rejected),
        "wall_s": est.wall_s,
        "real_time_factor": est.real_time_factor,
        "basis_s": obs.basis_s,
        "log_check": log_check.as_dict(),
        "metrics_from_s": start_up,
    }
    summary["estimator"] = config.estimator
    summary["smoothed"] = bool(smooth)
    if obs.ekf.model is obs.model and obs.model.method == "cached":
        summary["held_model_error"] = held_error_summary(obs.model)
    summary.update(extra_states(obs.ekf.model, *last))
    if met is not None:
        summary.update(met)
        if est.filtered_physical is not None:
            summary["filtered_rms_error"] = metrics(est.filtered_physical, run.truth, start_up)["rms_error"]
    if unobservable:
        summary["unobservable"] = unobservable
    # the ERLS model's validity along the motion (links turning fast against their clamped frequency; logged)
    from ..erls.validity import signal_warnings

    motion = run.truth if run.truth is not None else est.physical
    summary["validity"] = [w.as_dict() for w in signal_warnings(mech, motion)] if motion is not None else []
    if bnd is not None:
        summary["bound_rms"] = bnd
        summary["bound_kind"] = _bound_kind(along, smooth)
        summary["bound_for"] = {"interval_s": log_check.interval_s, "channel_rate_hz": log_check.channel_rate_hz,
                                "along": along, "smoothed": bool(smooth), "scored_from_s": start_up}
        summary["bound_wall_s"] = track.wall_s
        if smooth:
            summary["filtered_bound_rms"] = dict(zip(bnd, map(float, track.rms(scored)), strict=True))
        if met is not None:
            summary["ratio_to_bound"] = {k: met["rms_error"][k] / bnd[k] for k in met["rms_error"] if bnd.get(k)}
            if smooth and "filtered_rms_error" in summary:
                fb = summary["filtered_bound_rms"]
                summary["filtered_ratio_to_bound"] = {k: v / fb[k] for k, v in summary["filtered_rms_error"].items()
                                                      if fb.get(k)}
    return Outcome(est, met, bnd, summary)


def _estimate_kept(obs: Observer, t: np.ndarray, U, Y, keep_physical: bool, sink) -> tuple[Estimate, tuple]:
    """The record filtered in chunks (:func:`exuflex.observer.session.estimate_chunks`), of which only the NIS sequence (and with
    ``keep_physical`` the physical estimates) is kept; each chunk goes to ``sink``. Returns the estimate and the
    last sample's state and variances (None if the filter stores no covariance)."""
    n = len(t)
    nis = np.empty(n)
    dof = np.empty(n, dtype=np.int16)  # a count of channels
    names = physical_names(obs.mech)
    phys = np.empty((n, len(names))) if keep_physical else None
    nominal = None  # the nominal payload's probability per sample, where reported
    wall = 0.0
    final = (np.full(obs.ekf.nx, np.nan), None, None)
    for ch in estimate_chunks(obs, t, U, Y, innovations=False):
        r = ch.result
        a, b = ch.start, ch.start + len(r.t)
        nis[a:b] = r.nis
        dof[a:b] = r.nis_dof
        if phys is not None:
            phys[a:b] = ch.physical.data
        if r.nominal_p is not None:
            nominal = np.empty(n) if nominal is None else nominal
            nominal[a:b] = r.nominal_p
        wall += ch.wall_s
        if sink is not None:
            sink(ch)
        if b > a:
            final = (r.x_hat[-1].copy(), None if r.P is None else r.P_diag[-1].copy(),
                     None if r.nominal_p is None else float(r.nominal_p[-1]))
        # the run-level counters, flags and faults so far, without the chunk's arrays (one chunk alive at a time)
        last = replace(r, x_hat=None, P=None, innovations=None, S=None, P_theta=None, nominal_p=None)
        del ch, r
    res = replace(last, t=t, nis=nis, nis_dof=dof, wall_s=wall, nominal_p=nominal)
    span = float(t[-1] - t[0]) if n > 1 else 0.0
    est = Estimate(res, None if phys is None else Signals(t, names, phys, physical_units(obs.mech)), wall,
                   span / wall if wall > 0 else float("inf"))
    return est, final

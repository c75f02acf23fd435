"""Benchmark: observer speed on the paper's manoeuvre (reduced vs full order), basis build, ground truth.

One run on one core (the process is pinned to one CPU where the OS allows it; BLAS is single-threaded,
see :mod:`exuflex`):

1. plan the manoeuvre and its rigid computed torques (:func:`exuflex.truth.crossval.manoeuvre_table`);
2. simulate the Exudyn ground truth once (timed: ``truth_s``) and make the noisy 500 Hz log from it
   (:func:`exuflex.measure.measure`, fixed seed);
3. the reduced observer (:func:`exuflex.observer.session.make_observer` with the default
   :class:`~exuflex.observer.session.ObserverConfig`; the Craig-Bampton basis build is timed: ``basis_s``)
   filters the log ``repeat`` times (default 5, each from the prior) as ``exuflex observe`` does, through
   ``ekf.run`` (wall time and real-time factor), and ``repeat`` times sample by sample through ``ekf.step`` as
   a real-time loop would call it (``online``: each call timed, latency percentiles); the median runs' figures
   are reported, as the machine's speed drifts between runs of a fraction of a second;
4. the reduced observer's exact reference (``method="rk4"``: the configuration evaluated at every RK4 stage;
   not timed): the fast path's estimates against it, per physical quantity, as the RMS of
   their difference over the RMS estimation error (``reference``: the speed-ups' accuracy cost, which must
   be far below 1);
5. the same for the full-order observer (:class:`exuflex.observer.full.FullObserverModel`, RK4 at the same
   0.1 ms inside every 2 ms interval).

Wall times exclude planning and log generation. The real-time factor is simulated time / filter wall time
(> 1: faster than real time); ``cpu_s`` and ``real_time_factor_cpu`` use the thread's CPU time instead,
which a busy machine inflates less (on an idle core the two agree). Both observers' RMS errors of q against the truth are reported as a sanity
check that the timed filters work.
"""

from __future__ import annotations

import logging
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = ["DEFAULT_MODEL", "QUICK_DURATION", "run_bench", "time_filter", "time_run"]

log = logging.getLogger(__name__)

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "models" / "sixbar.toml"
QUICK_DURATION = 0.2


def _pin_one_core() -> tuple[int | None, set | None]:
    """Pin this process to one CPU (the lowest allowed); returns (cpu, previous affinity)."""
    if not hasattr(os, "sched_setaffinity"):
        return None, None
    try:
        old = os.sched_getaffinity(0)
        cpu = min(old)
        os.sched_setaffinity(0, {cpu})
        return cpu, old
    except OSError as exc:  # pragma: no cover - container restrictions
        log.warning("could not pin the benchmark to one CPU: %s", exc)
        return None, None


def time_filter(ekf, t, U, Y) -> dict:
    """Run ``ekf.step`` over a log, timing every call. Returns wall time, latencies and the estimates."""
    n = len(t)
    lat = np.empty(n)
    X = np.empty((n, ekf.nx))
    ekf.reset()
    err = None
    c_start = time.thread_time()
    t_start = time.perf_counter()
    k = 0
    try:
        for k in range(n):
            c0 = time.perf_counter()
            X[k] = ekf.step(t[k], U[k], Y[k])
            lat[k] = time.perf_counter() - c0
    except (FloatingPointError, RuntimeError, np.linalg.LinAlgError) as exc:
        err = f"{type(exc).__name__} at t = {t[k]:.4g} s: {exc}"
        log.warning("filter failed: %s", err)
        X[k:] = np.nan
        lat = lat[:k]
        n = k
    out = _timing(time.perf_counter() - t_start, time.thread_time() - c_start, t, n, err)
    out.update({
        "p50_update_ms": float(np.percentile(lat, 50) * 1e3) if len(lat) else float("nan"),
        "p99_update_ms": float(np.percentile(lat, 99) * 1e3) if len(lat) else float("nan"),
        "max_update_ms": float(np.max(lat) * 1e3) if len(lat) else float("nan"),
    })
    return {"timing": out, "X": X}


def time_run(ekf, t, U, Y) -> dict:
    """Filter a log with ``ekf.run`` (from the prior), timed as a whole. Returns wall and CPU time and the
    estimates, as :func:`time_filter` does but without per-update latencies."""
    n = len(t)
    err = None
    c_start = time.thread_time()
    t_start = time.perf_counter()
    try:
        X = ekf.run(t, U, Y).x_hat
    except (FloatingPointError, RuntimeError, np.linalg.LinAlgError) as exc:
        err = f"{type(exc).__name__}: {exc}"
        log.warning("filter failed: %s", err)
        X = np.full((n, ekf.nx), np.nan)
    return {"timing": _timing(time.perf_counter() - t_start, time.thread_time() - c_start, t, n, err), "X": X}


def _timing(wall: float, cpu: float, t, n: int, err: str | None) -> dict:
    """Wall and CPU time of a filter over samples ``t[:n]`` with their real-time factors."""
    span = float(t[n - 1] - t[0]) if n > 1 else 0.0
    return {
        "wall_s": wall,
        "simulated_s": span,
        "real_time_factor": span / wall if wall > 0 else float("inf"),
        "cpu_s": cpu,
        "real_time_factor_cpu": span / cpu if cpu > 0 else float("inf"),
        "n_updates": int(n),
        "failed": err,
    }


def _median_run(runs: list[dict]) -> tuple[dict, dict]:
    """The run of median wall time, and its timing with the spread over the runs added."""
    walls = [r["timing"]["wall_s"] for r in runs]
    med = runs[int(np.argsort(walls)[len(walls) // 2])]
    timing = dict(med["timing"])
    timing["repeats"] = len(runs)
    timing["wall_s_runs"] = walls
    timing["real_time_factor_best"] = timing["simulated_s"] / min(walls) if min(walls) > 0 else float("inf")
    return med, timing


def _q_rms(mech, t, Q, truth, start_up: float) -> float:
    sel = (t >= t[0] + start_up) & np.all(np.isfinite(Q), axis=1)
    if not sel.any():
        return float("nan")
    err = [Q[sel, j] - np.interp(t[sel], truth.t, truth[n]) for j, n in enumerate(mech.coordinate_names)]
    return float(np.max(np.sqrt(np.mean(np.square(err), axis=1))))


def run_bench(
    model: str | Path = DEFAULT_MODEL,
    *,
    quick: bool = False,
    duration: float | None = None,
    h: float = 1e-4,
    seed: int = 1,
    full: bool = True,
    reference: bool = True,
    repeat: int = 5,
    pin: bool = True,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Measure the observers, the basis build and the ground truth; returns the JSON-able results.

    Parameters
    ----------
    model : model file (default the six-bar).
    quick : a 0.2 s manoeuvre (for tests) instead of the model's full manoeuvre.
    duration : simulated time (s), overrides ``quick``.
    h : RK4 sub-step of both observers and step of the truth (s).
    seed : measurement-noise seed.
    full : also run the full-order observer (the slow part: about 100x the reduced one).
    reference : also run the reduced observer's reference path and compare the estimates.
    repeat : how many times the reduced observer filters the log; its figures are those of the median run
        (``wall_s_runs`` lists all, ``real_time_factor_best`` is the fastest).
    pin : pin the process to one CPU while measuring (restored afterwards).
    progress : called with a short message before each stage.
    """
    from .groundtruth import simulate_truth
    from .truth.crossval import manoeuvre_table
    from .measure import measure
    from .mechanism import load_mechanism
    from .observer.ekf import MultirateEKF
    from .observer.session import ObserverConfig, _noise_std, estimate, make_observer
    from .runs import held_torques
    from .scoring.run import metrics
    from .sensors import monotonic_record, sensor_channels, tip_dof_names, true_states

    say = progress or (lambda msg: log.info("%s", msg))
    mech = load_mechanism(model)
    if mech.manoeuvre is None:
        raise ValueError(f"{model}: the benchmark needs a model with a [manoeuvre]")
    if duration is None:
        duration = QUICK_DURATION if quick else float(mech.manoeuvre.duration)
    duration = float(duration)
    dt = 1.0 / mech.sample_rate_hz
    cpu, old_affinity = _pin_one_core() if pin else (None, None)
    try:
        say(f"plan {duration:g} s manoeuvre")
        t0 = time.perf_counter()
        t_tab, tau, q0, _qd0 = manoeuvre_table(mech, duration, h)
        plan_s = time.perf_counter() - t0

        say("Exudyn truth")
        t0 = time.perf_counter()
        c0 = time.thread_time()
        rec = simulate_truth(mech, t_tab, tau, duration, h=h, output_dt=dt, q0=q0)
        truth_s = time.perf_counter() - t0
        truth_cpu_s = time.thread_time() - c0
        rec = monotonic_record(rec)
        truth = true_states(mech, rec)
        meas = measure(mech, sensor_channels(mech, rec), t_tab, tau, seed=seed, t_end=duration)
        S = meas.signals
        U = held_torques(S.select(mech.motor_names).data)
        start_up = min(0.3, duration / 4)

        say("reduced observer")
        config = ObserverConfig.for_model(mech)
        t0 = time.perf_counter()
        obs = make_observer(mech, config)
        build_s = time.perf_counter() - t0
        Y = S.select(obs.channels).data
        # the whole log filtered `repeat` times from the prior (the same estimates each time), alternately
        # offline (ekf.run) and online (ekf.step per sample): the median wall times are the figures, as the
        # machine's speed drifts between runs of a fraction of a second
        runs, online_runs = [], []
        for _ in range(max(1, repeat)):
            runs.append(time_run(obs.ekf, S.t, U, Y))
            online_runs.append(time_filter(obs.ekf, S.t, U, Y))
        red, reduced = _median_run(runs)
        online = _median_run(online_runs)[1]
        for key in ("p50_update_ms", "p99_update_ms", "max_update_ms"):
            reduced[key] = online[key]  # latencies: per sample, from the online runs
        reduced["online"] = online
        est = obs.physical(S.t, red["X"])
        q_red = np.column_stack([est[n] for n in mech.coordinate_names])
        if not np.array_equal(red["X"], online_runs[0]["X"], equal_nan=True):
            reduced["failed"] = reduced["failed"] or "the online and offline estimates differ"
        reduced.update(
            {
                "ndof": int(obs.model.r),
                "n_states": int(obs.model.nx),
                "method": config.method,
                "build_s": build_s,
                "q_rms_error_rad": _q_rms(mech, S.t, q_red, truth, start_up),
            }
        )
        ex, ey = tip_dof_names(mech)
        tip_truth = np.sqrt(np.mean(truth[ex] ** 2 + truth[ey] ** 2))
        tip_err = np.sqrt(
            np.nanmean(
                (est[ex] - np.interp(S.t, truth.t, truth[ex])) ** 2
                + (est[ey] - np.interp(S.t, truth.t, truth[ey])) ** 2
            )
        )
        reduced["tip_nrms"] = float(tip_err / tip_truth) if tip_truth > 0 else float("nan")
        # per run (the repeats are identical runs from the prior)
        reduced["evaluations"] = int(getattr(obs.model, "n_refresh", 0)) // (2 * len(runs))
        reduced["step_map_rebuilds"] = int(getattr(obs.model, "n_remap", 0)) // (2 * len(runs))

        result = {
            "model": mech.name,
            "duration_s": duration,
            "h_s": h,
            "dt_s": dt,
            "quick": bool(quick),
            "reduced": reduced,
            "basis_s": float(obs.basis_s),
            "truth_s": truth_s,
            "truth_real_time_factor": duration / truth_s,
            "truth_cpu_s": truth_cpu_s,
            "plan_s": plan_s,
        }

        if reference and not red["timing"]["failed"]:
            say("reference path of the reduced observer")
            ref_obs = make_observer(mech, ObserverConfig(method="rk4"), cb=obs.model.rm.cb)
            ref = estimate(ref_obs, S.t, U, Y)
            names = [n for n in ref.physical.names if n in truth]
            err = metrics(ref.physical, truth, start_up=start_up, names=names)["rms_error"]
            diff = metrics(est, ref.physical, start_up=start_up, names=names)["rms_error"]
            ratio = {n: diff[n] / err[n] if err[n] > 0 else float("nan") for n in names}
            worst = max(ratio, key=lambda n: ratio[n])
            result["reference"] = {
                "method": "rk4",
                "wall_s": ref.wall_s,
                "rms_difference": diff,
                "rms_error": err,
                "difference_over_error": ratio,
                "worst": worst,
                "worst_ratio": ratio[worst],
            }
        else:
            result["reference"] = None

        if full:
            from .erls.model import ErlsModel
            from .observer.full import FullObserverModel

            say("full-order observer")
            t0 = time.perf_counter()
            fm = FullObserverModel(ErlsModel(mech), h=h)
            x0 = fm.initial_state(q0)
            n, nq = fm.n, fm.nq
            P0 = np.empty(fm.nx)
            P0[:nq] = config.q0_std**2
            P0[nq:n] = config.elastic0_std**2
            P0[n : n + nq] = config.qd0_std**2
            P0[n + nq :] = config.elastic_rate0_std**2
            ekf = MultirateEKF(fm, obs.channels, _noise_std(mech, obs.channels), x0, P0, dt=dt)
            fbuild = time.perf_counter() - t0
            amp, hlam = fm.rk4_stability(x0)
            fr = time_filter(ekf, S.t, U, Y)
            X = fr["X"]
            fullr = dict(fr["timing"])
            fullr.update(
                {
                    "n_states": int(fm.nx),
                    "build_s": fbuild,
                    "rk4_amplification_at_start": amp,  # > 1: RK4 unstable at h
                    "rk4_max_h_lambda_at_start": hlam,  # RK4's limit on the imaginary axis: 2.83
                    "q_rms_error_rad": _q_rms(mech, S.t, X[:, :nq], truth, start_up),
                }
            )
            result["full"] = fullr
            result["speedup_reduced_vs_full"] = fullr["wall_s"] / reduced["wall_s"]
        else:
            result["full"] = None
            result["speedup_reduced_vs_full"] = None
        result["machine"] = {
            "cpu_pinned": cpu,
            "cpus": os.cpu_count(),
            "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
            "python": platform.python_version(),
            "processor": platform.processor() or platform.machine(),
        }
        return result
    finally:
        if old_affinity is not None:
            os.sched_setaffinity(0, old_affinity)

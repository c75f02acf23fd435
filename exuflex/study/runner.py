"""Model-mismatch studies: the truth with changed parameters, the observer with the nominal model.

A study is a list of *levels* (a payload scale and/or parameter overrides applied to the truth only) and
``runs`` noise realisations per level. For each level the truth (manoeuvre, computed torque from the
*nominal* model, truth simulation with the changed parameters) is simulated once and cached on disk; each
run then draws seeded Table-3 noise on it (:func:`exuflex.measure.measure`, ``seed = base_seed + run``) and
runs the nominal observer. Per run: mean, standard deviation (eq. 21's per-run terms), RMS and maximum of the
absolute error of every estimated quantity after ``start_up``, NIS, divergence, wall time. Per level: the
paper's eq. 21 statistics mu and sigma (the run averages of those per-run terms, over the non-diverged runs).

The quantities are the observer's physical estimates (joint angles and rates, the tip *elastic* displacement
and its rate, e.g. ``x25 y26 dx25 dy26``) and the *absolute* tip position and velocity ``tip_x tip_y dtip_x
dtip_y`` (rigid tip point at q plus the elastic displacement, :func:`exuflex.sensors.absolute_tip`, computed
alike from the true and the estimated states with the nominal geometry): the paper's Fig. 11 caption, "the
linear displacements and velocities of the tip coordinates", reads either way (see :data:`TIP_READINGS`).

Layout of the output folder (everything written atomically; a study restarted with the same arguments skips
every finished run and every cached truth):

- ``truth/<level key>/truth.npz`` and ``level.json``: the cached truth of a level;
- ``runs/<level key>/run_NNNN.json``: one finished run (with the hash of all settings that determine it);
- ``results.csv`` (one row per run), ``summary.json`` (eq. 21 per level, settings, model and its sha256,
  seeds, package versions, wall time). The figure (``fig_payload.png`` / ``fig_sweep.png``) is drawn from the
  summary by :func:`exuflex.plots.study_figure` (the command line does it; the library does not plot).

A slenderness study (:func:`slenderness_levels`, ``exuflex study slenderness``) tests beam theory rather than a
parameter: each level changes a link's shape, the truth is that geometry as solid FFRF bodies (``StudySpec.beam``),
the observer is built on each level's own model (``observer_model = "level"``: the drive and observer keys then
follow the level), and each run is also scored against its posterior Cramer-Rao bound along the truth
(``with_bound``: ``bound_rms``, ``ratio_to_bound`` per run; per level ``ratio_to_bound_mean`` and the worst
quantity's ratio ``worst_ratio``).

Execution goes through a :class:`concurrent.futures.Executor`: in-process (``workers=1``), a
``ProcessPoolExecutor`` (``workers > 1``) or a Dask cluster (``scheduler="tcp://..."``). Workers get all their
data in the task (no shared file system needed) and build the observer once per process.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import datetime as _dt
import fcntl
import hashlib
import io
import json
import logging
import math
import os
import socket
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import _compile
from ..errors import UsageError
from ..mechanism import Mechanism, ModelFileError, load_mechanism
from ..observer.session import AUGMENTED_ESTIMATORS, ObserverConfig
from ..runs import (
    atomic_write_bytes,
    atomic_write_text,
    dump_json,
    file_sha256,
    output_folder,
    package_versions,
)
from ..sensors import ABSOLUTE_TIP_NAMES, Signals
from ..truth import Drive, TruthRecord, plan_drive, simulate
from .overrides import OverrideError, apply_overrides

__all__ = [
    "FORMAT",
    "Level",
    "StudyResult",
    "StudySpec",
    "estimator_figure_rows",
    "make_executor",
    "payload_levels",
    "run_estimator_studies",
    "run_study",
    "slenderness_levels",
    "sweep_levels",
]

log = logging.getLogger(__name__)

FORMAT = "exuflex-study/1"
TIP_QUANTITIES = ("x25", "y26", "dx25", "dy26")  # the six-bar's tip elastic displacement and rate
ABS_TIP_QUANTITIES = ABSOLUTE_TIP_NAMES  # tip_x tip_y dtip_x dtip_y: absolute tip position and velocity
STATS_VERSION = "abs-tip/1"  # the set of per-run statistics; part of the run hash (older run files are redone)
TIP_READINGS = (
    "The paper's Fig. 11 caption ('the linear displacements and velocities of the tip coordinates') reads two "
    "ways: the tip ELASTIC displacement and rate (the ERLS elastic dofs of the tip node, e.g. x25 y26 dx25 dy26: "
    "the tip's deflection from the rigid linkage at the same q), or the ABSOLUTE tip position and velocity "
    "(tip_x tip_y dtip_x dtip_y: rigid tip point at q plus the elastic displacement, true q and elastic states "
    "for the truth, estimated ones for the estimate, nominal geometry for both), whose error the joint-angle "
    "errors drive."
)


# ------------------------------------------------------------------------------------------ spec
@dataclass(frozen=True)
class Level:
    """One mismatch level: what the truth changes (the observer keeps the nominal model).

    label : shown in tables; value : the x-axis value (payload increase in %, or the swept value);
    overrides : ``(field path, value)`` pairs (:func:`exuflex.study.overrides.apply_overrides`);
    payload_scale : multiplies the truth's tip payload (after the overrides).
    """

    label: str
    value: Any
    overrides: tuple[tuple[str, Any], ...] = ()
    payload_scale: float = 1.0

    def as_dict(self) -> dict:
        return {"label": self.label, "value": self.value, "overrides": [list(o) for o in self.overrides],
                "payload_scale": self.payload_scale}


def payload_levels(increases_pct: Sequence[float]) -> tuple[Level, ...]:
    """Levels of the paper's Fig. 11: payload increase in % over nominal (scale ``1 + pct / 100``)."""
    out = []
    pcts = []
    for p in increases_pct:
        try:
            p = float(p)
        except (TypeError, ValueError):
            raise UsageError(f"levels (--levels): expected payload increases in %, got {p!r}") from None
        if not math.isfinite(p):
            raise UsageError(f"levels (--levels): expected finite payload increases in %, got {p!r}")
        if not 1 + p / 100 > 0:
            raise UsageError(f"levels (--levels): payload increase {p:g} % leaves no payload (scale {1 + p / 100:g}); "
                             "expected increases above -100 %")
        if p in pcts:
            raise UsageError(f"levels (--levels): the level {p:g} % is given twice; expected each level once")
        pcts.append(p)
        out.append(Level(f"{p:+g} %", p, (), 1.0 + p / 100.0))
    if not out:
        raise UsageError("levels (--levels): expected at least one payload increase in %, e.g. 0,25,50")
    return tuple(out)


def sweep_levels(sets: Sequence[tuple[str, Sequence[Any]]]) -> tuple[Level, ...]:
    """Levels of a sweep: one ``(field, values)`` gives one level per value; several fields are combined as a
    full grid (every combination), the first field varying slowest."""
    if not sets:
        raise UsageError("sets (--set): a sweep needs at least one --set FIELD=V1,V2,...")
    fields = [f for f, _ in sets]
    for fld, vals in sets:
        if fields.count(fld) > 1:
            raise UsageError(f"--set {fld}: the field is set twice; expected each field once (its values in one list)")
        seen = [str(v) for v in vals]
        dup = sorted({v for v in seen if seen.count(v) > 1})
        if dup:
            raise UsageError(f"--set {fld}: the value(s) {', '.join(dup)} given twice; expected each level once")
    combos: list[tuple[tuple[str, Any], ...]] = [()]
    for fld, vals in sets:
        combos = [c + ((fld, v),) for c in combos for v in vals]
    out = []
    for c in combos:
        label = ", ".join(f"{f}={v}" for f, v in c)
        value = c[0][1] if len(c) == 1 else label
        out.append(Level(label, value, c, 1.0))
    return tuple(out)


SLENDERNESS_KEEPS = ("dynamics", "material")


def slenderness_levels(mech: Mechanism, link: str, ratios: Sequence[float], mesh_scale: float | None = None,
                       keep: str = "dynamics") -> tuple[Level, ...]:
    """Levels of a beam-theory study: link ``link``'s slenderness ``L / d`` set to each of ``ratios`` by its
    diameter (a round section, ``d = L / ratio``; its length and everything else kept).

    ``keep``: ``"dynamics"`` (default) also sets the link's ``E`` and ``rho`` so that its bending stiffness ``EI``
    and mass per length ``rho A`` stay the nominal ones (``E ~ d^-4``, ``rho ~ d^-2``; Poisson's ratio kept): an
    Euler-Bernoulli model of the link is then the same at every level (up to its rotary inertia and axial
    stiffness), its first modes stay in the band and the motors' torques unchanged, and what changes is the
    solid's shape, which beam theory leaves out (shear, the section's rotary inertia and warping). ``"material"``
    keeps ``E`` and ``rho``: the link grows heavier (``d^2``) and stiffer (``d^4``), its modes leave the band and
    the motors need torques growing with ``d^2``. ``mesh_scale``: the FFRF truth's solid mesh size on that link
    as a multiple of ``d`` (default: the truth's own default)."""
    names = [lk.name for lk in mech.links]
    if link not in names:
        raise UsageError(f"link (--link): {link!r} is not a link of {mech.name}; expected one of {', '.join(names)}")
    lk = mech.link(link)
    if lk.section.shape != "round":
        raise UsageError(f"link (--link): {link!r} has a {lk.section.shape or 'A-and-I'} section; the slenderness "
                         "study scales a round section's diameter (expected shape round)")
    if keep not in SLENDERNESS_KEEPS:
        raise UsageError(f"keep (--keep): expected one of {', '.join(SLENDERNESS_KEEPS)}, got {keep!r}")
    if mesh_scale is not None and not (isinstance(mesh_scale, (int, float)) and mesh_scale > 0):
        raise UsageError(f"mesh_scale (--mesh-scale): expected a positive number, got {mesh_scale!r}")
    out, seen = [], []
    for r in ratios:
        try:
            r = float(r)
        except (TypeError, ValueError):
            raise UsageError(f"levels (--levels): expected slenderness ratios L/d, got {r!r}") from None
        if not (math.isfinite(r) and r > 1):
            raise UsageError(f"levels (--levels): slenderness L/d {r:g}; expected a finite ratio above 1")
        if r in seen:
            raise UsageError(f"levels (--levels): the level L/d = {r:g} is given twice; expected each level once")
        seen.append(r)
        d = lk.length / r
        ov = ((f"links.{link}.diameter", d),)
        if keep == "dynamics":
            f = lk.section.diameter / d
            ov += ((f"links.{link}.E", lk.material.E * f**4), (f"links.{link}.rho", lk.material.rho * f**2))
        if mesh_scale is not None:
            ov += ((f"links.{link}.mesh_size", mesh_scale * d),)
        try:
            apply_overrides(mech, ov)
        except OverrideError as exc:
            hint = (f"; keep=dynamics scales E with d^-4 and rho with d^-2 from the file's L/d = "
                    f"{lk.length / lk.section.diameter:g}: choose ratios nearer it, or --keep material"
                    if keep == "dynamics" else "")
            raise UsageError(f"levels (--levels): L/d = {r:g} on link {link!r}: {exc}{hint}") from None
        out.append(Level(f"L/d = {r:g}", r, ov, 1.0))
    if not out:
        raise UsageError("levels (--levels): expected at least one slenderness ratio L/d, e.g. 50,20,10,5,3")
    return tuple(out)


@dataclass(frozen=True)
class StudySpec:
    """Everything that determines a study's numbers (recorded in ``summary.json``)."""

    model: str
    levels: tuple[Level, ...]
    runs: int = 100
    base_seed: int = 0
    engine: str = "exudyn"
    duration: float | None = None  # None: the manoeuvre's
    h: float = 1e-4
    start_up: float | None = None  # None: min(observer.start_up, duration / 4)
    observer: ObserverConfig | None = None  # None: ObserverConfig.for_model(the nominal model)
    kind: str = "payload"
    beam: str = "ancf"  # the Exudyn truth's bodies (exuflex.truth.BEAMS)
    observer_model: str = "nominal"  # "nominal", or "level": the observer's model is each level's model
    with_bound: bool = False  # score each run against its posterior Cramer-Rao bound (ratio_to_bound)

    def settings(self, duration: float, start_up: float) -> dict:
        extra = {}  # non-default choices only (a study written before they existed resumes unchanged)
        if self.beam != "ancf":
            extra["beam"] = self.beam
        if self.observer_model != "nominal":
            extra["observer_model"] = "each level's model (the observer follows the level's geometry)"
        if self.with_bound:
            extra["bound"] = ("posterior Cramer-Rao bound of the observer's model along the level's truth, RMS after "
                              "start_up (ratio_to_bound = RMS error / bound, per run)")
        return {
            "kind": self.kind,
            "runs_per_level": self.runs,
            "base_seed": self.base_seed,
            "seeds": f"base_seed + run index ({self.base_seed} .. {self.base_seed + self.runs - 1}), same per level",
            "engine": self.engine,
            "duration_s": duration,
            "h_s": self.h,
            "start_up_s": start_up,
            "observer": None if self.observer is None else self.observer.as_dict(),
            "computed_torque_model": "rigid ERLS, nominal model (the controller's knowledge)",
            "observer_model": "nominal model",
            **extra,
        }


# ------------------------------------------------------------------------------------------ level truth
def _hash(obj: Any, n: int = 12) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:n]


def _sig_arrays(prefix: str, s: Signals) -> dict:
    return {f"{prefix}_t": s.t, f"{prefix}_data": s.data, f"{prefix}_names": np.array(s.names, dtype=str),
            f"{prefix}_units": np.array(s.units or ("",) * len(s.names), dtype=str)}


def _sig_from(z, prefix: str) -> Signals:
    return Signals(np.asarray(z[f"{prefix}_t"]), tuple(str(x) for x in z[f"{prefix}_names"]),
                   np.asarray(z[f"{prefix}_data"]), tuple(str(x) for x in z[f"{prefix}_units"]))


def _save_truth(path: Path, lt: TruthRecord) -> None:
    _atomic_npz(path, torque_t=lt.torque_t, torques=lt.torques, **_sig_arrays("clean", lt.clean),
                **_sig_arrays("truth", lt.truth))


def _atomic_npz(path: Path, **arrays) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def _load_truth(path: Path, timings: dict) -> TruthRecord:
    with np.load(path) as z:
        return TruthRecord(_sig_from(z, "clean"), _sig_from(z, "truth"), np.asarray(z["torque_t"]),
                          np.asarray(z["torques"]), timings)


def _hold_on_grid(lt: TruthRecord, rate: float, t_end: float) -> TruthRecord:
    """The torque table reduced to the measurement grid (the values :func:`measure` would read): keeps tasks
    small; ``measure`` gives bit-identical results on it."""
    k0 = int(np.ceil(lt.clean.t[0] * rate - 1e-6))
    t = np.arange(k0, int(np.floor(t_end * rate + 1e-6)) + 1) / rate
    tt = lt.torque_t
    dt_tab = np.min(np.diff(tt)) if len(tt) > 1 else 1.0
    i = np.clip(np.searchsorted(tt, t + 1e-6 * dt_tab, side="right") - 1, 0, len(tt) - 1)
    return TruthRecord(lt.clean, lt.truth, t, lt.torques[i], lt.timings)


def with_absolute_tip(nominal: Mechanism, lt: TruthRecord) -> TruthRecord:
    """The level truth with the absolute tip columns ``tip_x tip_y dtip_x dtip_y`` added to its true states
    (:func:`exuflex.sensors.absolute_tip` with the nominal geometry; computed once per level). Unchanged if the
    mechanism has no tip point, the truth lacks the tip elastic columns or already has the absolute ones."""
    from ..sensors import absolute_tip, tip_point, truth_names

    if tip_point(nominal) is None or any(n in lt.truth for n in ABS_TIP_QUANTITIES) or \
            any(n not in lt.truth for n in truth_names(nominal)):
        return lt
    tip = absolute_tip(nominal, lt.truth)
    return dataclasses.replace(lt, truth=lt.truth.hstack(tip))


def _cached_drive(path: Path, nominal: Mechanism, duration: float, h: float) -> Drive:
    if path.exists():
        try:
            with np.load(path) as z:
                return Drive(z["t"], z["tau"], z["q0"], z["qd0"], float(z["seconds"]))
        except (OSError, ValueError, KeyError) as exc:
            log.warning("%s unreadable (%s); planning again", path, exc)
    d = plan_drive(nominal, duration, h)
    _atomic_npz(path, t=d.t, tau=d.tau, q0=d.q0, qd0=d.qd0, seconds=d.seconds)
    return d


# ------------------------------------------------------------------------------------------ one run
@dataclass(frozen=True)
class RunTask:
    level_index: int
    level_key: str
    run: int
    seed: int
    run_hash: str
    observer_key: str
    nominal: Mechanism
    truth_mech: Mechanism
    level_truth: TruthRecord
    config: ObserverConfig
    start_up: float
    duration: float
    with_bound: bool = False


_OBSERVERS: dict[str, Any] = {}
_KINEMATICS: dict[str, Any] = {}
OBSERVER_RUNS = 0  # runs filtered in this process (tests count recomputations with it)


def _observer(key: str, mech: Mechanism, config: ObserverConfig):
    from ..observer.session import make_observer

    obs = _OBSERVERS.get(key)
    if obs is None:
        _OBSERVERS.clear()
        obs = _OBSERVERS[key] = make_observer(mech, config)
    return obs


def _kinematics(key: str, mech: Mechanism):
    """A closure solver of the nominal model for the absolute tip, kept per process (its own instance: the
    observer's solvers keep warm starts that must not depend on this evaluation)."""
    from ..erls.kinematics import Kinematics

    kin = _KINEMATICS.get(key)
    if kin is None:
        _KINEMATICS.clear()
        kin = _KINEMATICS[key] = Kinematics(mech)
    return kin


def _reset_observer(obs) -> None:
    """Restart the filter from its prior (which resets its model's caches too: the held configuration and its
    measurement rows would otherwise linearise the first update at the previous run's last configuration)."""
    obs.ekf.reset()


def _abs_error_stats(est: Signals, truth: Signals, start_up: float) -> dict:
    from ..scoring.stats import eq21_stats

    sel = est.t >= est.t[0] + start_up
    out = {"mean_abs": {}, "std_abs": {}, "rms": {}, "max": {}}
    for n in est.names:
        if n not in truth:
            continue
        tr = np.interp(est.t[sel], truth.t, truth[n])
        e = est[n][sel]
        ok = np.isfinite(e)
        if ok.sum() < 2 or not ok.all():
            for k in out:
                out[k][n] = float("nan")
            continue
        mu, sg = eq21_stats(tr[None, :], e[None, :])
        d = e - tr
        out["mean_abs"][n], out["std_abs"][n] = mu, sg
        out["rms"][n] = float(np.sqrt(np.mean(d**2)))
        out["max"][n] = float(np.max(np.abs(d)))
    return out


def _abs_tip_error_stats(task: RunTask, est: Signals, truth: Signals) -> dict | None:
    """eq. 21 terms of the absolute tip errors (``tip_x tip_y dtip_x dtip_y``) after the start-up, or None if the
    truth has no absolute tip columns. The estimate's absolute tip is evaluated at its samples after the
    start-up only; non-finite estimates or a closure that cannot be solved give NaN statistics (the run's
    divergence is judged from the joint angles, as before)."""
    from ..erls.kinematics import KinematicsError
    from ..sensors import absolute_tip

    if not all(n in truth for n in ABS_TIP_QUANTITIES):
        return None
    sel = est.t >= est.t[0] + task.start_up
    try:
        tip = absolute_tip(task.nominal, Signals(est.t[sel], est.names, est.data[sel], est.units),
                           kinematics=_kinematics(task.observer_key, task.nominal), on_error="nan")
    except (KeyError, KinematicsError) as exc:
        log.warning("level %s run %d: no absolute tip estimate (%s)", task.level_key, task.run, exc)
        tip = Signals(est.t[sel], ABS_TIP_QUANTITIES, np.full((int(sel.sum()), len(ABS_TIP_QUANTITIES)), np.nan))
    return _abs_error_stats(tip, truth, 0.0)


def run_one(task: RunTask) -> dict:
    """One noise realisation on a level's truth, filtered by the nominal observer (runs in a worker)."""
    global OBSERVER_RUNS
    from ..measure import measure
    from ..observer.session import estimate

    t0 = time.perf_counter()
    obs = _observer(task.observer_key, task.nominal, task.config)
    lt = task.level_truth
    meas = measure(task.truth_mech, lt.clean, lt.torque_t, lt.torques, seed=task.seed, t_end=task.duration)
    S = meas.signals
    U = S.select(task.nominal.motor_names).data
    Y = S.select(obs.channels).data
    _reset_observer(obs)
    # a run whose estimate blows up is a result (a diverged run, NaN errors from then on), not a study failure
    obs.ekf.nonfinite_action = "flag"
    est = estimate(obs, S.t, U, Y)
    if est.result.nonfinite:
        log.warning("level %s run %d (seed %d): estimate non-finite from t = %.4g s", task.level_key, task.run,
                    task.seed, est.result.diverged_at)
    OBSERVER_RUNS += 1
    res = est.result
    nis_mean, nis_exp = res.mean_nis()
    stats = _abs_error_stats(est.physical, lt.truth, task.start_up)
    tip_stats = _abs_tip_error_stats(task, est.physical, lt.truth)
    if tip_stats is not None:
        for k in stats:
            stats[k].update(tip_stats[k])
    from ..scoring.run import extra_states, last_state

    extra = extra_states(obs.ekf.model, *last_state(est))  # the payload scale (or disturbances) an augmented filter estimates
    if task.with_bound:
        extra.update(_bound_ratios(obs, S.t, U, lt.truth, task.start_up, stats["rms"]))
    return {
        **extra,
        "level_index": task.level_index,
        "level_key": task.level_key,
        "run": task.run,
        "seed": task.seed,
        "run_hash": task.run_hash,
        "nis_flagged": bool(res.nis_flagged),
        "nis_flagged_at": res.nis_flagged_at,
        "nonfinite": bool(getattr(res, "nonfinite", False)),
        "nis_mean": float(nis_mean),
        "nis_expected": float(nis_exp),
        "n_samples": len(S.t),
        "filter_wall_s": float(est.wall_s),
        "wall_s": time.perf_counter() - t0,
        "worker": f"{socket.gethostname()}:{os.getpid()}",
        **stats,
    }


def _bound_ratios(obs, t: np.ndarray, U: np.ndarray, truth: Signals, start_up: float, rms: dict) -> dict:
    """The run's bound (:func:`exuflex.scoring.bound.bound_track` along the truth, on the run's times and
    torques, every channel sampled; its RMS after ``start_up``) and each quantity's RMS error over it."""
    from ..observer.session import physical_names
    from ..scoring import bound_track

    track, _ = bound_track(obs, t, U, None, truth=truth)
    sel = t >= t[0] + start_up
    bound = dict(zip(physical_names(obs.mech), map(float, track.rms(sel)), strict=True))
    return {"bound_rms": bound,
            "ratio_to_bound": {q: rms[q] / b for q, b in bound.items() if b > 0 and q in rms}}


# ------------------------------------------------------------------------------------------ executors
class InlineExecutor(cf.Executor):
    """Runs each task at submission, in this process (``workers=1``): same interface, no pickling."""

    def submit(self, fn, /, *args, **kwargs):
        f: cf.Future = cf.Future()
        try:
            f.set_result(fn(*args, **kwargs))
        except BaseException as exc:
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise
            f.set_exception(exc)
        return f


@contextlib.contextmanager
def make_executor(workers: int = 1, scheduler: str | None = None, augmented: bool = False):
    """Yield ``(executor, max_in_flight)``: Dask if ``scheduler`` is given, else a process pool for
    ``workers > 1``, else in-process. ``augmented``: the observers are augmented estimators (their kernels are
    compiled ahead too)."""
    if scheduler:
        try:
            from distributed import Client
        except ImportError:
            raise RuntimeError(
                "--scheduler needs Dask's 'distributed' package: pip install 'dask[distributed]'"
            ) from None
        client = Client(scheduler)
        try:
            n = sum(client.nthreads().values()) or max(workers, 1)
            with client.get_executor() as ex:
                yield ex, 2 * n
        finally:
            client.close()
    elif workers > 1:
        cores = os.cpu_count() or 1
        if workers > cores:
            log.warning("workers (--workers): %d asked, %d used (the machine's cores; more processes only share them)",
                        workers, cores)
            workers = cores
    if not scheduler and workers > 1:
        # the kernels compiled once here (in parallel): the pool's processes load them
        _compile.prepare(augmented=augmented)
        with cf.ProcessPoolExecutor(max_workers=workers, initializer=_worker_init, initargs=(os.getpid(),)) as ex:
            yield ex, 2 * workers
    else:
        yield InlineExecutor(), 1


# ------------------------------------------------------------------------------------------ progress
class StudyProgress:
    """``study [######......]  12/50 runs  elapsed 31 s  ETA 1 m 38 s`` on stderr, redrawn in place on a terminal;
    elsewhere (a log file, a pipe) a plain line at every tenth of the runs (disabled: silent)."""

    def __init__(self, total: int, enabled: bool, stream=None, width: int = 28):
        self.total, self.enabled, self.width = total, enabled, width
        self.stream = stream or sys.stderr
        self.done = 0
        self.t0 = time.perf_counter()
        self.note = ""
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._tenth = -1

    @staticmethod
    def _fmt(s: float) -> str:
        if not math.isfinite(s):
            return "?"
        s = round(s)
        return f"{s // 3600} h {s % 3600 // 60:02d} m" if s >= 3600 else (f"{s // 60} m {s % 60:02d} s" if s >= 60
                                                                           else f"{s} s")

    def update(self, done: int | None = None, note: str | None = None) -> None:
        if done is not None:
            self.done = done
        if note is not None:
            self.note = note
        if not self.enabled:
            return
        el = time.perf_counter() - self.t0
        frac = self.done / self.total if self.total else 1.0
        eta = el / self.done * (self.total - self.done) if self.done else float("nan")
        if not self.tty:
            tenth = int(10 * frac)
            if tenth != self._tenth:
                self._tenth = tenth
                self.stream.write(f"study {self.done}/{self.total} runs  elapsed {self._fmt(el)}  "
                                  f"ETA {self._fmt(eta)}  {self.note}\n")
                self.stream.flush()
            return
        n = int(self.width * frac)
        self.stream.write(f"\rstudy [{'#' * n}{'.' * (self.width - n)}] {self.done}/{self.total} runs  "
                          f"elapsed {self._fmt(el)}  ETA {self._fmt(eta)}  {self.note:<24s}")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self.tty:
            self.stream.write("\n")
            self.stream.flush()


# ------------------------------------------------------------------------------------------ the study
@dataclass
class StudyResult:
    out: Path
    rows: list[dict]
    summary: dict
    n_computed: int
    n_reused: int


def manoeuvre_overrides(level: Level) -> tuple[tuple[str, Any], ...]:
    """The level's overrides of the manoeuvre (``manoeuvre.*``): they change the plan and its computed torque,
    which the other overrides (the truth's parameters, unknown to the controller) do not."""
    return tuple((f, v) for f, v in level.overrides if str(f).strip().startswith("manoeuvre."))


def drive_mech(nominal: Mechanism, level: Level) -> Mechanism:
    """The mechanism the level's drive is planned on: the nominal model with the level's manoeuvre."""
    ov = manoeuvre_overrides(level)
    return apply_overrides(nominal, ov) if ov else nominal


def _level_mech(nominal: Mechanism, level: Level) -> Mechanism:
    m = apply_overrides(nominal, level.overrides) if level.overrides else nominal
    return m.with_payload_scale(level.payload_scale) if level.payload_scale != 1.0 else m


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None


LOCK_NAME = ".study.lock"


_LOCK_FD: list[int] = []
"""The descriptor of the study lock this process holds (a worker forked from it closes its copy)."""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _lock_holders(path: Path) -> list[int]:
    """The processes holding a ``flock`` on ``path`` (Linux ``/proc/locks``; empty elsewhere)."""
    try:
        ino = path.stat().st_ino
        rows = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return []
    pids = []
    for row in rows:
        f = row.split()
        if len(f) > 5 and f[1] == "FLOCK" and f[5].rsplit(":", 1)[-1] == str(ino):
            pids.append(int(f[4]))
    return sorted(set(pids))


@contextlib.contextmanager
def study_lock(out: Path):
    """Exclusive lock on a study folder for the life of the block (``flock`` on ``out/.study.lock``, released
    by the kernel when the process dies; the workers close their inherited copy, :func:`_worker_init`): two
    studies writing one folder would mix their files. The file holds the holder's pid while it runs; a pid left
    there by a study that died is named when the lock is taken over."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            who = os.pread(fd, 200, 0).decode(errors="replace").strip()
            pid = int(who.split()[1]) if who.startswith("pid ") and who.split()[1].isdigit() else None
            if pid is not None and not _pid_alive(pid):
                holders = _lock_holders(path)
                raise UsageError(f"{out}: the study that ran here (pid {pid}) has died, but its worker processes "
                                 f"{', '.join(map(str, holders)) or '(unknown pids)'} still hold the folder's lock; "
                                 "expected them stopped: kill them, then run the study again") from None
            raise UsageError(f"{out}: another study is running in this folder ({who or 'lock held'}); wait for it "
                             "or use another folder") from None
        who = os.pread(fd, 200, 0).decode(errors="replace").strip()
        if who.startswith("pid ") and who.split()[1].isdigit() and int(who.split()[1]) != os.getpid():
            log.warning("%s: taking over the lock of a study that stopped without releasing it (pid %s no longer "
                        "runs); its finished runs are reused", out, who.split()[1])
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}\n".encode(), 0)
        _LOCK_FD.append(fd)
        try:
            yield
        finally:
            _LOCK_FD.remove(fd)
            os.ftruncate(fd, 0)  # released normally: no pid left to take over
    finally:
        os.close(fd)


def _exit_with_parent(parent: int) -> None:
    """Make this worker process end when ``parent`` (the study) dies, even by ``kill -9``: Linux's
    ``PR_SET_PDEATHSIG`` (SIGKILL), and elsewhere a daemon thread that polls the parent pid once a second."""
    import signal
    import threading

    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent died before the signal was armed
        os._exit(1)

    def watch():
        while True:
            time.sleep(1.0)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="exuflex-parent-watch", daemon=True).start()


def _worker_init(parent: int) -> None:
    """Initializer of a study's worker process: drop the inherited lock (only the study holds it) and exit with
    the study (:func:`_exit_with_parent`)."""
    for fd in _LOCK_FD:
        try:
            os.close(fd)
        except OSError:
            pass
    _LOCK_FD.clear()
    _exit_with_parent(parent)


def _check_same_study(out: Path, record: dict) -> None:
    """Refuse a folder that holds a study with other settings (more runs per level extend it: allowed)."""
    old = _read_json(out / "study.json")
    if old is None:
        return
    new = json.loads(dump_json(record, default=str))
    free = ("runs_per_level", "seeds")
    diff = []
    for k in ("model_sha256", "levels"):
        if old.get(k) != new.get(k):
            diff.append(k)
    so, sn = old.get("settings") or {}, new["settings"]
    diff += [f"settings.{k}" for k in sorted(set(so) | set(sn)) if k not in free and so.get(k) != sn.get(k)]
    if diff:
        raise UsageError(f"{out}: this folder holds a study with other settings (differing: {', '.join(diff)}); "
                         "use another folder, or delete this one to start over")


def _check_spec(spec) -> None:
    """A :class:`StudySpec`'s fields of the right kinds, before any work: else a
    :class:`~exuflex.errors.UsageError` naming the field and its flag."""
    from ..validate import check_positive

    if not isinstance(spec, StudySpec):
        raise UsageError(f"spec: expected an exuflex.study.StudySpec, got {type(spec).__name__}")
    if not isinstance(spec.model, (str, os.PathLike)) or not str(spec.model).strip():
        raise UsageError(f"model: expected the path of a model file, got {spec.model!r}")
    if not isinstance(spec.levels, (tuple, list)) or not all(isinstance(lv, Level) for lv in spec.levels):
        raise UsageError(f"levels (--levels): expected a sequence of Level (payload_levels, sweep_levels), got "
                         f"{type(spec.levels).__name__}")
    if isinstance(spec.runs, bool) or not isinstance(spec.runs, (int, np.integer)) or spec.runs < 1:
        raise UsageError(f"runs (--runs): expected a positive integer, got {spec.runs!r}")
    if isinstance(spec.base_seed, bool) or not isinstance(spec.base_seed, (int, np.integer)) \
            or not 0 <= spec.base_seed < 2**63 - spec.runs:
        raise UsageError(f"base_seed (--seed): expected an integer in 0 .. 2**63 - 1 - runs, got {spec.base_seed!r}")
    if spec.engine not in ("exudyn", "erls", "reduced"):
        raise UsageError(f"engine (--engine): expected exudyn, erls or reduced, got {spec.engine!r}")
    if spec.duration is not None:
        check_positive(spec.duration, "duration", "--duration")
    check_positive(spec.h, "h", "--h")
    if spec.start_up is not None:
        check_positive(spec.start_up, "start_up", "--start-up", allow_zero=True)
    from ..truth import BEAMS

    if spec.beam not in BEAMS:
        raise UsageError(f"beam (--beam): expected one of {', '.join(BEAMS)}, got {spec.beam!r}")
    if spec.observer_model not in ("nominal", "level"):
        raise UsageError(f"observer_model: expected 'nominal' or 'level', got {spec.observer_model!r}")
    if spec.observer is not None and not isinstance(spec.observer, ObserverConfig):
        raise UsageError(f"observer: expected an exuflex.ObserverConfig or None, got {type(spec.observer).__name__}")


def run_study(
    spec: StudySpec,
    out: str | os.PathLike,
    *,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool = False,
    on_result: Callable[[dict], None] | None = None,
    overwrite: bool = False,
) -> StudyResult:
    """Run (or resume) a study into ``out``; returns the per-run rows and the summary.

    ``out`` is claimed first (:func:`exuflex.runs.output_folder`): a folder holding anything exuflex did not write
    is refused; a study's folder is resumed; another exuflex result there is replaced only with ``overwrite``.

    The folder is locked for the run (:func:`study_lock`: a second study into it is refused while this one
    runs), and a folder holding a study with other settings is refused (only ``runs`` may grow).
    ``on_result`` is called in this process after each finished run has been written (tests use it to
    interrupt a study).
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise UsageError(f"workers (--workers): expected a positive integer, got {workers!r}")
    _check_spec(spec)
    with output_folder(out, "study", overwrite=overwrite, mode="resume") as folder, study_lock(folder):
        return _run_study(spec, folder, workers=workers, scheduler=scheduler, progress=progress, on_result=on_result)


def _run_study(spec, out: Path, *, workers, scheduler, progress, on_result) -> StudyResult:
    t_start = time.perf_counter()
    model_path = Path(spec.model)
    nominal = load_mechanism(model_path)
    from ..validate import check_configurations

    check_configurations(nominal)  # loops close, away from singularities
    if spec.observer is None:  # the model file's [observer] table over the defaults
        spec = dataclasses.replace(spec, observer=ObserverConfig.for_model(nominal))
    if isinstance(spec.runs, bool) or not isinstance(spec.runs, (int, np.integer)) or spec.runs < 1:
        raise UsageError(f"runs (--runs): expected a positive integer, got {spec.runs!r}")
    if not spec.levels:
        raise UsageError("levels (--levels): a study needs at least one level")
    if nominal.manoeuvre is None and spec.duration is None:
        raise ModelFileError(str(model_path), "manoeuvre", "a [manoeuvre] table: a study simulates it",
                             has_got=False)
    duration = float(spec.duration if spec.duration is not None else nominal.manoeuvre.duration)
    start_up = float(spec.start_up if spec.start_up is not None else min(spec.observer.start_up, duration / 4))
    if not 0 <= start_up < duration:
        raise UsageError(f"start_up (--start-up): {start_up:g} s; expected a value in [0, duration = {duration:g} s)")
    # bounds before work: every run's row is held (a few kB), and a run filters duration x rate samples (an EKF
    # sample about 10 nx^3 flop)
    from ..validate import check_work, state_size_estimate

    n_samples = duration * nominal.sample_rate_hz
    check_work(f"{spec.runs} runs x {len(spec.levels)} levels", spec.runs * len(spec.levels), param="runs",
               flag="--runs", what="observer runs", bytes_each=8192,
               flops_each=n_samples * 10 * state_size_estimate(nominal)**3, workers=workers)
    model_sha = file_sha256(model_path)
    scaled = sorted({lv.payload_scale for lv in spec.levels})
    if len(scaled) > 1 and (nominal.payload is None or not nominal.payload.mass > 0):
        raise UsageError(f"levels (--levels): the levels scale the payload, but {model_path} has "
                         f"{'no [payload]' if nominal.payload is None else 'a payload of mass 0'}: every level would "
                         "be the same truth; expected a model with a payload (payload.mass > 0)")
    truth_mechs = [_level_mech(nominal, lv) for lv in spec.levels]  # override errors before any work
    for lv, m in zip(spec.levels, truth_mechs, strict=True):  # the model file's configuration check, per level
        if lv.overrides:
            try:
                check_configurations(m)
            except ModelFileError as exc:
                raise OverrideError(f"level {lv.label}: the model file's check refuses it: "
                                    f"{str(exc).removeprefix(f'{exc.source}: ')}") from None
    # the mechanism each level's drive is planned on and its observer built from: the nominal one with the level's
    # manoeuvre, or (observer_model "level") the level's own model
    drive_mechs = truth_mechs if spec.observer_model == "level" else [drive_mech(nominal, lv) for lv in spec.levels]
    for lv, dm in zip(spec.levels, drive_mechs, strict=True):  # a longer manoeuvre than the nominal one is cut
        if spec.duration is None and dm.manoeuvre is not None and dm.manoeuvre.duration > duration:
            log.warning("level %s: its manoeuvre lasts %g s, the study simulates %g s (the nominal manoeuvre's; "
                        "--duration to change)", lv.label, dm.manoeuvre.duration, duration)
    settings = spec.settings(duration, start_up)
    # a level's own manoeuvre changes its drive and the observer's start (the controller knows the manoeuvre)
    man_ov = [{"manoeuvre": [list(o) for o in manoeuvre_overrides(lv)]} if manoeuvre_overrides(lv) else {}
              for lv in spec.levels]
    if spec.observer_model == "level":
        man_ov = [{"level_model": lv.as_dict()} for lv in spec.levels]
    obs_keys = [_hash({"model": model_sha, "observer": spec.observer.as_dict(), **m}) for m in man_ov]
    drive_keys = [_hash({"model": model_sha, "duration": duration, "h": spec.h, **m}, 10) for m in man_ov]
    keys, hashes = [], []
    for i, lv in enumerate(spec.levels):
        truth_def = {"model": model_sha, "level": lv.as_dict(), "engine": spec.engine, "duration": duration,
                     "h": spec.h}
        if spec.beam != "ancf":
            truth_def["beam"] = spec.beam
        keys.append(f"L{i:02d}-{_hash(truth_def, 10)}")
        hashes.append(_hash({"truth": truth_def, "observer": obs_keys[i], "start_up": start_up,
                             "stats": STATS_VERSION, **({"bound": True} if spec.with_bound else {})}))
    record = {"format": FORMAT, "model": str(model_path.resolve()), "model_sha256": model_sha, "settings": settings,
              "levels": [dict(lv.as_dict(), key=k) for lv, k in zip(spec.levels, keys, strict=True)]}
    _check_same_study(out, record)
    for sub in ("truth", "runs"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "study.json", dump_json(record, default=str) + "\n")

    # what is done already
    done: dict[tuple[int, int], dict] = {}
    pending: dict[int, list[int]] = {}
    for i, key in enumerate(keys):
        d = out / "runs" / key
        d.mkdir(parents=True, exist_ok=True)
        for j in range(spec.runs):
            r = _read_json(d / f"run_{j:04d}.json")
            if r is not None and r.get("run_hash") == hashes[i] and r.get("seed") == spec.base_seed + j:
                done[(i, j)] = r
            else:
                pending.setdefault(i, []).append(j)
    n_reused = len(done)
    if n_reused:
        log.info("%s: %d finished run(s) found, %d to do", out, n_reused, sum(map(len, pending.values())))
    bar = StudyProgress(sum(map(len, pending.values())), progress)
    timings: dict[str, dict] = {}
    n_new = 0

    def level_truth_file(i: int) -> Path:
        return out / "truth" / keys[i] / "truth.npz"

    n_tasks = sum(map(len, pending.values())) + len(pending)  # runs and (at most) one truth per level
    workers = max(1, min(workers, n_tasks))  # a process per task at most
    with make_executor(workers, scheduler, spec.observer.estimator in AUGMENTED_ESTIMATORS) as (ex, max_in_flight):
        queue: list[RunTask] = []
        in_flight: dict[cf.Future, tuple[str, Any]] = {}
        bar.update(0, "simulating truth" if pending else "")

        def enqueue_runs(i: int, lt: TruthRecord) -> None:
            small = _hold_on_grid(with_absolute_tip(nominal, lt), nominal.sample_rate_hz, duration)
            for j in pending.get(i, []):
                queue.append(RunTask(i, keys[i], j, spec.base_seed + j, hashes[i], obs_keys[i], drive_mechs[i],
                                     truth_mechs[i], small, spec.observer, start_up, duration, spec.with_bound))

        # truths: cached ones are loaded, the others simulated through the executor (in parallel with runs)
        truth_jobs = []
        for i in sorted(pending):
            f = level_truth_file(i)
            meta = _read_json(f.parent / "level.json")
            if f.exists() and meta is not None and meta.get("key") == keys[i]:
                timings[keys[i]] = meta.get("timings", {})
                enqueue_runs(i, _load_truth(f, timings[keys[i]]))
            else:
                truth_jobs.append(i)
        drives: dict[str, Drive] = {}

        def drive(i: int) -> Drive:
            """The level's drive, planned once per distinct manoeuvre (and cached on disk)."""
            k = drive_keys[i]
            if k not in drives:
                bar.update(None, "planning the manoeuvre")
                drives[k] = _cached_drive(out / "truth" / f"drive-{k}.npz", drive_mechs[i], duration, spec.h)
                bar.update(None, "simulating truth")
            return drives[k]

        for i in truth_jobs:
            fut = ex.submit(simulate, truth_mechs[i], drive(i), spec.engine, duration, spec.h, beam=spec.beam)
            in_flight[fut] = ("truth", i)
            if isinstance(ex, InlineExecutor):
                break  # in-process: simulate one level, run it, then the next
        waiting_truth = [i for i in truth_jobs if ("truth", i) not in in_flight.values()]

        def fill() -> None:
            while queue and sum(1 for v in in_flight.values() if v[0] == "run") < max_in_flight:
                task = queue.pop(0)
                in_flight[ex.submit(run_one, task)] = ("run", task)

        fill()
        while in_flight:
            finished, _ = cf.wait(list(in_flight), return_when=cf.FIRST_COMPLETED)
            for fut in finished:
                kind, what = in_flight.pop(fut)
                if kind == "truth":
                    i = what
                    lt = fut.result()  # a failed truth simulation stops the study (finished runs are kept)
                    f = level_truth_file(i)
                    f.parent.mkdir(parents=True, exist_ok=True)
                    _save_truth(f, lt)
                    timings[keys[i]] = lt.timings
                    atomic_write_text(f.parent / "level.json", dump_json(
                        {"key": keys[i], "level": spec.levels[i].as_dict(), "engine": spec.engine,
                         "duration_s": duration, "h_s": spec.h, "model_sha256": model_sha, "timings": lt.timings,
                         "versions": package_versions()}, indent=1, default=str) + "\n")
                    log.info("truth of level %s simulated in %.1f s", spec.levels[i].label,
                             lt.timings.get("truth_s", float("nan")))
                    enqueue_runs(i, lt)
                else:
                    r = fut.result()
                    atomic_write_text(out / "runs" / r["level_key"] / f"run_{r['run']:04d}.json",
                                      dump_json(r, default=float) + "\n")
                    done[(r["level_index"], r["run"])] = r
                    n_new += 1
                    bar.update(n_new, f"level {spec.levels[r['level_index']].label}")
                    if on_result is not None:
                        on_result(r)
            if waiting_truth and not any(v[0] == "truth" for v in in_flight.values()) and not queue:
                i = waiting_truth.pop(0)
                in_flight[ex.submit(simulate, truth_mechs[i], drive(i), spec.engine, duration, spec.h, beam=spec.beam)] = \
                    ("truth", i)
            fill()
    bar.close()
    for i, key in enumerate(keys):  # a level finished in an earlier session: its truth's provenance from level.json
        if key not in timings:
            meta = _read_json(level_truth_file(i).parent / "level.json")
            if meta is not None and meta.get("key") == key:
                timings[key] = meta.get("timings", {})

    rows = [done[k] for k in sorted(done)]
    summary = _summary(spec, model_path, model_sha, nominal, keys, rows, settings, timings,
                       time.perf_counter() - t_start, n_new, n_reused, workers, scheduler)
    _write_results_csv(out / "results.csv", spec, rows, nominal.coordinate_names)
    atomic_write_text(out / "summary.json", dump_json(summary, default=float) + "\n")
    return StudyResult(out, rows, summary, n_new, n_reused)


def run_estimator_studies(spec: StudySpec, out, estimators: Sequence[str], **kw) -> dict[str, StudyResult]:
    """The same study once per estimator (:data:`exuflex.observer.session.ESTIMATORS`): ``out/<estimator>`` is the
    study with the observer's ``estimator`` set (every other setting as ``spec``), and all of them run on the same
    level truths, simulated once: ``out/truth`` holds them, and each study's ``truth`` folder is a link to it (a
    level's truth does not depend on the observer). ``kw``: as :func:`run_study`."""
    from ..observer.session import ESTIMATORS

    if isinstance(estimators, str) or not isinstance(estimators, Sequence) or \
            not all(isinstance(e, str) for e in estimators):
        raise UsageError(f"estimators (--estimators): expected a list of estimator names, got {estimators!r}")
    estimators = [e.strip() for e in estimators]
    bad = [e for e in estimators if e not in ESTIMATORS]
    if bad or not estimators:
        raise UsageError(f"estimators (--estimators): expected names among {', '.join(ESTIMATORS)}; got {', '.join(bad) or 'none'}")
    if len(set(estimators)) != len(estimators):
        raise UsageError(f"estimators (--estimators): {', '.join(estimators)}: expected each at most once")
    with output_folder(out, "study-estimators", overwrite=kw.pop("overwrite", False), mode="resume") as folder:
        return _run_estimator_studies(spec, folder, estimators, **kw)


def _run_estimator_studies(spec: StudySpec, out: Path, estimators: Sequence[str], **kw) -> dict[str, StudyResult]:
    (out / "truth").mkdir(parents=True, exist_ok=True)
    results = {}
    for e in estimators:
        sub = out / e
        with output_folder(sub, "study", mode="resume"):  # the study's folder, with its link to the shared truths
            link = sub / "truth"
            if not link.exists():
                link.symlink_to(Path("..") / "truth", target_is_directory=True)
        base = spec.observer if spec.observer is not None else ObserverConfig.for_model(load_mechanism(spec.model))
        est_spec = dataclasses.replace(spec, observer=dataclasses.replace(base, estimator=e))
        results[e] = run_study(est_spec, sub, **kw)
    return results


def estimator_figure_rows(summaries: dict[str, dict], quantities: Sequence[str] | None = None) -> list[dict]:
    """:func:`figure_rows` of each estimator's study summary, with the estimator as the rows' ``series``."""
    return [dict(r, series=e) for e, sm in summaries.items() for r in figure_rows(sm, quantities)]


# ------------------------------------------------------------------------------------------ aggregation
def _quantities(rows: Sequence[dict]) -> list[str]:
    for r in rows:
        return list(r["mean_abs"])
    return []


TRACK_LOST_RAD = 0.05
DIVERGENCE = (
    "a run diverged if its estimate became non-finite or lost the mechanism: a joint-angle error after the "
    f"start-up above {TRACK_LOST_RAD} rad (the initial error the observer is required to recover from). The "
    "moving-window NIS test (n_nis_flagged) is reported separately: it flags innovations larger than the "
    "filter's own covariance explains, which model mismatch causes by design while the estimate still tracks."
)


def _max_q_error(r: dict, coords) -> float:
    """Largest joint-angle error of a run after the start-up (NaN if any is missing or not finite)."""
    vals = [float(r["max"].get(q, float("nan"))) for q in coords]
    return max(vals) if vals and all(math.isfinite(v) for v in vals) else float("nan")


def _nis_flagged(r: dict) -> bool:
    return bool(r.get("nis_flagged", r.get("diverged", False)))  # "diverged": run files of format <= 1.x


def diverged(r: dict, coords) -> bool:
    """Non-finite, or a joint-angle error above :data:`TRACK_LOST_RAD` after the start-up (see DIVERGENCE)."""
    err = _max_q_error(r, coords)
    return bool(r["nonfinite"]) or not (err <= TRACK_LOST_RAD)


def _finite_mean(values) -> float:
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(np.mean(v)) if v else float("nan")


def _summary(spec, model_path, model_sha, nominal, keys, rows, settings, timings, wall, n_new, n_reused,
             workers, scheduler) -> dict:
    qs = _quantities(rows)
    base_qs = [q for q in qs if q not in ABS_TIP_QUANTITIES]
    nan = float("nan")
    levels = []
    for i, lv in enumerate(spec.levels):
        rs = [r for r in rows if r["level_index"] == i]
        # the NIS test flags mismatch-induced inconsistency: such runs still count; only non-finite ones are left out.
        # The absolute tip does not decide this: a run whose estimated pose could not be solved has NaN tip_*
        # statistics and is left out of those alone (eq21[q]["n_runs"])
        good = [r for r in rs if not r["nonfinite"] and all(np.isfinite(r["mean_abs"].get(q, nan)) for q in base_qs)]
        coords = nominal.coordinate_names
        eq21 = {}
        for q in qs:
            ok = [r for r in good if math.isfinite(r["mean_abs"].get(q, nan))]
            eq21[q] = {"mu": _finite_mean(r["mean_abs"][q] for r in ok),
                       "sigma": _finite_mean(r["std_abs"][q] for r in ok), "n_runs": len(ok)}
        levels.append({
            "index": i,
            "key": keys[i],
            **lv.as_dict(),
            "n_runs": len(rs),
            "n_diverged": sum(1 for r in rs if diverged(r, coords)),
            "n_nonfinite": sum(1 for r in rs if r["nonfinite"]),
            "n_nis_flagged": sum(1 for r in rs if _nis_flagged(r)),
            "max_q_error_rad": max((_max_q_error(r, coords) for r in good), default=float("nan")),
            "n_in_stats": len(good),
            "seeds": [r["seed"] for r in rs],
            "eq21": eq21,
            "rms_mean": {q: _finite_mean(r["rms"].get(q, nan) for r in good) for q in qs},
            "max_mean": {q: _finite_mean(r["max"].get(q, nan) for r in good) for q in qs},
            "nis_mean": float(np.mean([r["nis_mean"] for r in good])) if good else float("nan"),
            "nis_expected": float(np.mean([r["nis_expected"] for r in good])) if good else float("nan"),
            **_ratio_summary(good, qs),
            "observer_wall_s_mean": float(np.mean([r["wall_s"] for r in rs])) if rs else float("nan"),
            "truth_timings": timings.get(keys[i], {}),
        })
    return {
        "format": FORMAT,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "model": {"path": str(model_path.resolve()), "sha256": model_sha, "name": nominal.name},
        "settings": settings,
        "quantities": qs,
        "tip_quantities": _tip_quantities(nominal, qs),
        "tip_readings": TIP_READINGS,
        "eq21": "mu = mean over runs of the per-run mean |error|; sigma = mean over runs of the per-run "
                "standard deviation (ddof 1) of |error|; samples after start_up; runs with non-finite estimates left out (runs the NIS test flags are kept)",
        "divergence": DIVERGENCE,
        "levels": levels,
        "execution": {"workers": workers, "scheduler": scheduler, "runs_computed": n_new, "runs_reused": n_reused,
                      "wall_s": wall},
        "versions": package_versions(),
    }


def _ratio_summary(rows: Sequence[dict], qs: Sequence[str]) -> dict:
    """Per level (runs scored against their bound): each quantity's ratio RMS error / bound, its mean over the runs,
    and the worst quantity's ratio per run (its mean, min and max over the runs); empty without bounds."""
    rows = [r for r in rows if r.get("ratio_to_bound")]
    if not rows:
        return {}
    names = [q for q in qs if all(q in r["ratio_to_bound"] for r in rows)]
    worst = [max(r["ratio_to_bound"][q] for q in names) for r in rows]
    return {"ratio_to_bound_mean": {q: _finite_mean(r["ratio_to_bound"][q] for r in rows) for q in names},
            "worst_ratio": {"mean": _finite_mean(worst), "min": float(np.min(worst)), "max": float(np.max(worst)),
                            "quantity": [max(names, key=lambda q: r["ratio_to_bound"][q]) for r in rows]}}


def _tip_quantities(nominal: Mechanism, qs: Sequence[str]) -> dict:
    """The tip elastic and absolute quantities among ``qs``, in the order x, y, rate x, rate y."""
    from ..sensors import tip_dof_names, tip_point

    elastic: list[str] = []
    if tip_point(nominal) is not None:
        ex, ey = tip_dof_names(nominal)
        elastic = [q for q in (ex, ey, "d" + ex, "d" + ey) if q in qs]
    return {"elastic": elastic, "absolute": [q for q in ABS_TIP_QUANTITIES if q in qs]}


def quantity_title(q: str, summary: dict | None = None) -> str:
    """Panel title of a study quantity: the tip ones say whether they are elastic or absolute (rigid + elastic)."""
    tips = (summary or {}).get("tip_quantities") or {}
    elastic = list(tips.get("elastic") or TIP_QUANTITIES)
    comp = {0: "x", 1: "y", 2: "x", 3: "y"}
    if q in ABS_TIP_QUANTITIES:
        k = ABS_TIP_QUANTITIES.index(q)
        return f"{q}: tip {'velocity' if k >= 2 else 'position'} {comp[k]} (rigid + elastic)"
    if q in elastic[:4]:
        k = elastic.index(q)
        return f"{q}: tip elastic {'velocity' if k >= 2 else 'displacement'} {comp[k]}"
    return q


def ordered_quantities(summary: dict, quantities: Sequence[str] | None = None) -> list[str]:
    """``quantities`` (default: all of the summary's) with each tip elastic quantity followed by its absolute
    counterpart (``x25 tip_x y26 tip_y dx25 dtip_x dy26 dtip_y``), so a two-column figure shows them side by side."""
    qs = list(quantities) if quantities else list(summary["quantities"])
    tips = summary.get("tip_quantities") or {}
    elastic, absolute = list(tips.get("elastic") or ()), list(tips.get("absolute") or ())
    if len(elastic) != 4 or len(absolute) != 4 or not all(q in qs for q in elastic + absolute):
        return qs
    out = [q for q in qs if q not in elastic and q not in absolute]
    for e, a in zip(elastic, absolute, strict=True):
        out += [e, a]
    return out


def _write_results_csv(path: Path, spec: StudySpec, rows: Sequence[dict], coords: Sequence[str]) -> None:
    qs = _quantities(rows)
    head = ["level_index", "level", "value", "payload_scale", "run", "seed", "diverged", "nis_flagged", "nis_mean",
            "nis_expected", "n_samples", "wall_s"]
    for stat in ("mean_abs", "std_abs", "rms", "max"):
        head += [f"{stat}_{q}" for q in qs]
    lines = [",".join(head)]

    def cell(v) -> str:
        if isinstance(v, bool):
            return str(int(v))
        if isinstance(v, float):
            return "" if math.isnan(v) else repr(v)
        s = str(v)
        return f'"{s}"' if ("," in s or '"' in s) else s

    for r in rows:
        lv = spec.levels[r["level_index"]]
        vals = [r["level_index"], lv.label, lv.value, lv.payload_scale, r["run"], r["seed"],
                diverged(r, coords), _nis_flagged(r), r["nis_mean"], r["nis_expected"], r["n_samples"], r["wall_s"]]
        for stat in ("mean_abs", "std_abs", "rms", "max"):
            vals += [r[stat].get(q, float("nan")) for q in qs]
        lines.append(",".join(cell(v) for v in vals))
    atomic_write_text(path, "\n".join(lines) + "\n")


def figure_rows(summary: dict, quantities: Sequence[str] | None = None) -> list[dict]:
    """Rows for :func:`exuflex.plots.payload_study_figure`: level value, quantity, mu, sigma and panel title."""
    # every estimated quantity: the tip ones (the paper's Fig. 11, elastic and absolute side by side, see
    # TIP_READINGS) and the joint ones, where the payload mismatch shows most (it changes link 5's inertia,
    # which the encoders and the dynamics must reconcile)
    qs = ordered_quantities(summary, quantities)
    return [{"level": lv["value"], "quantity": q, "mu": lv["eq21"][q]["mu"], "sigma": lv["eq21"][q]["sigma"],
             "title": quantity_title(q, summary)}
            for lv in summary["levels"] for q in qs]


def replace_levels(spec: StudySpec, levels: Sequence[Level]) -> StudySpec:
    return dataclasses.replace(spec, levels=tuple(levels))

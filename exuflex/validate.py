"""Checks of user input that sit between the readers and the numerics (robustness; see ``docs/robustness.md``).

- :func:`check_log`/:func:`check_run`: is a sensor log fit for the observer of a mechanism? Missing
  channels, a time column in milliseconds, a log at another rate, time stamps off the sample grid, too
  coarse (epoch) time stamps, gaps longer than allowed, values outside a channel's ADC full scale (a glitch
  or a unit slip such as degrees) are rejected with a :class:`~exuflex.errors.LogFormatError` naming the
  file, the channel or row and what was expected. What the observer handles as documented (gaps up to
  ``max_gap_s``, empty cells, channels never sampled) is counted in the returned :class:`LogCheck`.
- :func:`check_configurations`: the loops close, away from singularities, at every configuration the model
  file names (``model.q_ref``, ``reduction.q_star``); a failure is a
  :class:`~exuflex.mechanism.ModelFileError` naming that field. The branch the closure assembled at the
  reference configuration is compared with the links' ``angle_guess`` (:func:`assembly`); a link solved more
  than :data:`ANGLE_GUESS_TOL` away from its guess is warned about, naming the link.

Nothing here changes data; the observer session (``exuflex.scoring.run.observe_run``) is meant to call
:func:`check_run` before filtering.
"""

from __future__ import annotations

from collections.abc import Sequence
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import LogFormatError
from .mechanism import Mechanism, ModelFileError

__all__ = ["ANGLE_GUESS_TOL", "Assembly", "LogCheck", "MAX_STEPS", "FLOP_RATE", "TIME_LIMIT_S", "assembly", "check_actuation", "check_configurations", "check_log", "check_mechanism_argument", "check_observer_settings",
           "check_positive", "check_run", "check_provenance", "check_seed", "check_simulation_settings", "check_work",
           "memory_limit_bytes", "state_size_estimate", "truth_lag", "with_noise"]

log = logging.getLogger(__name__)

MAX_GAP_S = 1.0
"""Default longest gap (s) the observer predicts through; longer ones are rejected (split the log)."""

RATE_TOL = 1e-3
"""Clock tolerance: a log whose clock (the least-squares line through its time stamps against the sample index)
runs within 1000 ppm of the model's rate (or of a whole fraction of it) is taken as that rate; a crystal clock
drifts by 1-100 ppm, a wrong rate setting by far more (500 instead of 499 Hz is already 2000 ppm)."""

JITTER_TOL = 0.25
"""Jitter tolerance, in sample intervals: every time stamp within a quarter interval of the log's clock line
(0.5 ms at 500 Hz), so that each sample belongs unambiguously to one instant of the grid."""


@dataclass
class LogCheck:
    """What a log looks like to the observer (all counts over the base grid of spacing ``dt``)."""

    n_samples: int
    dt: float
    n_gaps: int = 0  # places where grid instants are skipped
    n_skipped: int = 0  # skipped grid instants in total (prediction-only intervals)
    longest_gap_s: float = 0.0
    n_empty_rows: int = 0  # rows where no used sensor channel is sampled (prediction only)
    never_sampled: tuple[str, ...] = ()  # used channels with no sample at all
    held_torques: int = 0  # empty torque cells (held at the previous value)
    interval_s: float = 0.0  # the log's nominal interval: a whole multiple of dt (median spacing)
    clock_interval_s: float = 0.0  # the log clock's interval, least-squares fit of t against the sample index
    clock_drift_ppm: float = 0.0  # (clock_interval_s / dt - 1) 1e6
    jitter_rms_s: float = 0.0  # time stamps about that clock
    jitter_max_s: float = 0.0
    sample_index: np.ndarray | None = None  # each row's instant in model intervals dt from the first row
    channel_rate_hz: dict = field(default_factory=dict)  # per used channel: samples / span (0: never sampled)
    channel_every: dict = field(default_factory=dict)  # per used channel: its usual spacing in log rows
    saturated: dict = field(default_factory=dict)  # per channel with samples at its full scale: their fraction
    warnings: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "sample_index"}
        d["never_sampled"] = list(self.never_sampled)
        return d

    def grid_times(self, t0: float = 0.0) -> np.ndarray:
        """The rows' instants on the model's grid ``t0 + k dt`` (jitter and drift removed)."""
        return t0 + self.sample_index * self.dt

    def availability(self) -> str:
        """One line per the used channels: rate (Hz) or 'blank'."""
        return ", ".join(f"{c} {'blank' if not r else f'{r:.4g} Hz'}" for c, r in self.channel_rate_hz.items())


def _row_line(k: int) -> str:
    return f"data row {k + 1}"


def check_log(
    mech: Mechanism,
    sensors,
    channels: Sequence[str],
    motors: Sequence[str] | None = None,
    *,
    dt: float | None = None,
    source: str = "sensors.csv",
    max_gap_s: float = MAX_GAP_S,
    check_full_scale: bool = True,
) -> LogCheck:
    """Check a log (:class:`~exuflex.sensors.Signals`: time, torques, channels) for the observer.

    Parameters
    ----------
    mech : Mechanism
    sensors : Signals
        The log (e.g. ``read_run(...).sensors``).
    channels : sequence of str
        Sensor channels the observer uses.
    motors : sequence of str, optional
        Torque columns (default: the model's motors).
    dt : float, optional
        Observer sample interval (default ``1 / mech.sample_rate_hz``).
    source : str
        File name used in messages.
    max_gap_s : float
        Longest gap accepted (the observer predicts through it without updates).
    check_full_scale : bool
        Reject values outside a channel's ADC full scale (``full_scale`` in the model file).

    Raises
    ------
    LogFormatError
        The log cannot be filtered as it is; the message says what to change.
    """
    motors = tuple(motors) if motors is not None else tuple(mech.motor_names)
    channels = tuple(channels)
    dt = float(dt or 1.0 / mech.sample_rate_hz)
    if len(motors) != len(mech.motors):
        raise LogFormatError(
            f"{source}: {len(motors)} torque column(s) {list(motors)}, but the model "
            f"{mech.source or mech.name} has {len(mech.motors)} motors {list(mech.motor_names)}: list one measured "
            "torque per motor, in the model's order (meta.json 'motors')"
        )
    names = tuple(sensors.names)
    missing = [c for c in (*motors, *channels) if c not in names]
    if missing:
        raise LogFormatError(
            f"{source}: missing channel(s) {missing} (torques {list(motors)}, sensors {list(channels)} are "
            f"needed); the log has {list(names)}"
        )
    t = np.asarray(sensors.t, float)
    f = float  # plain floats in messages (no np.float64(...) reprs)
    n = len(t)
    if n < 2:
        raise LogFormatError(f"{source}: {'no data rows' if n == 0 else 'one data row'}: too short to filter or "
                             "score; expected at least 2 samples")
    if n < MIN_SCORED_SAMPLES:
        warnings_early = [f"only {n} samples: too short to score (an RMS over so few samples says little; expected "
                          f"at least {MIN_SCORED_SAMPLES})"]
    else:
        warnings_early = []
    if not np.all(np.isfinite(t)):
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise LogFormatError(f"{source}: {_row_line(k)}: time {f(t[k])!r} is not a finite number")
    rep = LogCheck(n_samples=n, dt=dt)
    rep.warnings.extend(warnings_early)
    if n > 1:
        steps = np.diff(t)
        bad = np.flatnonzero(steps <= 0)
        if len(bad):
            k = int(bad[0]) + 1
            raise LogFormatError(
                f"{source}: time is not strictly increasing at {_row_line(k)} ({f(t[k - 1])!r} then {f(t[k])!r})"
            )
        med = float(np.median(steps))
        ratio = med / dt
        if 500 <= ratio <= 2000 and abs(ratio / 1000 - round(ratio / 1000)) < 0.2:
            raise LogFormatError(
                f"{source}: time steps of {med:g} for a {1 / dt:g} Hz model: is the time column in "
                f"milliseconds? expected seconds (exuflex observe ... --time-scale 1e-3 converts)"
            )
        mult = max(1, round(ratio))
        if abs(ratio / mult - 1) > 0.2:  # coarse screen on the median step; the clock line below is exact
            raise LogFormatError(
                f"{source}: the log is sampled every {med:g} s ({1 / med:.6g} Hz), not the model's sample interval "
                f"{dt:g} s ({1 / dt:g} Hz) or a whole multiple of it (clock tolerance {RATE_TOL * 1e6:g} ppm): "
                f"resample the log, or set model.sample_rate_hz in {mech.source or mech.name}"
            )
        with np.errstate(over="ignore", invalid="ignore"):  # absurd time columns are reported just below
            k_last = (t[-1] - t[0]) / dt
        if not np.isfinite(k_last) or k_last > 1e9:
            raise LogFormatError(
                f"{source}: the time column spans {f(t[-1] - t[0])!r} s, more than 1e9 samples of {dt:g} s; "
                "expected seconds from the start of the log (--time-scale converts other units)"
            )
        if abs(t[0]) * np.finfo(float).eps > 1e-7 * dt:
            raise LogFormatError(
                f"{source}: time stamps start at {f(t[0])!r} s; at that size they cannot resolve the {dt:g} s "
                "grid (epoch times?): write the time relative to the start of the log"
            )
        # sample indices: every step a whole number of intervals of the log's own clock (jitter < dt / 2); in
        # place, one array of the log's length at a time beside the clock fit's (a long log's memory)
        np.divide(steps, med / mult, out=steps)
        np.rint(steps, out=steps)
        np.maximum(steps, 1.0, out=steps)
        kk = np.empty(n)
        kk[0] = 0.0
        np.cumsum(steps, out=kk[1:])
        del steps
        A = np.column_stack([np.ones(n), kk])
        coef = np.linalg.lstsq(A, t, rcond=None)[0]
        rep.clock_interval_s = float(coef[1])
        rep.clock_drift_ppm = float((coef[1] / dt - 1) * 1e6)
        resid = A @ coef
        del A
        np.subtract(t, resid, out=resid)
        rep.jitter_rms_s = float(np.sqrt(np.mean(resid**2)))
        rep.jitter_max_s = float(np.max(np.abs(resid)))
        if rep.jitter_max_s > JITTER_TOL * dt:
            k = int(np.argmax(np.abs(resid)))
            raise LogFormatError(
                f"{source}: {_row_line(k)}: time {f(t[k])!r} is {resid[k] * 1e3:+.3g} ms off the log's clock "
                f"(t0 + k x {coef[1]:.6g} s); the jitter tolerance is {JITTER_TOL:g} of the {dt:g} s interval: "
                "samples cannot be told apart; check the time column"
            )
        # the slope's own uncertainty (short jittered logs) widens the tolerance: 3 standard errors
        se = float(np.sqrt(np.sum(resid**2) / max(n - 2, 1) / max(np.sum((kk - kk.mean()) ** 2), 1e-300)))
        if abs(coef[1] / dt - 1) > RATE_TOL + 3 * se / dt:
            raise LogFormatError(
                f"{source}: the log's clock runs at {1 / coef[1]:.6g} Hz over its {f(t[-1] - t[0]):.4g} s "
                f"({rep.clock_drift_ppm:+.0f} ppm from the model's {1 / dt:g} Hz; tolerance {RATE_TOL * 1e6:g} ppm): "
                f"a wrong rate; resample the log or set model.sample_rate_hz in {mech.source or mech.name}"
            )
        if rep.jitter_max_s > 1e-6 * dt or abs(rep.clock_drift_ppm) > 1e-3:
            rep.warnings.append(
                f"time stamps jitter by up to {rep.jitter_max_s * 1e6:.3g} us (RMS {rep.jitter_rms_s * 1e6:.3g} us) "
                f"about a clock of {1 / coef[1]:.7g} Hz ({rep.clock_drift_ppm:+.1f} ppm): within the tolerance "
                f"({JITTER_TOL:g} interval, {RATE_TOL * 1e6:g} ppm)"
            )
        if mult > 1:
            rep.warnings.append(f"the log is sampled every {med:g} s, {mult} model intervals: the observer "
                                "predicts through the instants in between")
        rep.sample_index = kk.astype(np.int64)
        jumps = np.diff(kk).astype(np.int64)
        gaps = np.flatnonzero(jumps > 1)
        rep.n_gaps = int(len(gaps))
        rep.n_skipped = int((jumps[gaps] - 1).sum()) if len(gaps) else 0
        if len(gaps):
            g = int(gaps[np.argmax(jumps[gaps])])
            rep.longest_gap_s = float(t[g + 1] - t[g])
            if rep.longest_gap_s > max_gap_s:
                raise LogFormatError(
                    f"{source}: a gap of {rep.longest_gap_s:g} s between {_row_line(g)} (t = {f(t[g])!r}) and "
                    f"{_row_line(g + 1)} (t = {f(t[g + 1])!r}); the observer predicts through gaps up to "
                    f"{max_gap_s:g} s: split the log there"
                )
            if rep.longest_gap_s > 1.5 * med:  # longer than the log's own interval
                n_own = int(np.sum(jumps > 1.5 * mult))
                rep.warnings.append(
                    f"{n_own} gap(s) in time longer than the log's interval (prediction only), longest "
                    f"{rep.longest_gap_s:g} s"
                )
        rep.interval_s = mult * dt  # nominal: the clock's own interval is clock_interval_s
    else:
        rep.sample_index = np.zeros(1, np.int64)
    # the columns as views of the log, one at a time (a long log's memory: never a copy of a whole selection)
    U = [sensors[c] for c in motors]
    Y = [sensors[c] for c in channels]
    for c, col in zip(motors, U, strict=True):
        if np.isinf(col).any():
            k = int(np.flatnonzero(np.isinf(col))[0])
            raise LogFormatError(f"{source}: {_row_line(k)}, torque {c!r}: {f(col[k])!r} is not a finite number")
        if np.isnan(col).all():
            raise LogFormatError(f"{source}: torque column {c!r} has no sample (the observer's input)")
    rep.held_torques = int(sum(np.count_nonzero(np.isnan(col)) for col in U))
    if rep.held_torques:
        rep.warnings.append(f"{rep.held_torques} empty torque cell(s), held at the previous value")
    for c, col in zip(channels, Y, strict=True):
        if np.isinf(col).any():
            k = int(np.flatnonzero(np.isinf(col))[0])
            raise LogFormatError(
                f"{source}: {_row_line(k)}, channel {c!r}: {f(col[k])!r} is not a finite number (leave the cell "
                "empty for 'not sampled')"
            )
    if check_full_scale:
        fs = {s.name: s.full_scale for s in mech.sensors}
        fs.update({m.name: m.full_scale for m in mech.motors})
        for names_, block in ((motors, U), (channels, Y)):
            for c, col in zip(names_, block, strict=True):
                lim = fs.get(c)
                if not lim:
                    continue
                over = np.flatnonzero(np.abs(np.nan_to_num(col)) > lim * (1 + 1e-9))
                if len(over):
                    k = int(over[0])
                    raise LogFormatError(
                        f"{source}: {_row_line(k)}, channel {c!r}: {f(col[k])!r} is outside the channel's full scale "
                        f"+-{lim:g} (model file: full_scale); a glitch, or wrong units (degrees? mm?)"
                    )
                # a reading at the full scale is a clipped one: a bound on the value, not a measurement of it
                n_at = int(np.count_nonzero(np.abs(np.nan_to_num(col)) >= lim * (1 - 1e-6)))
                n_ok = int(np.count_nonzero(np.isfinite(col)))
                if n_at and n_ok:
                    rep.saturated[c] = n_at / n_ok
                    rep.warnings.append(
                        f"channel {c!r}: {n_at} of its {n_ok} samples ({100 * n_at / n_ok:.3g} %) at its full scale "
                        f"+-{lim:g} (clipped: saturated readings are bounds, not values; leave the channel out with "
                        "--channels, or check its range and units)")
    if channels:
        any_present = np.zeros(n, dtype=bool)
        span = float(t[-1] - t[0]) if n > 1 else 0.0
        never_: list[str] = []
        for c, col in zip(channels, Y, strict=True):
            present = np.isfinite(col)
            any_present |= present
            rows = np.flatnonzero(present)
            del present
            rep.channel_rate_hz[c] = float((len(rows) - 1) / span) if span > 0 and len(rows) > 1 else 0.0
            rep.channel_every[c] = int(np.median(np.diff(rows))) if len(rows) > 1 else 0
            if not len(rows):
                never_.append(c)
        never = tuple(never_)
        rep.never_sampled = never
        if never:
            if len(never) == len(channels):
                raise LogFormatError(
                    f"{source}: none of the observer's channels {list(channels)} has a sample"
                )
            rep.warnings.append(f"channel(s) {list(never)} never sampled (the observer runs without them)")
        rep.n_empty_rows = int(n - np.count_nonzero(any_present))
        if rep.n_empty_rows:
            rep.warnings.append(f"{rep.n_empty_rows} row(s) without any sensor sample (prediction only)")
    return rep


def check_run(mech: Mechanism, run, channels: Sequence[str] | None = None, *, dt: float | None = None,
              max_gap_s: float = MAX_GAP_S, check_full_scale: bool = True) -> LogCheck:
    """:func:`check_log` on a run folder read by :func:`exuflex.runs.read_run` (default channels: the
    observer's default set for the mechanism, :func:`exuflex.sensors.default_channels`)."""
    if channels is None:
        from .sensors import default_channels

        channels = default_channels(mech)
    motors = run.motors or mech.motor_names
    path = Path(run.path)
    source = str(path) if path.suffix.lower() in (".csv", ".txt") or path.is_file() else str(path / "sensors.csv")
    return check_log(mech, run.sensors, channels, motors, dt=dt, source=source,
                     max_gap_s=max_gap_s, check_full_scale=check_full_scale)


ANGLE_GUESS_TOL = math.radians(15.0)
"""Largest difference (rad) between a link's ``angle_guess`` and the angle the closure solves at the reference
configuration before :func:`assembly` warns. Newton's method started from the guesses converges to the
assembly branch nearest to them; the other branch of a loop lies a finite angle away (the six-bar's crossed
parallelogram: links L3 and L4 about 1 rad from the open one), so a guess off by more than 15 degrees either
was not meant as the reference configuration or describes another branch. The guesses also set the 2 pi
branch of the encoder readings (:mod:`exuflex.sensors`), which only needs them within pi."""


@dataclass(frozen=True)
class Assembly:
    """The branch the closure assembled at ``q`` from the links' angle guesses (:func:`assembly`).

    ``angles[i]`` is link i's solved absolute angle (rad), shifted by a whole number of turns to lie within pi
    of its guess (or in (-pi, pi] without one); ``guesses[i]`` is its ``angle_guess`` or None;
    ``mismatched`` names the links solved more than ``tol`` from their guess."""

    q: tuple[float, ...]
    field: str  # the model-file field q comes from (model.q_ref or reduction.q_star)
    links: tuple[str, ...]
    angles: tuple[float, ...]
    guesses: tuple[float | None, ...]
    tol: float
    mismatched: tuple[str, ...]
    set_by: tuple[str | None, ...] = ()  # the absolute-angle coordinate that sets each link's angle, or None

    def deviation(self, link: str) -> float | None:
        """Solved minus guessed angle of ``link`` (rad), wrapped to [-pi, pi); None without a guess."""
        i = self.links.index(link)
        g = self.guesses[i]
        return None if g is None else self.angles[i] - g

    def warnings(self, source: str = "") -> list[str]:
        """One line per mismatched link, naming the file, the link's ``angle_guess`` field and both angles."""
        pre = f"{source}: " if source else ""
        out = []
        for name in self.mismatched:
            i = self.links.index(name)
            why = (f"the angle is set by coordinate {self.set_by[i]} there, so the guess is wrong"
                   if self.set_by[i] else "the closure assembled another branch than the guesses describe")
            out.append(f"{pre}links[{i}].angle_guess: link {name} assembled at {self.angles[i]:.4f} rad at "
                       f"{self.field} = {[round(v, 6) for v in self.q]}, {abs(self.deviation(name)):.3f} rad from "
                       f"its guess {self.guesses[i]:.4f} (tolerance {self.tol:.3f} rad): {why}; check the angle "
                       "guesses")
        return out

    def summary(self) -> str:
        """One line: the solved link angles and whether they match the guesses."""
        ang = ", ".join(f"{n} {a:.4f}" for n, a in zip(self.links, self.angles))
        if not self.mismatched:
            return f"assembled at {self.field}: {ang} rad (every guessed link within {self.tol:.3f} rad of its guess)"
        return (f"assembled at {self.field}: {ang} rad; {', '.join(self.mismatched)} more than {self.tol:.3f} rad "
                "from the angle guess (see the warnings)")

    def as_dict(self) -> dict:
        return {"q": list(self.q), "field": self.field, "tol_rad": self.tol, "mismatched": list(self.mismatched),
                "summary": self.summary(),
                "links": [{"name": n, "angle_rad": a, "angle_guess": g} for n, a, g in
                          zip(self.links, self.angles, self.guesses)]}


def assembly(mech: Mechanism, q=None, *, tol: float = ANGLE_GUESS_TOL) -> Assembly:
    """Solve the closure at ``q`` (default ``model.q_ref``, else ``reduction.q_star``) from the angle guesses
    alone (no warm start) and compare every link's solved angle with its ``angle_guess``:
    ``d_i = wrap(theta_i - guess_i)`` in [-pi, pi); a link with ``|d_i| > tol`` is listed in
    ``mismatched``. Raises :class:`~exuflex.erls.kinematics.KinematicsError` if the loop does not close."""
    from .erls.kinematics import Kinematics

    fld = "q"
    if q is None:
        if mech.q_ref:
            q, fld = mech.q_ref, "model.q_ref"
        elif mech.reduction.q_star:
            q, fld = mech.reduction.q_star, "reduction.q_star"
        else:
            raise ModelFileError(mech.source or mech.name, "model.q_ref",
                                 "a reference configuration to assemble the mechanism at", has_got=False)
    q = np.asarray(q, float)
    th = Kinematics(mech).solve(q)[2::3]
    angles, guesses, bad = [], [], []
    for lk, t in zip(mech.links, th):
        g = lk.angle_guess
        if g is None:
            angles.append(float(t - 2 * np.pi * np.round(t / (2 * np.pi))))
        else:
            d = float((t - g + np.pi) % (2 * np.pi) - np.pi)
            angles.append(float(g + d))
            if abs(d) > tol:
                bad.append(lk.name)
        guesses.append(None if g is None else float(g))
    by = {c.link: c.name for c in mech.coordinates if c.kind == "angle" and c.relative_to is None}
    return Assembly(tuple(float(v) for v in q), fld, tuple(lk.name for lk in mech.links), tuple(angles),
                    tuple(guesses), float(tol), tuple(bad), tuple(by.get(lk.name) for lk in mech.links))


def check_configurations(mech: Mechanism, cond_max: float = 1e6) -> Assembly | None:
    """Solve the closure at ``model.q_ref`` and ``reduction.q_star``; a loop that cannot close, or a
    configuration at or near a singularity (closure Jacobian condition number above ``cond_max``), is a
    :class:`ModelFileError` naming the field. Returns the :func:`assembly` at the first of them (None if the
    file names neither), after logging a warning for each link solved more than :data:`ANGLE_GUESS_TOL` from
    its ``angle_guess``."""
    from .erls.kinematics import Kinematics, KinematicsError

    src = mech.source or mech.name
    todo = []
    if mech.q_ref:
        todo.append(("model.q_ref", mech.q_ref))
    if mech.reduction.q_star:
        todo.append(("reduction.q_star", mech.reduction.q_star))
    for fld, q in todo:
        kin = Kinematics(mech, cond_max=cond_max)  # fresh: no warm start from another configuration
        try:
            kin.pose(np.asarray(q, float))
        except KinematicsError as exc:
            detail = str(exc).split(": ", 1)[-1]
            raise ModelFileError(
                src, fld,
                f"a configuration where every loop closes, away from singularities; {detail}", list(q)) from None
    if not todo:
        return None
    asm = assembly(mech)  # at todo[0]: q_ref, else q_star
    for msg in asm.warnings(src):
        log.warning("%s", msg)
    return asm


# ------------------------------------------------------------------------------------------ settings
def _where(param: str, flag: str | None) -> str:
    return f"{param} ({flag})" if flag else param


def check_positive(value, param: str, flag: str | None = None, *, allow_zero: bool = False) -> float:
    """``value`` as a float if it is a finite positive (or, with ``allow_zero``, non-negative) number, else a
    :class:`~exuflex.errors.UsageError` naming the parameter (and its command-line flag)."""
    from .errors import UsageError

    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    v = float(value) if ok else float("nan")
    if not (np.isfinite(v) and (v >= 0 if allow_zero else v > 0)):
        kind = "non-negative" if allow_zero else "positive"
        raise UsageError(f"{_where(param, flag)}: expected a {kind} finite number, got {value!r}")
    return v


def check_mechanism_argument(mech, param: str = "mech") -> None:
    """A :class:`~exuflex.mechanism.Mechanism` where one is expected (a path is not: load it first)."""
    from .errors import UsageError

    if not isinstance(mech, Mechanism):
        hint = (" (a path: load it with exuflex.mechanism.load_mechanism(path) first)"
                if isinstance(mech, (str, Path)) else "")
        raise UsageError(f"{param}: expected an exuflex.mechanism.Mechanism, got {type(mech).__name__}{hint}")


def check_simulation_settings(mech: Mechanism, duration: float, h: float, seed=None) -> None:
    """Simulation settings a run can be made with: ``duration`` (s) at least one sample interval of the model
    and at most :data:`MAX_STEPS` integration steps (memory: the plan and the torque table hold every step),
    ``h`` (s) at most one sample interval (the output grid is built from whole steps), ``seed`` a non-negative
    integer. Errors are :class:`~exuflex.errors.UsageError` naming the parameter and its flag."""
    from .errors import UsageError

    dt = 1.0 / mech.sample_rate_hz
    man = mech.manoeuvre
    if man is not None:
        src = mech.source or mech.name
        if man.duration < dt * (1 - 1e-9):
            raise ModelFileError(src, "manoeuvre.duration",
                                 f"a manoeuvre of at least one sample interval ({dt:g} s)", man.duration)
    duration = check_positive(duration, "duration", "--duration")
    h = check_positive(h, "h", "--h")
    if h > dt * (1 + 1e-9):
        raise UsageError(f"h (--h): the integration step {h:g} s is longer than the model's sample interval "
                         f"{dt:g} s ({mech.sample_rate_hz:g} Hz); expected h <= {dt:g} s")
    if duration < dt * (1 - 1e-9):
        raise UsageError(f"duration (--duration): {duration:g} s is shorter than one sample interval of the model "
                         f"({dt:g} s, model.sample_rate_hz = {mech.sample_rate_hz:g}); expected at least {dt:g} s")
    if duration / h > MAX_STEPS:
        raise UsageError(f"duration (--duration): {duration:g} s at h = {h:g} s is {duration / h:.3g} integration "
                         f"steps, more than {MAX_STEPS:.0e} (every step is held in memory); expected at most "
                         f"{MAX_STEPS * h:.3g} s at this step (split the run) or a coarser --h")
    nq, nm = len(mech.coordinates), len(mech.motors)
    # every step: the plan (q, q', q''), the torque table; every output sample: the clean and measured channels
    # and the truth's states, each held about three times (the engine's record, the measurement, the written table)
    check_work(f"{duration:g} s at h = {h:g} s", duration / h, param="duration", flag="--duration",
               what="integration steps", bytes_each=8 * 3 * (3 * nq + nm))
    cols = len(mech.sensors) + nm + 2 * nq + 8
    check_work(f"{duration:g} s at {mech.sample_rate_hz:g} Hz", duration * mech.sample_rate_hz, param="duration",
               flag="--duration", what="output samples", bytes_each=8 * 3 * cols)
    check_seed(seed)


def check_seed(seed) -> None:
    """``seed`` None (a fresh one) or an integer from ``0`` to ``2**63 - 1``; else a :class:`~exuflex.errors.UsageError`
    naming ``--seed``."""
    from .errors import UsageError

    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))
                             or not 0 <= int(seed) < 2**63):
        raise UsageError(f"seed (--seed): expected an integer in 0 .. 2**63 - 1, got {seed!r}")


def check_actuation(mech: Mechanism) -> None:
    """The motors can drive every coordinate at ``model.q_ref`` (rank of the coordinate rows of the input matrix
    equals the number of coordinates), as computed torque needs; else a :class:`ModelFileError` on ``motors``."""
    from .erls.model import ErlsModel

    model = ErlsModel(mech)
    q = np.asarray(mech.q_ref, float)
    A = model.input_matrix(model.configuration(q))[: model.nq]
    rank = int(np.linalg.matrix_rank(A))
    if rank < model.nq:
        raise ModelFileError(mech.source or mech.name, "motors",
                             f"motors that actuate all {model.nq} coordinates {list(mech.coordinate_names)} "
                             f"(computed torque); {list(mech.motor_names)} actuate only {rank}",
                             has_got=False)


MIN_SCORED_SAMPLES = 10
"""Fewest samples a log is scored on without a note (an RMS over fewer says little)."""

MAX_STEPS = 5e7
"""Most integration steps a simulation may take (about 20 bytes per step and table column are held)."""

RK4_FLOOR = (120 * 2.2e-16) ** 0.2 / 10
"""``h omega`` below which RK4's local error ``(h omega)^5 / 120`` is under double precision (2.2e-16) for modes
up to ten times the band's upper edge ``omega = 2 pi band_hz``: a smaller sub-step only adds work (about 1.9e-4)."""

FLOP_RATE = 1e9
"""Floating-point operations per second the work estimates of :func:`check_work` assume: about one core's
sustained rate on the dense matrices of tens to hundreds of rows exuflex works with (LAPACK on matrices this small
runs well below a core's peak), so that an estimate is of the order of the real time, not a wild underestimate."""

TIME_LIMIT_S = 24 * 3600.0
"""The most work one typed size may ask for, estimated at :data:`FLOP_RATE`: a day."""


def memory_limit_bytes() -> int:
    """The most memory one typed size may ask for: half of this machine's physical memory (8 GB where it cannot
    be read), leaving the rest to the model, the other processes and the estimate's own slack."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")) // 2
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def _bytes(n: float) -> str:
    for unit, k in (("GB", 2**30), ("MB", 2**20), ("kB", 2**10)):
        if n >= k:
            return f"{n / k:.3g} {unit}"
    return f"{n:.0f} B"


def _seconds(s: float) -> str:
    if s >= 86400:
        return f"{s / 86400:.3g} days"
    if s >= 3600:
        return f"{s / 3600:.3g} h"
    return f"{s:.3g} s"


def check_work(value, count: float, *, param: str, flag: str | None, what: str, bytes_each: float = 0.0,
               flops_each: float = 0.0, workers: int = 1) -> None:
    """Bounds before work on a size a user typed: ``count`` units of ``what`` (configurations, candidates,
    sub-steps, runs ...), each holding ``bytes_each`` bytes and costing ``flops_each`` floating-point operations,
    must fit in :func:`memory_limit_bytes` and :data:`TIME_LIMIT_S` at :data:`FLOP_RATE` (over ``workers``
    processes). Else a one-line :class:`~exuflex.errors.UsageError` naming the parameter, the estimate, the limit
    and the largest count that fits."""
    from .errors import UsageError

    mem_limit = memory_limit_bytes()
    mem = count * bytes_each
    secs = count * flops_each / FLOP_RATE / max(int(workers), 1)
    where = _where(param, flag)
    if mem > mem_limit:
        n_max = mem_limit / bytes_each
        raise UsageError(f"{where}: {value} means {count:.3g} {what}, about {_bytes(mem)} of memory at "
                         f"{_bytes(bytes_each)} each, more than {_bytes(mem_limit)} (half of this machine's memory); "
                         f"expected at most {n_max:.3g} {what}")
    if secs > TIME_LIMIT_S:
        n_max = TIME_LIMIT_S * FLOP_RATE * max(int(workers), 1) / flops_each
        raise UsageError(f"{where}: {value} means {count:.3g} {what}, about {_seconds(secs)} of work (estimated at "
                         f"{flops_each:.3g} flop each, {FLOP_RATE:.0e} flop/s per process), more than the "
                         f"{_seconds(TIME_LIMIT_S)} one setting may ask for; expected at most {n_max:.3g} {what}")


def state_size_estimate(mech: Mechanism) -> int:
    """The observer's state size before it is built, for the work estimates: ``2 (nq + 2 n_links)``, the rigid
    coordinates and about two elastic coordinates per link (the Craig-Bampton masters and interior modes of the
    gallery's models), positions and rates."""
    return 2 * (len(mech.coordinates) + 2 * len(mech.links))


def check_observer_settings(mech: Mechanism, config) -> tuple[str, ...]:
    """Check an :class:`~exuflex.observer.session.ObserverConfig` against a mechanism before anything is built;
    returns the channels the observer will use. The channels exist, are not repeated and have a positive
    ``noise_std`` (the filter's R); the model has at least one such sensor; the reduction's masters are not
    empty or repeated; ``n_interior`` is a non-negative integer or ``"auto"``; the sub-step ``h`` is at most the
    sample interval; the prior standard deviations and the process-noise scale are positive. Errors are
    :class:`~exuflex.errors.UsageError` naming the setting and its command-line flag."""
    from .errors import UsageError

    src = mech.source or mech.name
    sensors = {s.name: s for s in mech.sensors}
    if config.channels is not None:
        chans = tuple(config.channels)
        if isinstance(config.channels, str) or not all(isinstance(c, str) for c in chans):
            raise UsageError(f"channels (--channels): expected a sequence of channel names, got {config.channels!r}")
        if not chans:
            raise UsageError("channels (--channels): expected at least one sensor channel, got none")
        dup = sorted({c for c in chans if chans.count(c) > 1})
        if dup:
            raise UsageError(f"channels (--channels): repeated channel(s) {dup}")
        unknown = [c for c in chans if c not in sensors]
        if unknown:
            raise UsageError(f"channels (--channels): {unknown} not sensor channel(s) of {src}; it has "
                             f"{sorted(sensors)}")
        quiet = [c for c in chans if not sensors[c].noise_std > 0]
        if quiet:
            raise UsageError(f"channels (--channels): {quiet} ha{'s' if len(quiet) == 1 else 've'} no noise_std in "
                             f"{src}; the filter needs a positive standard deviation for every channel it uses "
                             "(set noise_std in the model file or --noise NAME=STD)")
    else:
        from .sensors import default_channels

        chans = default_channels(mech)
        if not chans:
            raise UsageError(f"{src}: no sensor with a positive noise_std, nothing to observe with; add [[sensors]] "
                             "with noise_std to the model file")
    if config.masters is not None:
        m = tuple(config.masters)
        if not m or not all(isinstance(x, str) and x.strip() for x in m):
            raise UsageError(f"masters (--masters): expected one or more elastic dof names, got {config.masters!r}")
        dup = sorted({x for x in m if m.count(x) > 1})
        if dup:
            raise UsageError(f"masters (--masters): repeated dof(s) {dup}")
    ni = config.n_interior
    if ni is not None and ni != "auto" and (isinstance(ni, bool) or not isinstance(ni, (int, np.integer))
                                            or ni < 0):
        raise UsageError(f"n_interior (--n-interior): expected a non-negative integer or 'auto', got {ni!r}")
    h = check_positive(config.h, "h", "--substep")
    dt = check_positive(config.dt, "dt") if config.dt is not None else 1.0 / mech.sample_rate_hz
    band = mech.reduction.band_hz
    if config.dt is None and mech.sample_rate_hz < 2 * band:
        raise ModelFileError(src, "model.sample_rate_hz", f"at least twice reduction.band_hz = {band:g} Hz, the "
                             f"highest frequency the reduced model keeps ({2 * band:g} Hz: a mode above half the "
                             "filter's rate aliases onto a slower one), or a lower reduction.band_hz",
                             mech.sample_rate_hz)
    if h > dt * (1 + 1e-9):
        raise UsageError(f"h (--substep): the RK4 sub-step {h:g} s is longer than the sample interval {dt:g} s")
    h_min = RK4_FLOOR / (2 * math.pi * mech.reduction.band_hz)
    if h < h_min:
        raise UsageError(f"h (--substep): the RK4 sub-step {h:g} s is below {h_min:.2g} s, where RK4's error "
                         f"(h omega)^5 / 120 is under double precision ten times above the model's band "
                         f"(reduction.band_hz = {mech.reduction.band_hz:g} Hz): smaller steps add only work "
                         f"({dt / h:.3g} sub-steps a sample); expected h >= {h_min:.2g} s")
    for name, flag in (("q0_std", "--q0-std"), ("qd0_std", "--qd0-std"), ("elastic0_std", "--elastic0-std"),
                       ("elastic_rate0_std", "--elastic-rate0-std"), ("q_scale", "--q-scale")):
        check_positive(getattr(config, name), name, flag)
    check_positive(config.q_extra_std, "q_extra_std", "--q-extra", allow_zero=True)
    check_positive(config.start_up, "start_up", "--start-up", allow_zero=True)
    return chans


def with_noise(mech: Mechanism, noise: dict[str, float]) -> Mechanism:
    """``mech`` with the noise standard deviations of some motors or sensors replaced (``{name: std}``, in the
    channel's unit: N m, rad, 1/m, m). The filter's R and the torque process noise Q follow."""
    import dataclasses

    from .errors import UsageError

    motors = {m.name for m in mech.motors}
    sensors = {s.name for s in mech.sensors}
    for k, v in noise.items():
        if k not in motors | sensors:
            raise UsageError(f"noise (--noise): {k!r} is not a motor or sensor of {mech.source or mech.name}; "
                             f"expected one of {sorted(motors) + sorted(sensors)}")
        check_positive(v, f"noise[{k!r}]", "--noise")
    return dataclasses.replace(
        mech,
        motors=tuple(dataclasses.replace(m, noise_std=float(noise[m.name])) if m.name in noise else m
                     for m in mech.motors),
        sensors=tuple(dataclasses.replace(s, noise_std=float(noise[s.name])) if s.name in noise else s
                      for s in mech.sensors),
    )


UNIT_FACTORS = {
    "rad": {"rad": 1.0, "deg": math.pi / 180, "degree": math.pi / 180, "degrees": math.pi / 180, "mrad": 1e-3},
    "m": {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "um": 1e-6},
    "1/m": {"1/m": 1.0, "1/mm": 1e3, "1/km": 1e-3},
    "N m": {"N m": 1.0, "Nm": 1.0, "N*m": 1.0, "N.m": 1.0, "mN m": 1e-3, "N mm": 1e-3, "Nmm": 1e-3},
    "rad/s": {"rad/s": 1.0, "deg/s": math.pi / 180},
    "m/s": {"m/s": 1.0, "mm/s": 1e-3},
}
"""Units a run folder's ``meta.json`` may give a column in, per the unit exuflex works in: the factor to it."""


def _expected_units(mech: Mechanism) -> dict[str, str]:
    from .sensors import SENSOR_UNITS

    out = {m.name: "N m" for m in mech.motors}
    out.update({s.name: SENSOR_UNITS.get(s.kind, "") for s in mech.sensors})
    return out


def check_provenance(mech: Mechanism, run, *, accept_other_model: bool = False, flag: str = "--accept-other-model"):
    """A run folder's provenance against the model it is observed with; returns ``(run, notes)``: the run with its
    columns in exuflex's units (``meta.json`` ``units`` honoured: degrees, millimetres ... converted) and one-line
    notes. Refused with a :class:`~exuflex.errors.UsageError` (or :class:`~exuflex.errors.LogFormatError`):

    - a ``meta.json`` naming another mechanism (unless ``accept_other_model``, then noted);
    - a column in a unit exuflex does not know for its kind (``rad``, ``m``, ``1/m``, ``N m`` and their multiples);
    - a truth that is not one (it has the log's torque or sensor columns: a ``sensors.csv``), or whose time is not
      aligned with the log's: the lag of a coordinate's channel against its true state (:func:`truth_lag`) more
      than half a sample interval from zero, where that shift at least halves the misfit (a real offset, not noise).
    """
    import dataclasses

    from .errors import LogFormatError, UsageError
    from .sensors import Signals

    notes: list[str] = []
    meta = run.meta or {}
    src = mech.source or mech.name
    name = meta.get("mechanism")
    if isinstance(name, str) and name and name != mech.name:
        what = f"{run.path}: meta.json says the run is of the mechanism {name!r}"
        path = (meta.get("model") or {}).get("path") if isinstance(meta.get("model"), dict) else None
        what += f" ({path})" if path else ""
        if not accept_other_model:
            raise UsageError(f"{what}, the model {src} is {mech.name!r}; expected a run of this model ({flag} to "
                             "observe it with this one all the same)")
        notes.append(f"{what}, observed with {mech.name!r} ({flag})")
    units = (meta.get("units") or {}).get("sensors.csv") or {}
    expected = _expected_units(mech)
    S = run.sensors
    data = None
    for i, c in enumerate(S.names):
        u, want = units.get(c), expected.get(c)
        if not u or not want or u == want:
            continue
        factor = UNIT_FACTORS.get(want, {}).get(u)
        if factor is None:
            raise LogFormatError(f"{run.path}/meta.json: units: column {c!r} in {u!r}; expected {want!r} or one of "
                                 f"{sorted(UNIT_FACTORS.get(want, {want: 1}))}")
        if data is None:
            data = S.data.copy()
        data[:, i] *= factor
        notes.append(f"column {c!r} converted from {u} to {want} (meta.json units)")
    if data is not None:
        S = Signals(S.t, S.names, data, tuple(expected.get(c, u) for c, u in zip(S.names, S.units, strict=True)))
        run = dataclasses.replace(run, sensors=S)
    truth = run.truth
    if truth is not None:
        log_cols = [c for c in truth.names if c in set(mech.motor_names) or c in {s.name for s in mech.sensors}
                    and not any(c == co.name for co in mech.coordinates)]
        if log_cols:
            raise LogFormatError(f"{run.path}: the truth has the log's column(s) {log_cols}: not a truth (time and "
                                 "the true states q.., dq.., the tip's elastic states); expected a truth.csv")
        found = truth_lag(mech, S, truth)
        lag, ratio = found if found is not None else (0.0, 1.0)
        if abs(lag) > 0.5 / mech.sample_rate_hz and ratio > 2.0:  # a shift that at least halves the misfit
            raise LogFormatError(f"{run.path}: the truth is {abs(lag):.4g} s {'late' if lag > 0 else 'early'} against "
                                 "the log (least-squares alignment of a coordinate's channel); expected their clocks "
                                 "aligned within half a sample interval")
    return run, notes


def truth_lag(mech: Mechanism, sensors, truth, max_lag_s: float = 0.5) -> tuple[float, float] | None:
    """``(lag, ratio)``: the time by which ``truth`` lags ``sensors`` (s; positive: the truth's stamps late), the
    shift ``d`` that minimises the mean square of ``y(t) - q(t + d)`` between the log's channel ``y`` and the truth's
    state ``q`` of the first coordinate both have (the truth interpolated linearly), searched on the log's grid
    within ``max_lag_s`` and refined by a parabola through the best three; and the ratio of that mean square at
    zero shift to its minimum (about 1 for aligned clocks, where the misfit is the channel's noise; large where
    the shift matters). None where they share no coordinate or the coordinate does not move."""
    for co in mech.coordinates:
        q = co.name
        if q not in sensors.names or q not in truth.names:
            continue
        ok = np.isfinite(sensors[q])
        t, y = sensors.t[ok], sensors[q][ok]
        if len(t) < 8 or not np.ptp(truth[q]) > 0:
            continue
        step = float(np.median(np.diff(t)))
        n = max(1, min(int(max_lag_s / step), len(t) // 4))
        lags = np.arange(-n, n + 1) * step
        cost = np.full(len(lags), np.inf)
        for i, d in enumerate(lags):
            w = np.interp(t + d, truth.t, truth[q], left=np.nan, right=np.nan)
            keep = np.isfinite(w)
            if keep.sum() >= len(t) // 2:
                cost[i] = float(np.mean((y[keep] - w[keep]) ** 2))
        k = int(np.argmin(cost))
        if not np.isfinite(cost[k]) or not np.isfinite(cost[n]):
            continue
        ratio = float(cost[n] / cost[k]) if cost[k] > 0 else (1.0 if cost[n] == 0 else math.inf)
        if 0 < k < len(lags) - 1 and np.all(np.isfinite(cost[k - 1 : k + 2])):
            c0, c1, c2 = cost[k - 1 : k + 2]
            den = c0 - 2 * c1 + c2
            return float(lags[k] + (0.5 * step * (c0 - c2) / den if den > 0 else 0.0)), ratio
        return float(lags[k]), ratio
    return None

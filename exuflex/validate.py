"""Checks of user input that sit between the readers and the numerics (robustness; see ``docs/robustness.md``).

- :func:`check_log`/:func:`check_run`: is a sensor log fit for the observer of a mechanism? Missing
  channels, a time column in milliseconds, a log at another rate, time stamps off the sample grid, too
  coarse (epoch) time stamps, gaps longer than allowed, values outside a channel's ADC full scale (a glitch
  or a unit slip such as degrees) are rejected with a :class:`~exuflex.errors.LogFormatError` naming the
  file, the channel or row and what was expected. What the observer handles as documented (gaps up to
  ``max_gap_s``, empty cells, channels never sampled) is counted in the returned :class:`LogCheck`.
- :func:`check_configurations`: the loops close, away from singularities, at every configuration the model
  file names (``model.q_ref``, ``reduction.q_star``); a failure is a
  :class:`~exuflex.mechanism.ModelFileError` naming that field.

Nothing here changes data; the observer session (``exuflex.observer.session.observe_run``) is meant to call
:func:`check_run` before filtering.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import LogFormatError
from .mechanism import Mechanism, ModelFileError

__all__ = ["LogCheck", "check_configurations", "check_log", "check_run"]

MAX_GAP_S = 1.0
"""Default longest gap (s) the observer predicts through; longer ones are rejected (split the log)."""


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
    warnings: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["never_sampled"] = list(self.never_sampled)
        return d


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
    if n == 0:
        raise LogFormatError(f"{source}: no data rows (expected at least one sample)")
    if not np.all(np.isfinite(t)):
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise LogFormatError(f"{source}: {_row_line(k)}: time {f(t[k])!r} is not a finite number")
    rep = LogCheck(n_samples=n, dt=dt)
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
                f"milliseconds? expected seconds (read_csv_log(..., time_scale=1e-3) converts)"
            )
        if ratio < 1 - 1e-6 or (ratio > 1 + 1e-6 and abs(ratio - round(ratio)) > 1e-3):
            raise LogFormatError(
                f"{source}: the log is sampled every {med:g} s ({1 / med:g} Hz), expected the model's sample "
                f"interval {dt:g} s ({1 / dt:g} Hz): resample the log to that grid or set model.sample_rate_hz"
            )
        if ratio > 1.5:
            rep.warnings.append(f"the log is sampled every {med:g} s, {round(ratio)} model intervals: the observer "
                                "predicts through the instants in between")
        k_rel = (t - t[0]) / dt
        if not np.isfinite(k_rel[-1]) or k_rel[-1] > 1e9:
            raise LogFormatError(
                f"{source}: the time column spans {f(t[-1] - t[0])!r} s, more than 1e9 samples of {dt:g} s; "
                "expected seconds from the start of the log"
            )
        kk = np.rint(k_rel)
        off = np.abs(k_rel - kk) > 1e-6 * np.maximum(1.0, kk)
        if off.any():
            k = int(np.flatnonzero(off)[0])
            if abs(t[0]) * np.finfo(float).eps > 1e-7 * dt:
                raise LogFormatError(
                    f"{source}: time stamps start at {f(t[0])!r} s; at that size they cannot resolve the {dt:g} s "
                    "grid (epoch times?): write the time relative to the start of the log"
                )
            raise LogFormatError(
                f"{source}: {_row_line(k)}: time {f(t[k])!r} is not on the {dt:g} s grid starting at {f(t[0])!r} "
                f"(expected {f(t[0] + kk[k] * dt)!r}); resample the log to the model's sample rate"
            )
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
            rep.warnings.append(
                f"{rep.n_gaps} gap(s) in time, {rep.n_skipped} sample(s) missing (prediction only), longest "
                f"{rep.longest_gap_s:g} s"
            )
    U = sensors.select(motors).data if motors else np.zeros((n, 0))
    Y = sensors.select(channels).data if channels else np.zeros((n, 0))
    for j, c in enumerate(motors):
        col = U[:, j]
        if np.isinf(col).any():
            k = int(np.flatnonzero(np.isinf(col))[0])
            raise LogFormatError(f"{source}: {_row_line(k)}, torque {c!r}: {f(col[k])!r} is not a finite number")
        if np.isnan(col).all():
            raise LogFormatError(f"{source}: torque column {c!r} has no sample (the observer's input)")
    rep.held_torques = int(np.isnan(U).sum())
    if rep.held_torques:
        rep.warnings.append(f"{rep.held_torques} empty torque cell(s), held at the previous value")
    for j, c in enumerate(channels):
        col = Y[:, j]
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
            for j, c in enumerate(names_):
                lim = fs.get(c)
                if not lim:
                    continue
                col = block[:, j]
                over = np.flatnonzero(np.abs(np.nan_to_num(col)) > lim * (1 + 1e-9))
                if len(over):
                    k = int(over[0])
                    raise LogFormatError(
                        f"{source}: {_row_line(k)}, channel {c!r}: {f(col[k])!r} is outside the channel's full scale "
                        f"+-{lim:g} (model file: full_scale); a glitch, or wrong units (degrees? mm?)"
                    )
    if channels:
        present = np.isfinite(Y)
        never = tuple(c for j, c in enumerate(channels) if not present[:, j].any())
        rep.never_sampled = never
        if never:
            if len(never) == len(channels):
                raise LogFormatError(
                    f"{source}: none of the observer's channels {list(channels)} has a sample"
                )
            rep.warnings.append(f"channel(s) {list(never)} never sampled (the observer runs without them)")
        rep.n_empty_rows = int((~present.any(axis=1)).sum())
        if rep.n_empty_rows:
            rep.warnings.append(f"{rep.n_empty_rows} row(s) without any sensor sample (prediction only)")
    return rep


def check_run(mech: Mechanism, run, channels: Sequence[str], *, dt: float | None = None,
              max_gap_s: float = MAX_GAP_S, check_full_scale: bool = True) -> LogCheck:
    """:func:`check_log` on a run folder read by :func:`exuflex.runs.read_run`, for the observer's ``channels``
    (e.g. :func:`exuflex.observer.session.default_channels`)."""
    motors = run.motors or mech.motor_names
    return check_log(mech, run.sensors, channels, motors, dt=dt, source=str(Path(run.path) / "sensors.csv"),
                     max_gap_s=max_gap_s, check_full_scale=check_full_scale)


def check_configurations(mech: Mechanism, cond_max: float = 1e6) -> None:
    """Solve the closure at ``model.q_ref`` and ``reduction.q_star``; a loop that cannot close, or a
    configuration at or near a singularity (closure Jacobian condition number above ``cond_max``), is a
    :class:`ModelFileError` naming the field."""
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

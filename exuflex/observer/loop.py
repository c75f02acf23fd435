"""The filter's sample loop, compiled: every sample of :class:`.ekf.MultirateEKF`, over a model's compiled interval
and measurement (:class:`.base.CompiledModel`) or, one sample at a time, over the prediction and measurement a
model without them returned (:meth:`.ekf.MultirateEKF.step`).

Per sample ``k`` (the interval from ``t[k-1]``, input ``U[k-1]`` held, measurement ``Y[k]``, NaN where a
channel has no sample)::

    the filter's input-step test                        (:func:`.kalman.step_statistic`)
    z, F, Q = the model's interval from x               (:func:`.expansion.cached_interval`, or given)
    P = F P F' + Q                                      (:func:`.kalman.predict_cov`, eq. 13; the first sample: P)
    y_pred, H = the model's measurement at z            (:func:`.expansion.cached_rows`, or given)
    x, P = the update with the channels sampled         (:func:`.kalman.condition_on`, eqs. 14-15; S indefinite:
                                                         an LU solve)
    the monitors on the normalised innovations: the    (:func:`screen`)
      hold-off after an input step, the sensor-fault
      windows and their verdicts, the isolation of a
      faulty channel, the gate
    if they leave a minority out, the update again without them
    record x, P, innovations, NIS

(a sample without a channel: the prediction alone, settled, and the monitor's "missing" test), until a sample
needs more (the model's arrays renewed: a new held configuration or step map, measurement rows made for the
prediction; the model's own interval: see :data:`.base.LOOP_DONE` ...). The filter's state lives in two buffer
pairs that alternate (``x, P`` current, ``x_alt, P_alt`` written): a sample left undone has written nothing but
scratch (and the prediction, where the measurement rows stopped it). ``tests/test_sample_loop.py`` holds a run
through the model's compiled step equal to one through its ``predict`` and ``measure``.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np
from numba.core import types
from numba.experimental import structref

from .base import INPUT_STEP, LOOP_DONE, MONITOR, NONFINITE, SINGULAR
from .expansion import (
    NO_DISTURBANCES,
    NO_PAYLOAD,
    CachedStep,
    HeldSystem,
    LoopExtras,
    LoopMap,
    LoopState,
    _example_system,
    cached_interval,
    cached_rows,
)
from .kalman import (
    LU,
    condition_on,
    gate,
    normalise,
    predict_cov,
    settle,
    step_statistic,
    window_push,
    window_seen,
)

__all__ = ["Buffers", "Monitors", "OneSample", "Record", "given", "one_sample", "plain", "samples", "screen",
           "warm_up"]

log = logging.getLogger(__name__)


class Buffers(NamedTuple):
    """The filter's state and scratch: the current ``x, P`` and the pair written (``x_alt, P_alt``), the predicted
    covariance, work space and ``H P``."""

    x: np.ndarray
    x_alt: np.ndarray
    P: np.ndarray
    P_alt: np.ndarray
    P_pred: np.ndarray
    work: np.ndarray
    HP: np.ndarray


class Monitors(NamedTuple):
    """The filter's measurement noise and tests: ``R``'s diagonal, the covariance's floor, the gate (chi-square(1)
    quantile) with the count of channels it left out, ``rejected``, the sensor-fault windows
    (:class:`.ekf.ChannelMonitor`'s arrays, ``win_Z`` empty: none) with their tests ``(clip, k_mean, hi, lo)``, their
    verdicts, each channel's open fault and its passed tests since (:attr:`.ekf.ChannelMonitor.loop_fields`), the
    time of the monitor's first sample ``t0`` (one entry, NaN: none yet), the findings ``events`` (one row per
    fault found, changed or cleared: ``(code, channel, t, mean z)``, :data:`CLEARED` ...) with their count
    ``n_events`` (one entry), ``isolate`` (a channel with an open offset or stuck fault left out of the updates),
    the count of updates solved by LU ``n_lu`` (one entry) and the input-step test ``step_w``, ``step_thr`` with
    the hold-off after a step, ``step_holdoff`` updates."""

    Rd: np.ndarray
    floor: np.ndarray
    gate: float
    rejected: np.ndarray
    win_Z: np.ndarray
    win_n: np.ndarray
    win_sum: np.ndarray
    win_sq: np.ndarray
    win_last: np.ndarray
    win_int: np.ndarray
    win_tests: np.ndarray
    win_status: np.ndarray
    win_kind: np.ndarray
    win_ok: np.ndarray
    t0: np.ndarray
    events: np.ndarray
    n_events: np.ndarray
    isolate: bool
    n_lu: np.ndarray
    step_w: np.ndarray
    step_thr: float
    step_holdoff: int


#: the codes of :attr:`Monitors.events` beside 1-4 (a fault of that kind opened: offset, scale, stuck, missing): a
#: scale fault found to be an offset, a fault cleared
BECAME_OFFSET, CLEARED = 5, 0


class Record(NamedTuple):
    """Where each sample done is recorded (:class:`.ekf.RunRecord`'s arrays): ``x[k]``, ``P[k]`` (``P_kind`` 0 its
    diagonal, 1 all of it flattened, -1 nothing), ``theta[k]`` the covariance's payload-scale column (empty: none),
    ``inn[k]``, ``S[k]`` (flattened; empty: none; the channels not updated with left as they are), ``nis[k]``, the
    number of channels updated with ``dof[k]`` (0: a prediction only), and the prediction ``x_pred[k]``, ``F[k]``,
    ``Q[k]`` (flattened; empty: none; what a smoother's backward pass needs)."""

    x: np.ndarray
    P: np.ndarray
    P_kind: int
    theta: np.ndarray
    inn: np.ndarray
    S: np.ndarray
    nis: np.ndarray
    dof: np.ndarray
    x_pred: np.ndarray
    F: np.ndarray
    Q: np.ndarray


@structref.register
class _OneSampleType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(typ)) for name, typ in fields)


class OneSample(structref.StructRefProxy):
    """A filter's :class:`Monitors` and a :class:`Record` of one row, their fields as one compiled structure: what
    :func:`given` takes at every :meth:`.ekf.MultirateEKF.step` and :func:`screen` at every update of the UKF and
    the IMM. Its arrays are the named tuples' own (written in place); one argument where the named tuples'
    thirty-odd arrays each cost numba's conversion at every call."""


structref.define_proxy(OneSample, _OneSampleType, [*Monitors._fields, *Record._fields])


def _one_sample(mon, rec):  # pragma: no cover - compiled (the proxy's own constructor is compiled at every start)
    return OneSample(*mon, *rec)


def _event(mon, code, i, t, mean_z):  # pragma: no cover - compiled into the loop
    """Channel ``i``'s fault ``code`` at ``t`` (:data:`CLEARED`, 1-4 opened, :data:`BECAME_OFFSET`): its kind and
    count of passed tests kept, the finding reported in ``mon.events``."""
    mon.win_kind[i] = 0 if code == CLEARED else 1 if code == BECAME_OFFSET else code
    e = mon.n_events[0]
    mon.events[e, 0], mon.events[e, 1], mon.events[e, 2], mon.events[e, 3] = code, i, t, mean_z
    mon.n_events[0] = e + 1


def _missing(mon, t, idx):  # pragma: no cover - compiled into the loop
    """The "missing" test at ``t`` with the channels ``idx`` sampled (:class:`.ekf.ChannelMonitor`): a channel
    without an open fault and without a sample for a window of its own intervals opens one; a missing channel
    sampled again closes it, its window emptied."""
    if math.isnan(mon.t0[0]):
        mon.t0[0] = t
    W = mon.win_Z.shape[0]
    seen = np.zeros(mon.win_kind.shape[0], np.bool_)
    for j in range(idx.shape[0]):
        seen[idx[j]] = True
    for i in range(seen.shape[0]):
        if not seen[i]:
            last_t = mon.win_last[i] if math.isfinite(mon.win_last[i]) else mon.t0[0]
            if mon.win_kind[i] == 0 and t - last_t > W * mon.win_int[i]:
                _event(mon, 4, i, t, math.nan)
        elif mon.win_kind[i] == 4:
            _event(mon, CLEARED, i, t, math.nan)
            mon.win_n[i] = 0
            mon.win_sum[i] = 0.0
            mon.win_sq[i] = 0.0
            for w in range(W):
                mon.win_Z[w, i] = 0.0


def _verdicts(mon, t, idx):  # pragma: no cover - compiled into the loop
    """The window tests' verdicts ``mon.win_status`` of the channels ``idx`` at ``t``: a failed test opens a fault
    (or finds a scale fault's window now offset), a whole window of passed tests since clears it."""
    W = mon.win_Z.shape[0]
    for j in range(idx.shape[0]):
        i, st = idx[j], mon.win_status[j]
        if st > 0:
            mon.win_ok[i] = 0
            if mon.win_kind[i] == 0 or (st == 1 and mon.win_kind[i] == 2):
                _event(mon, st if mon.win_kind[i] == 0 else BECAME_OFFSET, i, t, mon.win_sum[i] / W)
        elif st == 0 and mon.win_kind[i] != 0:
            mon.win_ok[i] += 1
            if mon.win_ok[i] >= W:
                _event(mon, CLEARED, i, t, math.nan)


def _screen(mon, t, idx, zn, n_over, holdoff, keep):  # pragma: no cover - compiled
    """One update's normalised innovations ``zn`` of the channels ``idx`` at ``t`` (``n_over`` beyond the gate)
    through the monitors (:mod:`.ekf`'s notes): the "missing" test; within the ``holdoff`` after an input step
    nothing is gated or tested; else the sensor-fault windows and their verdicts, the isolation of channels with an
    open offset or stuck fault and the gate (``idx`` empty, a prediction only: the "missing" test alone). Writes the channels kept to ``keep`` (counting the others in ``mon.rejected``); returns
    ``(n_keep, holdoff)``."""
    windows = mon.win_Z.shape[0] > 0
    if windows:
        _missing(mon, t, idx)
    if idx.shape[0] == 0:  # a prediction only: the "missing" test alone
        return 0, holdoff
    if holdoff > 0:
        holdoff -= 1
        n_over = 0
        if windows:
            window_seen(mon.win_last, mon.win_int, t, idx)
    elif windows:
        window_push(mon.win_Z, mon.win_n, mon.win_sum, mon.win_sq, mon.win_last, mon.win_int, t, idx, zn,
                    mon.win_tests[0], mon.win_tests[1], mon.win_tests[2], mon.win_tests[3], mon.win_status)
        _verdicts(mon, t, idx)
    for j in range(idx.shape[0]):
        kind = mon.win_kind[idx[j]]
        keep[j] = not (mon.isolate and (kind == 1 or kind == 3))
    n_keep = gate(zn, mon.gate, n_over, keep)
    if n_keep < idx.shape[0]:
        for j in range(idx.shape[0]):
            if not keep[j]:
                mon.rejected[idx[j]] += 1
    return n_keep, holdoff


def _sample(t_k, y, z, F, Qk, y_pred, H, holdoff, buf, mon, x_out, P_out):  # pragma: no cover - compiled into
    """One sample from the prediction ``z, F, Qk`` (``F`` empty: the first sample, the prior is the prediction) and
    the measurement ``y_pred, H`` of every channel (their rows of the channels not sampled, NaN in ``y``, not read),
    the hold-off ``holdoff`` left: the covariance's prediction, the update with the channels sampled, the monitors
    (:func:`screen`) and, where they leave a minority out, the update again without them, settled into ``x_out``,
    ``P_out``. Returns ``(status, holdoff, (sampled, kept, r, S), nis)``: ``LOOP_DONE``, or the update went
    non-finite (``NONFINITE``) or met a singular ``S`` (``SINGULAR``)."""
    m, n_x = y.shape[0], z.shape[0]
    if F.shape[0]:
        predict_cov(F, buf.P, Qk, buf.P_pred, buf.work)
    else:  # the first sample
        for i in range(n_x):
            for j in range(n_x):
                buf.P_pred[i, j] = buf.P[i, j]
    sampled = np.empty(m, np.bool_)
    n_s = 0
    for i in range(m):
        sampled[i] = math.isfinite(y[i])
        n_s += sampled[i]
    idx = np.empty(n_s, np.int64)  # the channels sampled
    j = 0
    for i in range(m):
        if sampled[i]:
            idx[j] = i
            j += 1
    kept, nis, r, S = idx, math.nan, np.empty(0), np.empty((0, 0))
    zn = np.empty(n_s)
    gated = np.empty(n_s, np.bool_)
    if n_s == 0:  # a prediction only, and the monitor's "missing" test
        for i in range(n_x):
            x_out[i] = z[i]
            for j in range(n_x):
                P_out[i, j] = buf.P_pred[i, j]
        finite = settle(x_out, P_out, mon.floor)
        if finite:
            _screen(mon, t_k, idx, zn, 0, holdoff, gated)
        return LOOP_DONE if finite else NONFINITE, holdoff, (idx, kept, r, S), nis
    nis, how, finite, r, S = condition_on(sampled, z, buf.P_pred, y, y_pred, H, mon.Rd, mon.floor, buf.HP, x_out,
                                          P_out)
    mon.n_lu[0] += how == LU
    if how > LU:  # S singular
        return SINGULAR, holdoff, (idx, kept, r, S), nis
    n_keep, holdoff = _screen(mon, t_k, idx, zn, normalise(r, S, mon.gate, zn), holdoff, gated)
    if n_keep < n_s:  # a minority left out: the update without them
        kept = np.empty(n_keep, np.int64)
        j = 0
        for i in range(n_s):
            sampled[idx[i]] = gated[i]
            if gated[i]:
                kept[j] = idx[i]
                j += 1
        nis, how, finite, r, S = condition_on(sampled, z, buf.P_pred, y, y_pred, H, mon.Rd, mon.floor, buf.HP,
                                              x_out, P_out)
        mon.n_lu[0] += how == LU
        if how > LU:
            return SINGULAR, holdoff, (idx, kept, r, S), nis
    return LOOP_DONE if finite else NONFINITE, holdoff, (idx, kept, r, S), nis


def _record(rec, k, x, P, last, nis, m):  # pragma: no cover - compiled into the loop
    """Sample ``k`` done, its posterior ``x, P``: recorded (:class:`Record`), element by element (a row or slice
    assignment compiles numba's shape checks and their messages into the loop, which then takes far longer to
    compile)."""
    n_x = x.shape[0]
    kept, r, S = last[1], last[2], last[3]
    for i in range(n_x):
        rec.x[k, i] = x[i]
        if rec.P_kind == 0:
            rec.P[k, i] = P[i, i]
        elif rec.P_kind == 1:
            for j in range(n_x):
                rec.P[k, i * n_x + j] = P[i, j]
    if rec.inn.shape[0]:  # the channels updated with (the others stay NaN)
        for i in range(kept.shape[0]):
            rec.inn[k, kept[i]] = r[i]
            for j in range(kept.shape[0]):
                rec.S[k, kept[i] * m + kept[j]] = S[i, j]
    rec.nis[k] = nis
    rec.dof[k] = kept.shape[0]


def _given(t_k, y, holdoff, buf, one, z, F, Q, y_pred, H):  # pragma: no cover - compiled
    """One sample with the model's prediction ``z, F, Q`` and measurement ``y_pred, H`` given (a model without a
    compiled step: :meth:`.ekf.MultirateEKF.step`), at ``t_k`` with the measurement ``y``: :func:`_sample` into
    ``buf.x_alt, buf.P_alt`` (``buf`` a plain tuple of :class:`Buffers`), recorded in row 0 of ``one``'s record
    (:class:`OneSample`). Returns ``(status, holdoff, last)`` (:func:`samples`)."""
    buf = Buffers(*buf)
    status, holdoff, last, nis = _sample(t_k, y, z, F, Q, y_pred, H, holdoff, buf, one, buf.x_alt, buf.P_alt)
    if status == LOOP_DONE:
        _record(one, 0, buf.x_alt, buf.P_alt, last, nis, y.shape[0])
    return status, holdoff, last


def _samples(t, U, Y, k0, k1, holdoff, rows_made, buf, mon, rec, step, state, extras):  # pragma: no cover - compiled
    """Samples ``k0 .. k1 - 1`` (module docstring) through the model's compiled step, ``holdoff`` updates of the
    hold-off after an input step left, ``rows_made``: the model's measurement rows were made for the prediction at
    ``k0`` (they serve it wherever it lies, as :meth:`.reduced.ReducedObserverModel.measure` takes rows it has just
    made), the filter's :class:`Buffers`, :class:`Monitors` and :class:`Record`, the model's
    :class:`.base.LoopModel` parts ``step``, ``state``, ``extras`` (None for a plain state: numba prunes the
    augmented branches).

    Returns ``(k, status, holdoff, swapped, state, mats, last)``: the first sample not done, why, the hold-off left,
    whether the current state is in the ``_alt`` buffers, the model's carried state, the last interval's held
    matrices (for :meth:`.base.CompiledModel.loop_done`) and of the last sample done (or the one that went
    non-finite) the channels sampled, those updated with, their innovations and its covariance.

    The named tuples arrive as plain tuples (:func:`plain`) and are named here: numba types a plain tuple of arrays
    from its fingerprint, a named one through a slower path that keeps a few objects alive per call."""
    buf, mon, rec = Buffers(*buf), Monitors(*mon), Record(*rec)
    step = CachedStep(*step[:-1], HeldSystem(*step[-1]))
    state = LoopState(LoopMap(*state[0]), state[1], state[2], state[3])
    x, x_alt, P, P_alt = buf.x, buf.x_alt, buf.P, buf.P_alt
    m = Y.shape[1]
    n_x = x.shape[0]
    y_pred = np.empty(m)
    H = np.zeros((m, n_x))  # (the columns beyond the model's rows stay zero)
    none = np.empty((0, 0))
    mats = (none, none, none, none)
    no_idx = np.empty(0, np.int64)
    last = (no_idx, no_idx, np.empty(0), none)
    swapped = False
    status = LOOP_DONE
    k = k0
    while k < k1:
        stepped = step_statistic(U[k - 1], U[k], mon.step_w) > mon.step_thr
        if stepped:  # an input step: the hold-off from this sample's update on (its transient is the model's)
            holdoff = mon.step_holdoff
        status, z, F, Qk, mats_k, state = cached_interval(step, extras, state, x, U[k - 1], U[k], t[k] - t[k - 1],
                                                          k == k0, k, P)
        if status != LOOP_DONE:
            break
        n_s = 0
        for i in range(m):
            n_s += math.isfinite(Y[k, i])
        if n_s:
            status = cached_rows(step, z, y_pred, H, rows_made and k == k0)
            if status != LOOP_DONE:  # (ROWS: the prediction, for the model's new rows, in the buffer not written)
                for i in range(n_x):
                    x_alt[i] = z[i]
                break
        status, holdoff, last, nis = _sample(t[k], Y[k], z, F, Qk, y_pred, H, holdoff,
                                             Buffers(x, x_alt, P, P_alt, buf.P_pred, buf.work, buf.HP), mon, x_alt,
                                             P_alt)
        if status != LOOP_DONE:
            break
        x, x_alt = x_alt, x
        P, P_alt = P_alt, P
        swapped = not swapped
        mats = mats_k
        _record(rec, k, x, P, last, nis, m)
        if rec.x_pred.shape[0]:
            for i in range(n_x):
                rec.x_pred[k, i] = z[i]
                for j in range(n_x):
                    rec.F[k, i * n_x + j] = F[i, j]
                    rec.Q[k, i * n_x + j] = Qk[i, j]
        if extras is not None and extras.pay_held:  # (pruned for a plain state) a held scale's interval done
            extras.pay_stats[0] += 1.0
        if extras is not None and rec.theta.shape[0]:  # (pruned for a plain state)
            n0 = 2 * step.system.Mr.shape[0]
            for i in range(n_x):
                rec.theta[k, i] = P[i, n0]
        k += 1
        if mon.n_events[0] > mon.events.shape[0] - 2 * m:  # the findings' report full: the filter reads it
            status = MONITOR
            break
        if stepped:
            status = INPUT_STEP
            break
    return k, status, holdoff, swapped, state, mats, last


try:  # numba is a core dependency; without it the loop runs as plain (slow) Python
    import numba

    _inline = numba.njit(inline="always", nogil=True, error_model="numpy", no_cfunc_wrapper=True)
    _event, _missing, _verdicts = _inline(_event), _inline(_missing), _inline(_verdicts)
    screen = numba.njit(cache=True, nogil=True, error_model="numpy", no_cfunc_wrapper=True)(_screen)
    _screen, _sample, _record = _inline(_screen), _inline(_sample), _inline(_record)
    given = numba.njit(cache=True, nogil=True, error_model="numpy", no_cfunc_wrapper=True)(_given)
    _one_sample = numba.njit(cache=True, nogil=True, no_cfunc_wrapper=True)(_one_sample)
    samples = numba.njit(cache=True, nogil=True, error_model="numpy", no_cfunc_wrapper=True)(_samples)
except ImportError:  # pragma: no cover
    samples, screen, given = _samples, _screen, _given


def plain(buf: Buffers, mon: Monitors, rec: Record, step, state) -> tuple:
    """The arguments :func:`samples` takes for ``buf``, ``mon``, ``rec`` and the model's ``step``
    (:class:`.expansion.CachedStep`) and ``state`` (:class:`.expansion.LoopState`): the same, as plain tuples."""
    return tuple(buf), tuple(mon), tuple(rec), (*step[:-1], tuple(step.system)), (tuple(state.map), *state[1:])


def one_sample(mon: Monitors, rec: Record) -> OneSample:
    """``mon`` and the one-row record ``rec`` as :func:`given` takes them (:class:`OneSample`: their arrays, not
    copies)."""
    return _one_sample(tuple(mon), tuple(rec))


def no_windows(m: int) -> tuple:
    """The sensor-fault monitor's fields of :class:`Monitors` (``win_Z`` ... ``n_events``) for a filter without one."""
    v, n = np.zeros(0), np.zeros(0, dtype=np.int64)
    return (np.zeros((0, m)), n, v, v, v, v, np.zeros(4), n, np.zeros(m, dtype=np.int64), n, np.full(1, np.nan),
            np.zeros((4 * m, 4)), np.zeros(1, dtype=np.int64))


def warm_up(compiled: str | None = None, screened: bool = True) -> None:
    """Compile (or load from numba's on-disk cache) the loop for the argument types the filter passes: called with
    no sample to do (``k0 = k1``), :func:`samples` returns at once. Always :func:`given`; ``screened``:
    :func:`screen` (what an update screened in Python calls: not the EKF's over a compiled step, whose updates
    :func:`given` screens); ``compiled`` "plain" or "augmented": :func:`samples` over a model's compiled step for a
    plain or an augmented state (with :func:`.expansion.extra_interval`)."""
    v, m, c, n = np.zeros(1), np.zeros((1, 1)), np.zeros((1, 1, 1)), np.zeros(1, dtype=np.int64)
    buf = Buffers(v, v, m, m, m, m, m)
    mon = Monitors(v, v, 0.0, n, m, n, v, v, v, v, v, n, n, n, v, m, n, False, n, v, 0.0, 0)
    rec = Record(m, m, 0, m, m, m, v, n, m, m, m)
    one = one_sample(mon, rec)
    given(0.0, v, 0, tuple(buf), one, v, m, m, v, m)
    if screened:
        screen(one, 0.0, n[:0], v[:0], 0, 0, np.zeros(0, np.bool_))
    if compiled is not None:
        step = CachedStep(v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, v, v, 0.0, 0.0, 0.0, v, m, c, c, v, 0.0, v, 0.0,
                          c, c, c, v, _example_system(1, 1))
        state = LoopState(LoopMap(v, 0.0, 0.0, 1, m, m, m, m), 0, -1, (False, 0.0, m, m, m, m))
        extras = LoopExtras(*NO_PAYLOAD, *NO_DISTURBANCES) if compiled == "augmented" else None
        samples(v, m, m, 1, 1, 0, False, *plain(buf, mon, rec, step, state), extras)

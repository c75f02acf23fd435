"""The filter's compiled sample loop: samples of a log, each exactly as :meth:`.ekf.MultirateEKF.step` takes it,
over a model's compiled interval and measurement (:class:`.base.CompiledModel`).

Per sample ``k`` (the interval from ``t[k-1]``, input ``U[k-1]`` held, measurement ``Y[k]``, NaN where a
channel has no sample)::

    the filter's input-step test                        (:func:`.kalman.step_statistic`)
    z, F, Q = the model's interval from x               (:func:`.expansion.cached_interval`)
    P = F P F' + Q                                      (:func:`.kalman.predict_cov`, eq. 13)
    y_pred, H = the model's measurement at z            (:func:`.expansion.cached_rows`)
    x, P = the update with the channels sampled         (:func:`.kalman.condition_on`, eqs. 14-15)
    the gate; if it leaves a minority out, the update   (:func:`.kalman.normalise`, :func:`.kalman.gate`)
      again without them
    hold-off, sensor-fault windows                      (:func:`.kalman.window_push`)
    record x, P, innovations, NIS

(a sample without a channel: the prediction alone, settled), until a sample needs more (the model's arrays
renewed: a new held configuration or step map, measurement rows made for the prediction; a sample for
:meth:`~.ekf.MultirateEKF.step`: see :data:`.base.LOOP_DONE` ...). The filter's state lives in two buffer pairs
that alternate (``x, P`` current, ``x_alt, P_alt`` written): a sample left undone has written nothing but scratch
(and the prediction, where the measurement rows stopped it). ``tests/test_sample_loop.py`` holds the loop and
``step`` bit-identical.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np

from .base import GENERAL, INPUT_STEP, LOOP_DONE, MONITOR
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
    condition_on,
    gate,
    normalise,
    predict_cov,
    settle,
    step_statistic,
    window_push,
    window_seen,
)

__all__ = ["Buffers", "Monitors", "Record", "plain", "samples", "warm_up"]

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
    verdicts, each channel's open fault and its passed tests since (:attr:`.ekf.ChannelMonitor.verdict_arrays`) and
    the time of the monitor's first sample ``t0``, and the input-step test ``step_w``, ``step_thr`` with the
    hold-off after a step, ``step_holdoff`` updates."""

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
    t0: float
    step_w: np.ndarray
    step_thr: float
    step_holdoff: int


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


def _verdicts(mon, idx):  # pragma: no cover - compiled into the loop
    """The window tests' verdicts ``mon.win_status`` of the channels ``idx`` (:meth:`.ekf.ChannelMonitor.verdicts`):
    where none opens, changes or clears a fault, the counts of passed tests since a fault (``win_ok``) and 0;
    else nothing is changed and the number of such verdicts (the monitor reports them after the sample)."""
    W = mon.win_Z.shape[0]
    n_events = 0
    for j in range(idx.shape[0]):
        i = idx[j]
        st, kind = mon.win_status[j], mon.win_kind[i]
        if st > 0 and (kind == 0 or (st == 1 and kind == 2)):  # found, or a scale fault's window now offset
            n_events += 1
        elif st == 0 and kind != 0 and mon.win_ok[i] + 1 >= W:  # cleared
            n_events += 1
    if n_events == 0:
        for j in range(idx.shape[0]):
            i, st = idx[j], mon.win_status[j]
            if st > 0:
                mon.win_ok[i] = 0
            elif st == 0 and mon.win_kind[i] != 0:
                mon.win_ok[i] += 1
    return n_events


def _samples(t, U, Y, k0, k1, holdoff, rows_made, buf, mon, rec, step, state, extras):  # pragma: no cover - compiled
    """Samples ``k0 .. k1 - 1`` (module docstring), ``holdoff`` updates of the hold-off after an input step left,
    ``rows_made``: the model's measurement rows were made for the prediction at ``k0`` (they serve it wherever it
    lies, as :meth:`.reduced.ReducedObserverModel.measure` takes rows it has just made),
    the filter's :class:`Buffers`, :class:`Monitors` and :class:`Record`, the model's :class:`.base.LoopModel`
    parts ``step``, ``state``, ``extras`` (None for a plain state: numba prunes the augmented branches).

    Returns ``(k, status, holdoff, swapped, state, mats, last)``: the first sample not done, why, the hold-off left,
    whether the current state is in the ``_alt`` buffers, the model's carried state, the last interval's held
    matrices (for :meth:`.base.CompiledModel.loop_done`) and of the last sample done the channels sampled, those
    updated with, their innovations and its covariance.

    The named tuples arrive as plain tuples (:func:`plain`) and are named here: numba types a plain tuple of arrays
    from its fingerprint, a named one through a slower path that keeps a few objects alive per call."""
    buf, mon, rec = Buffers(*buf), Monitors(*mon), Record(*rec)
    step = CachedStep(*step[:-1], HeldSystem(*step[-1]))
    state = LoopState(LoopMap(*state[0]), state[1], state[2], state[3])
    x, x_alt, P, P_alt = buf.x, buf.x_alt, buf.P, buf.P_alt
    m = Y.shape[1]
    n_x = x.shape[0]
    sampled = np.empty(m, np.bool_)
    keep = np.empty(m, np.bool_)
    y_pred = np.empty(m)
    H = np.zeros((m, n_x))  # (the columns beyond the model's rows stay zero)
    none = np.empty((0, 0))
    mats = (none, none, none, none)
    windows = mon.win_Z.shape[0] > 0
    no_idx = np.empty(0, np.int64)
    last = (no_idx, no_idx, np.empty(0), none)
    swapped = False
    status = LOOP_DONE
    k = k0
    while k < k1:
        stepped = step_statistic(U[k - 1], U[k], mon.step_w) > mon.step_thr
        if stepped:  # an input step: the hold-off from this sample's update on (its transient is the model's)
            holdoff = mon.step_holdoff
        n_s = 0
        for i in range(m):
            sampled[i] = math.isfinite(Y[k, i])
            if sampled[i]:
                n_s += 1
        if windows:  # would the sensor-fault monitor find a channel missing, or one back? (then step() takes it)
            due = False
            for i in range(m):  # missing: no sample for a window of its own intervals (:class:`.ekf.ChannelMonitor`)
                last_t = mon.win_last[i] if math.isfinite(mon.win_last[i]) else mon.t0
                if sampled[i]:
                    due |= mon.win_kind[i] == 4
                elif mon.win_kind[i] == 0:
                    due |= t[k] - last_t > mon.win_Z.shape[0] * mon.win_int[i]
            if due:
                status = GENERAL
                break
        status, z, F, Qk, mats_k, state = cached_interval(step, extras, state, x, U[k - 1], U[k], t[k] - t[k - 1],
                                                          k == k0, k, P)
        if status != LOOP_DONE:
            break
        predict_cov(F, P, Qk, buf.P_pred, buf.work)
        idx = np.empty(n_s, np.int64)  # the channels sampled
        j = 0
        for i in range(m):
            if sampled[i]:
                idx[j] = i
                j += 1
        kept, n_keep, nis, r, S = idx, n_s, math.nan, np.empty(0), none
        zn = np.empty(n_s)
        if n_s == 0:  # a prediction only
            for i in range(n_x):
                x_alt[i] = z[i]
                for j in range(n_x):
                    P_alt[i, j] = buf.P_pred[i, j]
            finite = settle(x_alt, P_alt, mon.floor)
        else:
            status = cached_rows(step, z, y_pred, H, rows_made and k == k0)
            if status != LOOP_DONE:  # (ROWS: the prediction, for the model's new rows, in the buffer not written)
                for i in range(n_x):
                    x_alt[i] = z[i]
                break
            nis, ok, finite, r, S = condition_on(sampled, z, buf.P_pred, Y[k], y_pred, H, mon.Rd, mon.floor,
                                                 buf.HP, x_alt, P_alt)
            if not ok:
                status = GENERAL
                break
            n_over = normalise(r, S, mon.gate, zn)
            gated = np.ones(n_s, np.bool_)
            n_keep = gate(zn, mon.gate, 0 if holdoff > 0 else n_over, gated)
            if n_keep < n_s:  # a minority gated: the update without them
                kept = np.empty(n_keep, np.int64)
                j = 0
                for i in range(m):
                    keep[i] = False
                for i in range(n_s):
                    if gated[i]:
                        keep[idx[i]] = True
                        kept[j] = idx[i]
                        j += 1
                nis, ok, finite, r, S = condition_on(keep, z, buf.P_pred, Y[k], y_pred, H, mon.Rd, mon.floor,
                                                     buf.HP, x_alt, P_alt)
                if not ok:
                    status = GENERAL
                    break
        if not finite:
            status = GENERAL
            break
        # the sample is done: the monitors' windows and counts (nothing was written to them before)
        n_bad = 0
        if n_s:
            if holdoff > 0:
                holdoff -= 1
                if windows:
                    window_seen(mon.win_last, mon.win_int, t[k], idx)
            elif windows:
                window_push(mon.win_Z, mon.win_n, mon.win_sum, mon.win_sq, mon.win_last, mon.win_int, t[k], idx, zn,
                            mon.win_tests[0], mon.win_tests[1], mon.win_tests[2], mon.win_tests[3], mon.win_status)
                n_bad = _verdicts(mon, idx)
            if n_keep < n_s:
                for i in range(n_s):
                    if not gated[i]:
                        mon.rejected[idx[i]] += 1
        x, x_alt = x_alt, x
        P, P_alt = P_alt, P
        swapped = not swapped
        mats = mats_k
        last = (idx, kept, r, S)
        # the record, element by element (a row or slice assignment compiles numba's shape checks and their
        # messages into the loop, which then takes far longer to compile)
        for i in range(n_x):
            rec.x[k, i] = x[i]
            if rec.P_kind == 0:
                rec.P[k, i] = P[i, i]
            elif rec.P_kind == 1:
                for j in range(n_x):
                    rec.P[k, i * n_x + j] = P[i, j]
        if rec.inn.shape[0]:  # the channels updated with (the others stay NaN)
            for i in range(n_keep):
                rec.inn[k, kept[i]] = r[i]
                for j in range(n_keep):
                    rec.S[k, kept[i] * m + kept[j]] = S[i, j]
        rec.nis[k] = nis
        rec.dof[k] = n_keep
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
        if n_bad:
            status = MONITOR
            break
        if stepped:
            status = INPUT_STEP
            break
    return k, status, holdoff, swapped, state, mats, last


try:  # numba is a core dependency; without it the loop runs as plain (slow) Python
    import numba

    _verdicts = numba.njit(inline="always", nogil=True, error_model="numpy", no_cfunc_wrapper=True)(_verdicts)
    samples = numba.njit(cache=True, nogil=True, error_model="numpy", no_cfunc_wrapper=True)(_samples)
except ImportError:  # pragma: no cover
    samples = _samples


def plain(buf: Buffers, mon: Monitors, rec: Record, step, state) -> tuple:
    """The arguments :func:`samples` takes for ``buf``, ``mon``, ``rec`` and the model's ``step``
    (:class:`.expansion.CachedStep`) and ``state`` (:class:`.expansion.LoopState`): the same, as plain tuples."""
    return tuple(buf), tuple(mon), tuple(rec), (*step[:-1], tuple(step.system)), (tuple(state.map), *state[1:])


def warm_up(augmented: bool | None = None) -> None:
    """Compile (or load from numba's on-disk cache) :func:`samples` for the argument types the filter passes: called
    with no sample to do (``k0 = k1``), it returns at once. ``augmented`` None: the plain state's specialisation;
    True: the augmented states' (with :func:`.expansion.extra_interval`)."""
    v, m, c, n = np.zeros(1), np.zeros((1, 1)), np.zeros((1, 1, 1)), np.zeros(1, dtype=np.int64)
    buf = Buffers(v, v, m, m, m, m, m)
    mon = Monitors(v, v, 0.0, n, m, n, v, v, v, v, v, n, n, n, 0.0, v, 0.0, 0)
    rec = Record(m, m, 0, m, m, m, v, n, m, m, m)
    step = CachedStep(v, 0.0, v, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, v, v, 0.0, 0.0, 0.0, v, m, c, c, v, 0.0, v, 0.0, c, c, c, v,
                      _example_system(1, 1))
    state = LoopState(LoopMap(v, 0.0, 0.0, 1, m, m, m, m), 0, -1, (False, 0.0, m, m, m, m))
    extras = LoopExtras(*NO_PAYLOAD, *NO_DISTURBANCES) if augmented else None
    samples(v, m, m, 1, 1, 0, False, *plain(buf, mon, rec, step, state), extras)

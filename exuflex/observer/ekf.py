"""Multirate extended Kalman filter (paper eqs. 10-15): one driver over a model's predict and measure steps.

One call of :meth:`MultirateEKF.step` processes one sample at time ``t``::

    predict  x_k|k-1, F, Q = model.predict(x_k-1, u_k-1, t_k - t_k-1)            (eqs. 10-12)
             P_k|k-1 = F P_k-1 F' + Q                                              (eq. 13)
    update   y_pred, H = model.measure(x_k|k-1, channels sampled at t_k)
             r = y_k - y_pred,  S = H P H' + R,  K = P H' S^-1                     (eq. 14)
             x_k = x_k|k-1 + K r,   P_k = (I - K H) P (I - K H)' + K R K'          (eq. 15, Joseph form)

then symmetrises ``P``, floors its diagonal and tests that the state and covariance are finite. The Joseph form
keeps ``P`` symmetric positive semi-definite for any gain, where ``(I - K H) P`` loses it to rounding; the gain
and ``S^-1 r`` come from one Cholesky solve of ``S`` (an LU solve with a warning if ``S`` is not positive
definite). Every sample goes through one compiled sample loop (:func:`.loop.samples`, over the kernels of
:mod:`.kalman`): :meth:`~MultirateEKF.step` hands it the model's prediction and measurement for one sample;
:meth:`~BeliefFilter.run` gives the numbers of ``step`` over a whole log, so the online and offline estimates are
the same: where the model has a compiled step (:class:`.base.CompiledModel`: the cached reduced model), ``run``
hands the loop the samples it can take (a valid interval and input) with the model's compiled interval and
measurement, until one needs more: the model renews its arrays (a new held configuration or step map, measurement
rows for the prediction) and the loop resumes, or ``step`` takes that sample (the first, the model's own interval
at a torque jump). ``tests/test_sample_loop.py`` holds the two bit-identical.

Each interval is as long as its two time stamps say: jitter, drift and irregular sampling need no grid. A
sample whose channels are partly NaN updates with the finite ones (``R`` restricted to them: multirate
sensors, a blank column); an all-NaN sample is a prediction only. Intervals longer than ``max_gap`` are
refused: the model would integrate an unbounded time without a measurement.

Filter consistency is monitored with the normalised innovation squared (NIS): over a moving window of the
last ``nis_window`` updates, the summed NIS is chi-square with the summed number of channels for a
consistent filter. The flag is *set* when that sum exceeds the ``divergence_confidence`` (99.9 %) quantile in
``divergence_confirm`` consecutive *disjoint* windows (default 2: a single outlier cannot set it) and *cleared*
when the window sum has stayed within the bound for a whole window of updates (hysteresis: the flag means "the
innovations are out of their band now", not "once"). Each set-to-clear stretch is one flagged interval.
"Diverged" is reserved for a non-finite state or covariance.

Sensor faults (:class:`ChannelMonitor`): each channel's innovation is normalised by its own innovation standard
deviation, ``z_i = r_i / sqrt(S_ii)`` (standard normal for a consistent filter and a healthy sensor).

- *Gating*: a channel with ``z_i**2`` above the chi-square(1) quantile ``1 - gate_p`` is left out of the update
  (counted per channel in ``n_rejected``), as long as fewer than half the channels of the sample exceed it (when
  most do, the filter, not a sensor, is off: nothing is gated and the NIS test sees it).
- *Offset / scale*: over the last ``fault_window`` samples of a channel, with ``z`` clipped at the gate (one
  spike moves the sums by at most one gate), ``|sum z| / sqrt(W)`` is tested against the two-sided normal
  quantile and ``sum z**2`` against both chi-square(W) tails at false-alarm probability ``fault_p``: an offset
  or gain error shows as a mean, spikes or a noisier sensor as a large scale, a stuck (frozen) sensor as a
  scale below its noise. A channel without a sample for ``fault_window`` of its own intervals is "missing".
  Each fault is reported with its channel, kind and the times it was found and cleared (after a whole window
  back in band).
- *Isolation* (``isolate=True``; off by default): a channel with an open offset or stuck fault is left out of the
  updates (counted in ``n_rejected``) until its innovations against the estimate from the others are back in
  band. A model error looks like a sensor offset to these tests (the six-bar with its payload doubled: q3
  reported as an offset, isolated, and its error 19 times the plain filter's), which is why the tests report and
  only isolate on request. If the others
  observe its quantity poorly, that may not happen before the end of the run: the fault then stays open.
  Within the hold-off after an input step nothing is gated (the step's innovations are real and large): spikes
  there reach the estimate, and a channel they drag may then be isolated for the rest of the run.
- *Allowance for input steps*: after a step in the input (a model with an ``n_jumps`` counter), nothing is
  gated and neither test runs for ``fault_holdoff`` updates.

Gating and the fault tests are off by default (``gate_p=None``, ``fault_window=0``: the textbook filter);
:class:`~exuflex.observer.session.ObserverConfig` turns them on for the observer.

Timing convention: ``x0``, ``P0`` are the *prior* at the first sample time. ``step(t_k, u_k, y_k)`` predicts
from the previous sample to ``t_k`` with the input stored at the previous call (zero-order hold, ``u_k-1``
drives ``x_k`` as in eq. 10), updates with ``y_k``, stores ``u_k`` and returns the posterior at ``t_k``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..erls.kinematics import KinematicsError
from . import kalman, loop
from .base import (INPUT_STEP, LOOP_DONE, MONITOR, NONFINITE, REFRESH, REMAP, ROWS, SINGULAR, Belief, DiscreteModel,
                   FilterDivergedError, hooks, takes_compiled_loop)
from .stats import chi2_ppf, norm_ppf

__all__ = ["BeliefFilter", "ChannelMonitor", "EstimationResult", "Monitoring", "MultirateEKF", "NISMonitor"]

log = logging.getLogger(__name__)

# what a model raises where it cannot be evaluated at the estimate (a runaway state where the mechanism's loops
# no longer close): the filter has diverged, the model file is not at fault
_MODEL_FAILURES = (ArithmeticError, np.linalg.LinAlgError, KinematicsError)


@dataclass
class EstimationResult:
    """Output of :meth:`MultirateEKF.run`.

    Attributes
    ----------
    t : ndarray, shape (n,)
        Sample times.
    x_hat : ndarray, shape (n, nx)
        Posterior state estimates (the prior where a sample was missing).
    P : ndarray or None
        Posterior covariance: diagonal, shape (n, nx) (``store_P="diag"``), full, shape (n, nx, nx)
        (``"full"``), or None (``"none"``).
    innovations : ndarray, shape (n, m), or None
        Innovation ``y - g(x_prior)`` per channel; NaN for channels not used at that sample (None: not recorded,
        ``run(..., innovations=False)``).
    S : ndarray, shape (n, m, m), or None
        Innovation covariance; NaN rows/columns for channels not used (None: not recorded).
    nis : ndarray, shape (n,)
        Normalised innovation squared ``r' S^-1 r``; NaN at samples without an update.
    nis_dof : ndarray of int, shape (n,)
        Number of channels used at each sample (the chi-square degrees of freedom of ``nis``).
    n_missing : int
        Prediction-only intervals: all-NaN samples plus whole intervals skipped between samples.
    n_updates : int
        Samples with at least one finite channel.
    diverged : bool
        The filter went non-finite (in ``nonfinite="flag"`` mode; estimates from then on are NaN).
    diverged_at : float or None
        Time the estimate became non-finite.
    nonfinite : bool
        Same as ``diverged`` (kept for readers of older results).
    nis_flagged : bool
        The NIS test was set at least once.
    nis_flagged_at : float or None
        Time the NIS test was first set.
    flagged_intervals : list of (float, float)
        Each ``(set, cleared)`` time of the NIS flag; a flag still set at the end closes at the last sample.
    channel_faults : list of dict
        Sensor faults found (:class:`ChannelMonitor`): ``channel``, ``kind`` ("offset", "scale", "stuck",
        "missing"), ``start`` and ``end`` (s), ``mean_z`` (window mean of the normalised innovation when found).
    n_rejected : dict str -> int
        Samples of each channel left out of the update by the gate.
    P_theta : ndarray, shape (n, nx), or None
        The covariance of every state with the model's payload scale (its column of the posterior covariance),
        recorded for a model with a payload state (``model.i_theta``), whatever ``P`` storage was chosen: what
        the estimate's conditioning on the nominal payload needs (:func:`.augmented.nominal_mixture`).
    nominal_p : ndarray, shape (n,), or None
        Set where ``x_hat`` and ``P`` are the payload estimator's report rather than the filter's posterior: the
        posterior probability of the nominal payload at each sample (:func:`.augmented.nominal_mixture`).
    x_pred, F, Q : ndarray, shapes (n, nx), (n, nx, nx), (n, nx, nx), or None
        Each sample's prediction: the predicted mean, the step Jacobian and the process noise of the interval
        that ends at it (undefined at the first sample; recorded with ``run(..., predictions=True)``: what the
        smoother's backward pass needs, :func:`.smoother.rts_backward`).
    wall_s : float
        Wall-clock time of the run (s).
    channels : tuple of str
        Channel order of the columns of ``innovations`` and ``S``.
    """

    t: np.ndarray
    x_hat: np.ndarray
    P: np.ndarray | None
    innovations: np.ndarray | None
    S: np.ndarray | None
    nis: np.ndarray
    nis_dof: np.ndarray
    n_missing: int
    n_updates: int
    diverged: bool
    diverged_at: float | None
    nonfinite: bool
    wall_s: float
    channels: tuple[str, ...] = ()
    nis_flagged: bool = False
    nis_flagged_at: float | None = None
    flagged_intervals: list = field(default_factory=list)
    channel_faults: list = field(default_factory=list)
    n_rejected: dict = field(default_factory=dict)
    P_theta: np.ndarray | None = None
    nominal_p: np.ndarray | None = None
    x_pred: np.ndarray | None = None
    F: np.ndarray | None = None
    Q: np.ndarray | None = None

    @property
    def P_diag(self) -> np.ndarray | None:
        """Posterior variances, shape (n, nx), whatever ``P`` storage was chosen (None if not stored)."""
        if self.P is None:
            return None
        return self.P if self.P.ndim == 2 else np.diagonal(self.P, axis1=1, axis2=2)

    def mean_nis(self, burn_in: int = 0) -> tuple[float, float]:
        """Time-averaged NIS and its expected value (mean number of channels per update) after ``burn_in``
        samples."""
        sel = np.isfinite(self.nis)
        sel[:burn_in] = False
        if not sel.any():
            return float("nan"), float("nan")
        return float(self.nis[sel].mean()), float(self.nis_dof[sel].mean())

    def summary(self) -> dict:
        """Small dict of run-level figures (for logs and reports)."""
        mn, ex = self.mean_nis()
        n = len(self.t)
        return {
            "n_samples": n,
            "n_updates": self.n_updates,
            "n_missing": self.n_missing,
            "mean_nis": mn,
            "expected_nis": ex,
            "diverged": self.diverged,
            "diverged_at": self.diverged_at,
            "nonfinite": self.nonfinite,
            "nis_flagged": self.nis_flagged,
            "nis_flagged_at": self.nis_flagged_at,
            "flagged_intervals": [list(iv) for iv in self.flagged_intervals],
            "channel_faults": [dict(f) for f in self.channel_faults],
            "n_rejected": dict(self.n_rejected),
            "wall_s": self.wall_s,
            "us_per_sample": 1e6 * self.wall_s / max(n, 1),
        }


class NISMonitor:
    """Moving-window chi-square test on the NIS sequence, with hysteresis.

    The flag is set when the window sum exceeds its bound in ``confirm`` consecutive disjoint windows, and
    cleared when the window sum has been within the bound at ``window`` consecutive updates (a whole window of
    innovations back in their band).

    Parameters
    ----------
    window : int
        Number of updates in a window.
    confidence : float
        One-sided chi-square quantile of the bound (0.999 = 99.9 %).
    confirm : int
        Number of consecutive disjoint windows that must all exceed the bound (>= 1).
    """

    def __init__(self, window: int = 100, confidence: float = 0.999, confirm: int = 2):
        if window < 1 or confirm < 1 or not 0 < confidence < 1:
            raise ValueError("need window >= 1, confirm >= 1 and 0 < confidence < 1")
        self.window = int(window)
        self.confidence = float(confidence)
        self.confirm = int(confirm)
        self._bounds: dict[int, float] = {}
        self.reset()

    def reset(self) -> None:
        self._nis = [0.0] * self.window
        self._dof = [0] * self.window
        self._sum = 0.0
        self._sdof = 0
        self._n = 0
        self._hist = [False] * ((self.confirm - 1) * self.window + 1)
        self.flag = False
        self._in_band = 0

    def bound(self, dof: int) -> float:
        """Chi-square ``confidence`` quantile for ``dof`` degrees of freedom (cached)."""
        b = self._bounds.get(dof)
        if b is None:
            b = float(chi2_ppf(self.confidence, dof))
            self._bounds[dof] = b
        return b

    def push(self, nis: float, dof: int) -> int:
        """Add one update's NIS; return +1 if the flag is set at this update, -1 if it is cleared, else 0."""
        i = self._n % self.window
        self._sdof += dof - self._dof[i]
        self._sum += nis - self._nis[i]
        self._nis[i] = nis
        self._dof[i] = dof
        self._n += 1
        if i == self.window - 1:  # once per window: exact sum (no drift or cancellation after outliers)
            self._sum = math.fsum(self._nis)
        if self._n < self.window:
            return 0
        exceed = self._sum > self.bound(self._sdof)
        h = self._hist
        j = (self._n - 1) % len(h)
        h[j] = exceed
        if self.flag:
            self._in_band = 0 if exceed else self._in_band + 1
            if self._in_band >= self.window:
                self.flag = False
                return -1
            return 0
        if not exceed or self._n < self.confirm * self.window:
            return 0
        for c in range(1, self.confirm):
            if not h[(j - c * self.window) % len(h)]:
                return 0
        self.flag = True
        self._in_band = 0
        return 1


#: a fault's kind as the compiled sample loop codes it (:attr:`.loop.Monitors.events`, ``win_kind``)
_FAULT_KINDS = {1: "offset", 2: "scale", 3: "stuck", 4: "missing"}


class ChannelMonitor:
    """Per-channel sensor-fault tests on the normalised innovations ``z_i = r_i / sqrt(S_ii)``.

    For a consistent filter and a healthy sensor ``z_i`` is standard normal and white. Over the last ``window``
    samples of a channel, with ``z`` clipped at ``+-clip`` (the gate: a single spike moves the sums by at most
    ``clip``), it tests

    - the mean: ``|sum z| / sqrt(W) > Phi^-1(1 - p/2)`` (an offset, or a gain error on a moving joint),
    - the scale: ``sum z**2 > chi2_W^-1(1 - p)`` (spikes, a noisier sensor) or ``< chi2_W^-1(p)`` (a frozen
      sensor: it varies less than its own noise),

    and calls a channel "missing" when it has had no sample for ``window`` of its own last sample intervals. A
    fault is set at the first failed test and cleared after ``window`` consecutive passed tests (or, for
    "missing", at the channel's next sample); ``faults`` lists them with their times. The tests run in the
    filter's compiled sample loop (:func:`.loop.screen`) on this monitor's arrays (:attr:`loop_fields`), which
    reports its findings; :meth:`report` lists them.
    """

    def __init__(self, channels: Sequence[str], window: int = 100, p: float = 1e-6, clip: float = 5.0,
                 dt: float = 1e-3):
        if window < 2 or not 0 < p < 0.5 or not clip > 0:
            raise ValueError("need window >= 2, 0 < p < 0.5 and clip > 0")
        self.channels = tuple(channels)
        self.window = W = int(window)
        self.p = float(p)
        self.clip = float(clip)
        self.dt = float(dt)
        self.window_tests = np.array([self.clip, float(norm_ppf(1 - p / 2)) * math.sqrt(W), float(chi2_ppf(1 - p, W)),
                                      float(chi2_ppf(p, W))])
        self.reset()

    def reset(self) -> None:
        m, W = len(self.channels), self.window
        # the moving windows, their sums, each channel's last sample time and interval (:func:`.kalman.window_push`),
        # the window tests' verdicts, each channel's open fault (_FAULT_KINDS; 0: none) and its passed tests since,
        # the time of the first sample, the findings and their count (:class:`.loop.Monitors`)
        self.loop_fields = (np.zeros((W, m)), np.zeros(m, dtype=np.int64), np.zeros(m), np.zeros(m), np.full(m, np.nan),
                            np.full(m, self.dt), self.window_tests, np.zeros(m, dtype=np.int64),
                            np.zeros(m, dtype=np.int64), np.zeros(m, dtype=np.int64), np.full(1, np.nan),
                            np.zeros((4 * m, 4)), np.zeros(1, dtype=np.int64))
        self._open: dict[int, dict] = {}
        self.faults: list[dict] = []

    def report(self) -> None:
        """List the findings the compiled loop reported (faults opened, found to be offsets, cleared) and empty its
        report."""
        events, n = self.loop_fields[-2], self.loop_fields[-1]
        for code, i, t, mean_z in events[: n[0]].tolist():
            i, mean_z = int(i), math.nan if math.isnan(mean_z) else mean_z  # (a fault found missing has no mean)
            if code == loop.CLEARED:
                self._open.pop(i)["end"] = t
            elif code == loop.BECAME_OFFSET:  # the window filled: a mean, not only a spread
                self._open[i].update(kind="offset", mean_z=mean_z)
            else:
                f = {"channel": self.channels[i], "kind": _FAULT_KINDS[int(code)], "start": t, "end": None,
                     "mean_z": mean_z}
                self._open[i] = f
                self.faults.append(f)
                log.info("channel %s: %s fault found at t=%.6g s (window mean of z %.3g)", f["channel"], f["kind"],
                         t, mean_z)
        n[0] = 0


def check_log(t, U, Y, m: int) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """A record's arrays as floats, with shape errors naming what was expected: times (n,), inputs (n, nu) or
    None, measurements (n, m)."""
    t = np.asarray(t, dtype=float).reshape(-1)
    Y = np.asarray(Y, dtype=float)
    n = len(t)
    if Y.shape != (n, m):
        raise ValueError(f"Y has shape {Y.shape}, expected ({n}, {m})")
    if np.isinf(Y).any():
        k = int(np.flatnonzero(np.isinf(Y).any(axis=1))[0])
        raise ValueError(f"Y: row {k} (t={t[k]:.6g} s) has an infinite measurement; expected finite values, or NaN "
                         "for 'not sampled'")
    if U is not None:
        U = np.asarray(U, dtype=float)
        if len(U) != n:
            raise ValueError(f"U has {len(U)} rows, expected {n}")
    return t, U, Y


def step_arguments(filt, t, u, y):
    """A filter's ``step`` arguments checked at the call: a :class:`~exuflex.errors.UsageError` naming the argument
    and what was expected (a number ``t``; ``u`` one finite torque per input, ``None`` only for a model without
    inputs: a missing torque is not zero; ``y`` an array in channel order, NaN for "not sampled", no infinity)."""
    from ..errors import UsageError

    if isinstance(t, (bool, np.bool_)) or not isinstance(t, (int, float, np.integer, np.floating)):
        raise UsageError(f"t: expected the sample time in s (a number), got {type(t).__name__}")
    t = float(t)
    if not math.isfinite(t):
        raise UsageError(f"t: the sample time {t!r} is not finite")
    n_in = filt.hooks.n_inputs
    if u is None:
        if n_in:
            raise UsageError(f"u: expected the input sample at t={t:.6g} s ({n_in} torques), got None (a missing "
                             "torque is not zero: skip the sample or hold the last one)")
    else:
        try:
            u = np.array(u, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise UsageError(f"u: expected an array of {n_in if n_in is not None else 'the'} input values, got "
                             f"{type(u).__name__}") from None
        if n_in is not None and u.shape != (n_in,):
            raise UsageError(f"u: expected {n_in} input values (one per motor), got {u.size}")
        if not np.isfinite(u).all():
            raise UsageError(f"u: the input sample at t={t:.6g} s is not finite: {u.tolist()}")
    if y is not None:
        if isinstance(y, (dict, str, bytes)) or hasattr(y, "keys"):
            raise UsageError(f"y: expected an array of {filt.m} values in channel order {filt.channels} (NaN: not "
                             f"sampled), got {type(y).__name__}")
        try:
            y = np.asarray(y, dtype=float)
        except (TypeError, ValueError):
            raise UsageError(f"y: expected an array of {filt.m} numbers in channel order {filt.channels}, got "
                             f"{type(y).__name__}") from None
        if y.shape != (filt.m,):
            raise UsageError(f"y: measurement has shape {y.shape}, expected ({filt.m},): channels {filt.channels}")
        if np.isinf(y).any():
            bad = [c for c, v in zip(filt.channels, y, strict=True) if np.isinf(v)]
            raise UsageError(f"y: channel(s) {bad} infinite at t={t:.6g} s; expected a finite value, or NaN for "
                             "'not sampled'")
    return t, u, y


class RunRecord:
    """The per-sample outputs of a filter run over a record (estimates, stored covariance, innovations, NIS), shared
    by the filters: :meth:`put` after each sample takes the estimate and covariance and reads what the filter's
    ``step`` left (``last_idx``, ``last_innovation``, ``last_S``, ``last_nis``, ``last_dof``, ``nonfinite``).

    Bytes a sample: ``8 nx`` (estimates), ``8 nx`` or ``8 nx**2`` (covariance, ``store_P`` "diag" or "full"),
    ``8 m + 8 m**2`` (innovations and their covariance, only with ``innovations``) and 16 (NIS and its degrees of
    freedom); the six-bar's 26 states and 6 channels: 432 bytes with the diagonal and without innovations, 768
    with them. A caller that needs less of a long log (the command line's ``observe``) runs it in chunks of rows
    and keeps what it needs of each (:func:`exuflex.observer.session.estimate_chunks`)."""

    def __init__(self, t: np.ndarray, nx: int, m: int, store_P: str, innovations: bool = True,
                 i_theta: int | None = None, predictions: bool = False):
        n = len(t)
        # each sample's prediction (x_pred, F, Q): 8 nx + 16 nx**2 bytes a sample more
        self.x_pred = np.full((n, nx), np.nan) if predictions else None
        self.F = np.full((n, nx, nx), np.nan) if predictions else None
        self.Q = np.full((n, nx, nx), np.nan) if predictions else None
        self.t, self.m, self.store_P = t, m, store_P
        # the payload scale's column of the covariance (a payload model): 8 nx bytes a sample more
        self.i_theta = i_theta
        self.P_theta = None if i_theta is None else np.empty((n, nx))
        self.x_hat = np.empty((n, nx))
        # only the kind asked for: a full (n, nx, nx) array of a long log is gigabytes
        self.P = np.empty((n, nx)) if store_P == "diag" else np.empty((n, nx, nx)) if store_P == "full" else None
        self.innovations = np.full((n, m), np.nan) if innovations else None
        self.S = np.full((n, m, m), np.nan) if innovations else None
        self.nis = np.full(n, np.nan)
        self.dof = np.zeros(n, dtype=np.int64)

    def put(self, k: int, x: np.ndarray, P: np.ndarray, f) -> None:
        """Sample ``k``'s estimate ``x`` with its covariance ``P`` and what the filter ``f`` recorded of it."""
        self.x_hat[k] = x
        if self.P is not None:
            self.P[k] = np.nan if f.nonfinite else (P.diagonal() if self.store_P == "diag" else P)
        if self.P_theta is not None:
            self.P_theta[k] = np.nan if f.nonfinite else P[:, self.i_theta]
        if self.x_pred is not None and f.last_prediction is not None:
            self.x_pred[k], self.F[k], self.Q[k] = f.last_prediction
        idx = f.last_idx
        if idx is not None:
            self.nis[k] = f.last_nis
            self.dof[k] = f.last_dof
            if self.S is None:
                return
            if len(idx) == self.m:
                self.innovations[k] = f.last_innovation
                self.S[k] = f.last_S
            else:
                self.innovations[k, idx] = f.last_innovation
                self.S[k][np.ix_(idx, idx)] = f.last_S

    def fail_from(self, k: int) -> None:
        """No estimate from sample ``k`` on (the filter failed there)."""
        self.x_hat[k:] = np.nan
        if self.P is not None:
            self.P[k:] = np.nan
        if self.P_theta is not None:
            self.P_theta[k:] = np.nan

    def result(self, f, wall_s: float, **extra) -> EstimationResult:
        """The :class:`EstimationResult` of the run, with the filter's counters."""
        return EstimationResult(t=self.t, x_hat=self.x_hat, P=self.P, innovations=self.innovations, S=self.S,
                                nis=self.nis, nis_dof=self.dof, n_missing=f.n_missing, n_updates=f.n_updates,
                                diverged=f.diverged, diverged_at=f.diverged_at, nonfinite=f.nonfinite, wall_s=wall_s,
                                channels=f.channels, P_theta=self.P_theta, x_pred=self.x_pred, F=self.F, Q=self.Q,
                                **extra)



#: no channels (a prediction only, for :meth:`BeliefFilter._screen`)
_NO_CHANNELS = np.zeros(0, dtype=np.int64)


#: no interval (the first sample): the step Jacobian and process noise the compiled loop is given
_NO_INTERVAL = np.zeros((0, 0))


def _empty_rows(width: int) -> np.ndarray:
    """A record of no rows (what the compiled loop writes nothing to)."""
    return np.zeros((0, width))


def _copy_of(name: str, doc: str) -> property:
    """A read-only property: a copy of the array held in the attribute ``name``."""
    return property(lambda self: getattr(self, name).copy(), doc=doc)


class Monitoring(NamedTuple):
    """What a filter tests its innovations with (module notes): the NIS test (``nis_window`` updates, 0: off; its
    ``divergence_confidence``, ``divergence_confirm`` and ``divergence_action``), the per-channel gate (``gate_p``,
    None: off), the sensor-fault windows (``fault_window`` samples, 0: off; ``fault_p``), the hold-off after an
    input step (``fault_holdoff`` updates; ``input_step`` the filter's test of one) and ``isolate``."""

    nis_window: int = 100
    divergence_confidence: float = 0.999
    divergence_confirm: int = 2
    divergence_action: str = "flag"
    gate_p: float | None = None
    fault_window: int = 0
    fault_p: float = 1e-6
    fault_holdoff: int = 200
    input_step: object = None
    isolate: bool = False


class BeliefFilter:
    """What the filters share (:class:`MultirateEKF`, :class:`.ukf.UnscentedKF`): the belief ``(x, P)`` about the
    state with its prior, the channels and their noise, and the innovation monitors: the NIS test, the gate, the
    hold-off after an input step and the sensor-fault windows, with one meaning of "diverged" (a non-finite state
    or covariance; the NIS test sets ``nis_flagged``). A filter calls :meth:`_screen` on each update's
    innovations and :meth:`_count_update` after it."""

    def _setup(self, model, channels: Sequence[str], R_std: Mapping[str, float], x0, P0, dt: float, max_gap: float,
               store_P: str, nonfinite: str, mon: Monitoring) -> None:
        """Check and keep the settings common to the filters (constructor parameters of :class:`MultirateEKF`)."""
        if store_P not in ("diag", "full", "none"):
            raise ValueError(f"store_P must be 'diag', 'full' or 'none', got {store_P!r}")
        if mon.divergence_action not in ("flag", "raise"):
            raise ValueError(f"divergence_action must be 'flag' or 'raise', got {mon.divergence_action!r}")
        if nonfinite not in ("flag", "raise"):
            raise ValueError(f"nonfinite must be 'flag' or 'raise', got {nonfinite!r}")
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"dt must be a positive number of seconds, got {dt}")
        if not (max_gap >= dt and math.isfinite(max_gap)):
            raise ValueError(f"max_gap must be a finite number of seconds >= dt={dt}, got {max_gap}")
        self.model = model
        self.nx = int(model.nx)
        self.hooks = hooks(model)
        if self.hooks.watch_covariance is not None:  # the model measures its approximations against the filter's P
            self.hooks.watch_covariance(lambda: self._P)
        self.channels = tuple(channels)
        if len(set(self.channels)) != len(self.channels):
            raise ValueError(f"duplicate channel names in {self.channels}")
        missing = [c for c in self.channels if c not in R_std]
        if missing:
            raise ValueError(f"R_std has no standard deviation for channel(s) {missing}")
        self.R_std = np.array([float(R_std[c]) for c in self.channels])
        if not np.all(self.R_std > 0):
            raise ValueError("all measurement standard deviations must be positive")
        self._Rdiag = self.R_std**2
        self.m = len(self.channels)
        self.dt = float(dt)
        self.max_gap = float(max_gap)
        self.store_P = store_P
        self.monitoring = mon
        self.divergence_action = mon.divergence_action
        self.nonfinite_action = nonfinite
        self.monitor = (NISMonitor(mon.nis_window, mon.divergence_confidence, mon.divergence_confirm)
                        if mon.nis_window > 0 else None)
        gate_p = mon.gate_p
        if gate_p is not None and not 0 < gate_p < 1:
            raise ValueError(f"gate_p must be None or in (0, 1), got {gate_p}")
        self.gate_p = gate_p
        self.fault_holdoff = int(mon.fault_holdoff)
        self.isolate = bool(mon.isolate)
        self.input_step = mon.input_step
        self._gate = float(chi2_ppf(1 - gate_p, 1)) if gate_p is not None else math.inf
        self.faults = (
            ChannelMonitor(self.channels, mon.fault_window, mon.fault_p, min(math.sqrt(self._gate), 10.0), dt)
            if mon.fault_window > 0 else None
        )
        self._x0, self._P0 = self._prior(x0, P0)
        self._floor = np.zeros(self.nx)  # (the covariance's floor: a filter with one sets its own)
        n = self.nx  # a record of one sample (what loop.given records a step in)
        self._one = loop.Record(np.empty((1, n)), _empty_rows(n), -1, _empty_rows(n), _empty_rows(self.m),
                                _empty_rows(self.m**2), np.empty(1), np.zeros(1, dtype=np.int64), _empty_rows(n),
                                _empty_rows(n * n), _empty_rows(n * n))
        self._n_lu = np.zeros(1, dtype=np.int64)  # updates solved by LU since the last report
        self._loop = None  # the compiled sample loop over a model's compiled step (the EKF's)
        self.record_theta = None  # the state whose covariance column run() records (the EKF's payload scale)
        # keep (x_pred, F, Q) of each sample's prediction in last_prediction (run(..., predictions=True) sets it)
        self.record_predictions = False

    def _prior(self, x0, P0) -> tuple[np.ndarray, np.ndarray]:
        x = np.array(x0, dtype=float).reshape(-1)
        if x.shape != (self.nx,):
            raise ValueError(f"x0 has shape {x.shape}, expected ({self.nx},)")
        P = np.array(P0, dtype=float)
        if P.ndim == 1:
            P = np.diag(P)
        if P.shape != (self.nx, self.nx):
            raise ValueError(f"P0 has shape {P.shape}, expected ({self.nx}, {self.nx}) or ({self.nx},)")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
            raise ValueError("the prior x0, P0 must be finite")
        return x, np.ascontiguousarray(0.5 * (P + P.T))

    def reset(self, x0=None, P0=None) -> None:
        """Restart from a prior (the constructor's unless ``x0``/``P0`` are given; a given one becomes the
        prior of later resets too) and clear every counter and monitor. A model with caches (``reset()``) is reset
        too, so that a run never depends on what the model evaluated before."""
        if x0 is not None or P0 is not None:
            self._x0, self._P0 = self._prior(self._x0 if x0 is None else x0, self._P0 if P0 is None else P0)
        if self.hooks.reset is not None:
            self.hooks.reset()
        self._x = self._x0.copy()
        self._P = self._P0.copy()
        self._t_prev: float | None = None
        self._u_prev = None
        self.n_missing = 0
        self.n_updates = 0
        self.diverged = False
        self.diverged_at: float | None = None
        self.nonfinite = False
        self.nis_flagged = False
        self.nis_flagged_at: float | None = None
        self.flagged_intervals: list[list] = []
        self._model_failure = None  # why the model could not step (the divergence message names it)
        self.n_rejected = np.zeros(self.m, dtype=np.int64)
        self._holdoff = 0
        self._held = False
        self.jump_times: list[float] = []
        if self.faults is not None:
            self.faults.reset()
        self._mon = loop.Monitors(self._Rdiag, self._floor, self._gate, self.n_rejected,
                                  *(self.faults.loop_fields if self.faults is not None else loop.no_windows(self.m)),
                                  self.isolate, self._n_lu, np.zeros(0), math.inf, self.fault_holdoff)
        self._one_sample = loop.one_sample(self._mon, self._one)  # (the two as loop.given and loop.screen take them)
        self.last_idx = None
        self.last_innovation = None
        self.last_S = None
        self.last_nis = float("nan")
        self.last_dof = 0
        self.last_prediction = None
        if self.monitor is not None:
            self.monitor.reset()

    @property
    def belief(self) -> Belief:
        """The current belief ``(x, P)`` (copies)."""
        return Belief(self._x.copy(), self._P.copy())

    x = _copy_of("_x", "Current state estimate (a copy).")
    x0 = _copy_of("_x0", "The prior mean the filter restarts from (a copy).")
    P = _copy_of("_P", "Current covariance (a copy).")
    P0 = _copy_of("_P0", "The prior covariance the filter restarts from (a copy).")

    @property
    def t(self) -> float | None:
        """Time of the current estimate (None before the first sample)."""
        return self._t_prev

    def step(self, t: float, u, y) -> np.ndarray:
        """Process one sample: predict to ``t`` with the input of the previous call held, update with ``y``: the
        filter's rules ``_predict_step(dt, u)`` (``dt`` None at the first sample) and ``_update_step(t, prediction,
        y)`` (the EKF's, the UKF's sigma points, the IMM's modes) between the checks and bookkeeping every filter
        shares.

        Parameters
        ----------
        t : float
            Sample time (s), after the previous sample's by at most ``max_gap``.
        u : array_like or None
            Input sample at ``t``, held over the next interval (zero-order hold).
        y : array_like, shape (m,) or None
            Measurement in channel order; NaN entries are channels without a sample at ``t``. ``None`` or
            all-NaN: prediction only.

        Returns
        -------
        ndarray, shape (nx,)
            Posterior estimate at ``t`` (a new array; NaN once the filter went non-finite in ``"flag"`` mode).

        Raises
        ------
        ValueError
            ``t`` not finite, not after the previous sample or more than ``max_gap`` after it; an input or
            measurement of the wrong shape; a non-finite input.
        FilterDivergedError
            Non-finite state/covariance (``nonfinite="raise"``) or failed NIS test (``"raise"``).
        """
        t, u, y = step_arguments(self, t, u, y)
        dt = self._interval(t)
        jumps = self.hooks.n_jumps()
        prediction = None if self.nonfinite else self._predict_step(dt, u)
        self._t_now = t
        self._input_steps(t, u, jumps)
        self._t_prev, self._u_prev = t, u
        self.last_idx, self.last_nis, self.last_dof = None, math.nan, 0
        if self.nonfinite:
            self.n_missing += 1
            return np.full(self.nx, np.nan)
        return self._update_step(t, prediction, y)

    def _input_steps(self, t: float, u, jumps: int) -> None:
        """The hold-off after a step in the input at ``t``: the filter's test of ``u`` against the previous input,
        or the model's torque-jump counter moved from ``jumps`` (the transient is the model's to follow, not a
        sensor fault)."""
        stepped = (self.input_step is not None and u is not None and self._u_prev is not None
                   and self.input_step(self._u_prev, u))
        if stepped or self.hooks.n_jumps() != jumps:
            self._holdoff = self.fault_holdoff
            self.jump_times.append(t)

    def _screen(self, idx: np.ndarray, r: np.ndarray, S: np.ndarray) -> np.ndarray | None:
        """One update's innovations ``r`` (covariance ``S``) of the channels ``idx`` (empty: a prediction only),
        normalised, through the monitors (:func:`.loop.screen`: the hold-off, the sensor-fault windows, the isolation
        and the gate; module notes): the mask of the channels to keep where a minority is left out (counted in
        ``n_rejected``), else None (all kept)."""
        m = len(idx)
        z, keep = np.empty(m), np.empty(m, dtype=bool)
        n_over = kalman.normalise(r, S, self._gate, z) if m else 0
        self._held = self._holdoff > 0
        n_keep, self._holdoff = loop.screen(self._one_sample, self._t_now, idx, z, n_over, self._holdoff, keep)
        self._report()
        return None if n_keep == m else keep

    def _report(self) -> None:
        """What the compiled monitors found: the sensor faults listed (:meth:`ChannelMonitor.report`), a warning
        where an update solved ``S`` by LU."""
        if self.faults is not None and self._mon.n_events[0]:
            self.faults.report()
        if self._n_lu[0]:
            log.warning("innovation covariance not positive definite at %d update(s) up to t=%s; using an LU solve",
                        self._n_lu[0], self._t_now)
            self._n_lu[0] = 0

    def _interval(self, t: float) -> float | None:
        """The interval from the previous sample to ``t`` (None at the first), checked: after it, by at most
        ``max_gap``; the grid samples it skipped counted in ``n_missing``."""
        if self._t_prev is None:
            return None
        dt = t - self._t_prev
        if not dt > 1e-9 * self.dt:
            raise ValueError(f"sample time {t!r} s is not after the previous sample's ({self._t_prev!r} s)")
        if dt > self.max_gap:
            raise ValueError(
                f"sample time {t:.6g} s is {dt:.6g} s after the previous sample, more than max_gap="
                f"{self.max_gap:g} s: a gap this long is not predicted through (restart the filter with reset())")
        self.n_missing += max(int(round(dt / self.dt)) - 1, 0)
        return dt

    def _close(self, t: float, finite: bool) -> np.ndarray:
        """The end of a sample: the divergence tests, then a copy of the estimate (NaN once non-finite)."""
        if not finite:
            return self._fail(t)
        if self.last_idx is not None:
            self._count_update(t, self.last_nis, self.last_dof, self._held)
        elif self.faults is not None:
            self._screen(_NO_CHANNELS, _NO_CHANNELS, _NO_CHANNELS)
        return self._x.copy()

    def _fail(self, t: float) -> np.ndarray:
        """A sample that went non-finite: flagged, raised (``nonfinite="raise"``) or NaN returned."""
        self._flag(t, "non-finite state or covariance")
        self.nonfinite = True
        if self.nonfinite_action == "raise":
            why = self._model_failure
            raise FilterDivergedError(
                f"non-finite state or covariance at t={t:.6g} s" + (f" (model step failed: {why})" if why else ""))
        return np.full(self.nx, np.nan)

    def _count_update(self, t: float, nis: float, dof: int, held: bool) -> None:
        """An update done at ``t``: counted, and its NIS into the divergence test (not within the hold-off after
        an input step: the allowance for planned steps)."""
        self.n_updates += 1
        mon = self.monitor
        ev = mon.push(nis, dof) if mon is not None and not held else 0
        if ev > 0:
            self.flagged_intervals.append([float(t), None])
            if not self.nis_flagged:
                self.nis_flagged, self.nis_flagged_at = True, float(t)
            log.info("NIS flag set at t=%.6g s: NIS over %d updates above its %.1f%% bound", t, mon.window,
                     100 * mon.confidence)
            if self.divergence_action == "raise":
                raise FilterDivergedError(f"NIS divergence test failed at t={t:.6g} s")
        elif ev < 0:
            self.flagged_intervals[-1][1] = float(t)
            log.info("NIS flag cleared at t=%.6g s", t)

    def _flag(self, t: float, why: str) -> None:
        if not self.diverged:
            self.diverged = True
            self.diverged_at = float(t)
            log.info("filter flagged at t=%.6g s: %s", t, why)

    def fault_report(self) -> tuple[list, list]:
        """``(flagged_intervals, channel_faults)`` so far, with intervals and faults still open closed at the
        current time (see :class:`EstimationResult`)."""
        t = self._t_prev
        iv = [(a, b if b is not None else t) for a, b in self.flagged_intervals]
        faults = [] if self.faults is None else [dict(f, end=f["end"] if f["end"] is not None else t)
                                                  for f in self.faults.faults]
        return iv, faults

    def run(self, t, U, Y, *, reset: bool = True, x0=None, P0=None, innovations: bool = True,
            predictions: bool = False) -> EstimationResult:
        """Filter a whole record: the numbers of :meth:`step` for every sample (the samples the model's compiled
        step can take go to the compiled sample loop, see the module notes). A step that fails where a covariance
        lost definiteness ends the run: raised as diverged, or (``nonfinite="flag"``) flagged with no estimates from
        there.

        Parameters
        ----------
        t : array_like, shape (n,)
            Sample times (increasing; any spacing up to ``max_gap``).
        U : array_like, shape (n, nu) or (n,), or None
            Input at each sample time, held over the following interval.
        Y : array_like, shape (n, m)
            Measurements in channel order, NaN where a channel has no sample.
        reset : bool
            Restart from the prior first (default). With False the run continues from the current state.
        x0, P0 : array_like, optional
            A prior for this run (implies ``reset``).
        innovations : bool
            Record the innovations and their covariance (``8 m + 8 m**2`` bytes a sample; without them the
            result's ``innovations`` and ``S`` are None). A record run in chunks of rows (``reset=False`` after
            the first) gives the same numbers as one run of the whole record.
        predictions : bool
            Record each sample's prediction (the result's ``x_pred``, ``F``, ``Q``: ``8 nx + 16 nx**2`` bytes a
            sample), what the smoother's backward pass needs (:func:`.smoother.rts_backward`).

        Returns
        -------
        EstimationResult
        """
        t, U, Y = check_log(t, U, Y, self.m)
        if reset or x0 is not None or P0 is not None:
            self.reset(x0, P0)
        rec = RunRecord(t, self.nx, self.m, self.store_P, innovations, self.record_theta, predictions)
        self.record_predictions = predictions
        t_start = time.perf_counter()
        n = len(t)
        loop_end = self._loop_ends(t, U, Y)
        if loop_end.any():  # the compiled loop's arrays: contiguous, the inputs one column per motor
            t, U, Y = np.ascontiguousarray(t), np.ascontiguousarray(U.reshape(n, -1)), np.ascontiguousarray(Y)
        k = 0
        while k < n:
            if self._loop_ready(U) and loop_end[k] > k:
                k, status, last = self._loop_samples(t, U, Y, k, int(loop_end[k]), rec)
                if status in (NONFINITE, SINGULAR):
                    rec.put(k, self._failed(float(t[k]), status, last), self._P, self)
                    k += 1
                    continue
                if k >= n:
                    break
            self.last_prediction = None
            try:
                x = self.step(t[k], None if U is None else U[k], Y[k])
            except (np.linalg.LinAlgError, ArithmeticError) as exc:
                if self.nonfinite_action == "raise":
                    raise FilterDivergedError(f"{type(self).__name__} failed at t={t[k]:.6g} s: {exc}") from exc
                self.nonfinite, self.diverged = True, True
                self.diverged_at = self.diverged_at or float(t[k])
                rec.fail_from(k)
                break
            rec.put(k, x, self._P, self)
            self._recorded(k)
            k += 1
        self.record_predictions = False
        res = self._result(rec, time.perf_counter() - t_start)
        log.info("%s run: %s", type(self).__name__, res.summary())
        return res

    def forward_pass(self, t, U, Y, *, x0=None, P0=None) -> EstimationResult:
        """A smoother's forward pass over a record (from the prior, or ``x0``/``P0``): :meth:`run` with the full
        covariance and each sample's prediction recorded, without the filter's variance floor (negative variances
        are still set to zero): the floor adds variance that ``Q`` does not hold, and a backward pass multiplies
        that by ``1 / lambda^2`` a sample in a direction that decays by ``lambda`` without process noise (an
        undriven damped mode; the five-bar's smoothed estimates overflowed).

        Raises
        ------
        FilterDivergedError
            The pass went non-finite (a smoother cannot run back through it).
        """
        store, floor = self.store_P, self._floor.copy()
        self.store_P = "full"
        self._floor[:] = 0.0
        try:
            res = self.run(t, U, Y, x0=x0, P0=P0, innovations=False, predictions=True)
        finally:
            self.store_P, self._floor[:] = store, floor
        if res.nonfinite:
            raise FilterDivergedError(f"the forward pass went non-finite at t={res.diverged_at:.6g} s; nothing to "
                                      "smooth")
        return res

    def _recorded(self, k: int) -> None:
        """After sample ``k`` of :meth:`run` went through :meth:`step` and was recorded (a filter that keeps more of
        each sample than the record does takes it here)."""

    def _loop_ends(self, t, U, Y) -> np.ndarray:
        """Per sample ``k`` the end of the run of samples from ``k`` that the compiled loop may take: the interval
        valid (as :meth:`step` tests it) and the input finite (empty without a loop)."""
        n = len(t)
        if self._loop is None or U is None or n < 2:
            return np.zeros(n, dtype=np.int64)
        ok = np.isfinite(U.reshape(n, -1)).all(axis=1)
        dt = np.diff(t)
        ok[1:] &= np.isfinite(dt) & (dt > 1e-9 * self.dt) & (dt <= self.max_gap)
        ok[0] = False
        ok &= np.isfinite(t)
        # the grid samples each interval skipped (step()'s count of missing samples), summed from the start
        skipped = np.maximum(np.rint(dt / self.dt) - 1.0, 0.0)
        self._skipped = np.concatenate(([0.0], np.cumsum(np.where(np.isfinite(skipped), skipped, 0.0))))
        bad = np.flatnonzero(~ok)
        # the first not-ok sample at or after k
        pos = np.searchsorted(bad, np.arange(n))
        return np.where(pos < len(bad), bad[np.minimum(pos, len(bad) - 1)], n).astype(np.int64)

    def _loop_ready(self, U) -> bool:
        """Can samples go to the model's compiled step now? (The model has one; a run with inputs, after a first
        sample; the input-step test one the loop computes.)"""
        return (self._loop is not None and U is not None and self._t_prev is not None and not self.nonfinite
                and (self.input_step is None or isinstance(self.input_step, kalman.InputStepTest)))

    def _result(self, rec: RunRecord, wall_s: float) -> EstimationResult:
        """The run's :class:`EstimationResult` with the monitors' findings."""
        intervals, faults = self.fault_report()
        return rec.result(self, wall_s, nis_flagged=self.nis_flagged, nis_flagged_at=self.nis_flagged_at,
                          flagged_intervals=intervals, channel_faults=faults,
                          n_rejected={c: int(k) for c, k in zip(self.channels, self.n_rejected, strict=True)})


class MultirateEKF(BeliefFilter):
    """Multirate extended Kalman filter over a :class:`DiscreteModel`.

    Parameters
    ----------
    model : DiscreteModel
        :meth:`~DiscreteModel.predict` (step map, Jacobian, process noise) and
        :meth:`~DiscreteModel.measure` (channels and their Jacobian).
    channels : sequence of str
        Names of the scalar sensor channels; the order of the columns of the measurement arrays.
    R_std : mapping str -> float
        Measurement-noise standard deviation of every channel (``R`` is diagonal).
    x0 : array_like, shape (nx,)
        Prior mean at the first sample time.
    P0 : array_like, shape (nx, nx) or (nx,)
        Prior covariance (a vector is taken as the diagonal).
    dt : float
        Nominal sample interval (s): used to count the samples a gap skipped (``n_missing``).
    store_P : {"diag", "full", "none"}
        What :meth:`run` records of the posterior covariance.
    monitoring : Monitoring
        What the filter tests its innovations with: the NIS test (``nis_window``, 0: off; see :class:`NISMonitor`;
        ``divergence_action`` "flag" records a set test and goes on, "raise" raises :class:`FilterDivergedError`),
        the per-channel gate (``gate_p``: a channel whose squared normalised innovation exceeds the chi-square(1)
        quantile ``1 - gate_p`` is left out of the update, see the module notes; None, the default: no gating, the
        textbook filter), the sensor-fault tests (``fault_window`` samples per channel, :class:`ChannelMonitor`;
        0, the default: off; ``fault_p`` their false-alarm probability; ``isolate`` leaves a channel with an open
        offset or stuck fault out of the updates until it clears), and the hold-off after a step in the input
        (``fault_holdoff`` updates after a model's ``n_jumps`` step, see
        :meth:`.reduced.ReducedObserverModel.input_jump`, or one ``input_step(u0, u1)`` detects, during which
        nothing is gated and the NIS and sensor-fault tests are paused: the allowance for planned torque steps,
        whose transient the model follows with a larger error than its steady state).
    nonfinite : {"raise", "flag"}
        On a non-finite state/covariance: raise :class:`FilterDivergedError`, or flag the run and return NaN
        estimates from then on.
    p_floor : float or array_like
        Floor on the diagonal of ``P`` (in the state's squared units).
    max_gap : float
        Longest interval (s) the filter predicts over; a longer one is an error (restart with :meth:`reset`).
    """

    def __init__(
        self,
        model: DiscreteModel,
        channels: Sequence[str],
        R_std: Mapping[str, float],
        x0,
        P0,
        dt: float = 1 / 500,
        *,
        store_P: str = "diag",
        nonfinite: str = "raise",
        p_floor=1e-18,
        max_gap: float = 1.0,
        monitoring: Monitoring = Monitoring(),
    ):
        self._setup(model, channels, R_std, x0, P0, dt, max_gap, store_P, nonfinite, monitoring)
        n = self.nx
        if np.size(p_floor) not in (1, n):
            raise ValueError(f"p_floor has {np.size(p_floor)} entries, expected 1 or {n}")
        self._floor = np.ascontiguousarray(np.broadcast_to(np.asarray(p_floor, float).reshape(-1), (n,)))
        self._all = np.arange(self.m)
        self._subsets: dict[bytes, tuple] = {}
        # the covariance lives in two buffers that alternate (a kernel never writes the P it reads); scratch
        self._Pspare = np.empty((n, n))
        self._Ppred = np.empty((n, n))
        self._work = np.empty((n, n))
        self._HP = np.empty((max(self.m, 1), n))
        self.record_theta = self.hooks.i_theta
        # the compiled sample loop: run() hands it the samples it can take where the model has a compiled step;
        # step() hands it one sample with the model's prediction and measurement (loop.given), in a record of a row
        self._loop = loop.samples if takes_compiled_loop(model) else None
        extra = self.hooks.i_theta is not None or self.hooks.i_inputs is not None
        # the kernels the filter calls loaded now (not in its first sample's time); those of the Python steps
        # only where there is no compiled loop
        loop.warm_up(None if self._loop is None else "augmented" if extra else "plain", screened=self._loop is None)
        kalman.warm_up(python_steps=self._loop is None)
        self.reset()

    # ------------------------------------------------------------------ the two steps
    def _predict_step(self, dt: float | None, u_next) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The model's step from the previous sample to this one (eqs. 10-12): the predicted mean, the step
        Jacobian and the process noise ``(x, F, Q)`` (NaN, where the model cannot step from the estimate; at the
        first sample, ``dt`` None, the prior mean and no interval)."""
        n = self.nx
        if dt is None:
            return self._x, _NO_INTERVAL, _NO_INTERVAL
        try:
            x, F, Q = self.model.predict(self._x, self._u_prev, dt, u_next)
        except _MODEL_FAILURES as exc:
            x, F, Q = np.full(n, np.nan), np.eye(n), np.zeros((n, n))
            self._model_failure = f"{type(exc).__name__}: {exc}"
        x, F, Q = (np.ascontiguousarray(a, dtype=float) for a in (x, F, Q))
        if x.shape != (n,) or F.shape != (n, n) or Q.shape != (n, n):
            # the kernels read without bounds checks: never a wrong shape
            raise ValueError(f"model.predict returned x {x.shape}, F {F.shape}, Q {Q.shape}; expected ({n},), "
                             f"({n}, {n}), ({n}, {n})")
        if self.record_predictions:
            self.last_prediction = (x, F, Q)
        return x, F, Q

    def _channel_set(self, y: np.ndarray) -> tuple | None:
        """``(idx, channels, R diagonal)`` of the finite entries of ``y`` (None if there are none)."""
        if math.isfinite(sum(y.tolist())):  # every channel (the common case): one sum of a list
            return self._all, self.channels, self._Rdiag
        mask = np.isfinite(y)
        if not mask.any():
            return None
        key = mask.tobytes()
        s = self._subsets.get(key)
        if s is None:
            idx = np.flatnonzero(mask)
            s = self._subsets[key] = (idx, tuple(self.channels[i] for i in idx), self._Rdiag[idx])
        return s

    # ------------------------------------------------------------------ public
    def _update_step(self, t: float, prediction: tuple, y) -> np.ndarray:
        """The update of :meth:`~BeliefFilter.step` with the model's prediction ``(x, F, Q)``: the model's
        measurement of the channels sampled, then the sample in the compiled loop (:func:`.loop.given`)."""
        z, F, Q = prediction
        n, m = self.nx, self.m
        y_pred, H = np.zeros(m), np.zeros((m, n))
        y_k = np.full(m, np.nan)
        chosen = None if y is None else self._channel_set(y)
        if chosen is not None:  # the model's measurement of the channels sampled
            idx, chans, _ = chosen
            try:
                meas = self.model.measure(z, chans)
            except _MODEL_FAILURES as exc:
                self._model_failure = f"{type(exc).__name__}: {exc}"
                return self._fail(t)
            if np.shape(meas[1]) != (len(idx), n) or np.shape(meas[0]) != (len(idx),):
                raise ValueError(f"model.measure returned y {np.shape(meas[0])}, H {np.shape(meas[1])} for "
                                 f"{len(idx)} channels; expected ({len(idx)},) and ({len(idx)}, {n})")
            y_pred[idx], H[idx], y_k = meas[0], meas[1], y
        hold0 = self._holdoff
        x_alt, P_alt = np.empty(n), self._Pspare
        buf = (self._x, x_alt, self._P, P_alt, self._Ppred, self._work, self._HP)  # (loop.Buffers)
        status, self._holdoff, last = loop.given(t, y_k, hold0, buf, self._one_sample,
                                                 np.ascontiguousarray(z, dtype=float), F, Q, y_pred, H)
        if status != LOOP_DONE:
            return self._failed(t, status, last)
        self._x, self._P, self._Pspare = x_alt, P_alt, self._P
        self._counted((t,), 0, 1, hold0, self._one.nis, self._one.dof, last, False)
        return self._x.copy()

    def _failed(self, t: float, status: int, last: tuple) -> np.ndarray:
        """A sample the compiled loop left non-finite (``status`` :data:`.base.NONFINITE`) or whose innovation
        covariance was singular (:data:`.base.SINGULAR`: raised), ``last`` what it saw."""
        self._report()
        if status == SINGULAR:
            raise FilterDivergedError(f"singular innovation covariance at t={t:.6g} s")
        d = len(last[1])
        self.last_idx, self.last_innovation, self.last_S = (last[1], last[2], last[3]) if d else (None, None, None)
        self.last_nis, self.last_dof = math.nan, d
        return self._fail(t)

    # ------------------------------------------------------------------ the compiled sample loop
    def _loop_samples(self, t, U, Y, k: int, k_end: int, rec: RunRecord) -> tuple[int, int, tuple]:
        """Samples ``k .. k_end - 1`` (valid times and inputs) through the model's compiled step (:func:`.loop.
        samples`) until one needs the model's own :meth:`predict`; the model renews its arrays where the loop asks.
        Returns the first sample not done, the loop's status and what it saw of that sample (where it went
        non-finite)."""
        model, m, n = self.model, self.m, self.nx
        step = self.input_step
        step_w, step_thr = (step.weights, step.threshold) if step is not None else (np.zeros(U.shape[1]), math.inf)
        mon = self._mon._replace(step_w=step_w, step_thr=step_thr)
        inn, S_rec = ((rec.innovations, rec.S.reshape(len(rec.t), -1)) if rec.S is not None
                      else (_empty_rows(m), _empty_rows(m * m)))
        rows = len(rec.t)
        pred = ((rec.x_pred, rec.F.reshape(rows, -1), rec.Q.reshape(rows, -1)) if rec.x_pred is not None
                else (_empty_rows(n), _empty_rows(n * n), _empty_rows(n * n)))
        record = loop.Record(rec.x_hat, _empty_rows(n) if rec.P is None else rec.P.reshape(rows, -1),
                             -1 if rec.P is None else 0 if rec.store_P == "diag" else 1,
                             _empty_rows(n) if rec.P_theta is None else rec.P_theta, inn, S_rec, rec.nis, rec.dof, *pred)
        rows_made, status, last = False, LOOP_DONE, None
        while k < k_end:
            x, x_alt, P, P_alt = self._x, np.empty(n), self._P, self._Pspare
            try:
                lm = model.loop_model(x, U[k - 1], t[k] - t[k - 1], self.channels)
            except _MODEL_FAILURES:  # the model cannot step from here: step() says why
                break
            hold0 = self._holdoff
            buf = loop.Buffers(x, x_alt, P, P_alt, self._Ppred, self._work, self._HP)
            k_next, status, self._holdoff, swapped, state, mats, last = self._loop(
                t, U, Y, k, k_end, hold0, rows_made, *loop.plain(buf, mon, record, lm.step, lm.state), lm.extras)
            z = x if swapped else x_alt  # (the buffer not current: the prediction where the rows stopped the loop)
            if swapped:
                self._x, self._P, self._Pspare = x_alt, P_alt, P
            if k_next > k:
                self.n_missing += int(self._skipped[k_next - 1] - self._skipped[k - 1])
                self._counted(t, k, k_next, hold0, rec.nis, rec.dof, last, status == INPUT_STEP)
                self._t_prev = self._t_now = float(t[k_next - 1])
                self._u_prev = U[k_next - 1]
                model.loop_done(mats, float(t[k_next - 1] - t[k_next - 2]), state, self._x, k_next)
                if status == INPUT_STEP:
                    self.jump_times.append(float(t[k_next - 1]))
            k = k_next
            if status in (NONFINITE, SINGULAR):  # the sample at k: its interval and input
                self.n_missing += int(self._skipped[k] - self._skipped[k - 1])
                self._t_prev = self._t_now = float(t[k])
                self._u_prev = U[k]
                break
            rows_made = status == ROWS
            if rows_made:  # the model's rows made for the prediction (as step()'s update makes them, from the
                try:  # channels sampled there: their error sets the next radius); resumed there
                    model.measure(z, self._channel_set(Y[k])[1])
                except _MODEL_FAILURES:  # step() says why
                    break
            if status not in (REFRESH, REMAP, MONITOR, INPUT_STEP, ROWS):
                break
        return k, status, last

    def _counted(self, t, k0: int, k1: int, hold0: int, nis, dof, last: tuple, stepped: bool) -> None:
        """After the compiled loop did samples ``k0 .. k1 - 1`` (their NIS and degrees of freedom ``nis``, ``dof``,
        the hold-off ``hold0`` at the first): what :meth:`step` keeps of each (counters, the NIS test) and of the
        last (the channels updated with and their innovations); ``last`` the loop's ``(sampled, kept, r, S)`` of
        the last sample, ``stepped`` an input step there; the monitors' findings."""
        held = hold0
        for j in range(k0, k1):
            if stepped and j == k1 - 1:
                held = self.fault_holdoff
            d = int(dof[j])
            if d:  # an update: the hold-off counts it down (the monitors' allowance after an input step)
                self._held = held > 0
                held -= self._held
                self._count_update(t[j], float(nis[j]), d, self._held)
            else:
                self.n_missing += 1
        d = int(dof[k1 - 1])
        self.last_idx, self.last_innovation, self.last_S = (last[1], last[2], last[3]) if d else (None, None, None)
        self.last_nis, self.last_dof = (float(nis[k1 - 1]), d) if d else (math.nan, 0)
        self._report()

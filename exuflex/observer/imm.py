"""Interacting multiple-model (IMM) filter: EKF modes over nested state spaces, mixed by their likelihoods.

The payload estimator (``estimator="imm"``, :func:`.session.make_observer`) has two modes: the reduced model at
the model file's payload (state ``z``) and the payload-augmented model (``[z; theta]``, :class:`.augmented.
AugmentedModel`). The modes' states are nested: mode ``j``'s state is the first ``n_j`` components of the common
state ``x`` (the largest mode's), and a mode holds the components beyond its own at fixed values, its ``tail``
(the nominal mode: ``theta = 1``).

One sample (Blom and Bar-Shalom 1988; Bar-Shalom, Li and Kirubarajan 2001, sec. 11.6.6), with ``T_ij`` the
probability of mode ``j`` at this sample given mode ``i`` at the previous one and ``mu_i`` the previous
sample's mode probabilities:

1. Mixing: ``c_j = sum_i T_ij mu_i``, ``w_ij = T_ij mu_i / c_j``, and mode ``j`` starts from the moments of the
   mixture ``x0_j = sum_i w_ij x_ij``, ``P0_j = sum_i w_ij (P_ij + (x_ij - x0_j)(x_ij - x0_j)')``. ``(x_ij,
   P_ij)`` is mode ``i``'s belief in mode ``j``'s state space: its own components; for the components mode ``j``
   has and mode ``i`` has not, mode ``j``'s own mean and covariance, uncorrelated with the rest ("unbiased
   mixing": entering the payload mode means the payload changed to a value that mode's own estimate is the best
   knowledge of, not that it is nominal; filling with the nominal ``theta = 1`` at zero variance instead would
   collapse the payload mode's scale variance at every sample where the nominal mode dominates, and it could
   not learn a payload changed later); components mode ``j`` has not are left out (the marginal: the physical
   state does not jump when the payload does).
2. Mode-matched filtering: each mode's EKF step from ``(x0_j, P0_j)``: :func:`.kalman.predict` over the model's
   interval (eq. 13) and :func:`.kalman.condition` on the measurement (eqs. 14-15).
3. Mode probabilities: ``mu_j = c_j L_j / sum_i c_i L_i``, with ``L_j = N(r_j; 0, S_j)`` the Gaussian likelihood
   of mode ``j``'s innovation ``r_j`` (covariance ``S_j``).
4. Combination (the estimate): ``x = sum_j mu_j x_j``, ``P = sum_j mu_j (P_j + (x_j - x)(x_j - x)')``, each mode
   in the common space with its tail at variance 0: the payload scale reported is ``mu_0 + mu_1 theta_1``.

With one mode every weight is 1 and the filter is that mode's EKF; with identical modes the likelihoods are
equal and the probabilities keep their prior (the tests check both, and the mixing and probabilities against
filterpy's ``IMMEstimator`` on a linear system).

Transition matrix. A mode is left at the rate ``1 / tau`` (``tau`` its expected dwell time), to each other mode
alike: the generator ``G_ii = -1 / tau``, ``G_ij = 1 / (tau (N - 1))``, and over an interval ``dt``
``T = expm(G dt)`` (each interval its own ``T``: irregular sampling needs no grid). The payload estimator's
``tau`` is ``ObserverConfig.imm_dwell_s``, by default a hundred manoeuvre durations
(:data:`.session.IMM_DWELL_MANOEUVRES`): a payload is picked or placed at rest, between motions, and changes
within a motion about once in a hundred. The dwell time sets how long the filter keeps evidence: a mode
probability driven down is pulled back towards the chain's stationary share at the rate ``1 / tau``, and a
``tau`` of the log's length lets a stretch of samples that one mode happens to fit better undo what the whole
log said.

Monitors. The innovations the monitors test (:class:`.ekf.BeliefFilter`: the gate, the hold-off after an input
step, the sensor-fault windows, the NIS test) are the mixture's: ``r = sum_j c_j r_j`` (the measurement less the
mixture's prediction ``sum_j c_j y_j``) with ``S = sum_j c_j (S_j + (r_j - r)(r_j - r)')``. A channel the gate or
the isolation leaves out is left out of every mode's update.

Smoothing (:meth:`IMMFilter.smooth`), backwards from the last sample (smoothed = filtered there):

1. Mode probabilities by Kim's recursion (Kim 1994; Kim and Nelson 1999, sec. 5.2): with ``W_ij = T_ij mu_i /
   c_j`` the forward mixing weight, ``P(s_k = i | s_k+1 = j, y_1..k)``, ``mu_i|n(k) = sum_j W_ij mu_j|n(k + 1)``
   (summing to 1, as each column of ``W`` does); ``P(s_k | s_k+1, y_1..n)`` is taken as ``P(s_k | s_k+1,
   y_1..k)``.
2. Each mode's state along its own chain of the forward pass (its posterior, the interval from its mixed start,
   its update), the mixing taken as a disturbance of that chain (the posterior's covariance with the next
   prediction ``P_k F'``, the prediction's covariance the filter's own): the RTS smoother in the modified
   Bryson-Frazier form (:func:`smooth_mode`), whose adjoint runs back through ``F'`` and the updates and never
   inverts ``F`` or a predicted covariance.
3. The estimate: the modes' smoothed beliefs combined as step 4 with the smoothed probabilities.

With one mode (or identical modes) this is the extended RTS smoother on the filter's pass
(:func:`.smoother.rts_backward`) to rounding. Kim's state smoother (each pair of modes ``i`` at ``k`` and ``j`` at
``k + 1`` one RTS step) was tried first: its gain is ``F^-1`` in undriven damped directions, and there the
collapse renews the modes' disagreement at every sample, so that it grew by ``1 / decay`` a sample backwards and
overflowed on the single link and the slider-crank. Within a mode's chain the switches are left to the
probabilities; the tests measure what that costs against the exact posterior over every mode sequence of a short
linear record (docs/imm.md).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import scipy.linalg

from . import kalman
from .base import Belief, Measurement, hooks
from .ekf import (
    _MODEL_FAILURES,
    BeliefFilter,
    EstimationResult,
    Monitoring,
)
from .smoother import SmoothedResult

__all__ = ["IMMFilter", "ModeTrack", "combine", "mix", "smooth_mode", "transition_matrix"]

def transition_matrix(dwell_s: Sequence[float], dt: float) -> np.ndarray:
    """``T = expm(G dt)``: the modes' transition probabilities over ``dt`` s, each mode left at the rate
    ``1 / dwell_s[i]`` to the others alike (module notes); rows sum to 1."""
    rate = 1.0 / np.asarray(dwell_s, float)
    k = len(rate)
    if k == 1:
        return np.ones((1, 1))
    G = np.repeat((rate / (k - 1))[:, None], k, axis=1)
    np.fill_diagonal(G, -rate)
    T = scipy.linalg.expm(G * dt)
    return T / T.sum(axis=1, keepdims=True)


def _moments(w: np.ndarray, X: Sequence[np.ndarray], P: Sequence[np.ndarray]) -> Belief:
    """Mean and covariance of the Gaussian mixture with the weights ``w`` (summing to 1), means ``X``, covariances
    ``P``."""
    x = sum(wi * xi for wi, xi in zip(w, X, strict=True))
    C = sum(wi * (Pi + np.outer(xi - x, xi - x)) for wi, xi, Pi in zip(w, X, P, strict=True))
    return Belief(x, 0.5 * (C + C.T))


def _extend(b: Belief, other: Belief) -> Belief:
    """``b`` with the components ``other`` has beyond it appended from ``other``, uncorrelated with the rest (step 1
    of the module notes: unbiased mixing)."""
    k, n = len(b.x), len(other.x)
    if n <= k:
        return b
    x, P = other.x.copy(), np.zeros((n, n))
    x[:k] = b.x
    P[:k, :k] = b.P
    P[k:, k:] = other.P[k:, k:]
    return Belief(x, P)


def mix(mu: np.ndarray, T: np.ndarray, beliefs: Sequence[Belief]) -> tuple[np.ndarray, list[Belief]]:
    """Step 1 of the module notes: the predicted mode probabilities ``c`` and each mode's mixed start, over modes
    whose beliefs may differ in size (nested states, unbiased mixing)."""
    c = mu @ T
    out = []
    for j, bj in enumerate(beliefs):
        n = len(bj.x)
        W = T[:, j] * mu / c[j] if c[j] > 0 else (np.arange(len(mu)) == j).astype(float)
        ext = [_extend(bi, bj) for bi in beliefs]
        out.append(_moments(W, [e.x[:n] for e in ext], [e.P[:n, :n] for e in ext]))
    return c, out


def combine(mu: np.ndarray, beliefs: Sequence[Belief], tails: Sequence[np.ndarray]) -> Belief:
    """Step 4 of the module notes: the mixture's moments in the common space, each mode's ``tail`` (its fixed
    components) appended at variance 0."""
    n = len(beliefs[0].x) + len(tails[0])
    X, P = [], []
    for b, tail in zip(beliefs, tails, strict=True):
        k = len(b.x)
        Pi = np.zeros((n, n))
        Pi[:k, :k] = b.P
        X.append(np.concatenate([b.x, tail]))
        P.append(Pi)
    return _moments(mu, X, P)


class IMMFilter(BeliefFilter):
    """Interacting multiple-model filter over EKF modes (module notes).

    Parameters
    ----------
    models : sequence of DiscreteModel
        The modes' models; mode ``j``'s state is the first ``models[j].nx`` components of the common state (the
        largest model's).
    tails : sequence of array_like
        Per mode, the values it holds the common state's components beyond its own at (empty for the largest).
    channels, R_std, x0, P0, dt, max_gap, store_P, nonfinite, p_floor
        As :class:`.ekf.MultirateEKF`; ``x0``, ``P0`` in the common state (each mode starts from its block).
    dwell_s : sequence of float
        Each mode's expected dwell time (s): the transition matrix (:func:`transition_matrix`).
    mode_p0 : sequence of float
        The modes' prior probabilities (summing to 1).
    monitoring : Monitoring, optional
        The innovation monitors on the mixture's innovations (default: the NIS test alone).
    """

    def __init__(self, models: Sequence, tails: Sequence, channels: Sequence[str], R_std: Mapping[str, float], x0,
                 P0, dt: float, *, dwell_s: Sequence[float], mode_p0: Sequence[float], max_gap: float = 1.0,
                 store_P: str = "diag", nonfinite: str = "raise", p_floor: float = 1e-18,
                 monitoring: Monitoring | None = None):
        dims = [int(m.nx) for m in models]
        top = int(np.argmax(dims))
        self._setup(models[top], channels, R_std, x0, P0, dt, max_gap, store_P, nonfinite,
                    monitoring if monitoring is not None else Monitoring())
        self.models, self.dims, self._top = tuple(models), dims, top
        self.tails = [np.asarray(tl, float).reshape(-1) for tl in tails]
        bad = [j for j, (n, tl) in enumerate(zip(dims, self.tails, strict=True)) if n + len(tl) != self.nx]
        if bad:
            raise ValueError(f"tails: mode(s) {bad} with {[dims[j] for j in bad]} states need "
                             f"{[self.nx - dims[j] for j in bad]} fixed values to fill the common {self.nx}")
        self.dwell_s = np.asarray(dwell_s, float).reshape(-1)
        self.mode_p0 = np.asarray(mode_p0, float).reshape(-1)
        if len(self.dwell_s) != len(dims) or not np.all(self.dwell_s > 0):
            raise ValueError(f"dwell_s: expected {len(dims)} positive dwell times (s), got {list(self.dwell_s)}")
        if len(self.mode_p0) != len(dims) or np.any(self.mode_p0 < 0) or abs(self.mode_p0.sum() - 1) > 1e-12:
            raise ValueError(f"mode_p0: expected {len(dims)} probabilities summing to 1, got {list(self.mode_p0)}")
        self._floor = np.full(self.nx, float(p_floor))
        self._hooks = [hooks(m) for m in models]
        for j, h in enumerate(self._hooks):  # each model measures its approximations against its own mode's P
            if h.watch_covariance is not None:
                h.watch_covariance(lambda j=j: self._beliefs[j].P)
        self._T: tuple[float, np.ndarray] | None = None
        self.reset()

    def reset(self, x0=None, P0=None) -> None:
        """Restart every mode from its block of the prior, with the prior mode probabilities
        (:meth:`.ekf.BeliefFilter.reset`; every mode's model reset)."""
        super().reset(x0, P0)
        for j, h in enumerate(self._hooks):  # (the largest mode's model: BeliefFilter.reset)
            if j != self._top and h.reset is not None:
                h.reset()
        self._beliefs = [Belief(self._x0[:n].copy(), self._P0[:n, :n].copy()) for n in self.dims]
        self.mode_p = self.mode_p0.copy()
        self.intervals: list = [None] * len(self.models)

    def _transition(self, dt: float) -> np.ndarray:
        if self._T is None or self._T[0] != dt:
            self._T = (dt, transition_matrix(self.dwell_s, dt))
        return self._T[1]

    def _predict(self, b: Belief, j: int, dt: float, u_next) -> Belief | None:
        """Mode ``j``'s prediction from its mixed start ``b`` (None where its model cannot step from there); the
        model's interval kept in ``intervals[j]`` (what the smoother needs)."""
        try:
            self.intervals[j] = self.models[j].predict(b.x, self._u_prev, dt, u_next)
        except _MODEL_FAILURES:
            return None
        return kalman.predict(b, self.intervals[j])

    def _condition(self, j: int, y: np.ndarray, idx: np.ndarray):
        """Mode ``j``'s update with the channels ``idx``: ``(belief, innovation, H)``, or None where its model cannot
        measure there or its innovation covariance is not positive definite."""
        b = self._beliefs[j]
        try:
            meas = self.models[j].measure(b.x, tuple(self.channels[i] for i in idx))
            H = np.asarray(meas.H, float)
            return (*kalman.condition(b, Measurement(np.asarray(meas.y, float), H), y[idx], self._Rdiag[idx],
                                      self._floor[: len(b.x)]), H)
        except (*_MODEL_FAILURES, np.linalg.LinAlgError):
            return None

    def _predict_step(self, dt: float | None, u_next) -> tuple[np.ndarray, np.ndarray]:
        """Steps 1-2 of the module notes up to the updates: mixing and each mode's prediction (no interval at the
        first sample, ``dt`` None). Returns the predicted mode probabilities and which modes could step."""
        self.updates: list = [None] * len(self.models)
        c = self.mode_p
        alive = np.ones(len(self.models), dtype=bool)
        if dt is not None:
            c, self._beliefs = mix(self.mode_p, self._transition(dt), self._beliefs)
            self.intervals = [None] * len(self.models)
            for j, b in enumerate(self._beliefs):
                p = self._predict(b, j, dt, u_next)
                alive[j] = p is not None
                self._beliefs[j] = b if p is None else p
            # a mode whose model cannot step from its start is dropped (probability 0); none left: diverged
            c = np.where(alive, c, 0.0)
            if not c.sum() > 0:
                self._beliefs = [Belief(np.full(len(b.x), np.nan), b.P) for b in self._beliefs]
                c = self.mode_p
            c = c / c.sum()
        return c, alive

    def _update_step(self, t: float, prediction: tuple, y) -> np.ndarray:
        """Steps 2-4 of the module notes from the predicted mode probabilities and the modes that could step: each
        mode's update, the mode probabilities and the combined estimate (a new array)."""
        c, alive = prediction
        idx = np.empty(0, dtype=np.int64) if y is None else np.flatnonzero(np.isfinite(y))
        if len(idx):
            self._update(c, alive, y, idx)
        else:
            self.n_missing += 1
            for b in self._beliefs:
                kalman.settle(b.x, b.P, self._floor[: len(b.x)])
            self.mode_p = c
        self._x, self._P = combine(self.mode_p, self._beliefs, self.tails)
        return self._close(t, bool(np.all(np.isfinite(self._x)) and np.all(np.isfinite(self._P))))

    def _update(self, c: np.ndarray, alive: np.ndarray, y: np.ndarray, idx: np.ndarray) -> None:
        """Steps 2-3 of the module notes on the channels ``idx``, the mixture's innovations through the monitors
        (:meth:`.ekf.BeliefFilter._screen`: a channel left out is left out of every mode's update)."""
        out = [self._condition(j, y, idx) if alive[j] else None for j in range(len(self.models))]
        ok = np.array([o is not None for o in out])
        w = np.where(ok, c, 0.0)
        if not w.sum() > 0:  # no mode could update: the filter has diverged
            self._beliefs = [Belief(np.full(len(b.x), np.nan), b.P) for b in self._beliefs]
            return
        w = w / w.sum()
        r, S = self._mixture(w, out)
        keep = self._screen(idx, r, S)
        if keep is not None:
            idx = idx[keep]
            out = [self._condition(j, y, idx) if ok[j] else None for j in range(len(self.models))]
            ok = np.array([o is not None for o in out])
            w = np.where(ok, w, 0.0)
            w = w / w.sum()
            r, S = self._mixture(w, out)
        m = len(idx)
        log_l = np.full(len(out), -np.inf)
        for j, o in enumerate(out):
            if o is not None:
                self.updates[j] = (self._beliefs[j].P, o[2], o[1])  # (what the smoother needs)
                self._beliefs[j] = o[0]
                sign, logdet = np.linalg.slogdet(o[1].S)
                log_l[j] = -0.5 * (o[1].nis + logdet + m * math.log(2.0 * math.pi)) if sign > 0 else -np.inf
        with np.errstate(divide="ignore"):
            log_p = np.log(c) + log_l
        top = np.max(log_p)
        p = np.exp(log_p - top) if np.isfinite(top) else w
        self.mode_p = p / p.sum()
        nis = float(r @ np.linalg.solve(S, r))
        self.last_idx, self.last_innovation, self.last_S, self.last_nis, self.last_dof = idx, r, S, nis, m

    @staticmethod
    def _mixture(w: np.ndarray, out: list) -> tuple[np.ndarray, np.ndarray]:
        """The mixture's innovation and its covariance, weights ``w`` over the modes' updates ``out`` (module
        notes, "Monitors")."""
        inn = [o[1] for o in out if o is not None]
        ww = w[[o is not None for o in out]]
        b = _moments(ww, [i.r for i in inn], [i.S for i in inn])
        return b.x, b.P

    def run(self, t, U, Y, *, reset: bool = True, x0=None, P0=None, innovations: bool = True,
            predictions: bool = False) -> EstimationResult:
        """:meth:`step` over a record (:meth:`.ekf.BeliefFilter.run`); the result's ``nominal_p`` is the first
        mode's probability at each sample. ``predictions``: each mode's posterior and interval per sample kept in
        ``track`` (:class:`ModeTrack`, what :meth:`smooth` needs)."""
        self._mode_p = np.full((len(np.reshape(t, -1)), len(self.models)), np.nan)
        self.track = ModeTrack(self._mode_p, [], [], []) if predictions else None
        res = super().run(t, U, Y, reset=reset, x0=x0, P0=P0, innovations=innovations)
        return replace(res, nominal_p=self._mode_p[:, 0])

    def _recorded(self, k: int) -> None:
        self._mode_p[k] = self.mode_p
        if self.track is not None:
            self.track.beliefs.append(list(self._beliefs))
            self.track.intervals.append(self.intervals)
            self.track.updates.append(self.updates)

    def smooth(self, t, U, Y, *, x0=None, P0=None) -> SmoothedResult:
        """Filter a record (from the prior, or ``x0``/``P0``) and smooth it backwards (module notes, "Smoothing"):
        the combined smoothed estimates and covariances, the first mode's smoothed probability in ``nominal_p`` and
        all modes' in ``mode_p``.

        Raises
        ------
        FilterDivergedError
            The forward pass went non-finite (a smoother cannot run back through it).
        """
        w0 = time.perf_counter()
        res = self.forward_pass(t, U, Y, x0=x0, P0=P0)  # (each mode's track kept: run's ``predictions``)
        w1 = time.perf_counter()
        tr, n = self.track, len(res.t)
        mu_s = tr.mode_p.copy()
        for k in range(n - 2, -1, -1):  # (Kim's recursion, module notes)
            T = self._transition(float(res.t[k + 1] - res.t[k]))
            c = mu_s[k] @ T
            mu_s[k] = np.divide(T * mu_s[k][:, None], c, out=np.zeros_like(T), where=c > 0) @ mu_s[k + 1]
        modes = [smooth_mode(tr, j) for j in range(len(self.models))]
        xs, Ps = np.empty_like(res.x_hat), np.empty_like(res.P)
        for k in range(n):
            xs[k], Ps[k] = combine(mu_s[k], [m[k] for m in modes], self.tails)
        self.track = None
        w2 = time.perf_counter()
        return SmoothedResult(res.t, xs, Ps, res.x_hat, res.P, res.nis, w2 - w0, w2 - w1, mu_s[:, 0], mu_s)


class ModeTrack(NamedTuple):
    """A run's per-mode record (:meth:`IMMFilter.run` with ``predictions``): the mode probabilities ``mode_p``
    (n, modes) and per sample ``k`` and mode ``j`` its posterior ``beliefs[k][j]``, the model's interval into the
    sample ``intervals[k][j]`` (a :class:`.base.Prediction`; None at the first sample and where the model could not
    step) and the update ``updates[k][j]``: ``(P, H, innovation)``, the predicted covariance, the measurement
    Jacobian of the channels used and the :class:`.kalman.Innovation` (None without an update)."""

    mode_p: np.ndarray
    beliefs: list
    intervals: list
    updates: list


def smooth_mode(track: ModeTrack, j: int) -> list[Belief]:
    """Mode ``j``'s smoothed beliefs along its own chain (module notes, "Smoothing"), by the modified Bryson-Frazier
    recursion (Bierman 1977): with the adjoint ``lam``, ``Lam`` after sample ``k``'s update (zero after the last),
    ``x_k|n = x_k - P_k lam``, ``P_k|n = P_k - P_k Lam P_k``; through the update (gain ``K``, ``A = I - K H``)
    ``lam <- A' lam - H' S^-1 r``, ``Lam <- A' Lam A + H' S^-1 H``; through the interval ``lam <- F' lam``,
    ``Lam <- F' Lam F``."""
    n = len(track.beliefs[0][j].x)
    lam, Lam = np.zeros(n), np.zeros((n, n))
    out = [None] * len(track.beliefs)
    for k in range(len(track.beliefs) - 1, -1, -1):
        b = track.beliefs[k][j]
        PL = b.P @ Lam
        out[k] = Belief(b.x - b.P @ lam, b.P - 0.5 * (PL @ b.P + (PL @ b.P).T))
        if track.updates[k][j] is not None:
            P, H, inn = track.updates[k][j]
            sol = np.linalg.solve(inn.S, np.column_stack([H, inn.r]))
            SiH, Sir = sol[:, :-1], sol[:, -1]
            A = np.eye(n) - P @ H.T @ SiH
            lam, Lam = A.T @ lam - H.T @ Sir, A.T @ Lam @ A + H.T @ SiH
        F = None if track.intervals[k][j] is None else track.intervals[k][j].F
        lam, Lam = (np.zeros(n), np.zeros((n, n))) if F is None else (F.T @ lam, F.T @ Lam @ F)
    return out

"""Unscented Kalman filter on a :class:`~exuflex.observer.base.DiscreteModel`'s step map.

The same model as the EKF's (:class:`~exuflex.observer.reduced.ReducedObserverModel` or an augmented one): its
:meth:`~DiscreteModel.predict` is used for its mean only (``Prediction.x``; ``F`` is not needed) and for the process
noise of the interval, :meth:`~DiscreteModel.measure` for the predicted channels only. Per sample::

    sigma points  X_i = x +- columns of chol((n + lambda) P), weights Wm, Wc   (Merwe's scaled set,
                                                                              filterpy's MerweScaledSigmaPoints)
    predict       X_i <- f(X_i, u, dt);  x = sum Wm X_i;  P = sum Wc (X_i - x)(X_i - x)' + Q
    update        sigma points of (x, P) anew (so that Q reaches the measurement), Z_i = g(X_i)
                  z = sum Wm Z_i,  S = sum Wc (Z_i - z)(Z_i - z)' + R,  C = sum Wc (X_i - x)(Z_i - z)'
                  K = C S^-1,  x += K (y - z),  P -= K S K'

The process noise ``Q`` is the one the model returns for the mean's interval (additive noise). On a linear model
the UKF is the Kalman filter exactly (the sigma points reproduce the mean and covariance through a linear map);
the tests check that. Channels and gaps are handled as by the EKF: NaN channels are left out of the update,
an all-NaN sample is a prediction only, intervals longer than ``max_gap`` are refused.

Cost: ``2 n + 1`` model steps and measurements per sample instead of one step and its Jacobian.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence

import numpy as np
import scipy.linalg
from filterpy.kalman import MerweScaledSigmaPoints

from .base import FilterDivergedError
from .ekf import EstimationResult, NISMonitor, RunRecord, check_log

__all__ = ["UnscentedKF"]

log = logging.getLogger(__name__)


class UnscentedKF:
    """Multirate unscented Kalman filter over a :class:`DiscreteModel` (module docstring).

    Parameters
    ----------
    model, channels, R_std, x0, P0, dt, max_gap, nis_window, nonfinite
        As :class:`~exuflex.observer.ekf.MultirateEKF`.
    alpha, beta, kappa : float
        Merwe's scaled sigma points: spread ``alpha = 1``, ``beta = 2`` (Gaussian prior), ``kappa = 0``. The points
        lie ``alpha sqrt(n + kappa)`` standard deviations from the mean, and (``kappa = 0``) the mean's weights are
        ``Wm0 = 1 - 1 / alpha^2`` and ``Wc0 = Wm0 + 1 - alpha^2 + beta``. ``alpha = 1`` makes every weight
        non-negative, so the predicted covariance is a sum of positive semi-definite terms; a small ``alpha`` (or
        ``kappa = 3 - n`` with tens of states) gives weights of hundreds with opposite signs, whose cancellation
        costs the covariance its small (elastic) entries and can make it indefinite.
    store_P : {"diag", "full", "none"}
    """

    def __init__(self, model, channels: Sequence[str], R_std: Mapping[str, float], x0, P0, dt: float,
                 alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0, max_gap: float = 1.0,
                 store_P: str = "diag", nis_window: int = 100, nonfinite: str = "raise"):
        self.model = model
        self.nx = int(model.nx)
        self.channels = tuple(channels)
        self.m = len(self.channels)
        missing = [c for c in self.channels if c not in R_std]
        if missing:
            raise ValueError(f"no measurement-noise std for channel(s) {missing}")
        self.R_std = np.array([float(R_std[c]) for c in self.channels])
        self._Rdiag = self.R_std**2
        self.dt = float(dt)
        self.max_gap = float(max_gap)
        self.store_P = store_P
        self.nonfinite_action = nonfinite
        n = self.nx
        self.points = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa,
                                             sqrt_method=lambda A: scipy.linalg.cholesky(A, lower=False))
        self.Wm, self.Wc = self.points.Wm, self.points.Wc
        self.monitor = NISMonitor(nis_window) if nis_window else None
        x0 = np.asarray(x0, float).reshape(-1)
        P0 = np.asarray(P0, float)
        self._x0 = x0.copy()
        self._P0 = np.diag(P0) if P0.ndim == 1 else P0.copy()
        self.reset()

    def reset(self, x0=None, P0=None) -> None:
        if x0 is not None:
            self._x0 = np.asarray(x0, float).reshape(-1).copy()
        if P0 is not None:
            P0 = np.asarray(P0, float)
            self._P0 = np.diag(P0) if P0.ndim == 1 else P0.copy()
        if hasattr(self.model, "reset"):
            self.model.reset()
        self._x = self._x0.copy()
        self._P = self._P0.copy()
        self._t_prev = None
        self._u_prev = None
        self.n_missing = self.n_updates = self.n_model_resets = 0
        self.diverged = False
        self.diverged_at = None
        self.nonfinite = False
        self.last_nis, self.last_dof, self.last_idx = math.nan, 0, None
        self.last_innovation = self.last_S = None
        if self.monitor is not None:
            self.monitor.reset()

    @property
    def x(self) -> np.ndarray:
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        return self._P.copy()

    def _sigmas(self, x, P) -> np.ndarray:
        return self.points.sigma_points(x, 0.5 * (P + P.T))

    def _moments(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        mean = self.Wm @ X
        D = X - mean
        return mean, (D.T * self.Wc) @ D, D

    def _predict(self, x, dt, u_next):
        """The model's step from ``x``. A model that caches configuration-dependent data (the reduced model's held
        configuration and its expansion) is built for a trajectory, not for points visited in turn around it:
        where its step from a sigma point is not finite, the step is taken again after ``model.reset()`` (the
        configuration evaluated at that point)."""
        p = self.model.predict(x, self._u_prev, dt, u_next)
        if not np.all(np.isfinite(p.x)) and hasattr(self.model, "reset"):
            self.model.reset()
            self.n_model_resets += 1
            p = self.model.predict(x, self._u_prev, dt, u_next)
        return p

    def step(self, t: float, u, y) -> np.ndarray:
        """Predict to ``t`` through the sigma points, update with the finite channels of ``y``."""
        t = float(t)
        if u is not None:
            u = np.array(u, dtype=float).reshape(-1)
        y = None if y is None else np.asarray(y, float)
        if self.nonfinite:  # flagged earlier ("flag" mode): NaN estimates from then on
            self._t_prev = t
            return np.full(self.nx, np.nan)
        if self._t_prev is not None:
            dt = t - self._t_prev
            if not dt > 0:
                raise ValueError(f"sample time {t!r} s is not after the previous sample's ({self._t_prev!r} s)")
            if dt > self.max_gap:
                raise ValueError(f"sample time {t:.6g} s is {dt:.6g} s after the previous sample, more than "
                                 f"max_gap={self.max_gap:g} s")
            self.n_missing += max(round(dt / self.dt) - 1, 0)
            X = self._sigmas(self._x, self._P)
            m0 = self._predict(X[0], dt, u)  # the mean's interval: its process noise
            Xf = np.empty_like(X)
            Xf[0] = m0.x
            for i in range(1, len(X)):
                Xf[i] = self._predict(X[i], dt, u).x
            self._x, P, _ = self._moments(Xf)
            self._P = P + m0.Q
            if not (np.all(np.isfinite(self._x)) and np.all(np.isfinite(self._P))):
                return self._nonfinite(t)
        self._t_prev, self._u_prev = t, u
        self.last_idx, self.last_nis, self.last_dof = None, math.nan, 0
        mask = None if y is None else np.isfinite(y)
        if mask is not None and mask.any():
            idx = np.flatnonzero(mask)
            chans = tuple(self.channels[i] for i in idx)
            X = self._sigmas(self._x, self._P)
            Z = np.array([self.model.measure(xi, chans).y for xi in X])
            zm, Pzz, Dz = self._moments(Z)
            Dx = X - self.Wm @ X
            S = Pzz + np.diag(self._Rdiag[idx])
            C = (Dx.T * self.Wc) @ Dz
            r = y[idx] - zm
            cf = scipy.linalg.cho_factor(S)
            K = scipy.linalg.cho_solve(cf, C.T).T
            self._x = self._x + K @ r
            P = self._P - K @ S @ K.T
            self._P = 0.5 * (P + P.T)
            nis = float(r @ scipy.linalg.cho_solve(cf, r))
            self.last_idx, self.last_nis, self.last_dof = idx, nis, len(idx)
            self.last_innovation, self.last_S = r, S
            self.n_updates += 1
            if self.monitor is not None and self.monitor.push(nis, len(idx)) and not self.diverged:
                self.diverged, self.diverged_at = True, t
        else:
            self.n_missing += 1
        if not (np.all(np.isfinite(self._x)) and np.all(np.isfinite(self._P))):
            return self._nonfinite(t)
        return self._x.copy()

    def _nonfinite(self, t: float) -> np.ndarray:
        """A non-finite state or covariance: raise, or flag the run and return NaN (``nonfinite="flag"``)."""
        if not self.diverged:
            self.diverged, self.diverged_at = True, t
        self.nonfinite = True
        if self.nonfinite_action == "raise":
            raise FilterDivergedError(f"non-finite state or covariance at t={t:.6g} s")
        return np.full(self.nx, np.nan)

    def run(self, t, U, Y, *, reset: bool = True, x0=None, P0=None) -> EstimationResult:
        """:meth:`step` over a record (as :meth:`MultirateEKF.run`)."""
        t, U, Y = check_log(t, U, Y, self.m)
        if reset or x0 is not None or P0 is not None:
            self.reset(x0, P0)
        rec = RunRecord(t, self.nx, self.m, self.store_P)
        w0 = time.perf_counter()
        for k in range(len(t)):
            try:
                x = self.step(t[k], None if U is None else U[k], Y[k])
            except (np.linalg.LinAlgError, ArithmeticError) as exc:  # a covariance lost definiteness
                if self.nonfinite_action == "raise":
                    raise FilterDivergedError(f"UKF failed at t={t[k]:.6g} s: {exc}") from exc
                self.nonfinite, self.diverged = True, True
                self.diverged_at = self.diverged_at or float(t[k])
                rec.fail_from(k)
                break
            rec.put(k, self, x)
        return rec.result(self, time.perf_counter() - w0)

"""Unscented Kalman filter on a :class:`~exuflex.observer.base.DiscreteModel`'s step map, in square-root form.

The same model as the EKF's (:class:`~exuflex.observer.reduced.ReducedObserverModel` or an augmented one): its
:meth:`~DiscreteModel.predict` is used for its mean only (``Prediction.x``; ``F`` is not needed) and for the process
noise of the interval, :meth:`~DiscreteModel.measure` for the predicted channels only. The filter carries the
mean and a lower Cholesky factor ``L`` of the covariance (``P = L L'``). Per sample::

    sigma points  X_0 = x,  X_i = x +- c L[:, i]  (c = alpha sqrt(n + kappa); Merwe's scaled set and weights
                  Wm, Wc, filterpy's MerweScaledSigmaPoints)
    predict       X_i <- f(X_i, u, dt);  x = sum Wm X_i
                  L = R' with R from the QR factorisation of [sqrt(Wc_i) (X_i - x)' ; sqrt(Q)']
                  (P = sum Wc (X_i - x)(X_i - x)' + Q)
    update        sigma points of (x, L) anew (so that Q reaches the measurement), Z_i = g(X_i)
                  z = sum Wm Z_i,  S = sum Wc (Z_i - z)(Z_i - z)' + R (its factor by QR likewise),
                  C = sum Wc (X_i - x)(Z_i - z)',  K = C S^-1,  x += K (y - z)
                  P+ = (I - K H) P (I - K H)' + K R K' with H = C' P^-1 (the measurement's statistical
                  linearisation), its factor by QR of [(I - K H) L, K sqrt(R)]'

Why the square-root form: the reduced flexible model's covariance spans many decades (joint angles against elastic
coordinates of micrometres) with strong correlations, and the covariance form's sums and its downdate
``P - K S K'`` lose positive definiteness to rounding there (a Cholesky failure at the next sigma points). Factors
from QR are triangular by construction, and the Joseph-form update is a sum of two positive semi-definite terms.
With a linear measurement ``H`` is its matrix and the update is the Kalman filter's (the tests check the UKF
against the Kalman filter on a linear model). A negative centre weight ``Wc_0`` (``alpha`` well below 1) enters
by a rank-one downdate of the factor, which fails (a ``LinAlgError``, the run flagged) where the covariance it
describes is not positive definite.

A sigma point's step can break down where the model is not built to be evaluated (the reduced model's held
expansion far from its centre): such a step is retaken after a model reset, and carried by the mean's
linearisation if it breaks down again (:meth:`UnscentedKF._predict`).

The process noise ``Q`` is the one the model returns for the mean's interval (additive noise). Channels and gaps
are handled as by the EKF: NaN channels are left out of the update, an all-NaN sample is a prediction only,
intervals longer than ``max_gap`` are refused. The innovations go through the EKF's monitors
(:class:`~exuflex.observer.ekf.BeliefFilter`: the NIS test, the gate, the hold-off after an input step, the
sensor-fault windows; "diverged" is a non-finite state or covariance, as for the EKF).

Cost: ``2 n + 1`` model steps and measurements per sample instead of one step and its Jacobian.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence

import numpy as np
import scipy.linalg

from .base import Prediction
from .ekf import BeliefFilter, Monitoring

__all__ = ["UnscentedKF"]

log = logging.getLogger(__name__)

#: a sigma point's step that departs from the mean's linearisation by more than this many times the linear
#: response itself is a breakdown of the model there, not its nonlinearity (see :meth:`UnscentedKF._predict`)
BREAKDOWN = 10.0


class UnscentedKF(BeliefFilter):
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
    monitoring : Monitoring, optional
        The innovation monitors, as :class:`~exuflex.observer.ekf.MultirateEKF`'s keyword arguments (default: the
        NIS test over ``nis_window`` updates alone).
    """

    def __init__(self, model, channels: Sequence[str], R_std: Mapping[str, float], x0, P0, dt: float,
                 alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0, max_gap: float = 1.0,
                 store_P: str = "diag", nis_window: int = 100, nonfinite: str = "raise",
                 monitoring: Monitoring | None = None):
        self._setup(model, channels, R_std, x0, P0, dt, max_gap, store_P, nonfinite,
                    monitoring if monitoring is not None else Monitoring(nis_window=nis_window))
        n = self.nx
        # Merwe's weights, lambda = alpha^2 (n + kappa) - n: Wm_0 = lambda / (n + lambda), Wc_0 = Wm_0 + 1 -
        # alpha^2 + beta, the others 1 / (2 (n + lambda)) (the arithmetic of filterpy's MerweScaledSigmaPoints)
        lam = alpha**2 * (n + kappa) - n
        self.Wm = np.full(2 * n + 1, 0.5 / (n + lam))
        self.Wc = self.Wm.copy()
        self.Wm[0] = lam / (n + lam)
        self.Wc[0] = lam / (n + lam) + (1 - alpha**2 + beta)
        self._spread = alpha * math.sqrt(n + kappa)  # sqrt(n + lambda), lambda = alpha^2 (n + kappa) - n
        self.reset()

    def reset(self, x0=None, P0=None) -> None:
        """Restart from a prior (:meth:`~exuflex.observer.ekf.BeliefFilter.reset`) with its covariance factor."""
        super().reset(x0, P0)
        self._L = np.linalg.cholesky(self._P0)
        self.n_model_resets = self.n_linearised = 0

    def _sigmas(self, x, L) -> np.ndarray:
        """Merwe's sigma points of the mean ``x`` and the covariance factor ``L``: ``x`` and ``x +- c L[:, i]``
        (filterpy's order: the ``+`` points, then the ``-`` points)."""
        D = self._spread * L.T
        return np.vstack([x, x + D, x - D])

    def _factor(self, D: np.ndarray, extra: np.ndarray) -> np.ndarray:
        """Lower factor of ``sum_i Wc_i D_i' D_i + extra' extra`` (``D`` the deviations of the sigma points, one
        per row; ``extra`` rows of a square root of the added covariance): QR of the weighted rows, with the
        centre's weight by a rank-one update (or downdate, for a negative weight)."""
        w0 = self.Wc[0]
        rows = [np.sqrt(self.Wc[1:])[:, None] * D[1:], extra]
        if w0 >= 0:
            rows.append(math.sqrt(w0) * D[:1])
        L = _lower_from_qr(np.vstack(rows))
        if w0 < 0:
            L = _cholupdate(L, math.sqrt(-w0) * D[0], -1.0)
        return L

    def _predict(self, x, dt, u_next, ref=None):
        """The model's step from ``x``. A model that caches configuration-dependent data (the reduced model's held
        configuration and its expansion) is built for a trajectory, not for points visited in turn around it:
        where its step from a sigma point breaks down (not finite, or, given the mean's point and prediction
        ``ref``, departing from the mean's linearisation by more than ``BREAKDOWN`` times the linear response
        itself: a held expansion used far from its centre, whose sub-steps are then unstable), the step is taken
        again after ``model.reset()`` (the configuration evaluated at that point). If it breaks down again, the
        point is carried by the mean's linearisation (counted in ``n_linearised``)."""
        p = self.model.predict(x, self._u_prev, dt, u_next)
        if self._broken(p.x, x, ref) and self.hooks.reset is not None:
            self.hooks.reset()
            self.n_model_resets += 1
            p = self.model.predict(x, self._u_prev, dt, u_next)
        if ref is not None and self._broken(p.x, x, ref):
            x0, m0 = ref
            self.n_linearised += 1
            return Prediction(m0.x + m0.F @ (x - x0), m0.F, m0.Q)
        return p

    @staticmethod
    def _broken(xn, x, ref) -> bool:
        if not np.all(np.isfinite(xn)):
            return True
        if ref is None:
            return False
        x0, m0 = ref
        lin = m0.F @ (x - x0)
        return float(np.max(np.abs(xn - m0.x - lin))) > BREAKDOWN * float(np.max(np.abs(lin)))

    def _predict_step(self, dt: float | None, u_next) -> bool:
        """The sigma points through the model's step (module notes): the predicted mean and covariance factor;
        whether they are finite."""
        if dt is None:
            return True
        X = self._sigmas(self._x, self._L)
        m0 = self._predict(X[0], dt, u_next)  # the mean's interval: its process noise
        Xf = np.empty_like(X)
        Xf[0] = m0.x
        ref = (X[0], m0) if np.all(np.isfinite(m0.x)) else None
        for i in range(1, len(X)):
            Xf[i] = self._predict(X[i], dt, u_next, ref).x
        if not np.all(np.isfinite(Xf)):
            return False
        self._x = self.Wm @ Xf
        self._L = self._factor(Xf - self._x, _psd_sqrt(m0.Q))
        return True

    def _update_step(self, t: float, finite: bool, y) -> np.ndarray:
        """The update with the finite channels of ``y`` that the gate and the sensor-fault isolation keep."""
        if not finite:
            return self._close(t, False)
        mask = None if y is None else np.isfinite(y)
        if mask is not None and mask.any():
            idx = np.flatnonzero(mask)
            X = self._sigmas(self._x, self._L)
            Z = np.array([self.model.measure(xi, tuple(self.channels[i] for i in idx)).y for xi in X])
            r, Ls, C = self._innovation(X, Z, y, idx)
            keep = self._screen(idx, r, Ls @ Ls.T)
            if keep is not None:  # the channels the gate or the isolation left out
                idx, Z = idx[keep], Z[:, keep]
                r, Ls, C = self._innovation(X, Z, y, idx)
            cf = (Ls, True)
            K = scipy.linalg.cho_solve(cf, C.T).T
            self._x = self._x + K @ r
            # Joseph form with the statistical linearisation H = C' P^-1: (I - K H) L = L - K (L^-1 C)'
            H_L = scipy.linalg.solve_triangular(self._L, C, lower=True).T  # H L
            self._L = _lower_from_qr(np.vstack([(self._L - K @ H_L).T, (K * np.sqrt(self._Rdiag[idx])).T]))
            nis = float(r @ scipy.linalg.cho_solve(cf, r))
            self.last_idx, self.last_nis, self.last_dof = idx, nis, len(idx)
            self.last_innovation, self.last_S = r, Ls @ Ls.T
        else:
            self.n_missing += 1
        self._P = self._L @ self._L.T
        return self._close(t, bool(np.all(np.isfinite(self._x)) and np.all(np.isfinite(self._P))))

    def _innovation(self, X: np.ndarray, Z: np.ndarray, y: np.ndarray, idx: np.ndarray) -> tuple:
        """``(r, Ls, C)`` of the sigma points ``X`` and their channels ``Z`` (columns: the channels ``idx``): the
        innovation ``y - z``, the lower factor of ``S = Ls Ls'`` and the cross covariance ``C``."""
        zm = self.Wm @ Z
        Dz = Z - zm
        Dx = X - self._x  # (the sigma points' weighted mean is x)
        Ls = self._factor(Dz, np.diag(np.sqrt(self._Rdiag[idx])))  # S = Ls Ls'
        C = (Dx.T * self.Wc) @ Dz
        return np.ascontiguousarray(y[idx] - zm), Ls, C


def _lower_from_qr(A: np.ndarray) -> np.ndarray:
    """Lower triangular ``L`` with ``L L' = A' A`` (from the QR factorisation of ``A``, rows at least its columns),
    its diagonal made non-negative."""
    R = np.linalg.qr(A, mode="r")
    sgn = np.where(np.diagonal(R) < 0, -1.0, 1.0)
    return (R * sgn[:, None]).T


def _psd_sqrt(Q: np.ndarray) -> np.ndarray:
    """Rows ``E`` with ``E' E = Q`` for a symmetric positive semi-definite ``Q`` (the process noise is often of
    low rank: the motors' torque noise through the step map), from its eigen-decomposition."""
    w, V = np.linalg.eigh(0.5 * (Q + Q.T))
    keep = w > 0
    return (V[:, keep] * np.sqrt(w[keep])).T


def _cholupdate(L: np.ndarray, v: np.ndarray, sign: float) -> np.ndarray:
    """Lower factor of ``L L' + sign v v'`` (a rank-one update, or downdate for ``sign = -1``, column by column);
    ``LinAlgError`` if a downdate leaves the matrix not positive definite."""
    L = L.copy()
    v = np.array(v, float)
    for k in range(len(v)):
        lkk = L[k, k]
        r2 = lkk * lkk + sign * v[k] * v[k]
        if not r2 > 0 or lkk == 0:
            raise np.linalg.LinAlgError("the covariance lost positive definiteness in a rank-one downdate")
        rk = math.sqrt(r2)
        c, s = rk / lkk, v[k] / lkk
        L[k, k] = rk
        L[k + 1 :, k] = (L[k + 1 :, k] + sign * s * v[k + 1 :]) / c
        v[k + 1 :] = c * v[k + 1 :] - s * L[k + 1 :, k]
    return L

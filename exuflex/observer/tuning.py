"""Construction and tuning of the process-noise covariance ``Q``.

Torque noise through the input matrix
-------------------------------------
The paper's process noise is the uncertainty of the motor torques. If the applied torque over one interval is
``u_k + w_k`` with ``w_k ~ N(0, diag(sigma_tau^2))`` held constant over the interval (zero-order hold, the way a
drive applies a sampled command), then to first order

    x_k+1 = f_d(x_k, u_k + w_k) ~ f_d(x_k, u_k) + Gamma w_k,   Gamma = d f_d / d u   (discrete input matrix),

so ``Q = Gamma diag(sigma_tau^2) Gamma'`` (:func:`zoh_torque_noise`). ``sigma_tau`` is the standard deviation
of the held torque sample, so there is *no* ``dt`` factor: the ``dt`` dependence is inside ``Gamma``
(``Gamma ~ B dt`` on the velocities for small ``dt``). For a model state ``[p; p']`` and an exactly
discretised linear model ``Gamma = int_0^dt expm(A s) ds B``; for a nonlinear model :func:`input_jacobian`
finite-differences the model's step.

If the torque disturbance is instead modelled as continuous white noise of intensity ``q`` (N^2 m^2 s), then
``Q = int_0^dt expm(A s) B q B' expm(A s)' ds ~ B q B' dt`` (:func:`continuous_torque_noise`, Van Loan).

A small diagonal ``extra_diag`` may be added for unmodelled dynamics (truncated modes, discretisation error)
and to keep ``Q`` full rank.

NIS-based scaling
-----------------
:func:`tune_q_scale` finds the single factor ``s`` (``Q -> s Q``) for which the time-averaged NIS of a run
equals its expected value (the mean number of channels per update): the usual one-knob consistency tuning.
It is only as informative as the NIS is sensitive to ``Q``: when the measurement noise dominates ``S``, the
mean NIS varies little with ``s`` and a run's sampling scatter of the mean NIS (``sqrt(2 m / n)``) maps to a
wide range of ``s``; check ``QScaleResult.history`` before trusting the factor.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm

from .base import DiscreteModel, Prediction

__all__ = [
    "QScaleResult",
    "van_loan",
    "ScaledNoiseModel",
    "continuous_torque_noise",
    "input_jacobian",
    "tune_q_scale",
    "zoh_torque_noise",
]

log = logging.getLogger(__name__)


def van_loan(A_c: np.ndarray, Qc: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation of ``x' = A_c x + w`` with white ``w`` of intensity ``Qc`` over ``dt`` (Van Loan).

    Returns
    -------
    A : ndarray
        ``expm(A_c dt)``.
    Q : ndarray
        ``int_0^dt expm(A_c s) Qc expm(A_c s)' ds``.
    """
    A_c = np.asarray(A_c, float)
    n = A_c.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A_c
    M[:n, n:] = Qc
    M[n:, n:] = A_c.T
    E = expm(M * dt)
    A = E[n:, n:].T
    Q = A @ E[:n, n:]
    return A, 0.5 * (Q + Q.T)


def _add_diag(Q: np.ndarray, extra_diag) -> np.ndarray:
    if extra_diag is not None:
        Q = Q + np.diag(np.broadcast_to(np.asarray(extra_diag, float), (Q.shape[0],)))
    return 0.5 * (Q + Q.T)


def zoh_torque_noise(Gamma, sigma_tau, extra_diag=None) -> np.ndarray:
    """``Q = Gamma diag(sigma_tau^2) Gamma' (+ diag(extra_diag))`` for zero-order-held torque noise.

    Parameters
    ----------
    Gamma : ndarray, shape (nx, nu) or (nx,)
        Discrete input matrix ``d x_next / d u`` over one interval (a vector for a single input).
    sigma_tau : float or array_like, shape (nu,)
        Standard deviation of each held torque (input units).
    extra_diag : float or array_like, shape (nx,), optional
        Variances added on the diagonal (unmodelled dynamics).

    Returns
    -------
    ndarray, shape (nx, nx)
    """
    Gamma = np.asarray(Gamma, float)
    if Gamma.ndim == 1:  # a single input
        Gamma = Gamma[:, None]
    s2 = np.broadcast_to(np.asarray(sigma_tau, float) ** 2, (Gamma.shape[1],))
    return _add_diag((Gamma * s2) @ Gamma.T, extra_diag)


def continuous_torque_noise(A_c, B_c, psd, dt: float, extra_diag=None) -> np.ndarray:
    """Exact ``Q`` of continuous white torque noise of intensity ``psd`` over ``dt`` (Van Loan).

    Parameters
    ----------
    A_c : ndarray, shape (nx, nx)
        Continuous system matrix (linearised).
    B_c : ndarray, shape (nx, nu)
        Continuous input matrix.
    psd : float or array_like, shape (nu,)
        White-noise intensity of each input (input units^2 * s).
    dt : float
    extra_diag : optional
        As in :func:`zoh_torque_noise`.
    """
    B_c = np.atleast_2d(np.asarray(B_c, float))
    q = np.broadcast_to(np.asarray(psd, float), (B_c.shape[1],))
    _, Q = van_loan(A_c, (B_c * q) @ B_c.T, dt)
    return _add_diag(Q, extra_diag)


def input_jacobian(model: DiscreteModel, x, u, dt: float, eps=None) -> np.ndarray:
    """``Gamma = d x_next / d u`` of a model's step by central differences.

    Parameters
    ----------
    model : DiscreteModel
    x : ndarray, shape (nx,)
    u : array_like, shape (nu,)
    dt : float
    eps : float or array_like, optional
        Perturbation per input (default ``1e-4 * max(1, |u_i|)``: the step is smooth in ``u`` and a small
        perturbation of a torque moves the state by little, so round-off dominates below this).

    Returns
    -------
    ndarray, shape (nx, nu)
    """
    u = np.atleast_1d(np.asarray(u, float))
    h = 1e-4 * np.maximum(1.0, np.abs(u)) if eps is None else np.broadcast_to(np.asarray(eps, float), u.shape)
    cols = []
    for i in range(len(u)):
        up, um = u.copy(), u.copy()
        up[i] += h[i]
        um[i] -= h[i]
        cols.append((model.predict(x, up, dt).x - model.predict(x, um, dt).x) / (2 * h[i]))
    return np.stack(cols, axis=1)


class ScaledNoiseModel:
    """A :class:`DiscreteModel` wrapper whose process noise is ``scale`` times the wrapped model's.

    Every other attribute is the wrapped model's.
    """

    def __init__(self, model: DiscreteModel, scale: float):
        self.model = model
        self.scale = float(scale)
        self.nx = model.nx

    def predict(self, x, u, dt, u_next=None):
        x_next, F, Q = self.model.predict(x, u, dt, u_next)
        return Prediction(x_next, F, self.scale * Q)

    def measure(self, x, channels):
        return self.model.measure(x, channels)

    def __getattr__(self, name):
        return getattr(self.model, name)


@dataclass
class QScaleResult:
    """Outcome of :func:`tune_q_scale`.

    Attributes
    ----------
    scale : float
        The factor on ``Q``.
    mean_nis, expected_nis : float
        Time-averaged NIS with that factor, and its expected value.
    converged : bool
        False if the target was not bracketed by ``bounds`` (``scale`` is then the nearer bound).
    history : list of (scale, mean_nis)
        Every evaluation.
    """

    scale: float
    mean_nis: float
    expected_nis: float
    converged: bool
    history: list = field(default_factory=list)


def tune_q_scale(filter_for: Callable[[DiscreteModel], object], model: DiscreteModel, t, U, Y, *,
                 bounds: tuple[float, float] = (1e-4, 1e4), burn_in: int = 0, rtol: float = 0.01,
                 max_iter: int = 40) -> QScaleResult:
    """One-parameter search of ``s`` in ``Q -> s Q`` bringing the mean NIS of a run to its expected value.

    The mean NIS decreases monotonically with ``s`` in practice (more process noise, larger ``S``); the
    root of ``log(mean NIS / expected)`` in ``log s`` is found by Brent's method inside ``bounds``.

    Parameters
    ----------
    filter_for : callable
        ``filter_for(model)``: the filter to run on a model (e.g. a :class:`~exuflex.observer.ekf.MultirateEKF`
        with ``nonfinite="flag"``, so that a blow-up counts as too little process noise).
    model : DiscreteModel
        Model with the nominal ``Q``.
    t, U, Y
        A recorded run (as for :meth:`~exuflex.observer.ekf.MultirateEKF.run`).
    bounds : (float, float)
        Search interval of ``s``.
    burn_in : int
        Leading samples left out of the NIS average (initial transient).
    rtol : float
        Relative tolerance on ``s``.
    max_iter : int
        Maximum evaluations inside the bracket.

    Returns
    -------
    QScaleResult
    """
    history: list[tuple[float, float]] = []
    expected = [float("nan")]

    def f(logs: float) -> float:
        s = float(np.exp(logs))
        res = filter_for(ScaledNoiseModel(model, s)).run(t, U, Y)
        mn, ex = res.mean_nis(burn_in)
        expected[0] = ex
        history.append((s, mn))
        if res.nonfinite or not np.isfinite(mn):
            return 50.0  # treat a blow-up as "far too little process noise"
        return float(np.log(mn / ex))

    lo, hi = np.log(bounds[0]), np.log(bounds[1])
    f_lo, f_hi = f(lo), f(hi)
    if f_lo <= 0 or f_hi >= 0:
        s = bounds[0] if f_lo <= 0 else bounds[1]
        log.warning("tune_q_scale: mean NIS target not bracketed by scale bounds %s; returning %g", bounds, s)
        mn = history[0][1] if f_lo <= 0 else history[1][1]
        return QScaleResult(s, mn, expected[0], False, history)
    from scipy.optimize import brentq  # here, not at import: scipy.optimize is a large import

    logs = brentq(f, lo, hi, xtol=np.log1p(rtol), maxiter=max_iter)
    s = float(np.exp(logs))
    f(logs)
    return QScaleResult(s, history[-1][1], expected[0], True, history)

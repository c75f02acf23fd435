"""The best achievable steady-state estimation error: the stationary Kalman covariance (the "bound").

For a linear (or linearised, frozen) model ``x+ = A x + w``, ``y = H x + v`` with ``cov w = Q``, ``cov v = R``
and every channel sampled every interval, no estimator does better in mean square than the steady-state Kalman
filter; its prior covariance solves the filter discrete algebraic Riccati equation

    P = A P A' - A P H' (H P H' + R)^-1 H P A' + Q,

and its posterior covariance is ``P+ = P - P H' (H P H' + R)^-1 H P``. ``sqrt(diag(P+))`` is the bound on
the RMS error of every state; an EKF on the nonlinear model with the same noise levels should come close to it
near that operating point.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.linalg import expm, solve_discrete_are

from .base import DiscreteModel

__all__ = ["bound_rms", "linearise", "steady_state_covariance", "van_loan"]


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


def steady_state_covariance(
    A, G_or_Q, H, R, dt: float | None = None, *, continuous: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Stationary prior and posterior error covariances of the Kalman filter (DARE).

    Parameters
    ----------
    A : ndarray, shape (nx, nx)
        Discrete transition matrix over one interval (or the continuous system matrix if ``continuous``).
    G_or_Q : ndarray, shape (nx, nx) or (nx, p)
        Either the process-noise covariance per interval ``Q`` (square), or a noise input matrix ``G``
        already scaled by the noise standard deviations, giving ``Q = G G'`` (for a zero-order-held torque
        noise: ``G = Gamma diag(sigma_tau)`` with ``Gamma`` the discrete input matrix). A square ``G`` must
        be passed as ``G @ G.T``.
    H : ndarray, shape (m, nx)
        Measurement matrix.
    R : ndarray, shape (m, m) or (m,)
        Measurement-noise covariance (a vector is its diagonal: variances, not stds).
    dt : float, optional
        Interval; only needed with ``continuous=True``.
    continuous : bool
        ``A`` and ``G_or_Q`` are continuous-time (system matrix, white-noise intensity); they are discretised
        exactly over ``dt`` (:func:`van_loan`).

    Returns
    -------
    P_prior, P_post : ndarray, shape (nx, nx)
        Steady-state covariance before and after a measurement update.
    """
    A = np.asarray(A, float)
    nx = A.shape[0]
    G_or_Q = np.asarray(G_or_Q, float)
    Q = G_or_Q if G_or_Q.shape == (nx, nx) else G_or_Q @ G_or_Q.T
    H = np.atleast_2d(np.asarray(H, float))
    R = np.asarray(R, float)
    if R.ndim == 1:
        R = np.diag(R)
    if continuous:
        if dt is None:
            raise ValueError("dt is required with continuous=True")
        A, Q = van_loan(A, Q, dt)
    Q = 0.5 * (Q + Q.T)
    # filter DARE = control DARE of the dual system (A', H')
    P_prior = solve_discrete_are(A.T, H.T, Q, R)
    P_prior = 0.5 * (P_prior + P_prior.T)
    PHt = P_prior @ H.T
    S = H @ PHt + R
    P_post = P_prior - PHt @ np.linalg.solve(S, PHt.T)
    return P_prior, 0.5 * (P_post + P_post.T)


def bound_rms(P_post: np.ndarray, rows) -> np.ndarray:
    """RMS error bound of selected states, or of linear combinations of states.

    Parameters
    ----------
    P_post : ndarray, shape (nx, nx)
        Error covariance (e.g. from :func:`steady_state_covariance`).
    rows : int, sequence of int, slice, or ndarray of shape (k, nx)
        State indices, or a matrix ``C`` whose rows are linear functionals of the state (e.g. the output map
        of a strain or tip deflection), giving ``sqrt(diag(C P C'))``.

    Returns
    -------
    ndarray
        Standard deviations.
    """
    P_post = np.asarray(P_post, float)
    if isinstance(rows, np.ndarray) and rows.ndim == 2:
        return np.sqrt(np.einsum("ij,jk,ik->i", rows, P_post, rows))
    return np.sqrt(np.diagonal(P_post)[rows])


def linearise(
    model: DiscreteModel, x, u, dt: float, channels: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frozen linearisation of a :class:`DiscreteModel` at ``(x, u)``.

    Parameters
    ----------
    model : DiscreteModel
    x : ndarray, shape (nx,)
        Operating point (an equilibrium for a meaningful steady state).
    u : ndarray or None
        Input at the operating point.
    dt : float
        Interval.
    channels : sequence of str
        Measured channels.

    Returns
    -------
    A : ndarray, shape (nx, nx)
        ``d x_next / d x`` (the model's step Jacobian).
    H : ndarray, shape (m, nx)
        ``d y / d x`` (the model's measurement Jacobian).
    Q : ndarray, shape (nx, nx)
        The model's process noise at the point.
    """
    x = np.asarray(x, float)
    _, A, Q = model.predict(x, u, dt)
    _, H = model.measure(x, list(channels))
    return np.array(A, float), np.array(H, float), np.array(Q, float)

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

__all__ = ["bound_rms", "linearise", "periodic_posterior", "steady_state_covariance", "unobservable_states", "van_loan"]


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


def unobservable_states(A, H, names: Sequence[str], scale=None, tol: float = 1e-7,
                        rank_tol: float = 1e-11) -> list[str]:
    """States that no measurement reveals, with their dynamics not decaying (PBH detectability test).

    For every eigenvalue ``l`` of ``A`` with ``|l| >= 1 - tol`` (a mode that does not die out by itself) the
    pair is detectable iff ``rank [l I - A; H] = nx``; otherwise the null vector is a direction of the state that
    grows or persists without any channel seeing it, and no filter has a steady-state error there (the Riccati
    equation has no stabilising solution). Returns the names of the states that carry each such direction
    (components above 10 % of its largest), empty if the pair is detectable. The state is divided by ``scale``
    (e.g. the process noise's spread, so that rigid and elastic coordinates weigh alike) and each row of ``H``
    normalised; a singular value below ``rank_tol`` times the largest counts as zero (an unobserved direction
    gives exact zeros, 1e-18 relative on the six-bar with gauges only, against 3e-7 for its weakest observed
    direction with encoders and gauges at 500 Hz).
    """
    A = np.asarray(A, float)
    H = np.atleast_2d(np.asarray(H, float))
    nx = A.shape[0]
    if scale is not None:
        d = np.asarray(scale, float)
        A = A * d[None, :] / d[:, None]
        H = H * d[None, :]
    lam = np.linalg.eigvals(A)
    hn = np.linalg.norm(H, axis=1, keepdims=True)
    Hs = H / np.where(hn > 0, hn, 1.0)
    out: list[str] = []
    seen = set()
    for lv in lam:
        if abs(lv) < 1 - tol:
            continue
        key = (round(lv.real, 6), round(lv.imag, 6))
        if key in seen:
            continue
        seen.add(key)
        M = np.vstack([lv * np.eye(nx) - A, Hs.astype(complex)])
        _, s, Vh = np.linalg.svd(M)
        smax = s[0] if s[0] > 0 else 1.0
        for k in np.flatnonzero(s < rank_tol * smax):
            v = np.abs(Vh[k].conj())
            for i in np.flatnonzero(v > 0.1 * v.max()):
                if names[i] not in out:
                    out.append(names[i])
    return out


def periodic_posterior(A, Q, H, R, pattern, *, tol: float = 1e-9, max_periods: int = 20_000):
    """Mean steady-state posterior covariance of a Kalman filter whose channels are sampled periodically.

    Parameters
    ----------
    A, Q : ndarray, shape (nx, nx)
        Transition and process-noise covariance over one interval of the log.
    H : ndarray, shape (m, nx)
        Rows of every channel that is ever sampled.
    R : ndarray, shape (m,)
        Their noise variances.
    pattern : ndarray of bool, shape (N, m)
        Which channels are sampled at each of the N intervals of one period (a channel at a fifth of the log's
        rate: every fifth row true).

    Returns
    -------
    ndarray, shape (nx, nx)
        The posterior covariance averaged over the period once the periodic Riccati recursion has converged:
        its diagonal is the mean-square error of the best linear filter at the samples, the bound on the RMS
        error over a long log. With one interval and every channel (``N = 1``) this is the DARE's posterior.

    Notes
    -----
    The recursion (predict ``P = A P+ A' + Q``, update with the rows sampled at that interval, Joseph form) is
    started from ``Q`` and iterated period by period until the covariance at the period's start changes by less
    than ``tol`` relative to its diagonal. Detectability is the caller's check (:func:`unobservable_states`).
    """
    A, Q = np.asarray(A, float), np.asarray(Q, float)
    H, R = np.atleast_2d(np.asarray(H, float)), np.asarray(R, float)
    pattern = np.atleast_2d(np.asarray(pattern, bool))
    nx = A.shape[0]
    I = np.eye(nx)
    P = Q.copy()

    def update(P, sel):
        if not sel.any():
            return P
        Hs, Rs = H[sel], np.diag(R[sel])
        S = Hs @ P @ Hs.T + Rs
        K = np.linalg.solve(0.5 * (S + S.T), Hs @ P).T
        IKH = I - K @ Hs
        Pp = IKH @ P @ IKH.T + K @ Rs @ K.T  # Joseph form: stays symmetric positive definite
        return 0.5 * (Pp + Pp.T)

    for _ in range(max_periods):
        P_start = P
        acc = np.zeros_like(P)
        for sel in pattern:
            Pp = update(P, sel)
            acc += Pp
            P = A @ Pp @ A.T + Q
            P = 0.5 * (P + P.T)
        d = np.sqrt(np.abs(np.diag(P_start)))
        d = np.where(d > 0, d, 1.0)
        if np.max(np.abs(P - P_start) / np.outer(d, d)) < tol:
            break
    return acc / len(pattern)

"""The estimation bound: the Riccati recursion of the Kalman covariance, along a trajectory or at a frozen pose.

**The bound** (:func:`riccati_track`). For ``x_k = f(x_k-1, u_k-1) + w_k``, ``y_k = h(x_k) + v_k`` with additive
Gaussian ``w ~ N(0, Q_k)``, ``v ~ N(0, R)`` and a Gaussian prior ``N(x_0, P_0)``, the posterior Cramer-Rao
bound (Tichavsky, Muravchik and Nehorai 1998) of the model linearised at the true trajectory ``x_k`` is the
Kalman filter's own covariance recursion with the Jacobians taken there,

    P_k|k-1 = F_k P_k-1|k-1 F_k' + Q_k,        F_k = df/dx (x_k-1, u_k-1),
    P_k|k   = (I - K_k H_k) P_k|k-1 (I - K_k H_k)' + K_k R_k K_k',    H_k = dh/dx (x_k),
    K_k     = P_k|k-1 H_k' (H_k P_k|k-1 H_k' + R_k)^-1,

with ``H_k`` and ``R_k`` the rows of the channels sampled at sample ``k`` (none: no update; a multirate log
updates each channel at its own samples). ``sqrt(diag(P_k|k))`` bounds the RMS error at sample ``k`` of any
unbiased estimator of the linearised model; for a linear-Gaussian model it is exactly the Kalman filter's
covariance, which the filter reaches. For the nonlinear model it is an approximation (the model linearised at the
truth): an EKF's scatter about it reflects its linearisation at its estimates instead. An RMS error over a
record scatters about the bound's RMS (a short record's by about ``1/sqrt(2 N)`` for ``N`` correlation times), so
a consistent filter's ratio is below 1 about as often as above.

The smoothed bound (:func:`riccati_track` with ``smooth``) is the fixed-interval (Rauch-Tung-Striebel) smoother
on these covariances, in its modified Bryson-Frazier form (:func:`smoothed_covariances`): the bound for an
estimate that uses the whole record.

The recursion's steps are the filter's own kernels (:func:`exuflex.observer.kalman.predict_cov`, the Joseph-form
:func:`exuflex.observer.kalman.update`): :func:`riccati_predict`, :func:`riccati_update`.

**The frozen steady state** (:func:`steady_posterior`, :func:`periodic_posterior`): with ``F``, ``Q``, ``H`` held
at one pose the recursion converges to the stationary solution of the discrete algebraic Riccati equation

    P = A P A' - A P H' (H P H' + R)^-1 H P A' + Q,

(periodic where channels are sampled at different rates); at a pose the trajectory stays at, the time-varying
bound approaches it. It is a quick estimate of the bound (no trajectory needed), not the bound of a moving record.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import logging

import numpy as np
import scipy.linalg
from scipy.linalg import expm, solve_discrete_are

from ..manoeuvre import plan, start_configuration
from ..mechanism import Mechanism
from ..observer import kalman
from ..observer.base import DiscreteModel
from ..observer.expansion import held_interval
from ..observer.reduced import ReducedObserverModel
from ..observer.session import Observer, physical_names
from ..runs import LogColumns
from .physical import physical_covariance
from ..sensors import Signals

log = logging.getLogger(__name__)

__all__ = ["BoundTrack", "UnobservableError", "bound_rms", "bound_track", "check_observable", "estimation_bound", "linearise", "periodic_posterior", "riccati_predict", "riccati_track",
           "riccati_update", "smoothed_covariances", "steady_bound", "steady_posterior", "steady_state_covariance", "unobservable_states", "van_loan"]


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
    A, Q = np.ascontiguousarray(A, float), np.ascontiguousarray(Q, float)
    H, R = np.atleast_2d(np.asarray(H, float)), np.asarray(R, float)
    pattern = np.atleast_2d(np.asarray(pattern, bool))
    rows = [(np.ascontiguousarray(H[sel]), np.ascontiguousarray(R[sel])) if sel.any() else None for sel in pattern]
    P = Q.copy()
    for _ in range(max_periods):
        P_start = P
        acc = np.zeros_like(P)
        for hr in rows:
            Pp = P if hr is None else riccati_update(P, *hr)
            acc += Pp
            P = riccati_predict(A, Pp, Q)
        d = np.sqrt(np.abs(np.diag(P_start)))
        d = np.where(d > 0, d, 1.0)
        if np.max(np.abs(P - P_start) / np.outer(d, d)) < tol:
            break
    return acc / len(pattern)


def steady_posterior(A, Q, H, R, tol: float = 1e-10, max_periods: int = 200_000) -> np.ndarray:
    """Steady-state posterior covariance with every channel at every interval: the DARE on a scaled state, else
    the Riccati recursion iterated to convergence (:func:`periodic_posterior` with a period of one interval).

    The rigid coordinates and the elastic ones differ by orders of magnitude, which can make the DARE's Schur
    reordering fail; scaling the state by the process noise's spread, and iterating the recursion as a fallback,
    make the result robust. ``R``: the channels' variances (m,).
    """
    A, Q, H, R = (np.asarray(a, float) for a in (A, Q, H, R))
    d = np.sqrt(np.clip(np.diag(Q), 0, None))
    d = np.where(d > 0, d, d[d > 0].min() if np.any(d > 0) else 1.0)
    Di = 1.0 / d
    As, Qs, Hs = Di[:, None] * A * d[None, :], Di[:, None] * Q * Di[None, :], H * d[None, :]
    try:
        _, Ps = steady_state_covariance(As, Qs, Hs, R)
        if np.all(np.isfinite(Ps)):
            return d[:, None] * Ps * d[None, :]
    except (ValueError, np.linalg.LinAlgError) as exc:
        log.info("DARE failed (%s); iterating the Riccati recursion", exc)
    return periodic_posterior(A, Q, H, R, np.ones((1, H.shape[0]), bool), tol=tol, max_periods=max_periods)


# ------------------------------------------------------------------------------ the recursion along a trajectory
def riccati_predict(F, P, Q) -> np.ndarray:
    """``F P F' + Q``: the covariance prediction of the filter (:func:`exuflex.observer.kalman.predict_cov`), a new array."""
    out = np.empty_like(P)
    kalman.predict_cov(np.ascontiguousarray(F, float), np.ascontiguousarray(P, float),
                       np.ascontiguousarray(Q, float), out, np.empty_like(out))
    return out


def riccati_update(P, H, Rd, floor: np.ndarray | None = None) -> np.ndarray:
    """The Joseph-form posterior covariance of a measurement update with rows ``H`` (m, nx) and variances ``Rd``
    (m,): the filter's :func:`exuflex.observer.kalman.update` (a Cholesky solve of ``H P H' + R``) with its end-of-sample
    symmetrisation and variance floor (:func:`exuflex.observer.kalman.fix_cov`), a new array."""
    P = np.ascontiguousarray(P, float)
    H = np.ascontiguousarray(H, float)
    m, n = H.shape
    out = np.empty_like(P)
    z = np.zeros(n)
    zm = np.zeros(m)
    _, ok = kalman.update(z, P, zm, zm, H, np.ascontiguousarray(Rd, float), np.empty((m, n)), np.empty(m),
                          np.empty((m, m)), np.empty(n), out)
    if not ok:
        raise np.linalg.LinAlgError("the innovation covariance H P H' + R is not positive definite")
    kalman.fix_cov(out, np.zeros(n) if floor is None else floor)
    return out


def smoothed_covariances(P_prior, F, updates) -> np.ndarray:
    """The fixed-interval smoothed covariances ``P_k|n`` from each sample's prior ``P_k|k-1`` (n, nx, nx), step
    Jacobian ``F[k]`` (from sample ``k - 1`` to ``k``; row 0 unused) and update ``updates[k] = (H_k, R_k)`` (the rows
    and variances of the channels sampled at ``k``; None: no update).

    The modified Bryson-Frazier form of the Rauch-Tung-Striebel smoother (Bierman 1977), on the adjoint
    ``Lambda``, from ``Lambda_n = 0`` backwards::

        S_k = H_k P_k|k-1 H_k' + R_k,    K_k = P_k|k-1 H_k' S_k^-1
        L_k = H_k' S_k^-1 H_k + (I - K_k H_k)' Lambda_k (I - K_k H_k)      (L_k = Lambda_k without an update)
        P_k|n = P_k|k-1 - P_k|k-1 L_k P_k|k-1,     Lambda_k-1 = F_k' L_k F_k

    In exact arithmetic the RTS recursion's ``P_k|n`` (:func:`exuflex.observer.smoother.rts_backward`); but the RTS gain
    ``P_k|k F' P_k+1|k^-1`` is ``1/lambda`` in a direction that decays by ``lambda`` a sample without process
    noise (a damped mode the torques do not drive: an overdamped interior mode decays by orders of magnitude in
    one sample), and the RTS backward pass multiplies the rounding error of such a direction by ``1/lambda^2`` a
    sample (the slider-crank's smoothed bound overflowed). Here the adjoint runs backwards through ``F'``, which
    contracts those directions: no inverse of a prior, no growth.
    """
    n, nx = len(P_prior), P_prior.shape[1]
    Ps = np.empty_like(P_prior)
    lam = np.zeros((nx, nx))
    eye = np.eye(nx)
    for k in range(n - 1, -1, -1):
        Pp = P_prior[k]
        up = updates[k]
        if up is None:
            L = lam
        else:
            H, Rd = up
            S = H @ Pp @ H.T + np.diag(Rd)
            cho = scipy.linalg.cho_factor(0.5 * (S + S.T))
            SiH = scipy.linalg.cho_solve(cho, H)  # S^-1 H
            A = eye - Pp @ H.T @ SiH  # I - K H
            L = H.T @ SiH + A.T @ lam @ A
        Pk = Pp - Pp @ L @ Pp
        Ps[k] = 0.5 * (Pk + Pk.T)
        if k:
            lam = F[k].T @ L @ F[k]
            lam = 0.5 * (lam + lam.T)
    return Ps


@dataclass(frozen=True)
class BoundTrack:
    """The bound along a record (:func:`riccati_track`).

    Attributes
    ----------
    t : ndarray, shape (n,)
        The record's sample times.
    var : ndarray, shape (n, k)
        The bound's variance of each output quantity at each sample: the posterior ``P_k|k`` mapped to the
        outputs (filtered).
    var_smoothed : ndarray, shape (n, k), or None
        The same from the smoothed covariances ``P_k|n`` (with ``smooth``).
    wall_s : float
        Wall-clock time of the recursion (s), the backward pass included.
    """

    t: np.ndarray
    var: np.ndarray
    var_smoothed: np.ndarray | None
    wall_s: float

    def rms(self, sel=slice(None), smoothed: bool = False) -> np.ndarray:
        """The RMS over the samples ``sel`` of the bound's standard deviation of each quantity,
        ``sqrt(mean_k var_k)``: the figure an RMS error over those samples is compared with."""
        v = self.var_smoothed if smoothed else self.var
        if v is None:
            raise ValueError("the track was computed without smooth=True")
        return np.sqrt(np.mean(v[sel], axis=0))


def riccati_track(model: DiscreteModel, t, X, U, channels: Sequence[str], R, P0, sampled=None, *,
                  outputs: Callable | None = None, smooth: bool = False, floor: float = 0.0,
                  rows: int = 512, linearise: Callable | None = None) -> BoundTrack:
    """The bound along a record: the Kalman covariance recursion of ``model`` linearised along the states ``X``
    (module docstring), on the record's own sampling schedule.

    Parameters
    ----------
    model : DiscreteModel
        Its :meth:`~exuflex.observer.base.DiscreteModel.predict` at ``X[k-1]`` with the input ``U[k-1]`` held over ``t[k] -
        t[k-1]`` gives ``F_k`` and ``Q_k``; its :meth:`~exuflex.observer.base.DiscreteModel.measure` at ``X[k]`` gives ``H_k``.
    t : ndarray, shape (n,)
        Sample times.
    X : ndarray or row-sliceable, shape (n, nx)
        The states the model is linearised at (the true trajectory, or a planned one); ``X[a:b]`` must give the
        rows ``a`` to ``b`` as an array.
    U : ndarray or row-sliceable, shape (n, nu), or None
        The inputs, each held over the interval after its sample.
    channels : sequence of str
        The channels, in the order of ``R`` and of ``sampled``'s columns.
    R : ndarray, shape (m,)
        The channels' noise variances.
    P0 : ndarray, shape (nx, nx) or (nx,)
        The prior covariance at the first sample (before its update).
    sampled : ndarray or row-sliceable of bool, shape (n, m), optional
        Which channels are sampled at each sample (default: all, at every sample).
    outputs : callable, optional
        ``outputs(a, b, X_ab, P_ab)`` -> (b - a, k) variances of the quantities of interest from the states and
        covariances (b - a, nx, nx) of rows ``a:b``; default the states' own variances.
    smooth : bool
        Also the smoothed bound (:func:`smoothed_covariances`; keeps every prior and ``F``: 16 nx^2 bytes a
        sample).
    floor : float
        A floor on the variances after each sample (:func:`exuflex.observer.kalman.fix_cov`). None by default: a floor adds
        variance the recursion's ``Q`` does not hold, and the smoother's backward pass multiplies that
        inconsistency by ``1/lambda^2`` a sample in a direction that decays by ``lambda`` with no process noise
        (an undriven damped mode), so that the smoothed bound of such a model diverges backwards (the five-bar's did with the
        filter's floor of 1e-18).
    rows : int
        Samples per block of ``outputs`` (the memory beyond the result is a block's covariances).
    linearise : callable, optional
        ``linearise(x, u, dt) -> (F, Q)``: the model's step Jacobian and process noise without its step (what
        :meth:`~exuflex.observer.base.DiscreteModel.predict` returns with the state, which the recursion does not need); default
        through ``predict``.

    Returns
    -------
    BoundTrack
    """
    w0 = time.perf_counter()
    t = np.asarray(t, float).reshape(-1)
    n, nx = len(t), model.nx
    channels = tuple(channels)
    Rd = np.ascontiguousarray(np.asarray(R, float).reshape(-1))
    if len(Rd) != len(channels):
        raise ValueError(f"R has {len(Rd)} entries, expected one per channel ({len(channels)})")
    P = np.array(P0, float)
    if P.ndim == 1:
        P = np.diag(P)
    if P.shape != (nx, nx):
        raise ValueError(f"P0 has shape {P.shape}, expected ({nx}, {nx}) or ({nx},)")
    fl = np.full(nx, float(floor))
    outputs = outputs or (lambda a, b, Xb, Pb: np.diagonal(Pb, axis1=1, axis2=2).copy())
    step = linearise or (lambda x, u, dt: model.predict(x, u, dt)[1:])
    cur = [P]
    if hasattr(model, "watch_covariance"):  # the model's held-matrix control measured against this covariance
        model.watch_covariance(lambda: cur[0])
    if hasattr(model, "reset"):
        model.reset()
    keep = smooth
    if keep:  # what the backward pass needs: each sample's prior, step Jacobian and update
        Ppri = np.empty((n, nx, nx))
        Fall = np.empty((n, nx, nx))
        Hall: list = [None] * n
    blocks, rows = [], max(int(rows), 1)
    m = len(channels)
    subsets: dict = {}  # per set of sampled channels: its rows and the update's buffers
    work, P_pred, zero, x_out = np.empty((nx, nx)), np.empty((nx, nx)), np.zeros(nx), np.empty(nx)
    P = np.ascontiguousarray(P)
    x_prev = u_prev = None
    for a in range(0, n, rows):
        b = min(a + rows, n)
        Xb = np.asarray(X[a:b], float)
        Ub = None if U is None else np.asarray(U[a:b], float)
        Sb = np.ones((b - a, m), bool) if sampled is None else np.asarray(sampled[a:b], bool)
        Pb = np.empty((b - a, nx, nx))
        for i in range(b - a):
            k = a + i
            P_out = Pb[i]  # (a C-contiguous view: the kernels write the posterior in place)
            sel = Sb[i]
            if k > 0:
                F, Q = step(x_prev, u_prev, t[k] - t[k - 1])
                F, Q = np.ascontiguousarray(F, float), np.ascontiguousarray(Q, float)
                if keep:
                    Fall[k] = F
            if sel.any():
                key = sel.tobytes()
                sub = subsets.get(key)
                if sub is None:
                    idx = np.flatnonzero(sel)
                    k_ = len(idx)
                    sub = subsets[key] = (idx if k_ < m else None, np.ascontiguousarray(Rd[idx]), np.empty((k_, nx)),
                                          np.empty(k_), np.empty((k_, k_)), np.zeros(k_))
                idx, Rs, HP, r, S, y0 = sub
                H = np.asarray(model.measure(Xb[i], channels).H, float)
                H = np.ascontiguousarray(H if idx is None else H[idx])
                if k > 0:
                    _, ok, _ = kalman.predict_update(F, P, Q, zero, y0, y0, H, Rs, fl, (P_pred, work, HP),
                                                     (r, S, x_out, P_out))
                else:
                    _, ok = kalman.update(zero, P, y0, y0, H, Rs, HP, r, S, x_out, P_out)
                    kalman.fix_cov(P_out, fl)
                if not ok:
                    raise np.linalg.LinAlgError(f"the innovation covariance at t={t[k]:.6g} s is not positive "
                                                "definite")
                if keep:
                    Ppri[k] = P_pred if k > 0 else P
                    Hall[k] = (H, Rs)
            else:
                if k > 0:
                    kalman.predict_cov(F, P, Q, P_out, work)
                else:
                    P_out[:] = P
                kalman.fix_cov(P_out, fl)
                if keep:
                    Ppri[k] = P_out
            P = cur[0] = P_out
            x_prev = Xb[i]
            u_prev = None if Ub is None else Ub[i]
        blocks.append(outputs(a, b, Xb, Pb))
    var = np.concatenate(blocks) if blocks else np.empty((0, 0))
    var_s = None
    if keep and n:
        Ps = smoothed_covariances(Ppri, Fall, Hall)
        var_s = np.concatenate([outputs(a, min(a + rows, n), np.asarray(X[a : min(a + rows, n)], float),
                                        Ps[a : min(a + rows, n)]) for a in range(0, n, rows)])
    if hasattr(model, "watch_covariance"):
        model.watch_covariance(None)
    return BoundTrack(t, var, var_s, time.perf_counter() - w0)


# ------------------------------------------------------------------------------------------ an observer's bound
def estimation_bound(obs: Observer, run=None, *, span: tuple[float, float] | None = None, smooth: bool = False,
                     log_check=None) -> dict[str, float]:
    """The bound an RMS error is compared with: the RMS over ``span`` of the posterior Cramer-Rao bound's standard
    deviation of each physical quantity (:func:`bound_track`).

    ``run`` (:class:`exuflex.runs.Run`): along its truth if it has one, else along the plan, on its log's times,
    torques and sampled channels; without: along the plan at the observer's interval, every channel at every
    sample, the plan's computed torques. ``span = (t0, t1)`` in seconds from the first sample (default: from the
    observer's ``start_up`` to the end). ``smooth``: the smoothed bound. ``log_check`` (the log's
    :class:`exuflex.validate.LogCheck`) is only used for the observability test's channel set.

    Raises
    ------
    UnobservableError
        As :func:`steady_bound`: the channels leave states that neither decay nor are measured.
    """
    mech = obs.mech
    if run is None:
        d = mech.manoeuvre.duration if mech.manoeuvre is not None else 1.0
        t = np.arange(0.0, d + 0.5 * obs.ekf.dt, obs.ekf.dt)
        U, sampled, truth = None, None, None
    else:
        S = run.sensors
        t = np.asarray(S.t, float)
        U = LogColumns.of(S, run.motors or mech.motor_names, hold=True)
        sampled = _Sampled(S, obs.channels)
        truth = run.truth
    check_observable(obs, log_check)
    track, _ = bound_track(obs, t, U, sampled, truth=truth, smooth=smooth)
    t0, t1 = (obs.config.start_up, float(t[-1] - t[0])) if span is None else (float(span[0]), float(span[1]))
    sel = (t - t[0] >= t0 - 1e-9) & (t - t[0] <= t1 + 1e-9)
    if not sel.any():
        raise ValueError(f"span {span} holds no sample of the record ({t[0]:.6g} to {t[-1]:.6g} s)")
    return dict(zip(physical_names(mech), map(float, track.rms(sel, smoothed=smooth)), strict=True))


class _Sampled:
    """Which of ``channels`` are sampled (finite) in each row of a log's table, a block of rows at a time."""

    def __init__(self, signals: Signals, channels: Sequence[str]):
        self._cols = LogColumns.of(signals, channels)

    def __getitem__(self, rows: slice) -> np.ndarray:
        return np.isfinite(self._cols[rows])


class _Trajectory:
    """Reduced states along a trajectory of the rigid coordinates, a block of rows at a time: ``q`` and ``q'`` at
    the times ``t`` from a truth (linear interpolation of its samples) or from the plan (cubic Hermite from the
    plan's grid at the log's interval). The truth files hold the tip's elastic displacement, not the reduced model's
    coordinates: the elastic rates are taken at zero, and the elastic coordinates at zero without gravity and at
    their quasi-static value under it (:meth:`~exuflex.reduction.ReducedModel.quasi_static`, once :attr:`U` holds the
    torques): a mechanism in a
    vertical plane always carries its sag, and the step's Jacobian at the undeformed state differs from the one
    at the sagged state by more than its own size (the crane arm's ``dq2''/dq2``: -6 1/s^2 undeformed, +52 with the
    sag, docs/gravity.md), so a bound linearised at zero would be the bound of a mechanism that does not exist."""

    #: the torques at the times ``t`` (an array or a log's columns, indexed by row slices), for the quasi-static
    #: elastic coordinates under gravity (None: the elastic coordinates at zero)
    U = None

    def __init__(self, obs: Observer, t: np.ndarray, truth: Signals | None):
        self.obs, self.t = obs, np.asarray(t, float)
        mech = obs.mech
        qn = list(mech.coordinate_names)
        self.plan_torque = None
        if truth is not None:
            self._q = lambda ts: np.column_stack([np.interp(ts, truth.t, truth[n]) for n in qn])
            self._qd = lambda ts: np.column_stack([np.interp(ts, truth.t, truth["d" + n]) for n in qn])
            self.along = "truth"
            return
        t0 = float(self.t[0])
        span = float(self.t[-1] - t0) if len(self.t) > 1 else 0.0
        if mech.manoeuvre is None:
            q = np.asarray(mech.q_ref, float)
            self._q = lambda ts: np.tile(q, (len(ts), 1))
            self._qd = lambda ts: np.zeros((len(ts), len(q)))
            self.along = "q_ref"
            return
        step = float(np.median(np.diff(self.t))) if len(self.t) > 1 else obs.ekf.dt
        p = plan(mech, dt=step, t_end=span + step)
        from scipy.interpolate import CubicHermiteSpline  # (here: scipy.interpolate is a large import)

        sq = CubicHermiteSpline(p.t, p.q, p.qd, axis=0)
        sqd = CubicHermiteSpline(p.t, p.qd, p.qdd, axis=0)
        self._q = lambda ts: sq(ts - t0)
        self._qd = lambda ts: sqd(ts - t0)
        self._plan = p
        self.along = "plan"

    def torques(self) -> np.ndarray:
        """The plan's computed torques (:func:`exuflex.manoeuvre.computed_torque`) at the times ``t``; zeros
        without a plan."""
        from ..manoeuvre import computed_torque

        nu = len(self.obs.mech.motors)
        if self.along != "plan":
            return np.zeros((len(self.t), nu))
        p = self._plan
        tau = computed_torque(self.obs.mech, p)
        return np.column_stack([np.interp(self.t - self.t[0], p.t, tau[:, i]) for i in range(nu)])

    def __getitem__(self, rows: slice) -> np.ndarray:
        som = self.obs.model
        ts = self.t[rows]
        X = np.zeros((len(ts), som.nx))
        X[:, : som.nq] = self._q(ts)
        X[:, som.r : som.r + som.nq] = self._qd(ts)
        if self.U is not None and np.any(som.model.g_N):
            U = np.asarray(self.U[rows], float)
            for k in range(len(ts)):
                X[k, som.nq : som.r] = som.rm.quasi_static(X[k, : som.nq], X[k, som.r : som.r + som.nq], U[k])
        return X


def bound_track(obs: Observer, t, U=None, sampled=None, *, truth: Signals | None = None,
                smooth: bool = False) -> tuple[BoundTrack, str]:
    """The posterior Cramer-Rao bound of the observer's reduced model along a record (:func:`.bound.riccati_track`):
    the Kalman covariance recursion with the model's step and measurement Jacobians evaluated at the true states
    (``truth``: :class:`~exuflex.sensors.Signals` with the truth columns) or, without a truth, at the planned ones,
    mapped into the reduced coordinates (:class:`_Trajectory`: the rigid coordinates and their rates; the elastic
    ones at zero). The filter's noise model and prior: the motors' stated torque noise as process noise through
    the model's interval maps (not ``q_scale`` or ``q_extra``, the filter's tuning), the channels' stated noise, the
    filter's prior covariance ``P0`` at the first sample, and the model's own step (``method``, held matrices and
    step maps under the same error control as the filter's, measured against this recursion's covariance).

    ``t`` (n,): the sample times; ``U``: the torques (n, n_motors) held over each interval (None: the plan's
    computed torques); ``sampled``: which channels of ``obs.channels`` each sample holds ((n, m) bool, default
    all). ``smooth``: also the smoothed bound. Returns the track (variances of the :func:`exuflex.observer.session.physical_names`
    quantities, through the maps of :func:`exuflex.scoring.physical.physical_covariance`) and what it runs along (``"truth"``,
    ``"plan"``, or ``"q_ref"`` at rest without a manoeuvre).
    """
    t = np.asarray(t, float)
    traj = _Trajectory(obs, t, truth)
    if U is None:
        U = traj.torques()
    traj.U = U
    model = _bound_model(obs)
    P0 = obs.ekf.P0
    nx = model.nx
    P0 = np.diag(P0[:nx]) if P0.ndim == 1 else P0[:nx, :nx]
    R = np.asarray(obs.ekf.R_std, float) ** 2
    carry: dict = {}

    def outputs(a, b, Xb, Pb):
        if a == 0:  # a pass over the record starts (the smoothed one after the filtered one)
            carry.clear()
        return np.diagonal(physical_covariance(obs, Xb, Pb, refresh_rad=BOUND_TIP_RADIUS, carry=carry),
                           axis1=1, axis2=2)

    track = riccati_track(model, t, traj, U, obs.channels, R, P0, sampled, outputs=outputs, smooth=smooth,
                          linearise=_step_linearisation(model))
    return track, traj.along


#: the radius (rad) within which the bound's tip rows follow q to first order (:func:`exuflex.scoring.physical.physical_covariance`):
#: their error, about half its square relative, stays below 5e-4 of the tip's standard deviations
BOUND_TIP_RADIUS = 3e-2


def _step_linearisation(model: ReducedObserverModel):
    """``(x, u, dt) -> (F, Q)``: the cached step's Jacobian and process noise at ``x`` (the held configuration and
    step map as :meth:`exuflex.observer.reduced.ReducedObserverModel.predict` renews them, and the interval kernel
    :func:`exuflex.observer.expansion.held_interval` it calls with them: the Jacobian takes the interval's mean
    motion, :func:`~exuflex.observer.expansion.position_forces` and the held matrices' change with the elastic
    coordinates); None for the reference step (``rk4``: through ``predict``). ``tests/test_bound.py`` checks that
    it returns ``predict``'s ``F`` and ``Q``."""
    if model.method != "cached":
        return None

    def linearise(x, u, dt):
        u = model.torques(u)
        _, dl, s, n, sm = model.prepare(x, u, dt)
        return held_interval(x, u, np.empty(0), dl, s, dt / n, n, *sm.tail)[1], sm.Q

    return linearise


def _bound_model(obs: Observer) -> ReducedObserverModel:
    """The observer's reduced model (its step ``method`` and sub-step ``h``) with the stated torque noise: a model of
    its own, so that the filter's caches are left alone."""
    var = getattr(obs.model, "torque_var_nominal", obs.model.torque_var)
    return ReducedObserverModel(obs.model.rm, h=obs.model.h, method=obs.model.method, torque_std=np.sqrt(var))


def check_observable(obs: Observer, log_check=None) -> None:
    """Raise :class:`UnobservableError` if the channels (those the log samples, with ``log_check``) leave states
    that neither decay nor are measured at the start of the manoeuvre (PBH test, :func:`.bound.unobservable_states`)."""
    _linearised(obs, start_configuration(obs.mech), None, log_check)


def steady_bound(obs: Observer, q=None, qd=None, points: int = 9, *, log_check=None,
                 span: tuple[float, float] | None = None) -> dict[str, float]:
    """A quick estimate of the bound: the steady-state Kalman covariance of the reduced model linearised and frozen
    at a configuration, the stated torque noise as process noise (no trajectory is followed: at a pose the
    trajectory stays at, :func:`estimation_bound` approaches it).

    The covariance depends on the configuration (a tip's global x and y swap roles as its link turns; the
    sensitivities of the encoders and gauges change with the pose), so by default it is evaluated at ``points``
    configurations of the manoeuvre (its plan, positions and rates, evenly spread over 5-95 % of its duration)
    and the per-quantity standard deviations are combined as an RMS. ``span = (t0, t1)`` (s from the manoeuvre's
    start): the configurations at the midpoints of ``points`` equal parts of that interval instead (past the
    manoeuvre's end: its final pose at rest). With ``q`` (and ``qd``) given, or without a manoeuvre (``q_ref``,
    at rest): that one configuration.

    ``log_check`` (:class:`exuflex.validate.LogCheck` of the log at hand) makes it the estimate for that log: the
    interval is the log's, channels never sampled are left out, and channels sampled every k-th row update
    every k-th interval (:func:`.bound.periodic_posterior`, averaged over the period). Without it: every channel
    of the observer at every interval of the model's rate.

    Raises
    ------
    UnobservableError
        The channels leave states that neither decay nor are measured (e.g. gauges only: the rigid motion); the
        message names them.
    """
    mech = obs.mech
    if q is not None or mech.manoeuvre is None or points < 1:
        return _bound_at(obs, _mid_q(mech) if q is None else q, qd, log_check)
    d = mech.manoeuvre.duration
    t_end = d if span is None else max(float(span[1]), float(span[0]))
    try:
        p = plan(mech, dt=t_end / 400 if t_end > 0 else d / 200, t_end=t_end if t_end > 0 else d)
    except Exception as exc:  # noqa: BLE001 - the bound at q_ref instead, with a note
        log.warning("could not plan the manoeuvre for the bound (%s); using the bound at q_ref", exc)
        return _bound_at(obs, np.asarray(mech.q_ref, float), None, log_check)
    if span is None:
        idx = np.unique(np.round(np.linspace(0.05, 0.95, points) * (len(p.t) - 1)).astype(int))
    else:
        t0, t1 = float(span[0]), t_end
        ts = t0 + (np.arange(points) + 0.5) * (t1 - t0) / points
        idx = np.unique(np.clip(np.searchsorted(p.t, ts), 0, len(p.t) - 1))
    per = [_bound_at(obs, p.q[k], p.qd[k], log_check) for k in idx]
    return {name: float(np.sqrt(np.mean([b[name] ** 2 for b in per]))) for name in per[0]}


def _linearised(obs: Observer, q, qd=None, log_check=None) -> tuple:
    """The reduced model frozen at ``q`` with rates ``qd`` (None: at rest) over the log's interval: ``(som, z, A, Q,
    H, R, channels, every)`` with the channels the log samples and their spacing in intervals; the PBH test of
    their observability first (:class:`UnobservableError`)."""
    mech = obs.mech
    som = ReducedObserverModel(obs.model.rm, h=obs.model.h, method="rk4")
    q = np.asarray(q, float)
    z = som.initial_state(q, qd)
    u = np.zeros(len(mech.motors))
    channels = list(obs.channels)
    R_all = {c: s**2 for c, s in zip(obs.channels, obs.ekf.R_std, strict=True)}
    dt = obs.ekf.dt
    every = {c: 1 for c in channels}
    if log_check is not None:
        dt = log_check.interval_s or dt
        mult = max(1, round(dt / obs.ekf.dt))
        channels = [c for c in channels if log_check.channel_rate_hz.get(c, 1.0) > 0]
        every = {c: max(1, round(log_check.channel_every.get(c, mult) / mult)) for c in channels}
    if not channels:
        raise UnobservableError(f"{mech.source or mech.name}: no channel of {list(obs.channels)} is sampled in the "
                                "log: nothing to estimate with")
    pred, _, maps = som.frozen_interval(z, u, dt)
    A = pred.F
    # the bound is a property of the sensors and the *stated* noise, not of the filter's tuning
    var = getattr(obs.model, "torque_var_nominal", som.torque_var)
    Q = (maps.L * var) @ maps.L.T
    _, H = som.measure(z, channels)
    R = np.array([R_all[c] for c in channels])
    nq, r = som.nq, som.r
    state_names = (list(mech.coordinate_names) + [f"p{i + 1}" for i in range(r - nq)]
                   + [f"d{c}" for c in mech.coordinate_names] + [f"dp{i + 1}" for i in range(r - nq)])
    d = np.sqrt(np.clip(np.diag(Q), 0, None))
    d = np.where(d > 0, d, d[d > 0].min() if np.any(d > 0) else 1.0)
    bad = unobservable_states(A, H, state_names, scale=d)
    if bad:
        rigid = [b for b in bad if not b.lstrip("d").startswith("p")]
        raise UnobservableError(
            f"the channels {channels} cannot observe {', '.join(bad)}"
            + (" (the rigid motion: add an encoder)" if rigid else " (add a strain gauge or a tip sensor)")
            + "; no filter has a bounded error there")
    return som, z, A, Q, H, R, channels, every


def _bound_at(obs: Observer, q, qd=None, log_check=None) -> dict[str, float]:
    """:func:`steady_bound` at one configuration ``q`` with rates ``qd`` (None: at rest)."""
    mech = obs.mech
    som, z, A, Q, H, R, channels, every = _linearised(obs, q, qd, log_check)
    period = int(np.lcm.reduce([every[c] for c in channels]))
    if period == 1:
        P = steady_posterior(A, Q, H, R)
    else:
        if period > 1000:
            raise UnobservableError(f"channel spacings {every} give a period of {period} intervals; resample the log")
        pattern = np.array([[k % every[c] == 0 for c in channels] for k in range(period)])
        P = periodic_posterior(A, Q, H, R, pattern)
    nq, r = som.nq, som.r
    q = np.asarray(q, float)
    names = physical_names(mech)
    out = {}
    value, _ = obs.row_columns()
    if not len(value):
        sd = np.sqrt(np.diag(P))
        for i in range(nq):
            out[names[i]] = float(sd[i])
            out[names[nq + i]] = float(sd[r + i])
        return out
    # the maps of Observer.physical linearised at z: the rows' values A(q) p + w and rates A(q) p' +
    # sum_i (dA/dq_i p) q'_i + w' (w = C (Gr p)^2 the tip's second order: at rest its Jacobian in p,
    # 2 C diag(Gr p) Gr, joins A), added to q and dq (the coordinates' readings) or to nothing (the tip's)
    A, dA, _, (Cw, _, Gw, _) = obs.physical_rows_and_rates(q)
    A = A + 2.0 * (Cw * (Gw @ z[:r])) @ Gw
    dAp = np.einsum("iaj,j->ai", dA, z[:r])
    base = np.zeros((len(names), som.nx))
    base[np.arange(nq), np.arange(nq)] = 1.0
    base[nq + np.arange(nq), r + np.arange(nq)] = 1.0
    for k, (iv, ir) in enumerate(zip(*obs.row_columns(), strict=True)):
        base[iv, :r] += A[k]
        base[iv, :nq] += dAp[k]
        base[ir, r:] += A[k]
        base[ir, :r] += np.tensordot(z[r : r + nq], dA, axes=1)[k]
        base[ir, r : r + nq] += dAp[k]
    for i, name in enumerate(names):
        out[name] = float(np.sqrt(base[i] @ P @ base[i]))
    return out


class UnobservableError(ValueError):
    """A channel set that leaves states unobservable (the bound does not exist); the message names them."""


def _mid_q(mech: Mechanism) -> np.ndarray:
    if mech.manoeuvre is not None:
        try:
            d = mech.manoeuvre.duration
            p = plan(mech, dt=d / 2, t_end=d)
            return np.asarray(p.q[len(p.q) // 2], float)
        except Exception as exc:  # noqa: BLE001
            log.warning("could not plan the manoeuvre's middle (%s); using q_ref", exc)
    return np.asarray(mech.q_ref, float)

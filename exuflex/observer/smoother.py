"""Rauch-Tung-Striebel smoother for logged runs, on :class:`~exuflex.observer.ekf.MultirateEKF`'s forward pass.

A logged run can use every sample, later ones included, for the state at each time. The forward pass is the
filter itself (:meth:`MultirateEKF.run` with ``predictions=True``, its compiled loop where the model has one: each
sample's predicted mean ``x_k|k-1``, step Jacobian ``F_k`` and process noise ``Q_k`` recorded); the backward pass
is the RTS recursion on the filter's linearisation (extended RTS)::

    P_k+1|k = F_k+1 P_k|k F_k+1' + Q_k+1
    C_k     = P_k|k F_k+1' P_k+1|k^-1
    x_k|n   = x_k|k + C_k (x_k+1|n - x_k+1|k)
    P_k|n   = P_k|k + C_k (P_k+1|n - P_k+1|k) C_k'

from ``x_n|n``, ``P_n|n`` at the last sample. ``C_k`` comes from a Cholesky solve of the symmetric
``P_k+1|k`` (no inverse). On a linear model this is the fixed-interval smoother of Rauch, Tung and Striebel
(1965); the tests compare it with filterpy's ``KalmanFilter.rts_smoother``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from .ekf import MultirateEKF

__all__ = ["SmoothedResult", "rts_backward", "rts_smooth"]


@dataclass
class SmoothedResult:
    """The smoothed estimates of a record and the filter's forward pass.

    Attributes
    ----------
    t : ndarray, shape (n,)
    x_hat : ndarray, shape (n, nx)
        Smoothed means ``x_k|n``.
    P : ndarray, shape (n, nx, nx)
        Smoothed covariances ``P_k|n``.
    x_filt, P_filt, nis : ndarray
        The forward pass: the filter's estimates ``x_k|k``, ``P_k|k`` and NIS (NaN without an update).
    wall_s : float
        Wall-clock time of both passes (s).
    backward_s : float
        Wall-clock time of the backward pass alone (s).
    nominal_p : ndarray, shape (n,), or None
        Set where ``x_hat`` and ``P`` are the payload estimator's report (:func:`.session.reported`): the nominal
        payload's posterior probability at each sample.
    mode_p : ndarray, shape (n, modes), or None
        The IMM's smoothed mode probabilities (:meth:`.imm.IMMFilter.smooth`).
    """

    t: np.ndarray
    x_hat: np.ndarray
    P: np.ndarray
    x_filt: np.ndarray
    P_filt: np.ndarray
    nis: np.ndarray
    wall_s: float
    backward_s: float
    nominal_p: np.ndarray | None = None
    mode_p: np.ndarray | None = None

    @property
    def P_diag(self) -> np.ndarray:
        return np.diagonal(self.P, axis1=1, axis2=2)


def rts_smooth(ekf: MultirateEKF, t, U, Y, *, x0=None, P0=None) -> SmoothedResult:
    """Filter a record with ``ekf`` (from its prior, or ``x0``/``P0``) and smooth it backwards (module docstring):
    the forward pass is :meth:`~.ekf.BeliefFilter.forward_pass` (the full covariance and each sample's prediction
    recorded; the compiled loop where the model has one), the backward pass :func:`rts_backward` on that record.

    Parameters
    ----------
    ekf : MultirateEKF
        Runs over the record from a reset (the filter's state is that of the last sample after).
    t, U, Y : as :meth:`MultirateEKF.run`.
    x0, P0 : array_like, optional
        A prior for this record.

    Returns
    -------
    SmoothedResult

    Raises
    ------
    FilterDivergedError
        The forward pass went non-finite (a smoother cannot run back through it).
    """
    if not isinstance(ekf, MultirateEKF):
        raise TypeError(f"the RTS smoother runs on the EKF's linearisation (MultirateEKF), not on a "
                        f"{type(ekf).__name__}")
    w0 = time.perf_counter()
    res = ekf.forward_pass(t, U, Y, x0=x0, P0=P0)
    w1 = time.perf_counter()
    xs, Ps = rts_backward(res.P, res.F, res.Q, res.x_hat, res.x_pred)
    w2 = time.perf_counter()
    return SmoothedResult(res.t, xs, Ps, res.x_hat, res.P, res.nis, w2 - w0, w2 - w1)


def rts_backward(P, F, Q, X=None, Xp=None) -> tuple[np.ndarray | None, np.ndarray]:
    """The RTS backward pass (module docstring) over filtered covariances ``P`` (n, nx, nx), with ``F[k]``,
    ``Q[k]`` the step from sample ``k - 1`` to ``k`` (row 0 unused).

    With ``X`` (filtered means, (n, nx)) and ``Xp`` (predicted means ``x_k|k-1``, row 0 unused) the means too;
    without, the covariances alone. Returns ``(x_k|n or None, P_k|n)``. (The bound's smoothed covariances use the
    modified Bryson-Frazier form instead, :func:`.bound.smoothed_covariances`, which does not amplify rounding in
    undriven damped directions.)
    """
    n = len(P)
    Ps = np.empty_like(P)
    Ps[-1] = P[-1]
    xs = None
    if X is not None:
        xs = np.empty_like(X)
        xs[-1] = X[-1]
    for k in range(n - 2, -1, -1):
        Fk = F[k + 1]
        PFt = P[k] @ Fk.T
        Pp = Fk @ PFt + Q[k + 1]
        Pp = 0.5 * (Pp + Pp.T)
        try:
            C = scipy.linalg.cho_solve(scipy.linalg.cho_factor(Pp), PFt.T).T  # P F' Pp^-1 (Pp symmetric)
        except np.linalg.LinAlgError:
            C = np.linalg.lstsq(Pp, PFt.T, rcond=None)[0].T
        if xs is not None:
            xs[k] = X[k] + C @ (xs[k + 1] - Xp[k + 1])
        Pk = P[k] + C @ (Ps[k + 1] - Pp) @ C.T
        Ps[k] = 0.5 * (Pk + Pk.T)
    return xs, Ps

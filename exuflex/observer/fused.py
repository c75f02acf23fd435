"""One whole filter sample of the cached reduced observer in a single compiled call.

:class:`~exuflex.observer.ekf.MultirateEKF` over :class:`~exuflex.observer.reduced.ReducedObserverModel`
(``method="cached"``) does per sample: the held model's step (:mod:`.held`), a step-map rebuild when q has
moved by ``remap_rad``, the Jacobian ``F = Pn + SQM dF/dz``, ``P = F P F' + Q``, the measurement rows along
the secant, the Joseph update and the end-of-sample symmetrisation. Each part is compiled, but called one
by one from Python it costs about as much in Python glue as in arithmetic (some 130 us per sample, against
the 100 us that 20x real time allows at 500 Hz). :func:`cached_sample` runs them all in one call, with the
same compiled functions in the same order, so the results equal the step-by-step path's (bit for bit on the
six-bar's 3 s log, ``tests/test_fused.py``). Measured on the six-bar: 44 us per call (the held RK4 steps 22 us,
Jacobian, covariance prediction and update 15 us, argument passing 4 us), 38 us more when the step map is
rebuilt.

Python keeps what happens a few dozen times per run: the configuration evaluations, the measurement rows
per held configuration, and every case the kernel declines (it then returns a nonzero status before it has
changed the filter's state, and the filter takes its step-by-step path for that sample):

- ``RESCUE``: the held model broke down (NaN step; the step-by-step path evaluates the configuration);
- ``FAR``: the predicted q left the held configuration's measurement radius;
- ``INDEFINITE``: the innovation covariance is not positive definite (the step-by-step path's LU solve);
- ``REFRESH``: q left the held configuration's radius; the caller evaluates the configuration and calls
  again.
"""

from __future__ import annotations

import math

import numpy as np

from ._compiled import predict_cov, settle, update
from .held import HAVE_NUMBA, _jit, held_step_loops, step_jacobian_loops, step_maps_held

__all__ = ["DONE", "FAR", "INDEFINITE", "REFRESH", "RESCUE", "cached_sample", "warm_up"]

DONE, RESCUE, FAR, INDEFINITE, REFRESH = 0, 1, 2, 3, 4


def _secant_factor(dl, d, dd, has_old):  # pragma: no cover - compiled; twin of reduced._secant_factor
    if not has_old:
        return 0.0
    a = 0.0
    n2 = 0.0
    for i in range(dl.shape[0]):
        a += dl[i] * d[i]
        n2 += dl[i] * dl[i]
    if a * a < 0.49 * n2 * dd:
        return 0.0
    return a / dd


def _cached_sample(z, P, u, y, Rd, floor, x_out, r, S, P_out, P_pred, work, HP, q0, rad, meas_rad, d, dd, held,
                   remap_rad, torque_var, q_extra, q_map, Pn, SQM, L, Q, Ts, Vs, C3, c0, Hm, dH):  # pragma: no cover
    """Predict over one interval and update with all channels of ``y``.

    Parameters
    ----------
    z, P : prior state and covariance at the previous sample (not written).
    u : input held over the interval; y, Rd : measurement and its variances (all channels finite).
    floor : diagonal floor of the posterior covariance.
    x_out, r, S, P_out : out: posterior mean, innovation and its covariance, posterior covariance (``P_out``
        symmetrised and floored); P_pred, work, HP : scratch.
    q0, rad, meas_rad, d, dd : held configuration, its refresh radius (``REFRESH`` beyond it) and
        measurement radius, secant direction and ``d . d``.
    held : the arguments of :func:`.held.held_step_loops` after ``(z, u, dl, s)`` (``held[0]``: has a secant
        partner; ``held[1]``: nq).
    remap_rad, torque_var, q_extra : step-map rebuild distance, torque variances, extra diagonal of ``Q``
        (length 0 for none).
    q_map, Pn, SQM, L, Q : configuration of the current step map and the map (rebuilt in place when q moved
        by ``remap_rad``; a NaN ``q_map`` forces the rebuild).
    Ts, Vs, C3 : the held forces' Jacobian tensors.
    c0, Hm, dH : ``y = c0 + (Hm + s dH) x`` (``dH`` with 0 rows: no secant).

    Returns
    -------
    status : int
        ``DONE`` or the reason the sample was declined (nothing but the map buffers written).
    nis : float
    remapped : bool
    finite : bool
        The posterior state and covariance are finite.
    """
    nq = held[1]
    dl = z[:nq] - q0
    for i in range(nq):
        if abs(dl[i]) > rad:
            return REFRESH, math.nan, False, False
    s = _secant_factor(dl, d, dd, held[0])
    z_next, Mr, Kr, Cr, Gr = held_step_loops(z, u, dl, s, *held)
    if not math.isfinite(z_next[0]) and (s != 0.0 or np.any(dl != 0.0)):
        return RESCUE, math.nan, False, False
    remapped = False
    for i in range(nq):
        if not abs(z[i] - q_map[i]) <= remap_rad:
            remapped = True
    if remapped:
        Pn_new, SQM_new, L_new, Q_new = step_maps_held(Mr, Kr, Cr, Gr, held[3], held[4], torque_var)
        Pn[:] = Pn_new
        SQM[:] = SQM_new
        L[:] = L_new
        Q[:] = Q_new
        for i in range(q_extra.shape[0]):
            Q[i, i] += q_extra[i]
        q_map[:] = z[:nq]
    F = step_jacobian_loops(z, Ts, Vs, C3, Pn, SQM)
    dlp = z_next[:nq] - q0
    for i in range(nq):
        if abs(dlp[i]) > meas_rad:
            return FAR, math.nan, remapped, False
    predict_cov(F, P, Q, P_pred, work)
    H = Hm
    if dH.shape[0]:
        sm = _secant_factor(dlp, d, dd, held[0]) * dd
        if sm != 0.0:
            H = Hm + sm * dH
    y_pred = c0 + H @ z_next
    nis, ok = update(z_next, P_pred, y, y_pred, H, Rd, HP, r, S, x_out, P_out)
    if not ok:
        return INDEFINITE, math.nan, remapped, False
    return DONE, nis, remapped, settle(x_out, P_out, floor)


_secant_factor = _jit(_secant_factor)
cached_sample = _jit(_cached_sample) if HAVE_NUMBA else None


def warm_up() -> None:
    """Compile (or load from numba's cache) :func:`cached_sample` for the argument types the filter passes."""
    if not HAVE_NUMBA:
        return
    r, nq, m = 2, 1, 1
    nx = 2 * r
    z, u, dl = np.zeros(nx), np.zeros(nq), np.zeros(nq)
    M, g2, f = np.eye(r), np.zeros((nq, r * r)), np.zeros(r)
    T2, V2, C2 = np.zeros((r, r * r)), np.zeros((nq * r, r)), np.zeros((r * nq, r))
    G = np.zeros((r, nq))
    held = (False, nq, 0.0, 1e-4, 1, M, M, M, G, g2, g2, f, T2, V2, C2, g2, g2, M, G, f, T2, V2, C2)
    P = np.eye(nx)
    sq = np.empty((nx, nx))
    cached_sample(z, P, u, np.zeros(m), np.ones(m), np.zeros(nx), np.empty(nx), np.empty(m), np.empty((m, m)), sq,
                  sq.copy(), sq.copy(), np.empty((m, nx)), dl, 1.0, 1.0, dl, 1.0, held, 1e-3, np.ones(nq), np.zeros(0),
                  np.full(nq, np.nan), sq.copy(), np.empty((nx, r)), np.empty((nx, nq)), sq.copy(),
                  np.zeros((r, r, r)), np.zeros((nq, r, r)), np.zeros((r, nq, r)), np.zeros(m), np.zeros((m, nx)),
                  np.zeros((0, nx)))

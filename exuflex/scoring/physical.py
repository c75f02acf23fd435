"""The covariance of the observer's physical estimates (q, dq/dt, tip elastic displacement and rate): the filter's
covariance of the reduced state through the maps :meth:`exuflex.observer.session.Observer.physical` takes the
estimates through, linearised at each state. What a NEES against a truth of the physical quantities, the bound's
tip quantities and the estimates' standard deviations need."""

from __future__ import annotations

import numpy as np

from ..observer.session import Observer, apply_rows, rows_along, second_order_along
from ..sensors import tip_point

__all__ = ["physical_covariance"]


def physical_covariance(obs: Observer, Z: np.ndarray, P: np.ndarray, refresh_rad: float = 1e-3, *,
                        carry: dict | None = None) -> np.ndarray:
    """Covariance (n, k, k) of the :meth:`.Observer.physical` quantities (q, dq/dt, tip elastic displacement and rate)
    from reduced states (n, nx) and the filter's full covariances (n, nx, nx; ``store_P="full"``), through
    their maps linearised at each state (the filter's extra states, if any, are left out; the rate's turning
    term is linearised in p and q', not in q). For NEES against a truth of the physical quantities. The rows
    are evaluated as in :meth:`.Observer.physical` (its own warm start; ``carry`` as there)."""
    carry = {} if carry is None else carry
    with obs.own_warm_start(carry):
        return _physical_covariance(obs, Z, P, refresh_rad, carry)


def _physical_covariance(obs: Observer, Z: np.ndarray, P: np.ndarray, refresh_rad: float, carry: dict) -> np.ndarray:
    som = obs.model
    nq, r, nx = som.nq, som.r, som.nx
    tp = tip_point(obs.mech)
    k = 2 * nq + (4 if tp is not None else 0)
    C = np.zeros((k, nx))
    C[:nq, :nq] = np.eye(nq)
    C[nq : 2 * nq, r : r + nq] = np.eye(nq)
    value, rate = obs.row_columns()
    if not len(value):
        return C @ P[:, :nx, :nx] @ C.T
    out = np.full((len(Z), k, k), np.nan)  # (rows in no run of the rows: no value)
    for a, b, (A0, dA, q0, second) in obs.row_segments(Z[:, :nx], refresh_rad, carry):
        z = Z[a:b, :nx]
        Cb = np.zeros((b - a, k, nx))
        Cb[:] = C
        _rows_jacobian(Cb, A0, dA, q0, z, value, rate, nq, r)
        _second_order_jacobian(Cb, second, z, q0, nq, r, value, rate)
        out[a:b] = Cb @ P[a:b, :nx, :nx] @ Cb.transpose(0, 2, 1)
    return out


def _rows_jacobian(Cb: np.ndarray, A0: np.ndarray, dA: np.ndarray, q0: np.ndarray, z: np.ndarray, value: np.ndarray,
                   rate: np.ndarray, nq: int, r: int) -> None:
    """Add to ``Cb`` (m, k, nx) the Jacobian of the rows' values ``A(q) p`` and rates ``A p' + sum_i (dA/dq_i p)
    q'_i`` (:meth:`.Observer.physical`) in the ``value`` and ``rate`` rows of ``Cb``, at the states ``z`` (m, nx)."""
    A = rows_along(A0, dA, z[:, :nq] - q0)  # (m, k, r)
    dAp = np.einsum("iaj,kj->kai", dA, z[:, :r])  # d(A p)/dq (m, k, nq)
    Cb[:, value, :r] += A
    Cb[:, value, :nq] += dAp
    Cb[:, rate, r:] += A
    Cb[:, rate, :r] += rows_along(0.0, dA, z[:, r : r + nq])
    Cb[:, rate, r : r + nq] += dAp
    # d(A p')/dq; the rate's turning term q' dA/dq p also varies with q (second derivatives of A),
    # left out: of the order of q' times the deflection per radian, times q's small uncertainty
    Cb[:, rate, :nq] += np.einsum("iaj,kj->kai", dA, z[:, r:])


def _second_order_jacobian(Cb: np.ndarray, second: tuple, z: np.ndarray, q0: np.ndarray, nq: int, r: int,
                           e: np.ndarray, ed: np.ndarray) -> None:
    """Add to ``Cb`` (m, k, nx) the Jacobian of the tip's second order ``w = C (Gr p)^2`` and of its rate ``w' =
    C' g^2 + 2 C (g (Gr p' + Gr' p))`` (``g = Gr p``, ``'`` the change along q') at the states ``z`` (m, nx): in
    ``p``, ``p'``, ``q'`` and ``q`` (the rate's in q: of ``2 C (g (Gr p'))``; that of its turning terms along q',
    second derivatives of the maps, is left out as it is for the linear rows)."""
    p, v, qd = z[:, :r], z[:, r : 2 * r], z[:, r : r + nq]
    Cw, Gw, Cwd, Gwd = second_order_along(second, z[:, :nq] - q0, qd)
    _, dC, _, dG = second
    g = apply_rows(Gw, p)  # (m, n_g)
    gd = apply_rows(Gw, v) + apply_rows(Gwd, p)
    two_Cg = 2.0 * Cw * g[:, None, :]  # (m, 2, n_g): dw/dg
    Cb[:, e, :r] += two_Cg @ Gw
    # dw/dq_i = dC_i g^2 + 2 C (g dGr_i p), also the rate's derivative in q'_i (its turning terms)
    dwdq = (np.einsum("iaj,kj->kai", dC, g * g)
            + np.einsum("kaj,kij->kai", two_Cg, np.einsum("ijl,kl->kij", dG, p)))
    Cb[:, e, :nq] += dwdq
    Cb[:, ed, r : r + nq] += dwdq
    Cb[:, ed, r:] += two_Cg @ Gw
    Cb[:, ed, :r] += 2.0 * (Cwd * g[:, None, :]) @ Gw + 2.0 * (Cw * gd[:, None, :]) @ Gw + two_Cg @ Gwd
    # d/dq_i of 2 C (g (Gr p')): 2 dC_i (g gv) + 2 C ((dGr_i p) gv + g (dGr_i p')), gv = Gr p'
    gv = apply_rows(Gw, v)
    dGp, dGv = np.einsum("ijl,kl->kij", dG, p), np.einsum("ijl,kl->kij", dG, v)  # (m, nq, n_g)
    Cb[:, ed, :nq] += 2.0 * (np.einsum("iaj,kj->kai", dC, g * gv)
                             + np.einsum("kaj,kij->kai", Cw, dGp * gv[:, None, :] + g[:, None, :] * dGv))

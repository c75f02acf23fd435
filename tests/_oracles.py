"""Independent NumPy implementations of what exuflex computes in compiled code: oracles for the tests only.

- :func:`numpy_filter`: the multirate EKF (predict, Joseph-form update with the finite channels) in plain NumPy;
- :func:`held_matrices`, :func:`quadratic_forces`, :func:`rk4_linear`, :func:`held_step`, :func:`prediction_error`,
  :func:`step_maps_noise`: the cached observer step's algebra (:mod:`exuflex.observer.expansion`).
"""

from __future__ import annotations

import numpy as np

from exuflex.observer.expansion import HeldSystem, step_maps


def numpy_filter(model, channels, R_std, x0, P0, t, U, Y, p_floor=1e-18):
    """The EKF of :class:`exuflex.observer.ekf.MultirateEKF` written with NumPy expressions: ``(x_hat, P, nis)``."""
    nx = model.nx
    x = np.array(x0, float)
    P = np.diag(P0) if np.ndim(P0) == 1 else np.array(P0, float)
    r2 = np.array([R_std[c] for c in channels]) ** 2
    X, Ps, N = np.empty((len(t), nx)), np.empty((len(t), nx, nx)), np.full(len(t), np.nan)
    if hasattr(model, "reset"):
        model.reset()
    watched = getattr(model, "state_cov", None)
    cov = [P]
    if hasattr(model, "watch_covariance"):  # the model measures its approximations against this filter's P
        model.watch_covariance(lambda: cov[0])
    for k in range(len(t)):
        if k:
            x, F, Q = model.predict(x, None if U is None else U[k - 1], t[k] - t[k - 1],
                                    None if U is None else U[k])
            P = F @ P @ F.T + Q
        idx = np.flatnonzero(np.isfinite(Y[k]))
        if len(idx):
            y_pred, H = model.measure(x, tuple(channels[i] for i in idx))
            R = np.diag(r2[idx])
            S = H @ P @ H.T + R
            K = np.linalg.solve(S, H @ P).T
            r = Y[k, idx] - y_pred
            N[k] = r @ np.linalg.solve(S, r)
            x = x + K @ r
            IKH = np.eye(nx) - K @ H
            P = IKH @ P @ IKH.T + K @ R @ K.T
        P = 0.5 * (P + P.T)
        np.fill_diagonal(P, np.maximum(np.diag(P), p_floor))
        X[k], Ps[k] = x, P
        cov[0] = P
    if hasattr(model, "watch_covariance"):
        model.watch_covariance(watched)
    return X, Ps, N


def held_matrices(dl, s, hs: HeldSystem, pe=None):
    """``(M_r, K_r, C_r, G_r)`` of the held system at ``q0 + dl`` with the elastic coordinates ``pe`` (None: zero):
    the q-expansion, then the elastic coordinates' first-order rows (and, for the symmetric ``M_r`` and damping,
    columns) as matrices, and the second-order rigid block of ``M_r`` and the damping as a double sum."""
    r = hs.Mr.shape[0]
    nq = dl.shape[0]
    gM, gK = dl @ hs.dM, dl @ hs.dK
    Ca, Gr = hs.Ca, hs.Gr
    if hs.has_old:
        gM = gM + 0.5 * s * (gM - dl @ hs.old_dM)
        gK = gK + 0.5 * s * (gK - dl @ hs.old_dK)
        Ca = hs.Ca + s * (hs.Ca - hs.old_Ca)
        Gr = hs.Gr + s * (hs.Gr - hs.old_Gr)
    Mr, Kr = hs.Mr + gM.reshape(r, r), hs.Kr + gK.reshape(r, r)
    if pe is not None and hs.pM.shape[0]:
        E = np.zeros((r, r))  # the rigid rows' change embedded in full matrices
        rows = {}
        for name in ("pM", "pK", "pC"):
            E = np.zeros((r, r))
            E[:nq] = (pe @ getattr(hs, name)).reshape(nq, r)
            rows[name] = E
        m = Gr.shape[1]
        dG = (pe @ hs.pG).reshape(nq, m + 1)[:, :m]
        Mr = Mr + rows["pM"] + rows["pM"].T
        Kr = Kr + rows["pK"]
        Ca = Ca + rows["pC"] + rows["pC"].T + hs.beta * rows["pK"].T
        Gr = Gr + np.vstack([dG, np.zeros((r - nq, m))])
        k, l = np.triu_indices(len(pe))  # the rigid block's second order: the pairs k <= l, the entries i <= j
        for X, p2 in ((Mr, hs.p2M), (Ca, hs.p2C)):
            B = np.zeros((nq, nq))
            B[np.triu_indices(nq)] = p2 @ (pe[k] * pe[l])
            X[:nq, :nq] += B + np.triu(B, 1).T
    return Mr, Kr, Ca + hs.beta * Kr, Gr


def quadratic_forces(p, pd, nq, fg, T2, V2, C2):
    """``f = fg - 1/2 (p' T p') - [p V_i p]_i - C(p' (x) q')``."""
    r = p.shape[0]
    f = fg - 0.5 * ((pd @ T2).reshape(r, r) @ pd)
    f[:nq] -= (V2 @ p).reshape(nq, r) @ p
    if C2.shape[0]:
        f -= np.outer(pd, pd[:nq]).ravel() @ C2
    return f


def rk4_linear(z, u, Mr, Kr, Cr, Gr, f, h, n):
    """``n`` RK4 steps of ``M p'' + C p' + K p = G u + f`` from ``z = [p; p']``."""
    r = Mr.shape[0]
    X = np.linalg.solve(Mr, np.column_stack([Kr, Cr, Gr @ u + f]))
    Ak, Ac, c = X[:, :r], X[:, r : 2 * r], X[:, 2 * r]
    p, v = z[:r].copy(), z[r:].copy()
    for _ in range(n):
        a1 = c - Ak @ p - Ac @ v
        p2, v2 = p + 0.5 * h * v, v + 0.5 * h * a1
        a2 = c - Ak @ p2 - Ac @ v2
        p3, v3 = p + 0.5 * h * v2, v + 0.5 * h * a2
        a3 = c - Ak @ p3 - Ac @ v3
        p4, v4 = p + h * v3, v + h * a3
        a4 = c - Ak @ p4 - Ac @ v4
        p = p + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
        v = v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
    return np.concatenate([p, v])


def held_step(z, u, dl, s, h, n, hs: HeldSystem):
    """One cached interval: ``(z_next, M_r, K_r, C_r, G_r)``, the matrices at the interval's midpoint elastic
    coordinates, the forces at its start."""
    r = hs.Mr.shape[0]
    nq = dl.shape[0]
    tm = 0.5 * h * n  # the matrices at the interval's midpoint elastic coordinates p_e + tm p_e'
    Mr, Kr, Cr, Gr = held_matrices(dl, s, hs, z[nq:r] + tm * z[r + nq :])
    f = quadratic_forces(z[:r], z[r:], nq, hs.fg, hs.T2, hs.V2, hs.C2)
    if hs.has_old:
        f = f + s * (f - quadratic_forces(z[:r], z[r:], nq, hs.old_fg, hs.old_T2, hs.old_V2, hs.old_C2))
    if hs.Wg.shape[0]:  # the weight by its gradient in q and, with a partner, its curvature along the secant
        w = hs.Wg[:, :nq] @ dl
        if hs.has_old:  # fg + (1 + s) Wg dl - s^2 (fg - old_fg), less the secant's s (fg - old_fg) in f already
            w = (1.0 + s) * w - (s + s * s) * (hs.fg - hs.old_fg)
        f = f + w
    if hs.pG.shape[0]:  # the weight's change with the elastic coordinates: pG's last column
        f[:nq] += (z[nq:r] @ hs.pG).reshape(nq, -1)[:, -1]
    return rk4_linear(z, u, Mr, Kr, Cr, Gr, f, h, n), Mr, Kr, Cr, Gr


def prediction_error(dl, s, Mr, Kr, hs: HeldSystem):
    """The held model's relative error of ``M_r``, ``K_r`` at ``q0 + dl`` in the metric of the exact ``Mr``."""
    Mp, Kp, _, _ = held_matrices(dl, s, hs._replace(Ca=hs.Mr, old_Ca=hs.Mr, Gr=hs.Mr, old_Gr=hs.Mr, beta=0.0))
    try:
        Li = np.linalg.inv(np.linalg.cholesky(Mr))
    except np.linalg.LinAlgError:
        return float("inf")
    EM, EK, KK = Li @ (Mp - Mr) @ Li.T, Li @ (Kp - Kr) @ Li.T, Li @ Kr @ Li.T
    return float(max(np.abs(EM).max(), np.abs(EK).max() / np.abs(KK).max()))


def step_maps_noise(Mr, Kr, Cr, Gr, h, n, torque_var):
    """``(P^n, S, L, L diag(var) L')`` of ``n`` RK4 steps of the linear system."""
    Pn, S, L = step_maps(np.linalg.inv(Mr), Kr, Cr, Gr, h, n)
    return Pn, S, L, (L * torque_var) @ L.T

"""Independent NumPy implementations of what exuflex computes in compiled code: oracles for the tests only.

- :func:`numpy_filter`: the multirate EKF (predict, Joseph-form update with the finite channels) in plain NumPy;
- :func:`held_matrices`, :func:`quadratic_forces`, :func:`rk4_linear`, :func:`held_step`, :func:`prediction_error`,
  :func:`step_maps_noise`: the cached observer step's algebra (:mod:`exuflex.observer.expansion`);
- :func:`exact_jacobian`: the cached step with its exact Jacobian, every term in (the filter's leaves some out).
"""

from __future__ import annotations

import numpy as np

from exuflex.observer.expansion import HeldSystem, held_system, step_maps


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
    columns) as matrices, and the damping's second-order rigid block as a sum over the pairs."""
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
        B = np.zeros((nq, nq))
        B[np.triu_indices(nq)] = hs.p2C @ (pe[k] * pe[l])
        Ca[:nq, :nq] += B + np.triu(B, 1).T
        if hs.Me.shape[0]:  # M_r's cross term in q and the elastic coordinates: sum_mi p_m dl_i (X_mi + X_mi^T)
            X = np.zeros((r, r))
            X[:nq] = np.einsum("m,i,miab->ab", pe, dl, hs.Me.reshape(len(pe), nq, nq, r))
            Mr = Mr + X + X.T
    return Mr, Kr, Ca + hs.beta * Kr, Gr


def quadratic_forces(p, pd, nq, fg, T2, V2, C2):
    """``f = fg - 1/2 (p' T p') - [p V_i p]_i - C(p' (x) q')``."""
    r = p.shape[0]
    f = fg - 0.5 * ((pd @ T2).reshape(r, r) @ pd)
    f[:nq] -= (V2 @ p).reshape(nq, r) @ p
    if C2.shape[0]:
        f -= np.outer(pd, pd[:nq]).ravel() @ C2
    return f


def velocity_terms(pe, pd, nq, pT, pC2):
    """The velocity forces' first order in the elastic coordinates (``expansion._velocity_terms``) and their
    derivatives: ``(f, df/dpe, df/dp')`` with ``f = -sum_m pe_m (1/2 p' T_m p' + sum_{j < nq} p'_k p'_j C_m[k, j])``."""
    r = pd.shape[0]
    n_el = pT.shape[0]
    T4 = pT.reshape(n_el, r, r, r)  # [m, k, i, j]
    C4 = pC2.reshape(n_el, r, nq, r)  # [m, k, j, c]
    g = -0.5 * np.einsum("mkij,k,j->im", T4, pd, pd) - np.einsum("mkjc,k,j->cm", C4, pd, pd[:nq])
    Te = np.einsum("m,mkij->kij", pe, T4)
    Ce = np.einsum("m,mkjc->kjc", pe, C4)
    dv = -0.5 * (np.einsum("aij,j->ia", Te, pd) + np.einsum("jia,j->ia", Te, pd))
    dv -= np.einsum("ajc,j->ca", Ce, pd[:nq])
    dv[:, :nq] -= np.einsum("kac,k->ca", Ce, pd)
    return g @ pe, g, dv


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


def motion_stiffness(u, z, nq, KGd) -> tuple[np.ndarray, np.ndarray]:
    """``(K_d, dK_d/dq')`` ((r, r), (nq, r, r)): the motion's geometric stiffness ``sum_k c_k KGd[k]``, ``c = [1, u,
    (q'_a q'_b)_{a <= b}]`` (``expansion.motion_stiffness``) and its change with the rates; zeros where ``KGd`` is
    empty."""
    r = z.shape[0] // 2
    if KGd.shape[0] == 0:
        return np.zeros((r, r)), np.zeros((nq, r, r))
    a, b = np.triu_indices(nq)
    qd = z[r : r + nq]
    c = np.concatenate([[1.0], u, qd[a] * qd[b]])
    dc = np.zeros((nq, len(c)))
    for k, (i, j) in enumerate(zip(a, b, strict=True)):
        dc[i, 1 + len(u) + k] += qd[j]
        dc[j, 1 + len(u) + k] += qd[i]
    K3 = KGd.reshape(-1, r, r)
    return np.tensordot(c, K3, 1), np.tensordot(dc, K3, 1)


def motion_form(hs: HeldSystem, dl):
    """The motion's geometric stiffness form at ``q0 + dl``: ``KGd + dKGd . dl`` (``expansion._motion_form``)."""
    if hs.dKGd.shape[0] == 0:
        return hs.KGd
    k, rr = hs.KGd.shape
    return hs.KGd + np.einsum("kit,i->kt", hs.dKGd.reshape(k, len(dl), rr), dl)


def forms_gradient(p, pd, nq, dT2, dV2, dC2) -> np.ndarray:
    """``g`` (r, nq): the held forms' forces differentiated in q (``expansion._forms_gradient``), column ``i``
    ``-1/2 p' dT_i p' - [p dV_{i,c} p]_c - sum_{k, j < nq} p'_k p'_j dC_i[k, j]``."""
    r = p.shape[0]
    g = -0.5 * np.einsum("ikab,k,b->ai", dT2.reshape(nq, r, r, r), pd, pd)
    g[:nq] -= np.einsum("icab,a,b->ci", dV2.reshape(nq, nq, r, r), p, p)
    if dC2.shape[0]:
        g -= np.einsum("ikjc,k,j->ci", dC2.reshape(nq, r, nq, r), pd, pd[:nq])
    return g


def _forms_along(dl, hs: HeldSystem) -> tuple:
    """The forms' change ``sum_i dl_i (dT2, dV2, dC2)_i`` for the step ``dl`` (shaped as ``T2``, ``V2``, ``C2``)."""
    nq, r = dl.shape[0], hs.Mr.shape[0]
    T = np.einsum("i,ix->x", dl, hs.dT2.reshape(nq, -1)).reshape(r, r * r)
    V = np.einsum("i,ix->x", dl, hs.dV2.reshape(nq, -1)).reshape(nq * r, r)
    C = np.einsum("i,ix->x", dl, hs.dC2.reshape(nq, -1)).reshape(r * nq, r) if hs.dC2.shape[0] else hs.dC2
    return T, V, C


def held_step(z, u, dl, s, h, n, hs: HeldSystem):
    """One cached interval: ``(z_next, M_r, K_r, C_r, G_r)``, the matrices at the interval's midpoint elastic
    coordinates, the forces at its start."""
    r = hs.Mr.shape[0]
    nq = dl.shape[0]
    tm = 0.5 * h * n  # the matrices at the interval's midpoint elastic coordinates p_e + tm p_e'
    Mr, Kr, Cr, Gr = held_matrices(dl, s, hs, z[nq:r] + tm * z[r + nq :])
    f = quadratic_forces(z[:r], z[r:], nq, hs.fg, hs.T2, hs.V2, hs.C2)
    grad = hs.dT2.shape[0] > 0  # the forms follow q by their gradients, not along the secant
    secant = hs.has_old and not grad
    if secant:
        f = f + s * (f - quadratic_forces(z[:r], z[r:], nq, hs.old_fg, hs.old_T2, hs.old_V2, hs.old_C2))
    if grad:
        f = f + forms_gradient(z[:r], z[r:], nq, hs.dT2, hs.dV2, hs.dC2) @ dl
    if hs.pT.shape[0]:  # the velocity forces' first order in the elastic coordinates
        f = f + velocity_terms(z[nq:r], z[r:], nq, hs.pT, hs.pC2)[0]
    if hs.Wg.shape[0]:  # the weight by its gradient in q and, with a partner, half the gradient's change along the
        # secant: fg + (Wg + s/2 (Wg - old_Wg)) dl, less the secant's s (fg - old_fg) in f already
        Wq = hs.Wg[:, :nq] + 0.5 * s * (hs.Wg[:, :nq] - hs.old_Wg[:, :nq]) if hs.has_old else hs.Wg[:, :nq]
        w = Wq @ dl
        if secant:
            w = w - s * (hs.fg - hs.old_fg)
        f = f + w
    if hs.pG.shape[0]:  # the weight's change with the elastic coordinates: pG's last column
        f[:nq] += (z[nq:r] @ hs.pG).reshape(nq, -1)[:, -1]
    if hs.We.shape[0]:  # ... and the cross term with q: sum_m p_m We[m] dl
        f[:nq] += np.einsum("m,mij,j->i", z[nq:r], hs.We.reshape(-1, nq, nq), dl)
    # the motion's geometric forces at the interval's midpoint positions (expansion._motion_forces), the form at q
    f = f - motion_stiffness(u, z, nq, motion_form(hs, dl))[0] @ (z[:r] + tm * z[r:])
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


def pair_blocks(p2: np.ndarray, n: int, nq: int) -> np.ndarray:
    """The damping's second-order form ``p2C`` of ``HeldSystem`` (packed per pair ``k <= l`` and entry ``i <= j``)
    as the symmetric blocks ``X`` (n, n, nq, nq) with ``sum_kl p_k p_l X_kl`` the rigid block's second order."""
    X = np.zeros((n, n, nq, nq))
    iu = np.triu_indices(nq)
    for c, (k, l) in enumerate(zip(*np.triu_indices(n), strict=True)):
        B = np.zeros((nq, nq))
        B[iu] = p2[:, c] if k == l else 0.5 * p2[:, c]
        B = B + np.triu(B, 1).T
        X[k, l] = X[l, k] = B
    return X


def exact_jacobian(z, u, dl, s, d, dd, h, n, hs: HeldSystem) -> tuple[np.ndarray, np.ndarray]:
    """``(z_next, F)``: the cached step over ``n`` sub-steps of ``h`` from ``z`` (``expansion.held_step`` at ``q0 +
    dl`` with the secant factor ``s`` of the secant ``d``, ``dd = d . d``; ``d`` empty without a partner) and its
    exact Jacobian in ``z``, by the tangent of its RK4 sub-steps: the reference for ``expansion.step_jacobian``,
    which leaves terms out (``tests/test_step_jacobian.py`` compares both with finite differences of the step,
    entry by entry; ``benchmarks/step_jacobian.py`` runs the filter with it). NumPy: a reference and a
    measurement, not the filter's (it carries the tangent of every state component through every RK4 stage).

    Every input of the held system ``M p'' + C p' + K p = G u + f`` (``expansion._held_model``) that the step
    takes from ``z`` is differentiated: ``M_r``, ``K_r`` in ``q`` (the gradients, the secant's second order and,
    where the secant is in use, the secant factor's own change ``ds/dq = d / dd``, which also moves ``C_a``,
    ``G_r`` and the forces along it); the rigid rows and columns of ``M_r``, ``K_r``, ``C_r``, ``G_r`` in the
    elastic coordinates (and the rigid block of ``C_r`` to second order) and, through the midpoint
    ``p_e + dt/2 p_e'``, their rates (``expansion._elastic_terms``);
    the forces ``(1 + s) f_held - s f_old`` (the weight by ``Wg`` and ``pG``) in the whole state. The sub-steps
    advance the state with its tangent ``X = dz_k / dz`` (``X_0 = I``): at each RK4 stage ``y`` (acceleration
    ``a``) the tangent's rate is ``A Y + [0; M^-1 (dG u + df - dK y_p - dC y_v - dM a)]``, ``A`` the held
    system's."""
    z = np.asarray(z, float)
    u = np.asarray(u, float)
    r = hs.Mr.shape[0]
    nq = dl.shape[0]
    nx = 2 * r
    m = hs.Gr.shape[1]
    p, pd = z[:r], z[r:]
    n_el = hs.pM.shape[0] if r > nq else 0
    tm = 0.5 * h * n
    for tm in (tm, 0.0):  # the midpoint elastic coordinates; the start where M_r is not positive definite there
        pem = p[nq:] + tm * pd[nq:]
        M, K, C, G = held_system(dl, s, pem if n_el else pem[:0], tuple(hs))
        try:
            Minv = np.linalg.inv(np.linalg.cholesky(M))
        except np.linalg.LinAlgError:
            continue
        Minv = Minv.T @ Minv
        break
    else:
        return np.full(nx, np.nan), np.full((nx, nx), np.nan)
    # the forces of the held and the old forms, and the derivatives of each: f = (1 + s) f_k - s f_o
    grad = hs.dT2.shape[0] > 0  # the forms follow q by their gradients (first order), not along the secant
    secant = hs.has_old and not grad
    forms = [(hs.fg, hs.T2, hs.V2, hs.C2, 1.0 + s if secant else 1.0)]
    if secant:
        forms.append((hs.old_fg, hs.old_T2, hs.old_V2, hs.old_C2, -s))
    if grad:  # the forms' change along dl, as forms of their own (their derivatives in p and p' alike)
        forms.append((np.zeros(r), *_forms_along(dl, hs), 1.0))
    f = np.zeros(r)
    dF = np.zeros((r, nx))
    fk = []
    for fg, T2, V2, C2, w in forms:
        T3 = T2.reshape(r, r, r)  # [k, i, j]
        V3 = V2.reshape(nq, r, r)  # [i, a, b]
        fi = fg - 0.5 * np.einsum("k,kij,j->i", pd, T3, pd)
        fi[:nq] -= np.einsum("a,iab,b->i", p, V3, p)
        dF[:, r:] -= 0.5 * w * (np.einsum("mij,j->im", T3, pd) + np.einsum("jim,j->im", T3, pd))
        dF[:nq, :r] -= w * (np.einsum("imb,b->im", V3, p) + np.einsum("iam,a->im", V3, p))
        if C2.shape[0]:
            C3 = C2.reshape(r, nq, r)  # [k, j, c]
            fi -= np.einsum("k,j,kjc->c", pd, pd[:nq], C3)
            dF[:, r:] -= w * np.einsum("j,mjc->cm", pd[:nq], C3)
            dF[:, r : r + nq] -= w * np.einsum("k,kmc->cm", pd, C3)
        fk.append(fi)
        f += w * fi
    if hs.pT.shape[0]:  # the velocity forces' first order in the elastic coordinates
        fv, dfe, dfv = velocity_terms(p[nq:], pd, nq, hs.pT, hs.pC2)
        f += fv
        dF[:, nq:r] += dfe
        dF[:, r:] += dfv
    # the secant factor's change with q where the secant is in use (expansion._secant_factor)
    act = False
    if hs.has_old and d.shape[0]:
        act = not (float(dl @ d) ** 2 < 0.49 * float(dl @ dl) * dd)
    ds = d / dd if act else np.zeros(nq)
    along = fk[0] - fk[1] if secant else 0.0
    if grad:  # ... and in q
        dF[:, :nq] += forms_gradient(p, pd, nq, hs.dT2, hs.dV2, hs.dC2)
    if hs.Wg.shape[0]:  # the weight to second order (expansion._held_model): (Wg + s/2 dW) dl - s (fg - fg_old)
        wdl = hs.Wg[:, :nq] @ dl
        f += wdl
        dF[:, :nq] += hs.Wg[:, :nq]
        if hs.has_old:
            dW = hs.Wg[:, :nq] - hs.old_Wg[:, :nq]
            dfg = hs.fg - hs.old_fg if secant else 0.0 * hs.fg  # (the forms' secant's weight, taken out)
            f += 0.5 * s * (dW @ dl) - s * dfg
            dF[:, :nq] += 0.5 * s * dW
            along = along + 0.5 * (dW @ dl) - dfg
    if act:  # the secant factor's own change moves everything along the secant
        dF[:, :nq] += np.outer(along, ds)
    # the motion's geometric forces -K_d(q') (p + dt/2 p') (expansion._motion_forces), K_d a function of the rates
    Kd, dKd = motion_stiffness(u, z, nq, motion_form(hs, dl))
    pm = p + 0.5 * h * n * pd
    f -= Kd @ pm
    dF[:, :r] -= Kd
    if hs.dKGd.shape[0]:  # the form's change with q (expansion._motion_form)
        rr = r * r
        for i in range(nq):
            dF[:, i] -= motion_stiffness(u, z, nq, hs.dKGd[:, i * rr : (i + 1) * rr])[0] @ pm
    dF[:, r:] -= 0.5 * h * n * Kd
    dF[:, r : r + nq] -= np.einsum("aij,j->ia", dKd, pm)
    if n_el:
        mg = hs.pG.shape[1] // nq
        wcol = hs.pG.reshape(n_el, nq, mg)[:, :, mg - 1]  # (n_el, nq)
        f[:nq] += p[nq:] @ wcol
        dF[:nq, nq:r] += wcol.T
    if hs.We.shape[0]:  # the weight's cross term sum_m p_m We[m] dl, in q and in the elastic coordinates
        We3 = hs.We.reshape(-1, nq, nq)
        f[:nq] += np.einsum("m,mij,j->i", p[nq:], We3, dl)
        dF[:nq, :nq] += np.einsum("m,mij->ij", p[nq:], We3)
        dF[:nq, nq:r] += np.einsum("mij,j->im", We3, dl)
    # the held matrices' derivatives per state component (zero where a component does not move them)
    dMj = np.zeros((nx, r, r))
    dKj = np.zeros((nx, r, r))
    dCj = np.zeros((nx, r, r))
    dGj = np.zeros((nx, r, m))
    gM, hM = dl @ hs.dM, (dl @ hs.old_dM if hs.has_old else 0.0)
    gK, hK = dl @ hs.dK, (dl @ hs.old_dK if hs.has_old else 0.0)
    for j in range(nq):
        vm, vk = hs.dM[j].copy(), hs.dK[j].copy()
        if hs.has_old:
            vm += 0.5 * s * (hs.dM[j] - hs.old_dM[j]) + 0.5 * ds[j] * (gM - hM)
            vk += 0.5 * s * (hs.dK[j] - hs.old_dK[j]) + 0.5 * ds[j] * (gK - hK)
            dCj[j] = ds[j] * (hs.Ca - hs.old_Ca)
            dGj[j] = ds[j] * (hs.Gr - hs.old_Gr)
        dMj[j] = vm.reshape(r, r)
        dKj[j] = vk.reshape(r, r)
        dCj[j] += hs.beta * dKj[j]
    Me4 = hs.Me.reshape(n_el, nq, nq, r) if n_el and hs.Me.shape[0] else None
    if Me4 is not None:  # M_r's cross term in q (and in the elastic coordinates below): sum_m pem_m (X_mj + X_mj^T)
        for j in range(nq):
            X = np.zeros((r, r))
            X[:nq] = np.einsum("m,mab->ab", pem, Me4[:, j])
            dMj[j] += X + X.T
    if n_el:
        mg = hs.pG.shape[1] // nq
        X2C = pair_blocks(hs.p2C, n_el, nq)
        for k in range(n_el):
            Pm = hs.pM[k].reshape(nq, r)
            if Me4 is not None:
                Pm = Pm + np.einsum("i,iab->ab", dl, Me4[k])
            Pk = hs.pK[k].reshape(nq, r)
            Pc = hs.pC[k].reshape(nq, r) + hs.beta * Pk
            # the second order's derivative, d/dp_k sum_ab p_a p_b X_ab = 2 sum_b p_b X_kb (X symmetric)
            dCe = 2.0 * np.einsum("b,bij->ij", pem, X2C[k])
            for j, c in ((nq + k, 1.0), (r + nq + k, tm)):
                dCj[j, :nq, :nq] += c * dCe
                dMj[j, :nq, :] += c * Pm
                dMj[j, :, :nq] += c * Pm.T
                dKj[j, :nq, :] += c * Pk
                dCj[j, :nq, :] += c * Pc
                dCj[j, :, :nq] += c * Pc.T
                dGj[j, :nq, :] += c * hs.pG[k].reshape(nq, mg)[:, :m]
    # the sub-steps with their tangent (the derivatives stacked: one product per stage and kind)
    KC = np.hstack([K, C])
    A = Minv @ KC  # [M^-1 K, M^-1 C]
    b0 = G @ u + f
    g0 = (dF + np.einsum("jac,c->aj", dGj, u)).T.copy()  # (nx, r): row j the forcing of column j
    dKC = np.concatenate([dKj, dCj], axis=2).reshape(nx * r, 2 * r)
    dM2 = dMj.reshape(nx * r, r)
    x, X = z.copy(), np.eye(nx)

    def rate(y, Y):
        a = Minv @ (b0 - KC @ y)
        g = g0 - (dKC @ y).reshape(nx, r) - (dM2 @ a).reshape(nx, r)
        return np.concatenate([y[r:], a]), np.vstack([Y[r:], Minv @ g.T - A @ Y])

    for _ in range(n):
        k1, K1 = rate(x, X)
        k2, K2 = rate(x + 0.5 * h * k1, X + 0.5 * h * K1)
        k3, K3 = rate(x + 0.5 * h * k2, X + 0.5 * h * K2)
        k4, K4 = rate(x + h * k3, X + h * K3)
        x = x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        X = X + h / 6.0 * (K1 + 2.0 * K2 + 2.0 * K3 + K4)
    return x, X

"""The arithmetic of one cached observer step, compiled with numba when it is installed.

The cached step (:class:`exuflex.observer.reduced.ReducedObserverModel`, ``method="cached"``) holds the
reduced model at a configuration ``q0`` and follows the links from there: ``M_r`` and ``K_r`` to second
order in ``q - q0`` (their analytic gradients at ``q0``, and the change of the gradients since the previous
held configuration along the line joining the two), the damping, input matrix and velocity-dependent forces
to first order along that line (a secant). Per measurement interval it then advances the linear system
``M p'' + C p' + K p = G u + f`` (forces and input held over the interval, as the paper's RK4 does between
two samples) by ``n`` RK4 steps.

Two implementations of the same arithmetic: NumPy expressions (:func:`rk4_held_numpy`, the reference, and
what runs without numba) and explicit loops compiled by numba (:func:`rk4_held_loops`), which remove the
per-call overhead of some 200 small NumPy operations per interval. ``tests/test_held.py`` checks that they
agree to rounding.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "HAVE_NUMBA",
    "held_matrices",
    "held_step_loops",
    "held_step_numpy",
    "held_system_loops",
    "held_system_numpy",
    "map_lookahead",
    "power_sum",
    "prediction_error",
    "prediction_error_loops",
    "quadratic_forces",
    "rk4_held_loops",
    "rk4_held_numpy",
    "step_jacobian_loops",
    "step_maps",
    "step_maps_held",
    "step_maps_held_numpy",
    "warm_up",
]

try:  # numba is a core dependency, but exuflex must still run (slower) where it cannot be installed
    import numba
    import numba.extending

    HAVE_NUMBA = True

    def _jit(f):
        return numba.njit(cache=True, nogil=True, error_model="numpy")(f)

    def _shared(f):
        """Plain NumPy function outside compiled code, compiled inline where a kernel calls it."""
        return numba.extending.register_jitable(f)

except ImportError:  # pragma: no cover - exercised only on machines without numba
    HAVE_NUMBA = False

    def _jit(f):
        return f

    _shared = _jit


def held_matrices(dl, s, Mr0, Kr0, Ca0, Gr0, dM2, dK2, beta, old=None):
    """``(M_r, K_r, C_r, G_r)`` at ``q = q0 + dl``.

    ``dM2, dK2``: (nq, r*r) gradients at ``q0``; ``Ca0``: the mass-proportional part of ``C_r`` (the
    stiffness part is ``beta K_r``). ``old = (dM2, dK2, Ca, Gr)`` of the previous held configuration and
    ``s = (dl . d) / (d . d)`` with ``d = q0 - q_old`` give the second-order term of ``M_r, K_r`` and the
    secant of ``Ca, G_r``.
    """
    r = Mr0.shape[0]
    gM = dl @ dM2
    gK = dl @ dK2
    Ca, Gr = Ca0, Gr0
    if old is not None:
        dM_old, dK_old, Ca_old, Gr_old = old
        gM = gM + 0.5 * s * (gM - dl @ dM_old)
        gK = gK + 0.5 * s * (gK - dl @ dK_old)
        Ca = Ca0 + s * (Ca0 - Ca_old)
        Gr = Gr0 + s * (Gr0 - Gr_old)
    Kr = Kr0 + gK.reshape(r, r)
    return Mr0 + gM.reshape(r, r), Kr, Ca + beta * Kr, Gr


def quadratic_forces(p, pd, nq, fg, T2, V2, C2):
    """``f = fg - 1/2 (p' T p') - [p V_i p]_i - C(p' (x) q')`` (see :class:`exuflex.reduction.model.QuadraticForces`)."""
    r = p.shape[0]
    f = fg - 0.5 * ((pd @ T2).reshape(r, r) @ pd)
    f[:nq] -= (V2 @ p).reshape(nq, r) @ p
    if C2.shape[0]:
        f -= np.outer(pd, pd[:nq]).ravel() @ C2
    return f


def rk4_held_numpy(z, u, Mr, Kr, Cr, Gr, f, h, n):
    """``n`` RK4 steps of ``M p'' + C p' + K p = G u + f`` from ``z = [p; p']`` (NumPy reference)."""
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


@_shared
def _cholesky_factor(A):  # pragma: no cover - compiled
    """``(L, ok)``: the lower Cholesky factor ``A = L L^T``; ``ok`` False (``L`` incomplete) if a pivot is not
    positive or is NaN: ``A`` is not positive definite."""
    r = A.shape[0]
    L = np.zeros((r, r))
    for j in range(r):
        d = A[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return L, False
        L[j, j] = np.sqrt(d)
        for i in range(j + 1, r):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc / L[j, j]
    return L, True


@_shared
def _cholesky_solve(A, B):  # pragma: no cover - compiled
    """``A^-1 B`` for a symmetric positive definite ``A`` (a reduced mass matrix); NaN if it is not."""
    r = A.shape[0]
    L, ok = _cholesky_factor(A)
    if not ok:
        return np.full(B.shape, np.nan)
    X = B.copy()
    m = B.shape[1]
    for i in range(r):  # forward: L Y = B, row i of Y from the rows above (axpy over the columns)
        for k in range(i):
            lik = L[i, k]
            for c in range(m):
                X[i, c] -= lik * X[k, c]
        d = 1.0 / L[i, i]
        for c in range(m):
            X[i, c] *= d
    for i in range(r - 1, -1, -1):  # backward: L^T X = Y
        for k in range(i + 1, r):
            lki = L[k, i]
            for c in range(m):
                X[i, c] -= lki * X[k, c]
        d = 1.0 / L[i, i]
        for c in range(m):
            X[i, c] *= d
    return X


def _rk4_held_loops(z, u, Mr, Kr, Cr, Gr, f, h, n):  # pragma: no cover - compiled; its twin is tested
    r = Mr.shape[0]
    rhs = np.empty((r, 2 * r + 1))
    rhs[:, :r] = Kr
    rhs[:, r : 2 * r] = Cr
    for i in range(r):
        acc = f[i]
        for j in range(u.shape[0]):
            acc += Gr[i, j] * u[j]
        rhs[i, 2 * r] = acc
    X = _cholesky_solve(Mr, rhs)
    # the vectors padded with zeros to a whole number of SIMD lanes (16 for the six-bar's 13): the sweeps then
    # have no scalar remainder (measured: 20 RK4 steps 10.2 -> 7.7 us); the padding stays zero
    rp = (r + 3) // 4 * 4
    XT = np.zeros((2 * r + 1, rp))  # column j of the operator is the contiguous row XT[j]
    for i in range(r):
        for j in range(2 * r + 1):
            XT[j, i] = X[i, j]
    b = XT[2 * r]
    p = np.zeros(rp)
    v = np.zeros(rp)
    p[:r] = z[:r]
    v[:r] = z[r:]
    a = np.empty(rp)  # stage acceleration
    w = np.empty(rp)  # stage velocity
    yp = np.empty(rp)  # stage position
    asum = np.empty(rp)  # weighted sums of the stage rates (1, 2, 2, 1)
    wsum = np.empty(rp)
    for _ in range(n):
        for st in range(4):
            if st == 0:  # stage st at (p + c w_{st-1}, v + c a_{st-1})
                for i in range(rp):
                    yp[i] = p[i]
                    w[i] = v[i]
            else:
                c = 0.5 * h if st < 3 else h
                for i in range(rp):
                    yp[i] = p[i] + c * w[i]
                    w[i] = v[i] + c * a[i]
            # a = b - X_K yp - X_C w, as axpy sweeps over contiguous rows, a position and a velocity column
            # per sweep (independent lanes: no serial add chain)
            for i in range(rp):
                a[i] = b[i]
            for j in range(r):
                xk = XT[j]
                xc = XT[r + j]
                pj = yp[j]
                vj = w[j]
                for i in range(rp):
                    a[i] -= xk[i] * pj + xc[i] * vj
            if st == 0:
                for i in range(rp):
                    wsum[i] = w[i]
                    asum[i] = a[i]
            else:
                g = 1.0 if st == 3 else 2.0
                for i in range(rp):
                    wsum[i] += g * w[i]
                    asum[i] += g * a[i]
        for i in range(rp):
            p[i] += h / 6.0 * wsum[i]
            v[i] += h / 6.0 * asum[i]
    out = np.empty(2 * r)
    out[:r] = p[:r]
    out[r:] = v[:r]
    return out


def _quadratic_forces_loops(p, pd, nq, fg, T2, V2, C2):  # pragma: no cover - compiled
    r = p.shape[0]
    f = fg.copy()
    tmp = np.zeros(r * r)  # sum_k p'_k T[k] (flattened rows: contiguous axpy sweeps)
    for k in range(r):
        w = pd[k]
        if w != 0.0:
            for ij in range(r * r):
                tmp[ij] += w * T2[k, ij]
    for i in range(r):
        acc = 0.0
        for j in range(r):
            acc += tmp[i * r + j] * pd[j]
        f[i] -= 0.5 * acc
    for i in range(nq):
        for a in range(r):
            acc = 0.0
            for b in range(r):
                acc += V2[i * r + a, b] * p[b]
            f[i] -= acc * p[a]
    if C2.shape[0]:
        for k in range(r):
            for j in range(nq):
                w = pd[k] * pd[j]
                if w != 0.0:
                    for c in range(r):
                        f[c] -= w * C2[k * nq + j, c]
    return f


@_shared
def _held_mass_stiffness(dl, s, has_old, Mr0, Kr0, dM2, dK2, oM2, oK2):  # pragma: no cover - compiled
    """``M_r``, ``K_r`` of the held model at ``q0 + dl``: the compiled twin of :func:`held_matrices`' first two."""
    r = Mr0.shape[0]
    nq = dl.shape[0]
    gM = np.zeros(r * r)
    gK = np.zeros(r * r)
    for i in range(nq):
        for k in range(r * r):
            gM[k] += dl[i] * dM2[i, k]
            gK[k] += dl[i] * dK2[i, k]
    if has_old:
        hM = np.zeros(r * r)
        hK = np.zeros(r * r)
        for i in range(nq):
            for k in range(r * r):
                hM[k] += dl[i] * oM2[i, k]
                hK[k] += dl[i] * oK2[i, k]
        for k in range(r * r):
            gM[k] += 0.5 * s * (gM[k] - hM[k])
            gK[k] += 0.5 * s * (gK[k] - hK[k])
    return Mr0 + gM.reshape(r, r), Kr0 + gK.reshape(r, r)


@_shared
def _held_system(dl, s, has_old, beta, Mr0, Kr0, Ca0, Gr0, dM2, dK2, oM2, oK2, oCa, oGr):  # pragma: no cover
    """``(M_r, K_r, C_r, G_r)`` of the held model at ``q0 + dl``: the compiled twin of :func:`held_matrices`."""
    Mr, Kr = _held_mass_stiffness(dl, s, has_old, Mr0, Kr0, dM2, dK2, oM2, oK2)
    Ca = Ca0.copy()
    Gr = Gr0.copy()
    if has_old:
        Ca += s * (Ca0 - oCa)
        Gr += s * (Gr0 - oGr)
    return Mr, Kr, Ca + beta * Kr, Gr


def _held_step_loops(z, u, dl, s, has_old, nq, beta, h, n, Mr0, Kr0, Ca0, Gr0, dM2, dK2, fg, T2, V2, C2,
                     oM2, oK2, oCa, oGr, ofg, oT2, oV2, oC2):  # pragma: no cover - compiled
    r = Mr0.shape[0]
    p = z[:r]
    pd = z[r:]
    Mr, Kr, Cr, Gr = _held_system(dl[:nq], s, has_old, beta, Mr0, Kr0, Ca0, Gr0, dM2, dK2, oM2, oK2, oCa, oGr)
    f = _quadratic_forces_loops(p, pd, nq, fg, T2, V2, C2)
    if has_old:
        fo = _quadratic_forces_loops(p, pd, nq, ofg, oT2, oV2, oC2)
        for i in range(r):
            f[i] += s * (f[i] - fo[i])
    z_next = _rk4_held_loops(z, u, Mr, Kr, Cr, Gr, f, h, n)
    return z_next, Mr, Kr, Cr, Gr


def _held_system_loops(dl, s, has_old, beta, Mr0, Kr0, Ca0, Gr0, dM2, dK2, oM2, oK2, oCa, oGr):  # pragma: no cover
    return _held_system(dl, s, has_old, beta, Mr0, Kr0, Ca0, Gr0, dM2, dK2, oM2, oK2, oCa, oGr)


def held_system_numpy(dl, s, has_old, beta, Mr0, Kr0, Ca0, Gr0, dM2, dK2, oM2, oK2, oCa, oGr):
    """``(M_r, K_r, C_r, G_r)`` of the held model at ``q0 + dl`` (:func:`held_matrices` with the arguments
    of :func:`held_system_loops`, its compiled twin)."""
    return held_matrices(dl, s, Mr0, Kr0, Ca0, Gr0, dM2, dK2, beta, (oM2, oK2, oCa, oGr) if has_old else None)


def map_lookahead(z, nq, remap_rad, ahead, horizon):  # pragma: no cover - compiled where a kernel calls it
    """How far ahead of ``q`` along its motion the step map is built: ``tau q'`` with ``tau`` the time the
    fastest coordinate takes to move ``ahead`` remap radii, at most ``horizon`` seconds (a filter at rest,
    whose estimated ``q'`` is noise, keeps its map at ``q``).

    A map built at ``q`` serves until ``q`` has moved ``remap_rad`` away; built ``remap_rad`` ahead it serves
    while ``q`` crosses it, twice the path for the same largest (and mean) distance between the map's and
    the step's configuration.
    """
    r = z.shape[0] // 2
    vmax = 0.0
    for i in range(nq):
        vmax = max(vmax, abs(z[r + i]))
    shift = np.zeros(nq)
    if vmax > 0.0 and ahead > 0.0:
        tau = min(ahead * remap_rad / vmax, horizon)
        for i in range(nq):
            shift[i] = tau * z[r + i]
    return shift


def _step_jacobian_loops(z, Ts, Vs, C3, Pn, SQM):  # pragma: no cover - compiled twin of _jacobian
    """``Pn + SQM dF/dz`` with ``dF/dz`` the derivatives of the held quadratic forces (see
    :meth:`exuflex.observer.reduced.ReducedObserverModel._jacobian`)."""
    r = Ts.shape[0]
    nq = Vs.shape[0]
    p = z[:r]
    pd = z[r:]
    G = np.zeros((r, 2 * r))  # generalised forces per unit state change
    # df/dp'_m of -1/2 p' T p' is -1/2 sum_j (T[m,i,j] + T[j,i,m]) p'_j, all (m, i) in one matrix-vector
    # product; df_i/dp_m of -p V_i p (q rows) likewise
    gt = np.ascontiguousarray(Ts).reshape(r * r, r) @ pd
    for m in range(r):
        for i in range(r):
            G[i, r + m] = -0.5 * gt[m * r + i]
    gv = np.ascontiguousarray(Vs).reshape(nq * r, r) @ p
    for i in range(nq):
        for m in range(r):
            G[i, m] = -gv[i * r + m]
    for k in range(C3.shape[0]):  # d/dp' of -sum p'_k p'_j C[k, j, :] (j < nq)
        for j in range(nq):
            for c in range(r):
                G[c, r + k] -= C3[k, j, c] * pd[j]
                G[c, r + j] -= pd[k] * C3[k, j, c]
    F = SQM @ G
    F += Pn
    return F


def prediction_error(dl, s, has_old, Mr0, Kr0, dM2, dK2, oM2, oK2, Mr, Kr):
    """How well a held model predicts ``M_r`` and ``K_r`` at ``q0 + dl`` (:func:`held_matrices`), against the
    exact ``Mr``, ``Kr`` there: the largest entry of the differences whitened by the exact mass matrix,
    ``L^-1 (M_pred - M) L^-T`` (``M = L L^T``; near 1 the prediction may be indefinite), and of ``K_r``'s
    relative to the largest entry of ``L^-1 K L^-T``. ``inf`` if ``Mr`` is not positive definite. NumPy
    reference of the compiled kernel."""
    old = (oM2, oK2, Mr0, Mr0) if has_old else None
    Mp, Kp, _, _ = held_matrices(dl, s, Mr0, Kr0, Mr0, Mr0, dM2, dK2, 0.0, old)
    try:
        Li = np.linalg.inv(np.linalg.cholesky(Mr))
    except np.linalg.LinAlgError:
        return float("inf")
    EM = Li @ (Mp - Mr) @ Li.T
    EK = Li @ (Kp - Kr) @ Li.T
    KK = Li @ Kr @ Li.T
    return float(max(np.abs(EM).max(), np.abs(EK).max() / np.abs(KK).max()))


def _prediction_error_loops(dl, s, has_old, Mr0, Kr0, dM2, dK2, oM2, oK2, Mr, Kr):  # pragma: no cover - compiled
    Mp, Kp = _held_mass_stiffness(dl, s, has_old, Mr0, Kr0, dM2, dK2, oM2, oK2)
    Li = _inverse_cholesky_factor(Mr)  # NaN if Mr is not positive definite
    if not np.isfinite(Li[0, 0]):
        return np.inf
    em = np.abs(Li @ (Mp - Mr) @ Li.T).max()
    ek = np.abs(Li @ (Kp - Kr) @ Li.T).max()
    kk = np.abs(Li @ Kr @ Li.T).max()
    return max(em, ek / kk)


@_shared
def _inverse_cholesky_factor(A):  # pragma: no cover - compiled
    """``L^-1`` of the Cholesky factor ``A = L L^T`` (NaN if ``A`` is not positive definite)."""
    r = A.shape[0]
    L, ok = _cholesky_factor(A)
    if not ok:
        return np.full((r, r), np.nan)
    Li = np.zeros((r, r))
    for c in range(r):  # column c of L^-1: L x = e_c
        for i in range(c, r):
            acc = 1.0 if i == c else 0.0
            for k in range(c, i):
                acc -= L[i, k] * Li[k, c]
            Li[i, c] = acc / L[i, i]
    return Li


def held_step_numpy(z, u, dl, s, has_old, nq, beta, h, n, Mr0, Kr0, Ca0, Gr0, dM2, dK2, fg, T2, V2, C2,
                    oM2, oK2, oCa, oGr, ofg, oT2, oV2, oC2):
    """One cached step: the model at ``q0 + dl`` (:func:`held_matrices`, forces with their secant) and the
    interval's RK4 steps. Returns ``(z_next, M_r, K_r, C_r, G_r)``. NumPy reference of the compiled kernel."""
    r = Mr0.shape[0]
    old = (oM2, oK2, oCa, oGr) if has_old else None
    Mr, Kr, Cr, Gr = held_matrices(dl, s, Mr0, Kr0, Ca0, Gr0, dM2, dK2, beta, old)
    f = quadratic_forces(z[:r], z[r:], nq, fg, T2, V2, C2)
    if has_old:
        f = f + s * (f - quadratic_forces(z[:r], z[r:], nq, ofg, oT2, oV2, oC2))
    return rk4_held_numpy(z, u, Mr, Kr, Cr, Gr, f, h, n), Mr, Kr, Cr, Gr


@_shared
def power_sum(P, n):
    """``P^n`` and ``sum_{k<n} P^k`` by binary doubling (O(log n) products)."""
    m = P.shape[0]
    Pk, Sk = P.copy(), np.eye(m)  # P^1, S_1 = I
    Pn, Sn = np.eye(m), np.zeros((m, m))  # accumulators for n = 0
    bits = n
    while bits:
        if bits & 1:
            Sn = Sn + Pn @ Sk  # S_{a+b} = S_a + P^a S_b
            Pn = Pn @ Pk
        bits >>= 1
        if bits:
            Sk = Sk + Pk @ Sk
            Pk = Pk @ Pk
    return Pn, Sn


@_shared
def step_maps(Minv, Kr, Cr, Gr, h, n):
    """``(P^n, SQM, L)`` of ``n`` RK4 steps of ``M p'' + C p' + K p = G u + f`` with the inputs held: the
    state map, the response to a held generalised force and to held motor torques (``L = SQM G``)."""
    r = Kr.shape[0]
    nx = 2 * r
    A = np.zeros((nx, nx))
    A[:r, r:] = np.eye(r)
    A[r:, :r] = -(Minv @ Kr)
    A[r:, r:] = -(Minv @ Cr)
    hA = h * A
    hA2 = hA @ hA
    hA3 = hA2 @ hA
    I = np.eye(nx)
    P = I + hA + hA2 / 2 + hA3 / 6 + hA3 @ hA / 24
    Qm = h * (I + hA / 2 + hA2 / 6 + hA3 / 24)
    Pn, Sn = power_sum(P, n)
    SQM = (Sn @ np.ascontiguousarray(Qm[:, r:])) @ Minv
    return Pn, SQM, SQM @ Gr


def _times_hA(Ak, Ac, h, X):  # pragma: no cover - compiled
    """``h A X`` for ``A = [[0, I], [-Ak, -Ac]]``: the top half is ``h X_v``, only the bottom needs products."""
    r = Ak.shape[0]
    out = np.empty(X.shape)
    out[:r] = h * X[r:]
    out[r:] = -h * (Ak @ np.ascontiguousarray(X[:r]) + Ac @ np.ascontiguousarray(X[r:]))
    return out


def _step_maps_held(Mr, Kr, Cr, Gr, h, n, torque_var):  # pragma: no cover - compiled twin of the NumPy path
    """:func:`step_maps` from ``M_r`` (not its inverse), plus the process noise ``L diag(var) L^T``.

    The same maps with about half the arithmetic (it runs some 250 times per 3 s of the six-bar):

    - the RK4 polynomials share one Horner chain, ``U = I + hA/2 (I + hA/3 (I + hA/4))``, ``P = I + hA U``
      and ``Q = h U``, and a product with ``hA`` only has ``A``'s lower block row to compute;
    - ``P^n`` and the response ``S_n B`` (``S_n = sum_{k<n} P^k``, ``B = Q[:, r:] M^-1``) by binary powering
      from the leading bit, ``S_2a B = S_a B + P^a S_a B`` and ``S_a+1 B = B + P S_a B``: the sum is only
      ever multiplied as the thin ``S B`` (nx x r).
    """
    r = Mr.shape[0]
    nx = 2 * r
    Minv = _cholesky_solve(Mr, np.eye(r))
    Ak = Minv @ Kr
    Ac = Minv @ Cr
    I = np.eye(nx)
    W = I.copy()  # I + hA/4, written out: hA I = [[0, hI], [-hAk, -hAc]]
    for i in range(r):
        W[i, r + i] += 0.25 * h
        for j in range(r):
            W[r + i, j] += 0.25 * (-h * Ak[i, j])
            W[r + i, r + j] += 0.25 * (-h * Ac[i, j])
    V = I + _times_hA(Ak, Ac, h, W) / 3.0
    U = I + 0.5 * _times_hA(Ak, Ac, h, V)
    P = I + _times_hA(Ak, Ac, h, U)
    B = (h * np.ascontiguousarray(U[:, r:])) @ Minv
    Pa = P.copy()
    SB = B.copy()
    sq = np.empty((nx, nx))  # product buffers: the doubling allocates nothing
    th = np.empty((nx, r))
    top = 0
    while (n >> (top + 1)) > 0:
        top += 1
    for bit in range(top - 1, -1, -1):
        np.dot(Pa, SB, th)
        SB += th
        np.dot(Pa, Pa, sq)
        Pa, sq = sq, Pa
        if (n >> bit) & 1:
            np.dot(P, SB, th)
            for i in range(nx):
                for j in range(r):
                    SB[i, j] = B[i, j] + th[i, j]
            np.dot(P, Pa, sq)
            Pa, sq = sq, Pa
    L = SB @ Gr
    return Pa, SB, L, (L * torque_var) @ L.T


def step_maps_held_numpy(Mr, Kr, Cr, Gr, h, n, torque_var):
    """NumPy reference of the compiled :func:`_step_maps_held`."""
    Pn, SQM, L = step_maps(np.linalg.inv(Mr), Kr, Cr, Gr, h, n)
    return Pn, SQM, L, (L * torque_var) @ L.T


_times_hA = _shared(_times_hA)
step_maps_held = _jit(_step_maps_held) if HAVE_NUMBA else step_maps_held_numpy

_rk4_held_loops = _jit(_rk4_held_loops)
_quadratic_forces_loops = _jit(_quadratic_forces_loops)
rk4_held_loops = _rk4_held_loops
held_step_loops = _jit(_held_step_loops)
held_system_loops = _jit(_held_system_loops) if HAVE_NUMBA else held_system_numpy
map_lookahead = _shared(map_lookahead)
step_jacobian_loops = _jit(_step_jacobian_loops)
prediction_error_loops = _jit(_prediction_error_loops) if HAVE_NUMBA else prediction_error


_warm = False


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) the kernels once per process, so that the first
    interval of a filter does not carry it (about 0.1 s from the cache, 10 s the very first time)."""
    global _warm
    if _warm or not HAVE_NUMBA:
        return
    r, nq = 2, 1
    z, u, dl = np.zeros(2 * r), np.zeros(nq), np.zeros(nq)
    M, g2, f = np.eye(r), np.zeros((nq, r * r)), np.zeros(r)
    T2, V2, C2 = np.zeros((r, r * r)), np.zeros((nq * r, r)), np.zeros((r * nq, r))
    G = np.zeros((r, nq))
    held_step_loops(z, u, dl, 0.0, False, nq, 0.0, 1e-4, 1, M, M, M, G, g2, g2, f, T2, V2, C2, g2, g2, M, G, f, T2,
                    V2, C2)
    step_maps_held(M, M, M, G, 1e-4, 1, np.ones(nq))
    held_system_loops(dl, 0.0, False, 0.0, M, M, M, G, g2, g2, g2, g2, M, G)
    step_jacobian_loops(z, np.zeros((r, r, r)), np.zeros((nq, r, r)), np.zeros((r, nq, r)), np.eye(2 * r),
                        np.zeros((2 * r, r)))
    prediction_error_loops(dl, 0.0, False, M, M, g2, g2, g2, g2, M, M)
    _warm = True

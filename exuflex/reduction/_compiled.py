"""Compiled (numba) twins of the reduced model's per-configuration arithmetic that the cached observer runs at
every configuration evaluation (about 30 times per 3 s of the six-bar).

At the six-bar's size (42 nodal dofs, 9 elements, 13 reduced coordinates) the NumPy expressions of
:meth:`exuflex.reduction.model.ReducedModel.force_model` cost far more in call overhead and temporaries than in
arithmetic: some 80 NumPy calls on arrays of a few hundred entries. :func:`force_terms` and
:func:`basis_derivative`, :func:`basis_at` and :func:`reduced_matrices` (the twins of
:meth:`exuflex.reduction.basis.CraigBampton.basis_derivative` and ``at``, and of
:meth:`exuflex.reduction.model.ReducedModel.matrices` without the forces) do the same arithmetic in one compiled
call each; :func:`held_evaluation` does all of :meth:`~exuflex.reduction.model.ReducedModel.held` (the cached
observer's evaluation) in five such calls, sharing ``W J`` and ``M_N W J`` between the reduced matrices and the
force model. The NumPy methods stay the reference (and what runs without numba); ``tests/test_reduction.py``
checks that all three agree to rounding.

Compilation: numba compiles a kernel that another kernel calls once on its own and then again, with everything
it calls, inside each caller (its code is linked into the caller's and optimised and translated to machine code
there anew). So the large kernels are called from Python only (:func:`held_evaluation` chains them); a helper
called at one place is compiled into its caller (numba's ``inline="always"``, the ``_inline`` decorator), and a
small helper called at several places (the products with the 0/1 map, the pairs' rotations) is compiled once and
called (``_shared``): numba copies an inlined helper's whole code into every call site.
Every kernel is compiled with the same options (no C-callable wrapper, which nothing here uses): numba compiles
the NumPy functions a kernel uses once per set of options. Arrays are copied element by element rather than by
slice assignment, whose compiled shape check links numba's error-message formatting into the kernel.

This module imports without numba: ``HAVE_NUMBA`` is then False and nothing here is called.
"""

from __future__ import annotations

import math

import numpy as np

from ..erls._closure import coordinate_rates_inline, solve_columns

try:
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only on machines without numba
    numba = None
    HAVE_NUMBA = False

__all__ = ["HAVE_NUMBA", "basis_at", "basis_derivative", "force_terms", "held_evaluation", "reduced_matrices"]


def _w_product(W, t_index, X, nq):  # pragma: no cover - compiled
    """``W X`` for ``W = [S, T]`` (N, nq + ne): ``S`` dense (the first ``nq`` columns), ``T`` the 0/1 map with at
    most one 1 per row (in column ``nq + t_index[a]`` of row ``a``; -1: none). A dense product would spend
    nine tenths of its work on T's zeros."""
    N = W.shape[0]
    k = X.shape[1]
    out = np.empty((N, k))
    for a in range(N):
        u = t_index[a]
        for b in range(k):
            acc = 0.0
            for c in range(nq):
                acc += W[a, c] * X[c, b]
            if u >= 0:
                acc += X[nq + u, b]
            out[a, b] = acc
    return out


def _t_product(t_index, X):  # pragma: no cover - compiled
    """``T X`` (N, k) for the 0/1 map ``T`` (N, ne) of :func:`_w_product`: rows of ``X`` picked (zero where a
    nodal dof has no elastic coordinate); exact."""
    N = t_index.shape[0]
    k = X.shape[1]
    out = np.zeros((N, k))
    for a in range(N):
        u = t_index[a]
        if u >= 0:
            for b in range(k):
                out[a, b] = X[u, b]
    return out


def _product_t(X, t_index, ne):  # pragma: no cover - compiled
    """``X T`` (m, ne) for the 0/1 map ``T`` of :func:`_w_product`: columns of ``X`` summed into the elastic
    coordinate they belong to (at most two per coordinate on the six-bar: the same sums as a dense product)."""
    m = X.shape[0]
    out = np.zeros((m, ne))
    for b in range(t_index.shape[0]):
        u = t_index[b]
        if u >= 0:
            for a in range(m):
                out[a, u] += X[a, b]
    return out


def _tt_product(t_index, X, ne):  # pragma: no cover - compiled
    """``T^T X`` (ne, k) for the 0/1 map ``T`` of :func:`_w_product`: rows of ``X`` summed per elastic
    coordinate."""
    k = X.shape[1]
    out = np.zeros((ne, k))
    for a in range(t_index.shape[0]):
        u = t_index[a]
        if u >= 0:
            for b in range(k):
                out[u, b] += X[a, b]
    return out


def _element_form(X, el_dofs, R, Km, S_th, nq):  # pragma: no cover - compiled
    """``sum_e S_th[e, k] X_e^T R_e K_e R_e^T X_e`` (nq, r, r), ``X_e`` the element's rows of ``X`` (N, r) and
    ``K_e`` (``Km[e]``, 6 x 6) an element matrix in the element's frame. Loops: 6 x 6 blocks are too small for a
    BLAS call to pay."""
    n_el = el_dofs.shape[0]
    r = X.shape[1]
    out = np.zeros((nq, r, r))
    Ae = np.empty((6, r))
    KA = np.empty((6, r))
    E = np.empty((r, r))
    for e in range(n_el):
        for a in range(6):  # element frame: Ae = R_e^T X_e
            for j in range(r):
                acc = 0.0
                for b in range(6):
                    acc += R[e, b, a] * X[el_dofs[e, b], j]
                Ae[a, j] = acc
        for a in range(6):
            for j in range(r):
                KA[a, j] = 0.0
            for b in range(6):
                w = Km[e, a, b]
                for j in range(r):
                    KA[a, j] += w * Ae[b, j]
        for i in range(r):
            for j in range(r):
                E[i, j] = 0.0
            for a in range(6):
                w = Ae[a, i]
                for j in range(r):
                    E[i, j] += w * KA[a, j]
        for k in range(nq):
            w = S_th[e, k]
            if w != 0.0:
                for i in range(r):
                    for j in range(r):
                        out[k, i, j] += w * E[i, j]
    return out


def _element_vector(X, v, el_dofs, R, Km, S_th, nq):  # pragma: no cover - compiled
    """``sum_e S_th[e, k] X_e^T R_e K_e R_e^T v_e`` (nq, r): :func:`_element_form` with a vector ``v`` (N,) on the
    right (the weight's change with the element masses' rotation, ``v = g``, ``K_e`` the mass rotation rate)."""
    r = X.shape[1]
    out = np.zeros((nq, r))
    Ae = np.empty((6, r))
    kv = np.empty(6)
    for e in range(el_dofs.shape[0]):
        for a in range(6):  # element frame: K_e R_e^T v_e
            acc = 0.0
            for b in range(6):
                acc += R[e, b, a] * v[el_dofs[e, b]]
            kv[a] = acc
        for a in range(6):
            for j in range(r):
                acc = 0.0
                for b in range(6):
                    acc += R[e, b, a] * X[el_dofs[e, b], j]
                Ae[a, j] = acc
        for j in range(r):
            acc = 0.0
            for a in range(6):
                w = 0.0
                for b in range(6):
                    w += Km[e, a, b] * kv[b]
                acc += Ae[a, j] * w
            for k in range(nq):
                out[k, j] += S_th[e, k] * acc
    return out


def _mass_stiffness_gradients(W, t_index, J, H, Kuu, MWJ, SE, SEe, Sd3, dHdq, nq, Mg, gradients):
    # pragma: no cover - compiled
    """``(dM_r/dq, dK_r/dq, dW)``: the q-gradients (nq, r, r) of ``M_r`` and ``K_r`` from the element terms ``SE``
    (mass) and ``SEe`` (stiffness) of :func:`force_terms` (see
    :meth:`~exuflex.reduction.model.ReducedModel.mass_derivative_analytic`; empty without ``gradients``), and
    ``dW[i, b] = (d(W J)/dq_i e_b)^T M_N g`` (nq, r) with ``Mg = M_N g`` (empty ``Mg``: ``dW`` empty), the part of
    the weight's gradient through the velocity map (:meth:`~exuflex.reduction.model.ReducedModel.weight_gradient`)."""
    N, n = W.shape
    r = J.shape[1]
    ne = n - nq
    if not gradients:
        dMr = dKr = np.zeros((0, r, r))
        if Mg.shape[0] == 0:
            return dMr, dKr, np.zeros((0, r))
    if gradients:  # dK_r/dq_i = SEe + dH_u^T K_uu H_u + its transpose
        KH = Kuu @ np.ascontiguousarray(H[nq:])  # (ne, r)
        dKr = np.empty((nq, r, r))
        dHu = np.empty((r, ne))
        for i in range(nq):
            for a in range(r):
                for u in range(ne):
                    dHu[a, u] = dHdq[a, nq + u, i]
            dHK = dHu @ KH  # (r, r)
            for a in range(r):
                for b in range(r):
                    dKr[i, a, b] = SEe[i, a, b] + dHK[a, b] + dHK[b, a]
        dMr = np.empty((nq, r, r))
    # dM_r/dq_i = dWJ_i^T M_N WJ + its transpose + SE, with dWJ_i = dS/dq_i J_q + W dH/dq_i
    Jq = np.ascontiguousarray(J[:nq])
    dW = np.zeros((nq if Mg.shape[0] else 0, r))
    dH = np.empty((n, nq * r))  # [a, i r + b] = dH/dq_i e_b, row a: W dH/dq_i for all i in one product
    for i in range(nq):
        for a in range(n):
            for b in range(r):
                dH[a, i * r + b] = dHdq[b, a, i]
    WdH = _w_product(W, t_index, dH, nq)  # (N, nq r)
    dWJ = np.empty((N, r))
    for i in range(nq):
        for a in range(N):
            for b in range(r):
                acc = WdH[a, i * r + b]
                for c in range(nq):
                    acc += Sd3[i, a, c] * Jq[c, b]
                dWJ[a, b] = acc
        if Mg.shape[0]:
            for a in range(N):
                w = Mg[a]
                for b in range(r):
                    dW[i, b] += dWJ[a, b] * w
        if gradients:
            A = np.ascontiguousarray(dWJ.T) @ MWJ
            for a in range(r):
                for b in range(r):
                    dMr[i, a, b] = A[a, b] + A[b, a] + SE[i, a, b]
    return dMr, dKr, dW


def _force_terms(W, J, H, M_N, t_index, Kuu, g_N, R, Gl, KGl, el_dofs, S_th, Sd3, dHdq, nq, consistent, gradients):
    # pragma: no cover - compiled twin of ReducedModel.force_model
    """``(fg, Tk, V, JtM, dMr, dKr, C2, Ts, Vs, Wg)`` of :class:`~exuflex.reduction.model.QuadraticForces` (``Ts, Vs``:
    its :meth:`~exuflex.reduction.model.QuadraticForces.jacobian_tensors`; ``Wg``: the weight's gradient, empty
    without gravity, :meth:`~exuflex.reduction.model.ReducedModel.weight_gradient`), see
    :meth:`~exuflex.reduction.model.ReducedModel.force_model` for the formulas. ``Gl`` (n_el, 6, 6): the element
    mass rotation rate in the element frame; ``Sd3`` (nq, N, nq): ``dS/dq_j``; ``t_index``: the 0/1 part of
    ``W = [S, T]`` (:func:`_w_product`); without ``gradients`` ``dMr`` and ``dKr`` are empty."""
    WJ = _w_product(W, t_index, J, nq)  # (N, r)
    return _force_terms_shared(W, J, WJ, M_N @ WJ, H, M_N, t_index, Kuu, g_N, R, Gl, KGl, el_dofs, S_th, Sd3, dHdq,
                               nq, consistent, gradients)


def _force_terms_shared(W, J, WJ, MWJ, H, M_N, t_index, Kuu, g_N, R, Gl, KGl, el_dofs, S_th, Sd3, dHdq, nq,
                        consistent, gradients):  # pragma: no cover - compiled
    """:func:`_force_terms` with ``W J`` and ``M_N W J`` given (:func:`_held_evaluation` shares them with the
    reduced matrices)."""
    N, n = W.shape
    r = J.shape[1]
    SE = _element_form(WJ, el_dofs, R, Gl, S_th, nq)  # element mass rotation term (nq, r, r)
    # velocity force tensor T[k] = J^T (dh/dv)(J e_k) J
    Tk = np.zeros((r, r, r))
    for k in range(nq):
        for i in range(r):
            for j in range(r):
                Tk[k, i, j] += SE[k, i, j]
                Tk[j, i, k] += SE[k, i, j]
                Tk[j, k, i] -= SE[k, i, j]
    for k in range(nq):
        for j in range(nq):
            for i in range(r):
                acc = 0.0
                for a in range(N):
                    acc += MWJ[a, i] * (Sd3[j, a, k] + Sd3[k, a, j])
                Tk[k, i, j] += acc
    # q-row geometric term and the element part of dK_r/dq
    TH = _t_product(t_index, H[nq:])  # (N, r)
    SEe = _element_form(TH, el_dofs, R, KGl, S_th, nq)
    V = np.empty((nq, r, r))
    for k in range(nq):
        for i in range(r):
            for j in range(r):
                V[k, i, j] = 0.25 * (SEe[k, i, j] + SEe[k, j, i])
    WJt = np.ascontiguousarray(WJ.T)
    Mg = M_N @ g_N
    fg = WJt @ Mg
    weight = False
    for a in range(N):
        if g_N[a] != 0.0:
            weight = True
    if consistent:  # J^T M W = (W J)^T [M_N S, M_N T]
        MW = np.empty((N, n))
        MS = M_N @ np.ascontiguousarray(W[:, :nq])
        MT = _product_t(M_N, t_index, n - nq)
        for a in range(N):
            for b in range(nq):
                MW[a, b] = MS[a, b]
            for b in range(n - nq):
                MW[a, nq + b] = MT[a, b]
        JtM = WJt @ MW
    else:
        JtM = np.zeros((0, n))
    dMr, dKr, dW = _mass_stiffness_gradients(W, t_index, J, H, Kuu, MWJ, SE, SEe, Sd3, dHdq, nq,
                                             Mg if weight else np.zeros(0), gradients)
    # the weight's gradient in the positions, Wg[c, m] = d fg_c / dp_m (empty without gravity): through the
    # velocity map and the element masses' rotation in the q columns; the q rows' change with the elastic
    # coordinates through J = H + [d(H p)/dq, 0] (consistent form) in the elastic columns
    Wg = np.zeros((r if weight else 0, r if weight else 0))
    if weight:
        Ev = _element_vector(WJ, g_N, el_dofs, R, Gl, S_th, nq)
        for c in range(r):
            for i in range(nq):
                Wg[c, i] = dW[i, c] + Ev[i, c]
        if consistent:
            for c in range(nq):
                for m in range(nq, r):
                    Wg[c, m] = dW[c, m]
    # bias term: C[k, j, :] = J^T M W dH/dq_j e_k, flattened (r nq, r) and doubled
    if consistent:
        X = np.empty((n, r * nq))  # [a, k nq + j] = dHdq[k, a, j]
        for k in range(r):
            for a in range(n):
                for j in range(nq):
                    X[a, k * nq + j] = dHdq[k, a, j]
        JX = JtM @ X  # (r, r nq)
        C2 = np.empty((r * nq, r))
        for kj in range(r * nq):
            for c in range(r):
                C2[kj, c] = 2.0 * JX[c, kj]
    else:
        C2 = np.zeros((0, r))
    # the symmetrised forms of QuadraticForces.jacobian_tensors
    Ts = np.empty((r, r, r))
    for m in range(r):
        for i in range(r):
            for j in range(r):
                Ts[m, i, j] = Tk[m, i, j] + Tk[j, i, m]
    Vs = np.empty((nq, r, r))
    for k in range(nq):
        for i in range(r):
            for j in range(r):
                Vs[k, i, j] = V[k, i, j] + V[k, j, i]
    return fg, Tk, V, JtM, dMr, dKr, C2, Ts, Vs, Wg


if HAVE_NUMBA:
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy", no_cfunc_wrapper=True)
    _inline = numba.njit(inline="always", nogil=True, error_model="numpy")
    # the small products and rotations the kernels call at several places: compiled once and called there (a
    # helper inlined with inline="always" is copied into every call site)
    _shared = numba.njit(nogil=True, error_model="numpy", no_cfunc_wrapper=True)
    _w_product = _shared(_w_product)
    _t_product = _shared(_t_product)
    _product_t = _shared(_product_t)
    _tt_product = _inline(_tt_product)
    _element_form = _jit(_element_form)
    _element_vector = _inline(_element_vector)
    _mass_stiffness_gradients = _inline(_mass_stiffness_gradients)
    _force_terms_shared = _jit(_force_terms_shared)
    force_terms = _jit(_force_terms)
else:  # pragma: no cover
    force_terms = None


def _rotate_rows(X, px, py, c, s, inverse):  # pragma: no cover - compiled
    """``Q^T X`` in place (``inverse``: ``Q X``) for the pairs' rotation ``Q`` (cosine ``c``, sine ``s`` per pair)
    acting on the rows of ``X`` (ne, m)."""
    m = X.shape[1]
    for pp in range(px.shape[0]):
        x, y = px[pp], py[pp]
        cc = c[pp]
        ss = -s[pp] if inverse else s[pp]
        for j in range(m):
            A, Bv = X[x, j], X[y, j]
            X[x, j] = cc * A + ss * Bv
            X[y, j] = -ss * A + cc * Bv


def _turn(X, px, py, plocal, Sn, nq):  # pragma: no cover - compiled
    """``D_i X`` (ne, k nq), column ``kk nq + i``: G2 = [[0, -1], [1, 0]] on each link-frame pair of ``X`` (ne, k)
    times the pair's angle rate ``Sn[pair, i]`` (the derivative of ``Q`` applied to ``Q^T``)."""
    ne, k = X.shape
    out = np.zeros((ne, k * nq))
    for pp in range(px.shape[0]):
        if not plocal[pp]:
            continue
        x, y = px[pp], py[pp]
        for kk in range(k):
            for i in range(nq):
                out[x, kk * nq + i] = -X[y, kk] * Sn[pp, i]
                out[y, kk * nq + i] = X[x, kk] * Sn[pp, i]
    return out


def _basis_derivative(V, nq, ne, im, is_, B, t_index, el_dofs, R, KGl, S_th, Kss_inv, c, s, Phi_u, px, py, Sn,
                      Kuu, qc, qs, plocal, keep, has_local):
    # pragma: no cover - compiled twin of CraigBampton.basis_derivative
    """``d(H v)/dq`` for each column of ``V`` (k, n, nq); see
    :meth:`~exuflex.reduction.basis.CraigBampton.basis_derivative` for the formulas. ``c, s``: cosine and sine
    of the interior-mode node pairs' rotation from q*, ``Sn`` (pairs, nq) their angle sensitivities (zero rows for
    pairs that do not turn); ``t_index``: the map ``T`` from the elastic coordinates to the nodal dofs
    (:func:`_w_product`). Link-frame masters (``has_local``): ``qc, qs`` the pairs' frame rotation ``Q`` (1, 0
    for global pairs), ``plocal`` the link-frame pairs, ``keep`` the rows the interior modes' rotation enters
    (the slaves and the link-frame pairs), ``Kuu`` the elastic stiffness."""
    k = V.shape[1]
    me = im.shape[0]
    ns = is_.shape[0]
    n_el = el_dofs.shape[0]
    out = np.zeros((k, nq + ne, nq))
    # Guyan fields w = [u_m; B u_m], u = Q w, and their nodal displacements
    Vm = np.ascontiguousarray(V[nq : nq + me])
    W = np.zeros((ne, k))
    for a in range(me):
        for kk in range(k):
            W[im[a], kk] = Vm[a, kk]
    BV = B @ Vm
    for a in range(ns):
        for kk in range(k):
            W[is_[a], kk] = BV[a, kk]
    if has_local:
        _rotate_rows(W, px, py, qc, qs, True)
    d = _t_product(t_index, W)  # (N, k)
    # per element: R K_G R^T applied to the element's displacements, weighted by its angle sensitivities, and
    # summed into the elastic coordinates of its nodes (T^T of the scattered element vectors)
    Cu = np.zeros((ne, k * nq))
    dl = np.empty((6, k))
    kd = np.empty((6, k))
    for e in range(n_el):
        for a in range(6):  # element frame: R_e^T d_e
            for kk in range(k):
                acc = 0.0
                for b in range(6):
                    acc += R[e, b, a] * d[el_dofs[e, b], kk]
                dl[a, kk] = acc
        for a in range(6):
            for kk in range(k):
                acc = 0.0
                for b in range(6):
                    acc += KGl[e, a, b] * dl[b, kk]
                kd[a, kk] = acc
        for a in range(6):
            u = t_index[el_dofs[e, a]]
            if u < 0:
                continue
            for kk in range(k):
                acc = 0.0
                for b in range(6):
                    acc += R[e, a, b] * kd[b, kk]
                for i in range(nq):
                    Cu[u, kk * nq + i] += acc * S_th[e, i]
    if has_local:  # dK_w/dq_i w_G = Q^T (dK_uu/dq_i u_G + K_uu D_i u_G - D_i K_uu u_G)
        DW = _turn(W, px, py, plocal, Sn, nq)
        KDW = Kuu @ DW
        DKW = _turn(Kuu @ W, px, py, plocal, Sn, nq)
        for u in range(ne):
            for j in range(k * nq):
                Cu[u, j] += KDW[u, j]
        for u in range(ne):
            for j in range(k * nq):
                Cu[u, j] -= DKW[u, j]
        _rotate_rows(Cu, px, py, qc, qs, False)
    Cs = np.empty((ns, k * nq))
    for a in range(ns):
        for j in range(k * nq):
            Cs[a, j] = Cu[is_[a], j]
    dB = Kss_inv @ Cs  # (s, k nq), negated below
    if has_local:  # d(Q w_G)/dq_i = D_i u_G + Q (0; dB_w/dq_i w_m)
        dW = np.zeros((ne, k * nq))
        for a in range(ns):
            for j in range(k * nq):
                dW[is_[a], j] = -dB[a, j]
        _rotate_rows(dW, px, py, qc, qs, True)
        for u in range(ne):
            for kk in range(k):
                for i in range(nq):
                    out[kk, nq + u, i] = dW[u, kk * nq + i] + DW[u, kk * nq + i]
    else:
        for a in range(ns):
            row = nq + is_[a]
            for kk in range(k):
                for i in range(nq):
                    out[kk, row, i] = -dB[a, kk * nq + i]
    # rotated interior modes: d(Psi eta)/dq_i = G2 (R Phi eta) dtheta_node/dq_i per node pair
    if Phi_u.shape[1]:
        Wu = Phi_u @ np.ascontiguousarray(V[nq + me :])  # (ne, k) unrotated
        dU = np.zeros((ne, k, nq))
        for pp in range(px.shape[0]):
            x, y = px[pp], py[pp]
            for kk in range(k):
                X, Y = Wu[x, kk], Wu[y, kk]
                RX = c[pp] * X - s[pp] * Y
                RY = s[pp] * X + c[pp] * Y
                for i in range(nq):
                    dU[x, kk, i] = -RY * Sn[pp, i]
                    dU[y, kk, i] = RX * Sn[pp, i]
        for u in range(ne):
            if keep[u]:
                for kk in range(k):
                    for i in range(nq):
                        out[kk, nq + u, i] += dU[u, kk, i]
    return out


if HAVE_NUMBA:
    _rotate_rows = _shared(_rotate_rows)
    _turn = _shared(_turn)
    basis_derivative = _jit(_basis_derivative)
    _basis_derivative_inline = _inline(_basis_derivative)
else:  # pragma: no cover
    basis_derivative = None


def _basis_at(K_N, t_index, ne, nq, im, is_, Phi_u, px, py, c, s, qc, qs, has_local):
    # pragma: no cover - compiled twin of CraigBampton.at
    """``(K_uu, B, K_ss^-1, Psi, H)`` of :meth:`~exuflex.reduction.basis.CraigBampton.at` from the assembled
    nodal stiffness: ``K_uu = T^T K_N T`` (``t_index``: the map ``T``, :func:`_w_product`), Guyan shapes
    ``B = -K_ss^-1 K_sm`` of ``K_w = Q^T K_uu Q``, interior modes rotated per node pair (``c, s``: cosine and sine
    of the pairs' rotation from q*) and the basis ``H = Q H_w`` (nq + ne, r); ``qc, qs``: the pairs' frame rotation
    ``Q`` (link-frame masters, ``has_local``; 1, 0 for global pairs)."""
    me = im.shape[0]
    ns = is_.shape[0]
    ki = Phi_u.shape[1]
    Kuu = _tt_product(t_index, _product_t(K_N, t_index, ne), ne)
    Kw = Kuu
    if has_local:  # Q^T K_uu Q: rows, then columns (K_uu symmetric)
        Kw = Kuu.copy()
        _rotate_rows(Kw, px, py, qc, qs, False)
        Kw = np.ascontiguousarray(Kw.T)
        _rotate_rows(Kw, px, py, qc, qs, False)
    Kss = np.empty((ns, ns))
    Ksm = np.empty((ns, me))
    for a in range(ns):
        for b in range(ns):
            Kss[a, b] = Kw[is_[a], is_[b]]
        for b in range(me):
            Ksm[a, b] = Kw[is_[a], im[b]]
    Kinv = np.linalg.inv(Kss)
    B = -(Kinv @ Ksm)
    P = Phi_u.copy()
    for pp in range(px.shape[0]):
        x, y = px[pp], py[pp]
        for j in range(ki):
            X, Y = Phi_u[x, j], Phi_u[y, j]
            P[x, j] = c[pp] * X - s[pp] * Y
            P[y, j] = s[pp] * X + c[pp] * Y
    if has_local:
        _rotate_rows(P, px, py, qc, qs, False)
    Psi = np.empty((ns, ki))
    for a in range(ns):
        for j in range(ki):
            Psi[a, j] = P[is_[a], j]
    r = nq + me + ki
    H = np.zeros((nq + ne, r))
    for i in range(nq):
        H[i, i] = 1.0
    if has_local:
        Hw = np.zeros((ne, r - nq))
        for a in range(me):
            Hw[im[a], a] = 1.0
        for a in range(ns):
            for b in range(me):
                Hw[is_[a], b] = B[a, b]
            for j in range(ki):
                Hw[is_[a], me + j] = Psi[a, j]
        _rotate_rows(Hw, px, py, qc, qs, True)
        for a in range(ne):
            for b in range(r - nq):
                H[nq + a, nq + b] = Hw[a, b]
        return Kuu, B, Kinv, Psi, H
    for a in range(me):
        H[nq + im[a], nq + a] = 1.0
    for a in range(ns):
        row = nq + is_[a]
        for b in range(me):
            H[row, nq + b] = B[a, b]
        for j in range(ki):
            H[row, nq + me + j] = Psi[a, j]
    return Kuu, B, Kinv, Psi, H


def _reduced_matrices(p, pd, H, dHdq, W, M_N, K_N, Kuu, t_index, B_N, alpha, beta, nq, consistent):
    # pragma: no cover - compiled twin of ReducedModel.matrices (forces=False, dHdq given)
    """``(J, M_r, K_r, C_r, G_r)`` of :meth:`~exuflex.reduction.model.ReducedModel.matrices` without the
    forces: ``J = H + [d(H p)/dq, 0]`` (consistent form) and the reduced matrices (``t_index``: the 0/1 part of
    ``W = [S, T]``, :func:`_w_product`)."""
    J, _, _, Mr, Kr, Cr, Gr = _reduced_terms(p, H, dHdq, W, M_N, K_N, Kuu, t_index, B_N, alpha, beta, nq,
                                             consistent)
    return J, Mr, Kr, Cr, Gr


def _strain_rate_columns(TJ, p, Hu, W, t_index, nq):  # pragma: no cover - compiled
    """Subtract in place from the rigid columns of ``T J_u`` (N, r) the nodal rates of the elastic displacement
    ``d = T H_u p`` turned with the links, ``Y(d)`` (:meth:`~exuflex.erls.model.ErlsModel.turned_rates`:
    ``(G3 d)_n`` times the rate of node n's link, the rows ``3 n + 2`` of ``S = W[:, :nq]``), so that ``T J_u p' -
    Y q'`` is the strain rate."""
    u = Hu @ p
    for a in range(TJ.shape[0]):
        comp = a % 3
        if comp == 2:
            continue
        b = a + 1 if comp == 0 else a - 1  # (G3 d)_x = -d_y, (G3 d)_y = d_x
        ib = t_index[b]
        if ib < 0:
            continue
        g = -u[ib] if comp == 0 else u[ib]
        row = 3 * (a // 3) + 2
        for j in range(nq):
            TJ[a, j] -= g * W[row, j]


def _reduced_terms(p, H, dHdq, W, M_N, K_N, Kuu, t_index, B_N, alpha, beta, nq, consistent):  # pragma: no cover
    """``(J, W J, M_N W J, M_r, K_r, C_r, G_r)``: :func:`_reduced_matrices` with the two products the force
    model shares (:func:`_held_evaluation`). The damping (consistent form, deformed ``p``) on the strain rate
    ``T J_u p' - Y q'`` (:func:`_strain_rate_columns`)."""
    n, r = H.shape
    J = H.copy()
    if consistent:
        for a in range(n):
            for i in range(nq):
                acc = 0.0
                for k in range(r):
                    acc += p[k] * dHdq[k, a, i]
                J[a, i] += acc
    WJ = _w_product(W, t_index, J, nq)
    MWJ = M_N @ WJ
    WJt = np.ascontiguousarray(WJ.T)
    Mr = WJt @ MWJ
    Hu = np.ascontiguousarray(H[nq:])
    Ju = np.ascontiguousarray(J[nq:])
    JtK = np.ascontiguousarray(Ju.T) @ Kuu
    Kr = JtK @ Hu
    if alpha != 0.0 or beta != 0.0:
        TJ = _t_product(t_index, Ju)
        turned = False
        if consistent:
            for k in range(nq, r):
                if p[k] != 0.0:
                    turned = True
        if turned:
            _strain_rate_columns(TJ, p, Hu, W, t_index, nq)
        TJt = np.ascontiguousarray(TJ.T)
        MS = M_N @ np.ascontiguousarray(W[:, :nq])
        X = TJt @ MS  # alpha M_e = alpha (T^T M_N T - M_uq M_qq^-1 M_qu), ErlsModel.elastic_mass
        Mqq = np.ascontiguousarray(W[:, :nq].T) @ MS
        Cr = alpha * (TJt @ (M_N @ TJ) - X @ solve_columns(Mqq, np.ascontiguousarray(X.T)))
        if turned:
            Cr += beta * (TJt @ (K_N @ TJ))
        else:
            Cr += beta * (JtK @ Ju)
    else:
        Cr = np.zeros((r, r))
    Gr = WJt @ B_N
    return J, WJ, MWJ, Mr, Kr, Cr, Gr


if HAVE_NUMBA:
    basis_at = _jit(_basis_at)
    _basis_at_inline = _inline(_basis_at)
    _strain_rate_columns = _inline(_strain_rate_columns)
    _reduced_terms = _inline(_reduced_terms)
    reduced_matrices = _jit(_reduced_matrices)
else:  # pragma: no cover
    basis_at = reduced_matrices = None


def _pair_rotations(r_nodes, S, Sz, pnode, plocal, theta_star, el_link, nq, rotate):  # pragma: no cover - compiled
    """``(c, s, qc, qs, Sn, S_th)`` at a pose: cosine and sine of every interior-mode node pair's rotation from
    q* (zero where the modes do not turn: ``rotate`` False and the pair in the global frame), its frame rotation
    ``Q`` (link-frame pairs ``plocal``: the angle of their node ``pnode``; 1, 0 for global pairs), the angle
    sensitivities ``d theta_node / dq`` of the pairs that turn, and the element angle sensitivities (``r_nodes``,
    ``S``: nodal poses and sensitivities; ``Sz``: the link poses' sensitivities; ``theta_star``: the nodal angles
    at q*)."""
    n_pairs = pnode.shape[0]
    c = np.empty(n_pairs)
    s = np.empty(n_pairs)
    qc = np.ones(n_pairs)
    qs = np.zeros(n_pairs)
    Sn = np.zeros((n_pairs, nq))  # d theta_node / dq of every pair
    for pp in range(n_pairs):
        node = pnode[pp]
        th = 0.0
        if rotate or plocal[pp]:
            th = r_nodes[3 * node + 2] - theta_star[node]
            for i in range(nq):
                Sn[pp, i] = S[3 * node + 2, i]
        if plocal[pp]:
            qc[pp] = math.cos(r_nodes[3 * node + 2])
            qs[pp] = math.sin(r_nodes[3 * node + 2])
        c[pp] = math.cos(th)
        s[pp] = math.sin(th)
    S_th = np.empty((el_link.shape[0], nq))  # element angle sensitivities
    for e in range(el_link.shape[0]):
        for i in range(nq):
            S_th[e, i] = Sz[3 * el_link[e] + 2, i]
    return c, s, qc, qs, Sn, S_th


def _held_matrices(p, H, dHdq, K_N, Kuu, M_N, W, z, Sz, Jinv, closure, node_link, node_station, t_index, B_N,
                   alpha, beta, nq, consistent):  # pragma: no cover - compiled
    """``(J, W J, M_N W J, M_r, K_r, C_r, G_r, dS/dq)`` from the basis ``H`` and its derivative ``dHdq`` at a
    pose: the reduced matrices (:func:`reduced_matrices`) with the two products the force model shares, and
    ``dS/dq`` (:func:`exuflex.erls._closure.coordinate_rates`; arguments: see :func:`held_evaluation`)."""
    J, WJ, MWJ, Mr, Kr, Cr, Gr = _reduced_terms(p, H, dHdq, W, M_N, K_N, Kuu, t_index, B_N, alpha, beta, nq,
                                                consistent)
    Sd3 = coordinate_rates_inline(z, Sz, Jinv, closure, node_link, node_station)
    return J, WJ, MWJ, Mr, Kr, Cr, Gr, Sd3


if HAVE_NUMBA:
    pair_rotations = _jit(_pair_rotations)
    held_matrices = _jit(_held_matrices)
else:  # pragma: no cover
    pair_rotations = held_matrices = None


def held_evaluation(p, K_N, M_N, R, W, z, Sz, r_nodes, S, Jinv, closure, node_link, node_station,
                    t_index, im, is_, Phi_u, px, py, pnode, plocal, keep, theta_star, B_N, g_N, Gl, KGl, el_dofs,
                    el_link, alpha, beta, nq, rotate, has_local, consistent, gradients):
    """``(K_uu, B, K_ss^-1, Psi, H, J, M_r, K_r, C_r, G_r, fg, Tk, V, dMr, dKr, C2, Ts, Vs, Wg, dHdq)``: what
    :meth:`~exuflex.reduction.model.ReducedModel.held` computes (without ``fr``) from a full configuration: the
    pairs' rotations (:func:`pair_rotations`), the basis at q (:func:`basis_at`), its derivative for every reduced
    coordinate (:func:`basis_derivative`), the reduced matrices (:func:`held_matrices`) and the force model
    (:func:`force_terms` without ``JtM``, with ``W J`` and ``M_N W J`` shared).
    ``z, Sz, r_nodes, S, Jinv``: the pose's link poses and sensitivities, nodal poses and sensitivities and
    closure Jacobian inverse; ``closure`` (:class:`exuflex.erls._closure.ClosureArrays`), ``node_link``,
    ``node_station``: the kinematics' arrays; ``pnode``, ``theta_star``: the node of every interior-mode pair and
    the nodal angles at q* (``rotate`` False: the modes do not turn,
    :attr:`~exuflex.reduction.basis.CraigBampton.rotate`); ``plocal``, ``keep``, ``has_local``: the link-frame
    pairs (:func:`basis_derivative`), which turn with the angle of their node ``pnode`` always.

    Five compiled calls from Python rather than one kernel calling the others: numba compiles a kernel that
    another kernel calls once on its own and again inside its caller (and :func:`basis_at` and
    :func:`basis_derivative` are called from Python as well)."""
    ne = Phi_u.shape[0]
    c, s, qc, qs, Sn, S_th = pair_rotations(r_nodes, S, Sz, pnode, plocal, theta_star, el_link, nq, rotate)
    Kuu, B, Kinv, Psi, H = basis_at(K_N, t_index, ne, nq, im, is_, Phi_u, px, py, c, s, qc, qs, has_local)
    dHdq = basis_derivative(np.eye(H.shape[1]), nq, ne, im, is_, B, t_index, el_dofs, R, KGl, S_th, Kinv, c, s,
                            Phi_u, px, py, Sn, Kuu, qc, qs, plocal, keep, has_local)
    J, WJ, MWJ, Mr, Kr, Cr, Gr, Sd3 = held_matrices(p, H, dHdq, K_N, Kuu, M_N, W, z, Sz, Jinv, closure, node_link,
                                                     node_station, t_index, B_N, alpha, beta, nq, consistent)
    fg, Tk, V, _, dMr, dKr, C2, Ts, Vs, Wg = _force_terms_shared(W, J, WJ, MWJ, H, M_N, t_index, Kuu, g_N, R, Gl,
                                                                 KGl, el_dofs, S_th, Sd3, dHdq, nq, consistent,
                                                                 gradients)
    return Kuu, B, Kinv, Psi, H, J, Mr, Kr, Cr, Gr, fg, Tk, V, dMr, dKr, C2, Ts, Vs, Wg, dHdq


if not HAVE_NUMBA:  # pragma: no cover
    held_evaluation = None

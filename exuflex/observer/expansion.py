"""The reduced model expanded about a held configuration, and the RK4 steps of its linear system (compiled).

The cached step (:class:`exuflex.observer.reduced.ReducedObserverModel`) holds the reduced model at a
configuration ``q0`` and follows the links from there: ``M_r`` and ``K_r`` to second order in ``q - q0`` (their
analytic gradients at ``q0``, and the change of the gradients since the previous held configuration along the
line joining the two), the damping, input matrix and velocity-dependent forces to first order along that line
(a secant). The held arrays are those of the configuration undeformed, and the matrices follow the elastic
coordinates to first order, the damping to second (the consistent velocity map ``J`` is linear in them, the
matrices at most quadratic: :func:`_elastic_terms`);
held at a deformed state instead, the mass-proportional damping and ``M_r`` would keep that state's elastic
coordinates for the whole radius, and the secant's differences would mix the change of the elastic
coordinates between two evaluations into the change with ``q``. Per interval it then advances the linear system ``M p'' + C p' + K p = G u + f`` (forces and input
held, as the paper's RK4 does between two samples) by ``n`` RK4 sub-steps. :class:`HeldSystem` names the held
arrays the kernels read.

These kernels are the only implementation; ``tests/_oracles.py`` keeps NumPy expressions of the same algebra as
independent oracles (``tests/test_expansion.py``).
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np

from .base import GENERAL, LOOP_DONE, REFRESH, REMAP, ROWS
from .kalman import step_statistic

__all__ = [
    "NO_DISTURBANCES",
    "NO_PAYLOAD",
    "NO_SCALED_MAP",
    "CachedStep",
    "HeldSystem",
    "LoopExtras",
    "LoopMap",
    "LoopState",
    "cached_interval",
    "cached_rows",
    "extra_interval",
    "held_interval",
    "held_ramp",
    "held_step",
    "held_system",
    "map_error",
    "map_lookahead",
    "measurement_rows",
    "motion_form_gradient",
    "motion_forces",
    "motion_gradient",
    "motion_rates",
    "motion_stiffness",
    "next_map_radius",
    "payload_interval",
    "position_forces",
    "power_sum",
    "prediction_error",
    "rebuild_map",
    "scaled_steps",
    "secant_factor",
    "step_jacobian",
    "step_maps",
    "step_maps_noise",
    "warm_up",
    "warm_up_held",
    "warm_up_interval",
    "warm_up_maps",
]

log = logging.getLogger(__name__)


class HeldSystem(NamedTuple):
    """The held configuration's arrays (``r`` reduced coordinates, ``nq`` rigid ones), and its secant partner's.

    The arrays are those of the configuration undeformed (elastic coordinates zero): ``M_r``, ``K_r``, ``G_r`` and
    ``Ca = C_r - beta K_r`` (the damping's mass-proportional part; the stiffness part follows ``K_r``) at ``q0``;
    ``dM``, ``dK`` (nq, r*r) the q-gradients of ``M_r`` and ``K_r``; ``fg``, ``T2``, ``V2``, ``C2`` the
    velocity-dependent forces as quadratic forms (:class:`exuflex.reduction.model.QuadraticForces`). ``old_*``: the
    same of the previous held configuration (the secant partner; the held configuration's own arrays when
    ``has_old`` is False). ``pM``, ``pK``, ``pC`` (r - nq, nq*r) and ``pG`` (r - nq, nq*(n_motors + 1)): the
    matrices' change with the elastic coordinates (:func:`_elastic_terms`; ``pG``'s last column the weight's;
    empty: none), ``p2C`` (nq (nq + 1) / 2, n (n + 1) / 2; ``n = r - nq``) the damping's second-order rigid block,
    packed by symmetry (:meth:`.ReducedModel.elastic_forms`). ``Wg`` (r, r): the weight's gradient in the positions, ``d fg / dp``
    (:meth:`exuflex.reduction.model.ReducedModel.weight_gradient`; its q rows' elastic columns are ``pG``'s last
    column): the weight follows ``q`` by it over the radius, and with a secant partner by the gradient's change
    along the secant too, from the partner's ``old_Wg`` (:func:`_held_model`: second order), and the step Jacobian
    holds it (:func:`_step_jacobian`); empty (0, 0) without gravity, where both are the held arrays' alone.
    ``pT`` (r - nq, r^3) and ``pC2`` (r - nq, r nq r): the velocity forms' change per unit elastic coordinate,
    ``d T / dp_m`` and ``d C2 / dp_m`` flattened as ``T2`` and ``C2`` (:meth:`.ReducedObserverModel._velocity_forms`;
    empty (0, 0): none), which the held forces add to first order (:func:`_velocity_terms`).
    ``KGd`` (k, r*r): the geometric stiffness of the motion's axial loads as a linear form in ``[1, u, (q'_a
    q'_b)_{a <= b}]`` (:meth:`exuflex.reduction.model.ReducedModel.motion_geometric`, flattened; empty (0, 0):
    none), which each interval contracts with its torques and start rates and holds as a force (:func:`_motion_forces`).
    ``We`` (r - nq, nq*nq): the weight's q rows differentiated in q and in each elastic coordinate,
    ``d^2 fg_i / dq_j dp_m`` at ``[m, i*nq + j]`` (:meth:`exuflex.reduction.model.ReducedModel.weight_curvature`;
    empty (0, 0): none): the held weight's q-gradient at a deformed state (the sag) is ``Wg + sum_m p_m We[m]``
    (:func:`_held_model`, :func:`_weight_curvature_forces`). ``dKGd`` (k, nq*r*r): ``KGd``'s q-gradient under
    gravity (:meth:`exuflex.reduction.model.ReducedModel.motion_geometric_gradient`; empty (0, 0): none): the form
    at ``q0 + dl`` is ``KGd + dKGd . dl`` (:func:`_motion_form`), so the geometric stiffness follows q at the
    interval's torques, not at the holding ones the static part's gradient carries. ``dT2`` (nq*r, r*r), ``dV2``
    (nq*nq*r, r), ``dC2`` (nq*r*nq, r; empty in the paper's form): ``T2``, ``V2``, ``C2`` differentiated in each
    ``q_i``, stacked over ``i`` (:meth:`exuflex.reduction.model.ReducedModel.velocity_forms_gradient`; empty (0, 0):
    none, as without gravity): the forms follow ``q`` by them to first order instead of along the secant
    (:func:`_held_model`), and the step Jacobian's q columns hold the forces they give (:func:`_forms_gradient`).
    ``Me`` (r - nq, nq*nq*r): ``M_r`` differentiated in ``q_i`` and in each elastic coordinate ``p_m``, its rigid
    rows ``X`` at ``[m, (i*nq + a)*r + b]`` (``d^2 M_r / dq_i dp_m = X + X^T``,
    :meth:`exuflex.reduction.model.ReducedModel.mass_curvature`; empty (0, 0): none, as without gravity): the held
    ``M_r`` at ``q0 + dl`` with the elastic coordinates ``p`` gains ``sum_mi p_m dl_i (X + X^T)``
    (:func:`_mass_curvature_terms`), so that its q-gradient at the sag, which the step Jacobian holds
    (:func:`_mass_curvature_forces`), is the mass matrix's there.
    """

    has_old: bool
    beta: float
    Mr: np.ndarray
    Kr: np.ndarray
    Ca: np.ndarray
    Gr: np.ndarray
    dM: np.ndarray
    dK: np.ndarray
    fg: np.ndarray
    T2: np.ndarray
    V2: np.ndarray
    C2: np.ndarray
    old_dM: np.ndarray
    old_dK: np.ndarray
    old_Ca: np.ndarray
    old_Gr: np.ndarray
    old_fg: np.ndarray
    old_T2: np.ndarray
    old_V2: np.ndarray
    old_C2: np.ndarray
    pM: np.ndarray
    pK: np.ndarray
    pC: np.ndarray
    pG: np.ndarray
    p2C: np.ndarray
    Wg: np.ndarray
    old_Wg: np.ndarray
    pT: np.ndarray
    pC2: np.ndarray
    KGd: np.ndarray
    We: np.ndarray
    dKGd: np.ndarray
    dT2: np.ndarray
    dV2: np.ndarray
    dC2: np.ndarray
    Me: np.ndarray


try:  # numba is a core dependency; without it the kernels run as plain (slow) Python
    import numba
    import numba.extending

    def _jit(f):
        return numba.njit(cache=True, nogil=True, error_model="numpy", no_cfunc_wrapper=True)(f)

    def _shared(f):
        """Plain NumPy function outside compiled code, compiled inline where a kernel calls it."""
        return numba.extending.register_jitable(f)

    def _linked(f):
        """A large helper compiled once per process as a function of its own and linked into each kernel that
        calls it (LLVM optimises it there again, but numba types and lowers it once): inlined (:func:`_inline`),
        its whole code would be copied to every call site."""
        return numba.njit(nogil=True, error_model="numpy", no_cfunc_wrapper=True)(f)

    def _inline(f):
        """A helper compiled into each kernel that calls it (numba's ``inline="always"``), not as a kernel of its
        own: a separately compiled kernel is compiled once on its own and optimised again inside every caller."""
        return numba.njit(inline="always", nogil=True, error_model="numpy", no_cfunc_wrapper=True)(f)

except ImportError:  # pragma: no cover

    def _jit(f):
        return f

    _shared = _inline = _linked = _jit


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
def _substitute_row(X, L, i, lo, hi, transpose):  # pragma: no cover - compiled
    """Row ``i`` of a triangular solve in place: ``X[i] = (X[i] - sum_k l_k X[k]) / L[i, i]`` over the solved
    rows ``lo <= k < hi``, with ``l_k = L[i, k]`` (forward, ``L Y = B``) or ``L[k, i]`` (``transpose``: backward,
    ``L^T X = Y``); an axpy over the columns per row."""
    m = X.shape[1]
    for k in range(lo, hi):
        lk = L[k, i] if transpose else L[i, k]
        for c in range(m):
            X[i, c] -= lk * X[k, c]
    d = 1.0 / L[i, i]
    for c in range(m):
        X[i, c] *= d


@_shared
def _cholesky_solve(A, B):  # pragma: no cover - compiled
    """``A^-1 B`` for a symmetric positive definite ``A`` (a reduced mass matrix); NaN if it is not."""
    r = A.shape[0]
    L, ok = _cholesky_factor(A)
    if not ok:
        return np.full(B.shape, np.nan)
    X = B.copy()
    for i in range(r):  # forward: L Y = B, row i of Y from the rows above
        _substitute_row(X, L, i, 0, i, False)
    for i in range(r - 1, -1, -1):  # backward: L^T X = Y, row i from the rows below
        _substitute_row(X, L, i, i + 1, r, True)
    return X


def _ramps(du):  # pragma: no cover - compiled
    """Whether the input changes over the interval (``du`` not all zero: a linear input, :func:`_rk4_linear`)."""
    for j in range(du.shape[0]):
        if du[j] != 0.0:
            return True
    return False


def _rk4_linear(z, u, du, Mr, Kr, Cr, Gr, f, h, n):  # pragma: no cover - compiled
    """``n`` RK4 steps of ``h`` of ``M p'' + C p' + K p = G u(t) + f`` from ``z = [p; p']`` (NaN if ``M`` is not
    positive definite), the input linear over the interval ``T = n h``: ``u(t) = u + (t / T) du`` (``du`` zero or
    empty: held). Each stage takes the input at its own time (``t = i h``, ``+ h/2``, ``+ h``): RK4's order holds for an
    input linear in time, whereas the input held at its start errs by ``G du / 2`` on average, a first-order lag
    of half an interval (docs/held_step.md, "The input over a sample interval")."""
    r = Mr.shape[0]
    ramp = _ramps(du)
    nc = 2 * r + 2 if ramp else 2 * r + 1
    rhs = np.empty((r, nc))
    for i in range(r):  # element copies, not slice assignments (whose shape check links numba's message code)
        for j in range(r):
            rhs[i, j] = Kr[i, j]
            rhs[i, r + j] = Cr[i, j]
        acc = f[i]
        for j in range(u.shape[0]):
            acc += Gr[i, j] * u[j]
        rhs[i, 2 * r] = acc
        if ramp:  # the input's rate over the interval
            acc = 0.0
            for j in range(du.shape[0]):
                acc += Gr[i, j] * du[j]
            rhs[i, 2 * r + 1] = acc / (h * n)
    X = _cholesky_solve(Mr, rhs)
    # the vectors padded with zeros to a whole number of SIMD lanes: the sweeps then have no scalar remainder;
    # the padding stays zero
    rp = (r + 3) // 4 * 4
    XT = np.zeros((nc, rp))  # column j of the operator is the contiguous row XT[j]
    for i in range(r):
        for j in range(nc):
            XT[j, i] = X[i, j]
    b = XT[2 * r]
    b1 = XT[nc - 1]  # (ramp: M^-1 G du / T)
    p = np.zeros(rp)
    v = np.zeros(rp)
    for i in range(r):
        p[i] = z[i]
        v[i] = z[r + i]
    a = np.empty(rp)  # stage acceleration
    w = np.empty(rp)  # stage velocity
    yp = np.empty(rp)  # stage position
    asum = np.empty(rp)  # weighted sums of the stage rates (1, 2, 2, 1)
    wsum = np.empty(rp)
    for step in range(n):
        for st in range(4):
            c = 0.0 if st == 0 else 0.5 * h if st < 3 else h
            if st == 0:  # stage st at (p + c w_{st-1}, v + c a_{st-1})
                for i in range(rp):
                    yp[i] = p[i]
                    w[i] = v[i]
            else:
                for i in range(rp):
                    yp[i] = p[i] + c * w[i]
                    w[i] = v[i] + c * a[i]
            # a = b - X_K yp - X_C w, as axpy sweeps over contiguous rows, a position and a velocity column
            # per sweep (independent lanes: no serial add chain)
            if ramp:  # the input at the stage's time
                ts = step * h + c
                for i in range(rp):
                    a[i] = b[i] + ts * b1[i]
            else:
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
    for i in range(r):
        out[i] = p[i]
        out[r + i] = v[i]
    return out


def _quadratic_forces(p, pd, nq, fg, T2, V2, C2):  # pragma: no cover - compiled
    """``f = fg - 1/2 (p' T p') - [p V_i p]_i - C(p' (x) q')`` (:class:`exuflex.reduction.model.QuadraticForces`)."""
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


def _velocity_terms(pe, pd, nq, pT, pC2, f, G):  # pragma: no cover - compiled
    """Add to ``f`` (in place) the velocity forces' first order in the elastic coordinates ``pe``: ``-sum_m pe_m (1/2
    (p' pT_m p') + (p' (x) q') pC2_m)`` (:class:`HeldSystem`'s ``pT``, ``pC2``: the forms ``T2``, ``C2``
    differentiated in ``p_m``), and with ``G`` not empty (r, 2r) its derivative in the state into ``G``: the
    forces per unit ``p_m`` in position column ``nq + m``, and their change with the rates in the rate columns.

    The held forms are those of the configuration undeformed; the velocity map ``J = H + [d(H p)/dq, 0]`` is linear
    in the elastic coordinates and the forms are polynomials in ``J``, so at a deformed state the velocity forces
    gain terms of first order in them times the rates squared: a link turning while bent, its deflection's velocity
    turning with it (``J^T h(J p')`` and the bias force ``J^T M a_b``, both through ``J``)."""
    r = pd.shape[0]
    n_el = pT.shape[0]
    rr = r * r
    w = np.empty(rr)  # p'_k p'_j
    for k in range(r):
        for j in range(r):
            w[k * r + j] = pd[k] * pd[j]
    jac = G.shape[0] > 0
    Te = np.zeros(r * rr) if jac else np.zeros(0)  # sum_m pe_m pT_m (for the rate columns)
    Ce = np.zeros(r * nq * r) if jac else np.zeros(0)
    for m in range(n_el):
        e = pe[m]
        if e == 0.0 and not jac:
            continue
        for i in range(r):  # g_i: the forces per unit p_m
            acc = 0.0
            for k in range(r):
                base = k * rr + i * r
                for j in range(r):
                    acc += pT[m, base + j] * w[k * r + j]
            g = -0.5 * acc
            for k in range(r):
                for j in range(nq):
                    g -= pC2[m, (k * nq + j) * r + i] * w[k * r + j]
            f[i] += e * g
            if jac:
                G[i, nq + m] += g
        if jac and e != 0.0:
            for t in range(r * rr):
                Te[t] += e * pT[m, t]
            for t in range(r * nq * r):
                Ce[t] += e * pC2[m, t]
    if jac:  # d/dp'_a of -1/2 p' Te p' and of -sum p'_k p'_j Ce[k, j] (j < nq)
        for i in range(r):
            for a in range(r):
                acc = 0.0
                for j in range(r):
                    acc += (Te[a * rr + i * r + j] + Te[j * rr + i * r + a]) * pd[j]
                d = -0.5 * acc
                for j in range(nq):
                    d -= Ce[(a * nq + j) * r + i] * pd[j]
                if a < nq:
                    for k in range(r):
                        d -= Ce[(k * nq + a) * r + i] * pd[k]
                G[i, r + a] += d


@_inline
def _along(dl, dA, dB):  # pragma: no cover - compiled
    """The changes ``sum_i dl_i dA[i]`` and ``sum_i dl_i dB[i]`` of two matrices (rows of ``dA``, ``dB``: their
    flattened q-gradients) for the step ``dl`` in q."""
    n = dA.shape[1]
    gA = np.zeros(n)
    gB = np.zeros(n)
    for i in range(dl.shape[0]):
        for k in range(n):
            gA[k] += dl[i] * dA[i, k]
            gB[k] += dl[i] * dB[i, k]
    return gA, gB


@_inline
def _mass_stiffness(dl, s, hs):  # pragma: no cover - compiled
    """``M_r``, ``K_r`` of the held model at ``q0 + dl``: gradients at ``q0`` and, with a secant partner, half the
    change of the gradients along the secant (``s = (dl . d) / (d . d)``, ``d = q0 - q_old``): second order."""
    r = hs.Mr.shape[0]
    gM, gK = _along(dl, hs.dM, hs.dK)
    if hs.has_old:
        hM, hK = _along(dl, hs.old_dM, hs.old_dK)
        for k in range(r * r):
            gM[k] += 0.5 * s * (gM[k] - hM[k])
            gK[k] += 0.5 * s * (gK[k] - hK[k])
    Mr = np.empty((r, r))
    Kr = np.empty((r, r))
    for i in range(r):  # loops, not array expressions: the same sums in a fraction of the compiled code
        for j in range(r):
            Mr[i, j] = hs.Mr[i, j] + gM[i * r + j]
            Kr[i, j] = hs.Kr[i, j] + gK[i * r + j]
    return Mr, Kr


@_inline
def _elastic_terms(pe, hs, Mr, Kr, Ca, Gr):  # pragma: no cover - compiled
    """Add to the held ``M_r``, ``K_r``, ``C_a``, ``G_r`` (in place) their change with the elastic coordinates
    ``pe = p[nq:]`` (the held arrays are those of the configuration undeformed, :class:`HeldSystem`).

    The consistent velocity map ``J = H + [d(H p)/dq, 0]`` is linear in the elastic coordinates and changes
    only the ``nq`` rigid columns: with ``A_k = d(W H e_k)/dq`` the rigid columns of ``W J`` gain
    ``sum_k p_k A_k``. Per unit ``p_k`` the reduced matrices' rigid rows gain ``pM_k = A_k^T M_N W H``,
    ``pK_k = (d(H_u e_k)/dq)^T K_uu H_u``, ``pC_k = alpha (A_k - E_k)^T P T H_u - beta E_k^T K_N T H_u`` (``P``
    the mass relative to the rigid motion, ``E_k`` the deflection ``H e_k``'s rates turned with the links, which
    the strain-rate damping takes out of ``A_k``) and ``pG_k = A_k^T B_N`` (rows ``[i * ncol + j]``,
    :meth:`.ReducedModel.elastic_forms`); ``M_r`` and the damping gain the transposed columns too (symmetric
    forms), the damping also ``beta`` times the transpose of ``K_r``'s rows (its rows come with ``beta K_r``).
    The damping is quadratic in ``J``: its rigid block gains ``sum_kl p_k p_l X_kl`` (``(A_k - E_k)^T (alpha P +
    beta K_N) (A_l - E_l)``), symmetric in ``(k, l)`` and in its entries, so ``p2C`` holds it per pair ``k <= l``
    and entry ``i <= j`` (:meth:`.ReducedModel.elastic_forms`); ``K_r = J_u^T K_uu H_u`` and ``G_r`` are linear in
    it. So ``K_r``, ``G_r`` and the damping are exact in the elastic coordinates at the held configuration.
    Left out, the damping's second order makes the first-order damping matrix indefinite
    (``tests/test_held_elastic.py``). ``M_r`` is quadratic too,
    its second order ``p_k p_l A_k^T M_N A_l`` left out: its error has no sign of its own, and where the elastic
    coordinates are poorly observed (the six-bar without its gauge c4, ``tests/test_log_bound.py``) the filter's
    estimates of them, squared, and a Jacobian without their effect on ``M_r`` did worse with it in
    (docs/held_elastic.md)."""
    n_el = hs.pM.shape[0] if pe.shape[0] else 0
    if n_el == 0:
        return
    r = Mr.shape[0]
    nq = r - n_el
    m = Gr.shape[1]
    mg = hs.pG.shape[1] // nq  # the input matrix's columns (and the weight's, last)
    gM = np.zeros(nq * r)
    gK = np.zeros(nq * r)
    gC = np.zeros(nq * r)
    gG = np.zeros(nq * mg)
    for k in range(n_el):
        w = pe[k]
        if w != 0.0:
            for j in range(nq * r):
                gM[j] += w * hs.pM[k, j]
                gK[j] += w * hs.pK[k, j]
                gC[j] += w * hs.pC[k, j]
            for j in range(nq * mg):
                gG[j] += w * hs.pG[k, j]
    for i in range(nq):
        for j in range(r):
            a = gM[i * r + j]
            Mr[i, j] += a
            Mr[j, i] += a
            Kr[i, j] += gK[i * r + j]
            c = gC[i * r + j]
            Ca[i, j] += c
            Ca[j, i] += c + hs.beta * gK[i * r + j]
        for j in range(m):
            Gr[i, j] += gG[i * mg + j]
    n2 = hs.p2C.shape[1] if hs.p2C.shape[0] else 0
    if n2:  # the damping's second order: per entry i <= j a dot product over the pairs k <= l
        w2 = np.empty(n2)
        cp = 0
        for k in range(n_el):
            for l in range(k, n_el):
                w2[cp] = pe[k] * pe[l]
                cp += 1
        t = 0
        for i in range(nq):
            for j in range(i, nq):
                ac = 0.0
                for cp in range(n2):
                    ac += w2[cp] * hs.p2C[t, cp]
                Ca[i, j] += ac
                if j != i:
                    Ca[j, i] += ac
                t += 1


@_inline
def _mass_curvature_terms(dl, pe, Me, Mr):  # pragma: no cover - compiled
    """Add to the held ``M_r`` (in place) its cross term in ``q`` and the elastic coordinates, ``sum_{m, i} p_m dl_i (X_mi
    + X_mi^T)`` (:class:`HeldSystem`'s ``Me``: ``X_mi`` the rigid rows of ``d^2 M_r / dq_i dp_m``); nothing where
    ``Me`` or ``pe`` is empty."""
    n_el = Me.shape[0] if pe.shape[0] else 0
    if n_el == 0:
        return
    r = Mr.shape[0]
    nq = dl.shape[0]
    g = np.zeros(nq * r)
    for k in range(n_el):
        for i in range(nq):
            w = pe[k] * dl[i]
            if w != 0.0:
                o = i * nq * r
                for t in range(nq * r):
                    g[t] += w * Me[k, o + t]
    for a in range(nq):
        for b in range(r):
            x = g[a * r + b]
            Mr[a, b] += x
            Mr[b, a] += x


@_inline
def _system(dl, s, pe, hs):  # pragma: no cover - compiled
    """``(M_r, K_r, C_r, G_r)`` of the held model at ``q0 + dl`` with the elastic coordinates ``pe`` (empty: the
    configuration undeformed); ``C_a`` and ``G_r`` along the secant (:func:`_elastic_terms`)."""
    Mr, Kr = _mass_stiffness(dl, s, hs)
    r = Mr.shape[0]
    Ca = np.empty((r, r))
    Gr = hs.Gr.copy()
    for i in range(r):  # C_a along the secant; loops, not array expressions (see _mass_stiffness)
        for j in range(r):
            ca = hs.Ca[i, j]
            if hs.has_old:
                ca += s * (hs.Ca[i, j] - hs.old_Ca[i, j])
            Ca[i, j] = ca
        if hs.has_old:
            for j in range(Gr.shape[1]):
                Gr[i, j] += s * (hs.Gr[i, j] - hs.old_Gr[i, j])
    _elastic_terms(pe, hs, Mr, Kr, Ca, Gr)
    _mass_curvature_terms(dl, pe, hs.Me, Mr)
    Cr = np.empty((r, r))
    for i in range(r):  # + beta K_r
        for j in range(r):
            Cr[i, j] = Ca[i, j] + hs.beta * Kr[i, j]
    return Mr, Kr, Cr, Gr


def _held_model(z, dl, s, tm, hs, tf=0.0):  # pragma: no cover - compiled
    """The held model over an interval from ``z`` (``q = q0 + dl``): the matrices (:func:`_system`) at ``q`` with
    the elastic coordinates ``tm`` seconds on, ``p_e + tm p_e'`` (the interval's midpoint for ``tm = dt/2``), and
    the forces at ``z`` along the secant: ``(M_r, K_r, C_r, G_r, f)``; the weight at the configuration ``tf``
    seconds on, ``q + tf q'`` (:func:`held_interval`: the interval's midpoint with a linear input, its start with a
    held one). Where the held system has a weight gradient
    (gravity) the weight follows ``q`` to second order instead, as ``M_r`` and ``K_r`` do: its gradient in every
    direction and, with a secant partner (``d = q0 - q_old``, ``s = (dl . d) / (d . d)``), half the gradient's
    change along the secant, ``f_g = fg + (Wg + s/2 (Wg - Wg_old)) dl``: with ``Wg - Wg_old = D2(d, .)`` to first
    order and ``dl = s d + w``, its error is ``1/2 D2(w, dl)``, third order on the secant's line (``w = 0``) and
    second order off it (``tests/test_held_weight.py``). To first order only, the weight's error ``1/2 D2(dl, dl)``
    is of one sign over the whole radius: a bias the filter takes for signal (docs/gravity.md measures what it did
    to the filter on its own model). The weight must not be extrapolated along the secant from the two weights
    alone (``fg + (1 + s) Wg dl - s^2 (fg - fg_old)``, exact on the line): off the line that leaves the first-order
    error ``s Wg w``, of one sign too, which on an arm whose weight gradient is large (the crane arm's upright mast,
    ``benchmarks/models/crane_arm.toml``) biased the filter on its own model (``benchmarks/held_step.py`` measures it).

    The matrices change with the elastic coordinates (:func:`_elastic_terms`), which move fast: held at the
    interval's start they are wrong by ``dM/dp_e p_e' dt`` at its end, an error of first order in ``dt`` in the
    state's rate; held at the midpoint (the exponential midpoint rule) the error averages to second order. The
    configuration ``q`` stays at the start: advanced too, the step depends on the rates through ``dM/dq q'``, a
    term the step Jacobian leaves out, strong where ``M`` changes fast with ``q`` (a slider-crank near its dead
    centres); both measured in docs/step_jacobian.md. The forces stay at the start (their advance needs the
    accelerations of the fast elastic modes). Where the held system has the forms' q-gradients (``dT2``, ``dV2``,
    ``dC2``: under gravity) the forces of the rates and the q rows' elastic term follow ``q`` by them, to first
    order, in place of the secant (:func:`_forms_gradient`), so that the step's q-derivative is the one its
    Jacobian holds."""
    r = hs.Mr.shape[0]
    nq = dl.shape[0]
    p = z[:r]
    pd = z[r:]
    pem = np.empty(r - nq)
    for k in range(r - nq):
        pem[k] = p[nq + k] + tm * pd[nq + k]
    Mr, Kr, Cr, Gr = _system(dl, s, pem, hs)
    f = fo = hs.fg
    for k in range(2 if hs.has_old else 1):  # the held and the old forms, one inlined copy of the forces for both
        fk = _quadratic_forces(p, pd, nq, hs.fg if k == 0 else hs.old_fg, hs.T2 if k == 0 else hs.old_T2,
                               hs.V2 if k == 0 else hs.old_V2, hs.C2 if k == 0 else hs.old_C2)
        if k == 0:
            f = fk
        else:
            fo = fk
    secant = hs.has_old and hs.dT2.shape[0] == 0  # the forms along the secant, or by their q-gradients
    if secant:
        for i in range(r):
            f[i] += s * (f[i] - fo[i])
    elif hs.dT2.shape[0]:  # the forms' forces follow q by their gradients, to first order
        g = _forms_gradient(p, pd, nq, hs.dT2, hs.dV2, hs.dC2)
        for i in range(r):
            for j in range(nq):
                f[i] += g[i, j] * dl[j]
    if hs.pT.shape[0]:  # the velocity forces' first order in the elastic coordinates
        _velocity_terms(p[nq:], pd, nq, hs.pT, hs.pC2, f, np.empty((0, 0)))
    if hs.Wg.shape[0]:  # the weight to second order: its gradient, and half the gradient's change along the secant
        for i in range(r):
            acc = 0.0
            for j in range(nq):
                g = hs.Wg[i, j]
                if hs.has_old:
                    g += 0.5 * s * (hs.Wg[i, j] - hs.old_Wg[i, j])
                acc += g * (dl[j] + tf * pd[j])
            if secant:  # the forms' secant moved the weight along it already: taken out
                acc -= s * (hs.fg[i] - hs.old_fg[i])
            f[i] += acc
    n_el = hs.pG.shape[0]
    if n_el:  # the weight's change with the elastic coordinates (pG's last column, :func:`_elastic_terms`)
        mg = hs.pG.shape[1] // nq
        for k in range(n_el):
            w = p[nq + k]
            for i in range(nq):
                f[i] += w * hs.pG[k, i * mg + mg - 1]
    for k in range(hs.We.shape[0]):  # ... and its change with q: the weight's moment across the sag turning
        w = p[nq + k]
        if w != 0.0:
            for i in range(nq):
                acc = 0.0
                for j in range(nq):
                    acc += hs.We[k, i * nq + j] * (dl[j] + tf * pd[j])
                f[i] += w * acc
    return Mr, Kr, Cr, Gr, f


def _motion_coefficients(u, z, nq, nk):  # pragma: no cover - compiled
    """``c = [1, u, (q'_a q'_b)_{a <= b}]`` (nk,), the rates ``q'`` of ``z``: the coefficients of the motion's
    geometric stiffness form (:meth:`exuflex.reduction.model.ReducedModel.motion_geometric`)."""
    r = z.shape[0] // 2
    c = np.empty(nk)
    c[0] = 1.0
    nm = u.shape[0]
    for j in range(nm):
        c[1 + j] = u[j]
    k = 1 + nm
    for a in range(nq):
        for b in range(a, nq):
            c[k] = z[r + a] * z[r + b]
            k += 1
    return c


def _motion_stiffness(u, z, nq, KGd):  # pragma: no cover - compiled
    """``sum_k c_k KGd[k]`` (r, r), ``c = [1, u, (q'_a q'_b)_{a <= b}]`` with the rates ``q'`` of ``z``: the geometric
    stiffness of the motion's axial loads beyond the static ones at the held configuration
    (:meth:`exuflex.reduction.model.ReducedModel.motion_geometric`; zeros where ``KGd`` is empty)."""
    r = z.shape[0] // 2
    K = np.zeros((r, r))
    nk = KGd.shape[0]
    if nk == 0:
        return K
    c = _motion_coefficients(u, z, nq, nk)
    for k in range(nk):
        w = c[k]
        if w != 0.0:
            for i in range(r):
                for j in range(r):
                    K[i, j] += w * KGd[k, i * r + j]
    return K


def _motion_form(KGd, dKGd, dl):  # pragma: no cover - compiled
    """``KGd + dKGd . dl`` (k, r*r): the motion's geometric stiffness form at ``q0 + dl`` to first order in q
    (:class:`HeldSystem`'s ``dKGd``); ``KGd`` itself where ``dKGd`` is empty."""
    if dKGd.shape[0] == 0:
        return KGd
    nk, rr = KGd.shape
    nq = dl.shape[0]
    out = KGd.copy()
    for k in range(nk):
        for i in range(nq):
            a = dl[i]
            if a != 0.0:
                for t in range(rr):
                    out[k, t] += a * dKGd[k, i * rr + t]
    return out


def _motion_form_gradient(Fp, u, z, tm, dKGd, nq):  # pragma: no cover - compiled
    """Subtract from the held forces' position gradient ``Fp`` (r, r; in place) the motion's geometric forces'
    change with q through the form's gradient: ``-sum_k c_k dKGd[k, i] (p + tm p')`` in column ``i < nq``
    (:func:`_motion_form`, :func:`_motion_forces`; ``c = [1, u, (q'_a q'_b)_{a <= b}]``); nothing where ``dKGd`` is
    empty."""
    nk = dKGd.shape[0]
    if nk == 0:
        return
    r = z.shape[0] // 2
    rr = r * r
    c = _motion_coefficients(u, z, nq, nk)
    pm = np.empty(r)
    for j in range(r):
        pm[j] = z[j] + tm * z[r + j]
    for k in range(nk):
        w = c[k]
        if w == 0.0:
            continue
        for i in range(nq):
            o = i * rr
            for a in range(r):
                acc = 0.0
                for b in range(r):
                    acc += dKGd[k, o + a * r + b] * pm[b]
                Fp[a, i] -= w * acc


def _motion_rates(F, z, u, nq, SQM, KGd, Kd, dt):  # pragma: no cover - compiled
    """Add to the step Jacobian ``F`` (in place) the response ``SQM g`` to the motion's geometric forces' change with
    the rates: the force ``-K_d (p + dt/2 p')`` held over the interval (:func:`_motion_forces`) in rate column ``m``
    ``-dt/2 K_d e_m``, and ``K_d`` itself changes with the rates, ``-d(K_d)/dq'_a (p + dt/2 p')`` (the centripetal
    axial loads, ``c_k = q'_a q'_b``); nothing where ``KGd`` is empty."""
    nk = KGd.shape[0]
    if nk == 0:
        return
    r = z.shape[0] // 2
    nm = u.shape[0]
    g = np.empty((r, r))
    for i in range(r):
        for m in range(r):
            g[i, m] = -0.5 * dt * Kd[i, m]
    k = 1 + nm
    for a in range(nq):
        for b in range(a, nq):
            for i in range(r):  # d(q'_a q'_b)/dq'_a = q'_b, /dq'_b = q'_a
                acc = 0.0
                for j in range(r):
                    acc += KGd[k, i * r + j] * (z[j] + 0.5 * dt * z[r + j])
                g[i, a] -= z[r + b] * acc
                g[i, b] -= z[r + a] * acc
            k += 1
    _rate_response(F, SQM, g)


def _rate_response(F, SQM, g):  # pragma: no cover - compiled
    """``F[:, r + m] += SQM g[:, m]`` (in place): the step's response to generalised forces ``g`` (r, k) per unit
    change of the first ``k`` rates."""
    r = SQM.shape[1]
    for i in range(F.shape[0]):
        for m in range(g.shape[1]):
            acc = 0.0
            for c in range(r):
                acc += SQM[i, c] * g[c, m]
            F[i, r + m] += acc


def _held_interval(z, u, du, dl, s, h, n, Ts, Vs, C3, Pn, SQM, hs):  # pragma: no cover - compiled
    """One interval of the cached step, the model at ``q0 + dl`` (:func:`_held_model`) advanced by ``n`` RK4
    sub-steps of ``h``, and its Jacobian (:func:`_step_jacobian`, with the velocity forces' and the held
    matrices' change with the elastic coordinates, :func:`_velocity_jacobian`, :func:`_elastic_tangent`) (what the
    cached step does per interval):
    ``(z_next, F, M_r, K_r, C_r, G_r)``. The input over the interval ``T = n h``: ``du`` empty, the torques ``u``
    held (a log's zero-order hold); else linear, ``u + (t / T) du`` (:func:`_rk4_linear`), and the forces that
    follow the configuration with it: the motion's geometric stiffness, a force held over the interval at its
    midpoint positions, at the midpoint torques ``u + du / 2``, and the weight at the midpoint configuration
    ``q + T/2 q'`` (:func:`_held_model`), with the Jacobian's terms in them (:func:`_weight_rates`). With the
    torques held the weight stays at the interval's start: a table's torque that carries a link against its
    weight follows the weight, so the held torque lags it by half an interval as the weight held at the start
    does, and the two lags cancel (docs/held_step.md, "The input over a sample interval"). An empty ``Pn`` leaves the Jacobian out (``F`` empty): the one kernel
    then serves :func:`held_step` too (see :func:`_inline` for why one). ``z_next`` is NaN if the held ``M_r``
    is not positive definite at the start either. The helpers are called here directly: numba copies an inlined helper's whole code once
    per block, so one large helper costs far more to inline than its parts. ``hs``: the held system
    (:class:`HeldSystem`'s fields as a plain tuple: numba types a plain tuple from its fingerprint, a named one
    through a slower path)."""
    hs = HeldSystem(*hs)
    nq = dl.shape[0]
    linear = du.shape[0] > 0
    um = u.copy()  # the torques at the interval's midpoint
    if linear:
        for j in range(u.shape[0]):
            um[j] += 0.5 * du[j]
    tf = 0.5 * h * n if linear else 0.0  # where the weight is taken
    KGe = _motion_form(hs.KGd, hs.dKGd, dl)
    Kd = motion_stiffness(um, z, nq, KGe)
    tm = 0.5 * h * n
    Mr_, Kr_, Cr_, Gr_, f = _held_model(z, dl, s, tm, hs, tf)
    motion_forces(f, z, 0.5 * h * n, Kd)
    z_next = _rk4_linear(z, u, du, Mr_, Kr_, Cr_, Gr_, f, h, n)
    if not math.isfinite(z_next[0]):
        # M_r not positive definite at the midpoint's elastic coordinates: a long interval (a gap, a log sampled
        # far below the modes), over which their linear advance means nothing; the matrices at the start
        tm = 0.0
        Mr_, Kr_, Cr_, Gr_, f = _held_model(z, dl, s, tm, hs, tf)
        motion_forces(f, z, 0.5 * h * n, Kd)
        z_next = _rk4_linear(z, u, du, Mr_, Kr_, Cr_, Gr_, f, h, n)
    F = np.empty((0, 0))
    if Pn.shape[0]:  # the kernel itself, not inlined: the filter calls it from Python as well
        Fp = hs.Wg
        if hs.Wg.shape[0]:  # gravity: the held matrices' change with q as well (position_forces)
            Fp = position_forces(z, z_next, h * n, hs.Wg, hs.dM, hs.dK, hs.beta)
            dlw = dl.copy()  # where the weight is taken (:func:`_held_model`)
            for j in range(nq):
                dlw[j] += tf * z[Mr_.shape[0] + j]
            _weight_curvature_forces(Fp, z, dlw, hs.We)
            _mass_curvature_forces(Fp, z, z_next, h * n, tm, nq, hs.Me)
            _forms_gradient_forces(Fp, z, nq, hs.dT2, hs.dV2, hs.dC2)
        if hs.KGd.shape[0]:  # the step map's P^n holds the static K_r: the motion's stiffness as a force gradient
            Fp = motion_gradient(Fp, Kd)
            motion_form_gradient(Fp, um, z, 0.5 * h * n, hs.dKGd, nq)
        F = step_jacobian(z, Ts, Vs, C3, Pn, SQM, Fp)
        motion_rates(F, z, um, nq, SQM, KGe, Kd, h * n)
        if tf != 0.0:
            _weight_rates(F, z, s, tf, SQM, hs)
        _velocity_jacobian(F, z, dl.shape[0], SQM, hs.pT, hs.pC2)
        Y = _elastic_tangent(z, u, du, dl, Mr_, Kr_, Cr_, Gr_, f, h, n, tm, hs)  # the matrices' change with p_e
        nq = dl.shape[0]
        r = nq + Y.shape[1]
        for k in range(Y.shape[1]):
            for i in range(F.shape[0]):
                F[i, nq + k] += Y[i, k]
                F[i, r + nq + k] += tm * Y[i, k]
    return z_next, F, Mr_, Kr_, Cr_, Gr_


def _weight_rates(F, z, s, tf, SQM, hs):  # pragma: no cover - compiled
    """Add to the step Jacobian ``F`` (in place) the response ``SQM g`` to the weight taken ``tf`` seconds into the
    interval (:func:`_held_model`: ``q + tf q'``): in rate column ``j < nq`` ``tf`` times the held weight's
    q-gradient, ``Wg + s/2 (Wg - Wg_old)`` with the sag's ``sum_m p_m We[m]`` in the q rows; nothing without
    gravity."""
    if hs.Wg.shape[0] == 0:
        return
    r = SQM.shape[1]
    nq = hs.dM.shape[0]
    g = np.zeros((r, nq))
    for i in range(r):
        for j in range(nq):
            x = hs.Wg[i, j]
            if hs.has_old:
                x += 0.5 * s * (hs.Wg[i, j] - hs.old_Wg[i, j])
            g[i, j] = tf * x
    for k in range(hs.We.shape[0]):
        w = z[nq + k]
        if w != 0.0:
            for i in range(nq):
                for j in range(nq):
                    g[i, j] += tf * w * hs.We[k, i * nq + j]
    _rate_response(F, SQM, g)


def _velocity_jacobian(F, z, nq, SQM, pT, pC2):  # pragma: no cover - compiled
    """Add to the step Jacobian ``F`` (in place) the response ``SQM dG`` to the velocity forces' first order in the
    elastic coordinates (:func:`_velocity_terms`; nothing where ``pT`` is empty)."""
    if pT.shape[0] == 0:
        return
    r = SQM.shape[1]
    Ge = np.zeros((r, 2 * r))
    _velocity_terms(z[nq:r], z[r:], nq, pT, pC2, np.zeros(r), Ge)
    Fe = SQM @ Ge
    for i in range(F.shape[0]):
        for j in range(F.shape[1]):
            F[i, j] += Fe[i, j]


def _elastic_tangent(z, u, du, dl, Mr, Kr, Cr, Gr, f, h, n, tm, hs):  # pragma: no cover - compiled
    """``Y`` (2r, n_el): the change of the interval's end state per unit elastic coordinate ``p_k`` at which the
    held matrices are taken (``p_e + tm p_e'``, :func:`_held_model`; ``tm = dt/2``, or 0 where the interval fell back
    to its start), through the matrices alone: the step Jacobian's columns of ``p_k`` gain ``Y[:, k]`` and those of
    ``p'_k`` ``tm Y[:, k]``. Per unit ``p_k`` the held system ``M p'' + C p' + K p = G u + f`` changes by ``dM_k``,
    ``dC_k``, ``dK_k``, ``dG_k`` (:func:`_elastic_terms`: ``pM_k``, ``pK_k``, ``pC_k`` with ``beta pK_k``, since
    ``C_r = C_a + beta K_r``, ``pG_k``, and the damping's second order ``p2C`` differentiated at the held point), a
    force ``g_k = dG_k u - dM_k a - dC_k p' - dK_k p`` along the interval's motion; ``Y`` is the tangent of the
    same RK4 sub-steps driven by it from zero (stage by stage at the stage's state and acceleration: the elastic
    modes oscillate within an interval, and a force taken at the interval's mean motion is no approximation of
    it). The torques at each stage's time, ``u + (t / T) du`` (:func:`_rk4_linear`), in ``G u`` and ``dG_k u``.
    Exact for the step as computed (``tests/_oracles.py``'s ``exact_jacobian`` carries the same tangent)."""
    n_el = hs.pM.shape[0]
    r = Mr.shape[0]
    if n_el == 0 or r == n_el:
        return np.zeros((2 * r, 0))
    nq = r - n_el
    m = u.shape[0]
    mg = hs.pG.shape[1] // nq
    pe = np.empty(n_el)
    for k in range(n_el):
        pe[k] = z[nq + k] + tm * z[r + nq + k]
    # the matrices' changes per unit p_k, stacked by rows: D[k * r + c, :]
    dM = np.zeros((n_el * r, r))
    dK = np.zeros((n_el * r, r))
    dC = np.zeros((n_el * r, r))
    dGu = np.zeros((r, n_el))
    dGd = np.zeros((r, n_el))  # dG_k du: the input matrix's change times the input's change over the interval
    T = h * n
    n2 = hs.p2C.shape[1] if hs.p2C.shape[0] else 0
    for k in range(n_el):
        o = k * r
        for i in range(nq):
            for j in range(r):
                t = i * r + j
                a = hs.pM[k, t]
                if hs.Me.shape[0]:  # M_r's cross term in q and p_k at q0 + dl (:func:`_mass_curvature_terms`)
                    for c in range(nq):
                        a += dl[c] * hs.Me[k, c * nq * r + t]
                kk = hs.pK[k, t]
                cc = hs.pC[k, t] + hs.beta * kk
                dM[o + i, j] += a
                dM[o + j, i] += a
                dK[o + i, j] += kk
                dC[o + i, j] += cc
                dC[o + j, i] += cc
            for j in range(m):
                dGu[i, k] += hs.pG[k, i * mg + j] * u[j]
            for j in range(du.shape[0]):
                dGd[i, k] += hs.pG[k, i * mg + j] * du[j] / T
        if n2:  # d/dp_k of sum_{a <= b} p_a p_b X_ab (p2C's packing, :func:`_elastic_terms`)
            cp = 0
            for a_ in range(n_el):
                for b_ in range(a_, n_el):
                    w = 0.0
                    if a_ == k:
                        w += pe[b_]
                    if b_ == k:
                        w += pe[a_]
                    if w != 0.0:
                        t = 0
                        for i in range(nq):
                            for j in range(i, nq):
                                x = w * hs.p2C[t, cp]
                                dC[o + i, j] += x
                                if j != i:
                                    dC[o + j, i] += x
                                t += 1
                    cp += 1
    o1 = 2 * r + 2 + n_el  # the input's rates' columns: G du / T, dG du / T
    rhs = np.empty((r, o1 + n_el))
    for i in range(r):
        for j in range(r):
            rhs[i, j] = Kr[i, j]
            rhs[i, r + j] = Cr[i, j]
        acc = f[i]
        acc1 = 0.0
        for j in range(m):
            acc += Gr[i, j] * u[j]
        for j in range(du.shape[0]):
            acc1 += Gr[i, j] * du[j] / T
        rhs[i, 2 * r] = acc
        rhs[i, 2 * r + 1 + n_el] = acc1
        for k in range(n_el):
            rhs[i, 2 * r + 1 + k] = dGu[i, k]
            rhs[i, o1 + k] = dGd[i, k]
    X = _cholesky_solve(Mr, rhs)  # M^-1 [K, C, G u + f, dG u, G du / T, dG du / T]
    AK = np.ascontiguousarray(X[:, :r])
    AC = np.ascontiguousarray(X[:, r : 2 * r])
    b0 = np.ascontiguousarray(X[:, 2 * r])
    bG0 = np.ascontiguousarray(X[:, 2 * r + 1 : 2 * r + 1 + n_el])
    b1 = np.ascontiguousarray(X[:, 2 * r + 1 + n_el])
    bG1 = np.ascontiguousarray(X[:, o1:])
    Minv = _cholesky_solve(Mr, np.eye(r))
    y = z.copy()
    Y = np.zeros((2 * r, n_el))
    ky = np.empty((4, 2 * r))
    kY = np.empty((4, 2 * r, n_el))
    cs = (0.0, 0.5 * h, 0.5 * h, h)
    for step in range(n):
        for st in range(4):
            ys = y.copy()
            Ys = Y.copy()
            if st:
                ys += cs[st] * ky[st - 1]
                Ys += cs[st] * kY[st - 1]
            ts = step * h + cs[st]  # the stage's time: its input
            b = b0 + ts * b1
            bG = bG0 + ts * bG1
            a = b - AK @ ys[:r] - AC @ ys[r:]
            g = -((dM @ a + dC @ ys[r:] + dK @ ys[:r]).reshape(n_el, r)).T  # (r, n_el): the forces less dG u
            ky[st, :r] = ys[r:]
            ky[st, r:] = a
            kY[st, :r] = Ys[r:]
            kY[st, r:] = Minv @ g + bG - AK @ Ys[:r] - AC @ Ys[r:]
        y += h / 6.0 * (ky[0] + 2.0 * ky[1] + 2.0 * ky[2] + ky[3])
        Y += h / 6.0 * (kY[0] + 2.0 * kY[1] + 2.0 * kY[2] + kY[3])
    return Y


def _motion_forces(f, z, tm, Kd):  # pragma: no cover - compiled
    """``f -= K_d (p + tm p')`` (in place): the motion's geometric forces (:func:`_motion_stiffness`) at the
    interval's midpoint positions (``tm = dt/2``), held over it as the other forces are. As a force, not in the held
    ``K_r``: the step map's ``P^n`` and the step Jacobian then take it exactly (:func:`_motion_gradient`,
    :func:`_motion_rates`); held at the midpoint its error over the interval is second order, ``(w dt)^2 / 24`` of
    ``K_d p`` for a mode of ``w`` rad/s (some percent of a few percent of the stiffness at the gauges' modes)."""
    r = f.shape[0]
    if Kd.shape[0] == 0:
        return
    for i in range(r):
        acc = 0.0
        for j in range(r):
            acc += Kd[i, j] * (z[j] + tm * z[r + j])
        f[i] -= acc


def _motion_gradient(Fp, Kd):  # pragma: no cover - compiled
    """``Fp - Kd`` (r, r; ``Fp`` empty: ``-Kd``): the held forces' position gradient with the motion's geometric
    forces (:func:`_motion_forces`); their change with the rates: :func:`_motion_rates`."""
    r = Kd.shape[0]
    out = np.empty((r, r))
    for i in range(r):
        for j in range(r):
            out[i, j] = (Fp[i, j] if Fp.shape[0] else 0.0) - Kd[i, j]
    return out


def _forms_gradient(p, pd, nq, dT2, dV2, dC2):  # pragma: no cover - compiled
    """``g`` (r, nq): the forces of the held quadratic forms (:func:`_quadratic_forces` without the weight)
    differentiated in ``q``, column ``i`` ``-1/2 p' dT_i p' - [p dV_{i,c} p]_c - sum_{k, j < nq} p'_k p'_j dC_i[k,
    j]`` at ``(p, p')`` from the forms' q-gradients (:class:`HeldSystem`'s ``dT2``, ``dV2``, ``dC2``; zeros where
    ``dT2`` is empty)."""
    r = p.shape[0]
    g = np.zeros((r, nq))
    if dT2.shape[0] == 0:
        return g
    for i in range(nq):
        for k in range(r):
            w = pd[k]
            if w != 0.0:
                row = i * r + k
                for a in range(r):
                    acc = 0.0
                    for b in range(r):
                        acc += dT2[row, a * r + b] * pd[b]
                    g[a, i] -= 0.5 * w * acc
        for c in range(nq):
            for a in range(r):
                acc = 0.0
                row = (i * nq + c) * r + a
                for b in range(r):
                    acc += dV2[row, b] * p[b]
                g[c, i] -= acc * p[a]
        if dC2.shape[0]:
            for k in range(r):
                for j in range(nq):
                    w = pd[k] * pd[j]
                    if w != 0.0:
                        row = (i * r + k) * nq + j
                        for c in range(r):
                            g[c, i] -= w * dC2[row, c]
    return g


def _forms_gradient_forces(Fp, z, nq, dT2, dV2, dC2):  # pragma: no cover - compiled
    """Add to the forces' position gradient ``Fp`` (r, r; in place) the held forms' forces' q-gradient at ``z``
    (:func:`_forms_gradient`) in its q columns; nothing where ``dT2`` is empty."""
    if dT2.shape[0] == 0:
        return
    r = z.shape[0] // 2
    g = _forms_gradient(z[:r], z[r:], nq, dT2, dV2, dC2)
    for c in range(r):
        for i in range(nq):
            Fp[c, i] += g[c, i]


def _mass_curvature_forces(Fp, z, z_next, dt, tm, nq, Me):  # pragma: no cover - compiled
    """Subtract from the held forces' position gradient ``Fp`` (r, r; in place) the held ``M_r``'s cross term
    (:func:`_mass_curvature_terms`) differentiated in ``q_i`` times the interval's mean acceleration, as
    :func:`_position_forces` takes ``dM/dq_i a``: ``sum_m p_m (X_mi + X_mi^T) a`` in column ``i``, ``p`` the elastic
    coordinates the matrices are held at (``p_e + tm p_e'``, :func:`_held_model`), ``a = (p'_next - p') / dt``; its
    change with the elastic coordinates is :func:`_elastic_tangent`'s. Nothing where ``Me`` is empty."""
    n_el = Me.shape[0]
    if n_el == 0:
        return
    r = z.shape[0] // 2
    am = np.empty(r)
    for k in range(r):
        am[k] = (z_next[r + k] - z[r + k]) / dt
    for k in range(n_el):
        w = z[nq + k] + tm * z[r + nq + k]
        if w == 0.0:
            continue
        for i in range(nq):
            o = i * nq * r
            for a in range(nq):
                acc = 0.0  # (X a)_a
                for b in range(r):
                    x = w * Me[k, o + a * r + b]
                    acc += x * am[b]
                    Fp[b, i] -= x * am[a]  # (X^T a)_b
                Fp[a, i] -= acc


def _weight_curvature_forces(Fp, z, dl, We):  # pragma: no cover - compiled
    """Add to the held forces' position gradient ``Fp`` (r, r; in place) the held weight's cross term
    ``sum_m p_m We[m] dl`` (:func:`_held_model`) differentiated: ``sum_m p_m We[m]`` in the q columns (the weight's
    q-gradient at the state's sag) and ``We[m] dl`` in the elastic columns; nothing where ``We`` is empty."""
    n_el = We.shape[0]
    if n_el == 0:
        return
    nq = dl.shape[0]
    for k in range(n_el):
        w = z[nq + k]
        for i in range(nq):
            acc = 0.0
            for j in range(nq):
                x = We[k, i * nq + j]
                Fp[i, j] += w * x
                acc += x * dl[j]
            Fp[i, nq + k] += acc


def _position_forces(z, z_next, dt, Wg, dM, dK, beta):  # pragma: no cover - compiled
    """``Fp`` (r, r): the change of the held system's generalised forces with the positions over an interval from
    ``z`` to ``z_next`` (``dt``), where gravity loads the mechanism: the weight's gradient ``Wg`` and, in the q
    columns, the held matrices' change with q as the forces it causes, ``-dK/dq_i (p + beta p') - dM/dq_i a``
    (``M p'' + C p' + K p = G u + f`` differentiated in ``q_i`` with the state held: ``M da = dF/dq_i - dK/dq_i p -
    dC/dq_i p' - dM/dq_i a``; the damping's mass-proportional part follows the secant only and is left out), with
    the interval's mean positions ``(p + p_next) / 2``, rates ``(p_next - p) / dt`` and accelerations
    ``(p'_next - p') / dt``: the step Jacobian takes the forces as held over the interval (its response ``S``),
    and within it the elastic coordinates oscillate (at the start of a log, undeformed under the weight, their
    accelerations are thousands of times their mean). ``dM``, ``dK``: :class:`HeldSystem`'s gradients (nq, r*r).

    Under gravity the positions carry the links' static sag and the accelerations the weight's share, both of the
    weight's size: in global elastic coordinates a sagging link turned by ``dq`` changes its elastic force by
    about as much as its weight's load changes (``dK/dq p``), and the two enter together. Without gravity they
    multiply vibrations only, and the filter gained nothing from them (docs/step_jacobian.md): the step
    Jacobian then leaves them out."""
    r = z.shape[0] // 2
    nq = dM.shape[0]
    pm = np.empty(r)  # p + beta p' over the interval
    am = np.empty(r)
    for k in range(r):
        pm[k] = 0.5 * (z[k] + z_next[k]) + beta * (z_next[k] - z[k]) / dt
        am[k] = (z_next[r + k] - z[r + k]) / dt
    Fp = Wg.copy()
    for i in range(nq):
        for c in range(r):
            acc = 0.0
            for k in range(r):
                acc += dK[i, c * r + k] * pm[k] + dM[i, c * r + k] * am[k]
            Fp[c, i] -= acc
    return Fp


def held_step(z, u, dl, s, h, n, system: HeldSystem, du=None):
    """One interval of the cached step (:func:`held_interval` without the Jacobian): ``(z_next, M_r, K_r, C_r,
    G_r)`` of the held ``system``, the torques ``u`` held (``du`` None) or ``u + (t / T) du``."""
    du = _NO_VECTOR if du is None else np.ascontiguousarray(du, float)
    z_next, _, Mr, Kr, Cr, Gr = held_interval(z, u, du, dl, s, h, n, _NO_TENSOR, _NO_TENSOR, _NO_TENSOR,
                                              _NO_MATRIX, _NO_MATRIX, tuple(system))
    return z_next, Mr, Kr, Cr, Gr


def _held_system(dl, s, pe, hs):  # pragma: no cover - compiled
    """:func:`_system` of the held system ``hs`` (a plain tuple, see :func:`_held_interval`); its own kernel, as the
    filter calls it at every step-map rebuild."""
    return _system(dl, s, pe, HeldSystem(*hs))


_NO_TENSOR = np.empty((0, 0, 0))  # held_interval's Jacobian inputs where it computes none
_NO_MATRIX = np.empty((0, 0))
_NO_VECTOR = np.empty(0)


class LoopExtras(NamedTuple):
    """The arrays of an augmented state that :func:`cached_interval` takes (``ex``): the payload scale's
    (``pay`` ... ``pay_Q``; its increment ``i*``, :class:`.augmented.PayloadIncrement`'s fields) and the torque
    disturbances' (``inp_var``, ``inp_tau``). See :func:`cached_interval` for their meaning; ``pay_lin_tol`` the
    held scale's linearity test (:meth:`.augmented.AugmentedModel.predict`), ``pay_stats`` where the loop counts the
    held intervals it did and the kernel leaves the last one's linearity measure."""

    pay: bool
    pay_held: bool
    pay_var: float
    pay_dtheta: float
    pay_rho: float
    pay_tol: float
    pay_dTs: np.ndarray
    pay_lin_tol: float
    pay_stats: np.ndarray
    iMr: np.ndarray
    iCa: np.ndarray
    idM: np.ndarray
    ifg: np.ndarray
    iT2: np.ndarray
    iC2: np.ndarray
    iold_dM: np.ndarray
    iold_Ca: np.ndarray
    iold_fg: np.ndarray
    iold_T2: np.ndarray
    iold_C2: np.ndarray
    inp_var: np.ndarray
    inp_tau: float


#: :class:`LoopExtras`' payload fields (``pay`` ... ``iold_T2``) of a state without the payload scale
NO_PAYLOAD = (False, False, 0.0, 0.0, 0.0, 0.0, _NO_TENSOR, 0.0, _NO_VECTOR, _NO_MATRIX, _NO_MATRIX, _NO_MATRIX,
              _NO_VECTOR, _NO_MATRIX, _NO_MATRIX, _NO_MATRIX, _NO_MATRIX, _NO_VECTOR, _NO_MATRIX, _NO_MATRIX)
#: no scaled step map, ``(c, Pn, S, L, Q)`` (:func:`payload_interval`'s ``map_c`` ... ``map_Q``)
NO_SCALED_MAP = (0.0, _NO_MATRIX, _NO_MATRIX, _NO_MATRIX, _NO_MATRIX)
#: :class:`LoopExtras`' disturbance fields (``inp_var``, ``inp_tau``) of a state without torque disturbances
NO_DISTURBANCES = (_NO_VECTOR, 0.0)


def _secant_factor(dl, d, dd):  # pragma: no cover - compiled
    """``(dl . d) / (d . d)``: how far along the secant ``d`` (to the previous held configuration) ``q`` has moved
    from the held one, ``dl = q - q0``; zero without a secant (``d`` empty) or when ``dl`` leaves the secant's
    line (cosine below 0.7). See :func:`.reduced._secant_factor`."""
    if d.shape[0] == 0:
        return 0.0
    a = 0.0
    n2 = 0.0
    for i in range(dl.shape[0]):
        a += dl[i] * d[i]
        n2 += dl[i] * dl[i]
    if a * a < 0.49 * n2 * dd:
        return 0.0
    return a / dd


def _measurement_rows(c0, Hm, D, G, x, dl, y, H):  # pragma: no cover - compiled
    """The measurement at ``x``, ``dl = q - q0`` from the held configuration, into ``y``, ``H``
    (:meth:`.reduced.ReducedObserverModel.measure`): ``y_i = c0_i + (Hm + sum_k dl_k D_k)_i x + 1/2 dl^T G_i dl``
    and its derivative ``H = Hm + sum_k dl_k D_k`` with the rigid part's ``G_i dl`` added to q-column ``j``; the
    elastic rows' own q-derivative ``D_j x`` is left out of ``H`` (see the method)."""
    m, n = Hm.shape
    nq = dl.shape[0]
    r = D.shape[2]
    for i in range(m):
        for j in range(n):
            H[i, j] = Hm[i, j]
        for k in range(nq):
            a = dl[k]
            for j in range(r):
                H[i, j] += a * D[k, i, j]
        acc = c0[i]
        for j in range(n):
            acc += H[i, j] * x[j]
        for j in range(nq):
            g = 0.0
            for k in range(nq):
                g += G[i, j, k] * dl[k]
            acc += 0.5 * g * dl[j]
            H[i, j] += g
        y[i] = acc


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


def _step_jacobian(z, Ts, Vs, C3, Pn, SQM, Fp):  # pragma: no cover - compiled
    """The step's Jacobian ``Pn + SQM dF/dz``.

    ``Pn`` is the Jacobian of the interval's RK4 steps with the matrices and forces held; the forces held over
    the interval depend on the start state (the velocity-dependent forces and the geometric q-row term: exact
    derivatives of their quadratic forms ``Ts``, ``Vs``, ``C3``, :meth:`QuadraticForces.jacobian_tensors`; under
    gravity ``Fp``, the weight's gradient with the held matrices' change with q, :func:`position_forces`; empty
    without gravity), and ``SQM`` is the interval's response to a held generalised force. Leaving the second term
    out lets the filter diverge in start-up transients, where the elastic rates are large; without ``Fp`` it
    propagates its covariance as if the mechanism had no gravity stiffness. The cached step adds the held
    matrices' change with the elastic coordinates (:func:`_elastic_tangent`, in :func:`held_interval`). Without
    gravity the q-dependence of ``M_r`` and ``K_r`` is left out (``tests/test_step_jacobian.py`` compares ``F``
    with finite differences of the
    step and with the step's exact Jacobian, ``exact_jacobian`` of ``tests/_oracles.py``; docs/step_jacobian.md
    measures what the left-out terms change and why they stay out)."""
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
    for c in range(Fp.shape[0]):  # the forces' change with the positions under gravity
        for m in range(r):
            G[c, m] += Fp[c, m]
    F = SQM @ G
    for i in range(F.shape[0]):  # + Pn, as a loop (an in-place array expression compiles to far more code)
        for j in range(F.shape[1]):
            F[i, j] += Pn[i, j]
    return F


def _prediction_error(dl, s, Mr_exact, Kr_exact, hs):  # pragma: no cover - compiled
    """How well the held model predicts ``M_r`` and ``K_r`` at ``q0 + dl`` against the exact ``Mr``, ``Kr`` there:
    the largest entry of the differences whitened by the exact mass matrix, ``L^-1 (M_pred - M) L^-T``
    (``M = L L^T``; near 1 the prediction may be indefinite), and of ``K_r``'s relative to the largest entry of
    ``L^-1 K L^-T`` (within a factor ``r`` of the spectral norms, at a tenth of their cost). ``inf`` if ``Mr`` is
    not positive definite. ``hs``: the held system (a plain tuple, see :func:`_held_interval`)."""
    Mp, Kp = _mass_stiffness(dl, s, HeldSystem(*hs))
    Mr, Kr = Mr_exact, Kr_exact
    Li = _inverse_cholesky_factor(Mr)  # NaN if Mr is not positive definite
    if not np.isfinite(Li[0, 0]):
        return np.inf
    r = Mr.shape[0]
    dMp = np.empty((r, r))
    dKp = np.empty((r, r))
    for i in range(r):
        for j in range(r):
            dMp[i, j] = Mp[i, j] - Mr[i, j]
            dKp[i, j] = Kp[i, j] - Kr[i, j]
    em = _abs_max(Li @ dMp @ Li.T)
    ek = _abs_max(Li @ dKp @ Li.T)
    kk = _abs_max(Li @ Kr @ Li.T)
    return max(em, ek / kk)


@_shared
def _abs_max(A):  # pragma: no cover - compiled
    """``np.abs(A).max()`` (NaN if ``A`` holds one) as a loop: the same value in a fraction of the compiled code."""
    m = 0.0
    for i in range(A.shape[0]):
        for j in range(A.shape[1]):
            a = abs(A[i, j])
            if np.isnan(a):
                return a
            m = max(m, a)
    return m


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
    KX = Ak @ np.ascontiguousarray(X[:r])
    CX = Ac @ np.ascontiguousarray(X[r:])
    for i in range(r):  # loops, not slice assignments and array expressions (see _rk4_linear)
        for j in range(X.shape[1]):
            out[i, j] = h * X[r + i, j]
            out[r + i, j] = -h * (KX[i, j] + CX[i, j])
    return out


def _step_maps_noise(Mr, Kr, Cr, Gr, h, n, torque_var):  # pragma: no cover - compiled
    """:func:`step_maps` from ``M_r`` (not its inverse), plus the process noise ``L diag(var) L^T``.

    The same maps with about half the arithmetic:

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
    # the sums as loops, not array expressions: the same arithmetic in a fraction of the compiled code
    T = _times_hA(Ak, Ac, h, W)
    V = np.empty((nx, nx))
    for i in range(nx):
        for j in range(nx):
            V[i, j] = I[i, j] + T[i, j] / 3.0
    T = _times_hA(Ak, Ac, h, V)
    U = np.empty((nx, nx))
    for i in range(nx):
        for j in range(nx):
            U[i, j] = I[i, j] + 0.5 * T[i, j]
    T = _times_hA(Ak, Ac, h, U)
    P = np.empty((nx, nx))
    hU = np.empty((nx, r))
    for i in range(nx):
        for j in range(nx):
            P[i, j] = I[i, j] + T[i, j]
        for j in range(r):
            hU[i, j] = h * U[i, r + j]
    B = hU @ Minv
    Pa = P.copy()
    SB = B.copy()
    sq = np.empty((nx, nx))  # product buffers: the doubling allocates nothing
    th = np.empty((nx, r))
    top = 0
    while (n >> (top + 1)) > 0:
        top += 1
    for bit in range(top - 1, -1, -1):
        np.dot(Pa, SB, th)
        for i in range(nx):
            for j in range(r):
                SB[i, j] += th[i, j]
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
    Lv = np.empty(L.shape)
    for i in range(nx):
        for j in range(L.shape[1]):
            Lv[i, j] = L[i, j] * torque_var[j]
    return Pa, SB, L, Lv @ L.T


def _within(x, c, radius):  # pragma: no cover - compiled
    """``max_i |x_i - c_i| <= radius`` over the entries of ``c`` (False if one is NaN)."""
    for i in range(c.shape[0]):
        if not abs(x[i] - c[i]) <= radius:
            return False
    return True


class CachedStep(NamedTuple):
    """The cached step as the filter's compiled sample loop takes it (:meth:`.reduced.ReducedObserverModel.
    loop_model`): what :func:`cached_interval` and :func:`cached_rows` read, fixed while the held configuration
    is held.

    ``jump_w``, ``jump_thr``: the model's torque-jump test (:func:`.kalman.step_statistic`); ``ramp`` the input
    over an interval: 0.0 held at its start sample, 1.0 linear to the next one (the log's input hold), ``delay`` the
    time (s) by which the linear torques reach the mechanism after their samples (a truth's table held over its
    own step: half of it); ``q0`` the held
    configuration with its refresh radius ``rad`` and reach ``meas_rad`` (how far from it a step map may be built);
    ``h_min`` the shortest
    sub-step; the step map's rebuild rule: the interval-length tolerance ``dt_tol``, the look-ahead ``ahead``,
    ``horizon`` (:func:`map_lookahead`), the process noise's ``torque_var`` and ``q_extra`` (may be empty), the
    radius rule ``rad_tol``, ``rad_min``, ``rad_max`` (:func:`next_map_radius`); the measurement rows ``c0, Hm,
    D, G`` (:func:`measurement_rows`) about ``rows_q0``, serving within ``rows_rad`` of it; the secant ``d``, ``dd``; the step Jacobian's velocity forms ``Ts, Vs,
    C3``; ``errs``, where the replaced maps' errors go (its length bounds the rebuilds of one call); the held
    system (:class:`HeldSystem`)."""

    jump_w: np.ndarray
    jump_thr: float
    ramp: float
    delay: float
    q0: np.ndarray
    rad: float
    meas_rad: float
    h_min: float
    dt_tol: float
    ahead: float
    horizon: float
    torque_var: np.ndarray
    q_extra: np.ndarray
    rad_tol: float
    rad_min: float
    rad_max: float
    c0: np.ndarray
    Hm: np.ndarray
    D: np.ndarray
    G: np.ndarray
    rows_q0: np.ndarray
    rows_rad: float
    d: np.ndarray
    dd: float
    Ts: np.ndarray
    Vs: np.ndarray
    C3: np.ndarray
    errs: np.ndarray
    system: HeldSystem


class LoopMap(NamedTuple):
    """The step map the compiled loop steps with (it rebuilds it where q leaves its radius): its centre ``q``,
    radius ``rad``, interval length ``dt`` in ``n`` sub-steps, the maps ``Pn`` (state), ``SQM`` (held force),
    ``L`` (torque) and the noise ``Q``."""

    q: np.ndarray
    rad: float
    dt: float
    n: int
    Pn: np.ndarray
    SQM: np.ndarray
    L: np.ndarray
    Q: np.ndarray


class LoopState(NamedTuple):
    """What :func:`cached_interval` carries from one interval to the next: the step map, the maps rebuilt so far
    (their errors in :attr:`CachedStep.errs`), the sample the last was built for (-1: none) and the augmented
    state's scaled step map ``(ok, c, Pn, S, L, Q)`` (:func:`payload_interval`)."""

    map: LoopMap
    n_maps: int
    k_map: int
    scaled: tuple


def _system_args(hs):  # pragma: no cover - compiled
    """The held system's fields as a plain tuple (numba passes ``f(a, *t)`` as a tuple concatenation, which a
    named tuple does not join)."""
    return (hs.has_old, hs.beta, hs.Mr, hs.Kr, hs.Ca, hs.Gr, hs.dM, hs.dK, hs.fg, hs.T2, hs.V2, hs.C2, hs.old_dM,
            hs.old_dK, hs.old_Ca, hs.old_Gr, hs.old_fg, hs.old_T2, hs.old_V2, hs.old_C2, hs.pM, hs.pK, hs.pC, hs.pG,
            hs.p2C, hs.Wg, hs.old_Wg, hs.pT, hs.pC2, hs.KGd, hs.We, hs.dKGd, hs.dT2, hs.dV2, hs.dC2, hs.Me)


def _cached_interval(cs, ex, st, x, u, u1, dt, first, k, P):  # pragma: no cover - compiled
    """One interval of the cached step as :meth:`.reduced.ReducedObserverModel.predict` (or, with ``ex``,
    :meth:`.augmented.AugmentedModel.predict`) takes it from the filter's state ``x`` with the torques ``u``
    over ``dt`` (``u1`` the sample that ends it: the torques ``u + (t / dt) cs.ramp (u1 - u)``, held where
    ``ramp`` is 0, linear where 1, the log's input hold), where the held arrays ``cs`` (:class:`CachedStep`) serve:
    ``(status, z, F, Q, mats, st)``, the prediction, the interval's held matrices ``(M_r, K_r, C_r, G_r)`` and
    the carried state (:class:`LoopState`). ``status`` (:mod:`.base`'s loop codes) is ``LOOP_DONE`` where it
    served, ``REFRESH`` where q left the held configuration's radius, ``REMAP`` where the step map must be
    renewed from Python (another interval length or sub-step count; :attr:`CachedStep.errs` full), ``GENERAL``
    where the model's own step must take the interval (a torque jump, a held payload scale its linearity test
    releases).

    Not at the ``first`` interval (the model renewed its arrays for it): where q leaves the step map's radius
    the map is rebuilt ahead of q (:func:`rebuild_map`), its radius from the replaced map's error in the
    covariance prediction from the filter's ``P`` (:func:`map_error`, :func:`next_map_radius`).

    ``ex`` (:class:`LoopExtras`) holds an augmented state's arrays; None for a plain state (numba then prunes
    the augmented branches from the compiled code). With ``pay`` the state is ``[z; theta]``: the interval is
    :func:`payload_interval`'s at ``c + pay_dtheta`` and ``c = max(theta, 0) - 1`` with the increment ``i*``
    and ``pay_var dt`` the scale's noise (:func:`extra_interval`). With ``inp_var`` (not empty) the state ends
    with a torque disturbance per motor, added to the torques (the torque-jump test's too)."""
    sm, n_maps, k_map, scaled = st
    hs = _system_args(cs.system)
    nq = cs.q0.shape[0]
    n0 = 2 * cs.system.Mr.shape[0]
    none = np.empty((0, 0))
    z, F, Qk = x, none, none
    mats = (none, none, none, none)
    uu, uu1 = u, u1
    pay, n_in = False, 0
    if ex is not None:  # (pruned for a plain state, as every "ex is not None" below)
        pay, n_in = ex.pay, ex.inp_var.shape[0]
        if n_in:  # the torques with the disturbance
            s0 = x.shape[0] - n_in
            uu, uu1 = np.empty(u.shape[0]), np.empty(u.shape[0])
            for j in range(u.shape[0]):
                uu[j] = u[j]
                uu1[j] = u1[j]
            for j in range(n_in):
                uu[j] = u[j] + x[s0 + j]
                uu1[j] = u1[j] + x[s0 + j]
    if step_statistic(uu, uu1, cs.jump_w) > cs.jump_thr:
        return GENERAL, z, F, Qk, mats, st
    n = max(1, math.ceil(dt / cs.h_min - 1e-9))
    if not first:  # (the model's arrays are renewed for the first interval)
        if not _within(x, cs.q0, cs.rad):
            return REFRESH, z, F, Qk, mats, st
        same_length = abs(sm.dt - dt) <= cs.dt_tol * dt
        if not (same_length and _within(x, sm.q, sm.rad)):
            if not (same_length and n == sm.n) or n_maps == cs.errs.shape[0]:
                return REMAP, z, F, Qk, mats, st
            # the step map rebuilt ahead of q, its radius from the replaced map's error
            q_new, Pn_new, SQM, L, Q_new = rebuild_map(x[:n0], cs.q0, cs.meas_rad, sm.rad, cs.ahead, cs.horizon, cs.d,
                                                       cs.dd, dt, n, cs.torque_var, cs.q_extra, hs)
            err = map_error(sm.Pn, Pn_new, sm.Q, Q_new, P)
            rad = next_map_radius(q_new, sm.q, err, sm.rad, cs.rad_tol, cs.rad_min, cs.rad_max)
            cs.errs[n_maps] = err
            n_maps += 1
            k_map = k
            sm = LoopMap(q_new, rad, dt, sm.n, Pn_new, SQM, L, Q_new)
            if ex is not None:  # the scaled map follows the nominal one
                scaled = (False, scaled[1], scaled[2], scaled[3], scaled[4], scaled[5])
    dl = x[:nq] - cs.q0
    s = secant_factor(dl, cs.d, cs.dd)
    du = np.empty(u.shape[0] if cs.ramp else 0)  # the torques' change over the interval: linear (empty: held)
    for j in range(du.shape[0]):
        du[j] = u1[j] - u[j]
    if cs.ramp and cs.delay != 0.0:  # the ramp delayed: its value at the interval's start
        c = cs.delay / dt
        u0 = np.empty(u.shape[0])
        for j in range(u.shape[0]):
            u0[j] = u[j] - c * du[j]
        u = u0
        if ex is not None:  # the torques with the disturbance, delayed as well
            if n_in:
                for j in range(n_in):
                    uu[j] = u0[j] + x[x.shape[0] - n_in + j]
            else:
                uu = u0
    extra = False
    if ex is not None:  # noqa: SIM102 (numba prunes a plain state's branch on this test alone)
        if pay or n_in:
            z, F, Qk, Mo, Ko, Co, Go, new_scaled, release = extra_interval(
                x, uu, du, dl, s, dt, n, ex, P[n0, n0], scaled, (sm.Pn, sm.SQM, sm.L, sm.Q, cs.torque_var, cs.q_extra),
                (cs.Ts, cs.Vs, cs.C3), hs)
            if release:  # the held scale's linearity test passes: the model's own step releases it
                return GENERAL, z, F, Qk, mats, LoopState(sm, n_maps, k_map, scaled)
            scaled = new_scaled
            mats = (Mo, Ko, Co, Go)
            extra = True
    if not extra:
        z, F, Mo, Ko, Co, Go = held_interval(x, u, du, dl, s, dt / n, n, cs.Ts, cs.Vs, cs.C3, sm.Pn, sm.SQM, hs)
        Qk = sm.Q
        mats = (Mo, Ko, Co, Go)
    return LOOP_DONE, z, F, Qk, mats, LoopState(sm, n_maps, k_map, scaled)


def _cached_rows(cs, z, y, H, made):  # pragma: no cover - compiled
    """The measurement at the predicted state ``z`` into ``y``, ``H`` (:meth:`.reduced.ReducedObserverModel.
    measure` with every channel): ``LOOP_DONE``; nothing written where ``z`` is not finite (``GENERAL``) or
    left the rows' radius (``ROWS``: the model rebuilds them; not where they were ``made`` for ``z``)."""
    if not math.isfinite(z[0]):
        return GENERAL
    if not made and not _within(z, cs.rows_q0, cs.rows_rad):
        return ROWS
    measurement_rows(cs.c0, cs.Hm, cs.D, cs.G, z, z[: cs.rows_q0.shape[0]] - cs.rows_q0, y, H)
    return LOOP_DONE


def _extra_interval(x, u, du, dl, s, dt, n, ex, var, scaled, maps, forms, hs):  # pragma: no cover - compiled
    """One interval of an augmented state (:func:`cached_interval`'s ``ex``, the torques ``u`` with the
    disturbances, ``u + (t / dt) du`` over the interval; ``var`` the filter's variance of the payload scale): ``(x_next, F, Q, M_r, K_r, C_r, G_r, scaled,
    release)``, the scaled step map ``scaled = (pay_ok, pay_c, pay_Pn, pay_S, pay_L, pay_Q)`` as this interval
    leaves it; ``maps = (Pn, SQM, L, Q, torque_var, q_extra)`` the nominal step map with the noise's parts, ``forms = (Ts, Vs,
    C3)`` the step Jacobian's; ``hs`` the held system (plain tuples, see :func:`_held_interval`). With the payload
    scale not at exactly 1 the interval is :func:`payload_interval`'s at ``c + pay_dtheta`` and ``c`` (which
    chooses, and rebuilds, the step map: the nominal one or the scaled ``pay_*``); at exactly 1 and without the
    scale, :func:`held_interval`'s (with the scale, the steps at ``pay_dtheta`` for its column:
    :func:`scaled_steps`). The disturbances then decay, gain their noise and enter through
    the map's torque response.

    A ``held`` scale (:meth:`.augmented.AugmentedModel.predict`): the steps at ``c +- sigma`` (``sigma`` the
    filter's standard deviation of the scale, within ``[pay_dtheta, 1 + c]``) and ``c``; where the first-order model
    over them is within ``lin_tol`` of the interval's process noise (its second-order term, measured into
    ``stats[1]``), ``release`` and the scale's column their central difference (the model's own step releases it),
    else the noise the scale's uncertainty causes added to ``Q`` and no column of the scale in ``F``."""
    pay, pay_var, pay_dtheta, pay_rho, pay_tol, pay_dTs = ex.pay, ex.pay_var, ex.pay_dtheta, ex.pay_rho, ex.pay_tol, ex.pay_dTs
    held, lin_tol, stats, inp_var, inp_tau = ex.pay_held, ex.pay_lin_tol, ex.pay_stats, ex.inp_var, ex.inp_tau
    inc = (ex.iMr, ex.iCa, ex.idM, ex.ifg, ex.iT2, ex.iC2, ex.iold_dM, ex.iold_Ca, ex.iold_fg, ex.iold_T2, ex.iold_C2)
    Pn, SQM, L, Q = maps[0], maps[1], maps[2], maps[3]
    Ts, Vs, C3 = forms
    n_x = x.shape[0]
    n0 = 2 * hs[2].shape[0]
    n_in = inp_var.shape[0]
    s0 = n_x - n_in
    release = False
    if pay:
        th = x[n0]
        c = max(th, 0.0) - 1.0
        sig = max(min(math.sqrt(max(var, 0.0)), 1.0 + c), pay_dtheta) if held else pay_dtheta
        scales = np.empty((2 if held else 1) + (1 if c != 0.0 else 0))
        scales[0] = c + sig
        if held:
            scales[1] = c - sig
        if c != 0.0:  # the held system at the scale c (and the scales of the column) in one call
            scales[-1] = c
            rows, z, F, Qk, L_u, scaled, Mo, Ko, Co, Go = payload_interval(
                x[:n0], (u, du), dl, s, dt / n, n, scales, th, n_x, (0.0 if held else pay_dtheta, pay_var * dt, pay_rho,
                                                               pay_tol), scaled, maps, (Ts, pay_dTs, Vs, C3), hs, inc)
            xc = rows[-1]
        else:  # the nominal step, and the scaled steps of the same held configuration for the scale's column
            xc, F0, Mo, Ko, Co, Go = held_interval(x[:n0], u, du, dl, s, dt / n, n, Ts, Vs, C3, Pn, SQM, hs)
            z, F, Qk = _augmented(xc, F0, Q, n_x)
            L_u = L
            rows = scaled_steps(x[:n0], u, du, dl, s, dt / n, n, scales, hs, inc)[0]
            if not np.all(np.isfinite(rows)):  # as the nominal step's rescue: first order only
                rows = scaled_steps(x[:n0], u, du, dl, 0.0, dt / n, n, scales, hs, inc)[0]
            z[n0] = th
            F[n0, n0] = 1.0
            Qk[n0, n0] = pay_var * dt
            if not held:
                for i in range(n0):
                    F[i, n0] = (rows[0, i] - xc[i]) / pay_dtheta
        if held:  # the first-order model over +-sigma: its second-order term against the interval's noise
            lin, nan = 0.0, False
            for i in range(n0):
                v = abs(0.5 * (rows[0, i] + rows[1, i]) - xc[i]) / math.sqrt(max(Qk[i, i], 1e-300))
                nan |= math.isnan(v)
                lin = max(lin, v)
            stats[1] = math.nan if nan else lin
            release = stats[1] <= lin_tol
            for i in range(n0):  # released: the column over +-sigma; else the scale's uncertainty as noise
                e1 = 0.5 * (rows[0, i] - rows[1, i])
                if release:
                    F[i, n0] = e1 / sig
                for j in range(n0):
                    Qk[i, j] += 0.0 if release else e1 * 0.5 * (rows[0, j] - rows[1, j])
    else:
        z0, F0, Mo, Ko, Co, Go = held_interval(x[:n0], u, du, dl, s, dt / n, n, Ts, Vs, C3, Pn, SQM, hs)
        z, F, Qk = _augmented(z0, F0, Q, n_x)
        L_u = L
    if n_in:  # the disturbances: their decay, noise and the step's response to them
        phi = math.exp(-dt / inp_tau) if inp_tau > 0.0 else 1.0
        for j in range(n_in):
            z[s0 + j] = phi * x[s0 + j]
            F[s0 + j, s0 + j] = phi
            Qk[s0 + j, s0 + j] = inp_var[j] * (1.0 - phi * phi) if inp_tau > 0.0 else inp_var[j] * dt
            for i in range(n0):
                F[i, s0 + j] = L_u[i, j]
    return z, F, Qk, Mo, Ko, Co, Go, scaled, release


def _augmented(z, F, Q, nx):  # pragma: no cover - compiled
    """``(x, F, Q)`` of an augmented state of ``nx``: the step's in the leading entries, zeros elsewhere."""
    n0 = z.shape[0]
    xa = np.zeros(nx)
    Fa = np.zeros((nx, nx))
    Qa = np.zeros((nx, nx))
    for i in range(n0):  # loops, not slice assignments (see _rk4_linear)
        xa[i] = z[i]
        for j in range(n0):
            Fa[i, j] = F[i, j]
            Qa[i, j] = Q[i, j]
    return xa, Fa, Qa


def _map_error(Pn_old, Pn_new, Q_old, Q_new, P):  # pragma: no cover - compiled
    """The error of the step map ``Pn_old`` where ``Pn_new`` is built, in the covariance prediction from ``P``
    (:meth:`.reduced.ReducedObserverModel._step_map`): with ``E = Pn_old - Pn_new`` and ``sigma_i^2 =
    (Pn_new P Pn_new' + Q_new)_ii``, ``max_i (sqrt((E P E')_ii) + |Q_new,ii - Q_old,ii| / (2 sigma_i)) / sigma_i``.
    ``P`` may be larger than the maps (an augmented state): its leading block is used.

    To first order this bounds the relative change of every predicted standard deviation (the first term from
    the state map, the second from the process noise). The step Jacobian's velocity-force correction ``S dF/dz``
    is left out of both (the maps' ``S`` change along with ``P^n``, and the correction is small against ``P^n``);
    with it the measure costs more than the rebuild it decides on."""
    nx = Pn_new.shape[0]
    e = np.empty(nx)
    err = 0.0
    for i in range(nx):
        for j in range(nx):
            e[j] = Pn_old[i, j] - Pn_new[i, j]
        de = 0.0
        dn = 0.0
        for a in range(nx):  # (e P e', p P p') with p the row of Pn_new
            sa = 0.0
            sn = 0.0
            for b in range(nx):
                sa += P[a, b] * e[b]
                sn += P[a, b] * Pn_new[i, b]
            de += e[a] * sa
            dn += Pn_new[i, a] * sn
        var = max(dn + Q_new[i, i], 1e-300)
        sig = math.sqrt(var)
        err = max(err, (math.sqrt(max(de, 0.0)) + 0.5 * abs(Q_new[i, i] - Q_old[i, i]) / sig) / sig)
    return err


def _rebuild_map(z, q0, lim, map_rad, ahead, horizon, d, dd, dt, n, torque_var, q_extra, hs):  # pragma: no cover - compiled
    """A step map of the held configuration ``q0`` for an interval of ``dt`` in ``n`` sub-steps, built ahead of
    ``q`` along its motion (:func:`map_lookahead`, not beyond ``lim`` from ``q0``): the held model there,
    undeformed (:func:`_system`, along the secant ``d``; the elastic coordinates of the instant of the rebuild
    would stay in the map while they oscillate, measured in docs/step_jacobian.md) and its maps :func:`step_maps_noise`, ``q_extra`` (may be empty)
    added to the noise's diagonal. ``hs``: the held system (a plain tuple, see :func:`_held_interval`). Returns
    ``(q_map, P^n, S, L, Q)`` (:meth:`.reduced.ReducedObserverModel._step_map`)."""
    nq = q0.shape[0]
    shift = map_lookahead(z, nq, map_rad, ahead, horizon)
    dla = np.empty(nq)
    for i in range(nq):
        dla[i] = min(max((z[i] - q0[i]) + shift[i], -lim), lim)
    s = secant_factor(dla, d, dd)
    Ma, Ka, Ca_, Ga = _system(dla, s, z[:0], HeldSystem(*hs))
    Pn, S, L, Q = step_maps_noise(Ma, Ka, Ca_, Ga, dt / n, n, torque_var)
    for i in range(q_extra.shape[0]):
        Q[i, i] += q_extra[i]
    q = np.empty(nq)
    for i in range(nq):
        q[i] = q0[i] + dla[i]
    return q, Pn, S, L, Q


def _next_map_radius(q_new, q_old, err, map_rad, tol, rmin, rmax):  # pragma: no cover - compiled
    """The map radius after a rebuild at ``q_new`` where the map of ``q_old`` had the error ``err``
    (:func:`map_error`): the error grows linearly with the distance between the maps' centres, and a map serves up
    to one radius from its centre, so the radius ``tol * dist / (2 err)`` keeps its largest error in use near
    ``tol / 2``; at most twice the last radius, within ``[rmin, rmax]``."""
    dist = 0.0
    for i in range(q_new.shape[0]):
        dist = max(dist, abs(q_new[i] - q_old[i]))
    rad = 2.0 * map_rad if not err > 0 else tol * dist / (2.0 * err)
    return min(max(rad, rmin), 2.0 * map_rad, rmax)


def _scaled_steps(z, u, du, dl, s, h, n, a, hs, inc):  # pragma: no cover - compiled
    """The held step (:func:`held_step`) of the system ``S + a_k dS`` for each entry ``a_k`` of ``a``:
    row ``k`` is the state at the interval's end for the payload scale ``1 + a_k``. Returns ``(rows, M_r, K_r,
    C_r, G_r)``, the held matrices those of the last scale; the torques ``u + (t / T) du`` (:func:`held_interval`).
    ``hs``: the held system (a plain tuple, see
    :func:`_held_interval`); ``inc``: the payload's increment ``dS`` (:class:`.augmented.PayloadIncrement`'s fields,
    a plain tuple).

    The held model (:func:`_held_model`) is linear in the held arrays, and the stiffness, input matrix
    and geometric forms do not depend on the payload: it is evaluated once for ``S`` and once for ``dS`` (with
    zero stiffness, input and geometric arrays) and combined per scale, ``M_r = M_r(S) + a_k M_r(dS)``, likewise
    the damping and the forces (the weight, the velocity forms and the bias force ``J^T M a_b``, the increment's
    ``iC2``); each scale then costs its Cholesky factor and RK4 sub-steps only."""
    hs = HeldSystem(*hs)
    iMr, iCa, idM, ifg, iT2, iC2, iold_dM, iold_Ca, iold_fg, iold_T2, iold_C2 = inc
    r = hs.Mr.shape[0]
    zr, zg, zq = np.zeros((r, r)), np.zeros(hs.Gr.shape), np.zeros(hs.dK.shape)
    zv = np.zeros(hs.V2.shape)
    ze = np.zeros((0, 0))  # the increment's elastic-coordinate terms: none (the payload's share of them is left out)
    di = HeldSystem(hs.has_old, 0.0, iMr, zr, iCa, zg, idM, zq, ifg, iT2, zv, iC2, iold_dM, zq, iold_Ca, zg, iold_fg,
                    iold_T2, zv, iold_C2, ze, ze, ze, ze, ze, ze, ze, ze, ze, ze, ze, ze, ze, ze, ze, ze)
    M0 = K0 = C0 = Mb = Cb = np.empty((r, r))
    G0 = np.empty(hs.Gr.shape)
    f0 = fb = np.empty(r)
    for k in range(2):  # the nominal's and the increment's held model, one inlined copy of it for both
        Mk, Kk, Ck, Gk, fk = _held_model(z, dl, s, 0.5 * h * n, hs if k == 0 else di,
                                         0.5 * h * n if du.shape[0] else 0.0)
        if k == 0:
            M0, K0, C0, G0, f0 = Mk, Kk, Ck, Gk, fk
        else:
            Mb, Cb, fb = Mk, Ck, fk
    # the nominal's geometric forces of the motion (held_interval's; the payload's share of the axial loads left out)
    um = u.copy()  # the torques at the interval's midpoint (held_interval's)
    for j in range(du.shape[0]):
        um[j] += 0.5 * du[j]
    motion_forces(f0, z, 0.5 * h * n, motion_stiffness(um, z, dl.shape[0], _motion_form(hs.KGd, hs.dKGd, dl)))
    out = np.empty((a.shape[0], z.shape[0]))
    M, C, f = np.empty((r, r)), np.empty((r, r)), np.empty(r)
    for k in range(a.shape[0]):
        c = a[k]
        for i in range(r):  # loops, not array expressions (see _mass_stiffness)
            for j in range(r):
                M[i, j] = M0[i, j] + c * Mb[i, j]
                C[i, j] = C0[i, j] + c * Cb[i, j]
            f[i] = f0[i] + c * fb[i]
        x = _rk4_linear(z, u, du, M, K0, C, G0, f, h, n)
        for i in range(z.shape[0]):
            out[k, i] = x[i]
    return out, M, K0, C, G0


def _payload_interval(z, ud, dl, s, h, n, a, theta, nx, scale, scaled, maps, forms, hs, inc):  # pragma: no cover - compiled
    """One interval of the cached step with the payload scaled (:meth:`.augmented.AugmentedModel.predict`).

    The steps at the scales ``1 + a_k`` (:func:`scaled_steps` of the held system ``hs`` and the increment ``inc``;
    the last entry of ``a`` is the interval's own scale ``c``), taken again without the secant (``s = 0``, first
    order) if one is not finite; the held matrices at ``c``; the step map: the nominal one, ``maps = (Pn, SQM, L,
    Q, torque_var, q_extra)`` with the noise's parts, where the payload's change of the modal masses ``|c| rho`` is
    within ``tol`` (``scale = (dtheta, theta_var, rho, tol)``), else the scaled one, ``scaled = (map_ok, map_c,
    map_Pn, map_S, map_L, map_Q)``, built at the scale ``map_c``, where it is the current nominal map's
    (``map_ok``) and ``c`` is within ``tol / rho`` of ``map_c``, else rebuilt as the maps of the held linear system
    at ``c`` (:func:`step_maps_noise`, ``q_extra``, may be empty, added to the noise's diagonal); and the step's
    Jacobian in the state (:func:`step_jacobian`) with that map and, of ``forms = (Ts, dTs, Vs, C3)``, the velocity
    forms ``Ts + c dTs`` and bias form ``C3 + c iC2`` (``Ts``, ``C3`` with the nominal map). The tuples are plain
    (see :func:`_held_interval`).

    Returns ``(rows, x, F, Qx, L, (map_ok, map_c, map_Pn, map_S, map_L, map_Q), M_r, K_r, C_r, G_r)`` with the
    augmented state's prediction (``nx`` states, the scale ``theta`` after the ``n0 = 2 r`` reduced ones, zeros
    beyond), the map's torque response and the scaled map as the interval leaves it: ``x = [rows[-1]; theta; 0]``,
    ``F`` the step's Jacobian in its leading block, the scale's column the forward difference
    ``(rows[0] - rows[-1]) / dtheta`` (zero where ``dtheta`` is zero) and ``F[n0, n0] = 1``, ``Qx`` the process
    noise ``Q`` in its leading block and ``theta_var`` the scale's. ``ud = (u, du)``: the torques ``u + (t / T) du``
    over the interval (:func:`held_interval`)."""
    u, du = ud
    dtheta, theta_var, rho, tol = scale
    map_ok, map_c, map_Pn, map_S, map_L, map_Q = scaled
    Pn, SQM, L, Q, torque_var, q_extra = maps
    Ts, dTs, Vs, C3 = forms
    iC2 = inc[5]
    rows, Mo, Ko, Co, Go = scaled_steps(z, u, du, dl, s, h, n, a, hs, inc)
    finite = True
    for k in range(rows.shape[0]):
        for i in range(rows.shape[1]):
            if not math.isfinite(rows[k, i]):
                finite = False
    if not finite:  # as the nominal step's rescue: first order only
        rows, Mo, Ko, Co, Go = scaled_steps(z, u, du, dl, 0.0, h, n, a, hs, inc)
    c = a[a.shape[0] - 1]
    scaled = abs(c) * rho > tol
    cT = c if scaled else 0.0
    if scaled and map_ok and abs(c - map_c) * rho <= tol:
        Pn, SQM, L, Q = map_Pn, map_S, map_L, map_Q
    elif scaled:  # (re)built at c: the scaled map of the current nominal map
        Pn, SQM, L, Q = step_maps_noise(Mo, Ko, Co, Go, h, n, torque_var)
        for i in range(q_extra.shape[0]):
            Q[i, i] += q_extra[i]
        map_ok, map_c, map_Pn, map_S, map_L, map_Q = True, c, Pn, SQM, L, Q
    T = np.empty(Ts.shape)
    for i in range(Ts.shape[0]):  # loops, not array expressions (see _mass_stiffness)
        for j in range(Ts.shape[1]):
            for k in range(Ts.shape[2]):
                T[i, j, k] = Ts[i, j, k] + cT * dTs[i, j, k]
    C = C3.copy()  # the bias form with the payload's share (iC2 is C3's flattening, [k * nq + j, c])
    if iC2.shape[0]:
        for k in range(C3.shape[0]):
            for j in range(C3.shape[1]):
                for i in range(C3.shape[2]):
                    C[k, j, i] += cT * iC2[k * C3.shape[1] + j, i]
    Fz = step_jacobian(z, T, Vs, C, Pn, SQM, _NO_MATRIX)  # (the forces' change with q left out, as by no gravity)
    n0 = z.shape[0]
    last = rows.shape[0] - 1
    x = np.zeros(nx)
    F = np.zeros((nx, nx))
    Qx = np.zeros((nx, nx))
    for i in range(n0):  # loops, not slice assignments (see expansion._rk4_linear)
        x[i] = rows[last, i]
        for j in range(n0):
            F[i, j] = Fz[i, j]
            Qx[i, j] = Q[i, j]
        if dtheta != 0.0:
            F[i, n0] = (rows[0, i] - rows[last, i]) / dtheta
    x[n0] = theta
    F[n0, n0] = 1.0
    Qx[n0, n0] = theta_var
    return rows, x, F, Qx, L, (map_ok, map_c, map_Pn, map_S, map_L, map_Q), Mo, Ko, Co, Go


_times_hA = _shared(_times_hA)
map_lookahead = _shared(map_lookahead)
_motion_coefficients = _shared(_motion_coefficients)
motion_stiffness = _shared(_motion_stiffness)
motion_gradient = _shared(_motion_gradient)
motion_forces = _shared(_motion_forces)
_rate_response = _shared(_rate_response)
motion_rates = _shared(_motion_rates)
_motion_form = _shared(_motion_form)
motion_form_gradient = _shared(_motion_form_gradient)
_ramps = _inline(_ramps)
held_ramp = _jit(_rk4_linear)  # called from Python (the reference step's response to a torque ramp)
_rk4_linear = _linked(_rk4_linear)
_quadratic_forces = _linked(_quadratic_forces)
_velocity_terms = _linked(_velocity_terms)
_velocity_jacobian = _inline(_velocity_jacobian)
_weight_rates = _inline(_weight_rates)
_elastic_tangent = _linked(_elastic_tangent)
_held_model = _linked(_held_model)
step_jacobian = _jit(_step_jacobian)
position_forces = _jit(_position_forces)
_weight_curvature_forces = _shared(_weight_curvature_forces)
_mass_curvature_forces = _shared(_mass_curvature_forces)
_forms_gradient = _shared(_forms_gradient)
_forms_gradient_forces = _shared(_forms_gradient_forces)
held_system = _jit(_held_system)
held_interval = _jit(_held_interval)
measurement_rows = _jit(_measurement_rows)
secant_factor = _jit(_secant_factor)
prediction_error = _jit(_prediction_error)
step_maps_noise = _jit(_step_maps_noise)
_within = _inline(_within)
_augmented = _inline(_augmented)
scaled_steps = _jit(_scaled_steps)
payload_interval = _jit(_payload_interval)
extra_interval = _jit(_extra_interval)
_system_args = _inline(_system_args)
cached_interval = _inline(_cached_interval)
cached_rows = _inline(_cached_rows)
map_error = _jit(_map_error)
rebuild_map = _jit(_rebuild_map)
next_map_radius = _jit(_next_map_radius)


def _example_system(r: int = 2, nq: int = 1, has_old: bool = False) -> HeldSystem:
    """A small held system (for compiling the kernels, and for tests)."""
    M, g2, f = np.eye(r), np.zeros((nq, r * r)), np.zeros(r)
    T2, V2, C2 = np.zeros((r, r * r)), np.zeros((nq * r, r)), np.zeros((r * nq, r))
    G = np.zeros((r, nq))
    pf, pg = np.zeros((r - nq, nq * r)), np.zeros((r - nq, nq * (nq + 1)))
    p2 = np.zeros((nq * (nq + 1) // 2, (r - nq) * (r - nq + 1) // 2))
    return HeldSystem(has_old, 0.0, M, M, M, G, g2, g2, f, T2, V2, C2, g2, g2, M, G, f, T2, V2, C2, pf, pf, pf, pg,
                      p2, np.zeros((0, 0)), np.zeros((0, 0)), np.zeros((0, 0)), np.zeros((0, 0)),
                      np.zeros((0, 0)), np.zeros((0, 0)), np.zeros((0, 0)), np.zeros((0, 0)), np.zeros((0, 0)),
                      np.zeros((0, 0)), np.zeros((0, 0)))


_warm = False


def warm_up_held() -> None:
    """Compile (or load from numba's on-disk cache) the kernel of the held configuration's renewal (called from
    Python; no other kernel calls it): :func:`prediction_error`. (:func:`held_system`, which the observer does not
    call, compiles at its first call.)"""
    r, nq = 2, 1
    dl = np.zeros(nq)
    M = np.eye(r)
    for has_old in (False, True):
        prediction_error(dl, 0.0, M, M, tuple(_example_system(r, nq, has_old)))


def warm_up_interval() -> None:
    """Compile (or load) :func:`held_interval` with the step Jacobian it calls (:func:`step_jacobian`, called from
    Python too, at the step map's rebuilds)."""
    r, nq = 2, 1
    z, u, dl = np.zeros(2 * r), np.zeros(nq), np.zeros(nq)
    jac = (np.zeros((r, r, r)), np.zeros((nq, r, r)), np.zeros((r, nq, r)), np.eye(2 * r), np.zeros((2 * r, r)))
    step_jacobian(z, *jac, np.zeros((0, 0)))
    for has_old in (False, True):
        held_interval(z, u, u, dl, 0.0, 1e-4, 1, *jac, tuple(_example_system(r, nq, has_old)))


def warm_up_maps() -> None:
    """Compile (or load) the step map's kernels and the measurement rows': :func:`rebuild_map` (with
    :func:`step_maps_noise` and :func:`secant_factor`, each also as Python calls it), :func:`map_error`,
    :func:`next_map_radius`, :func:`measurement_rows`."""
    r, nq = 2, 1
    z, dl = np.zeros(2 * r), np.zeros(nq)
    M, G = np.eye(r), np.zeros((r, nq))
    step_maps_noise(M, M, M, G, 1e-4, 1, np.ones(nq))
    secant_factor(dl, dl, 1.0)
    rebuild_map(z, dl, 1.0, 0.1, 0.0, 0.0, dl, 0.0, 1e-4, 1, np.ones(nq), np.zeros(2 * r), tuple(_example_system(r, nq)))
    map_error(np.eye(2 * r), np.eye(2 * r), M, M, np.eye(2 * r))
    next_map_radius(dl, dl, 0.0, 0.1, 0.5, 0.01, 1.0)
    measurement_rows(np.zeros(1), np.zeros((1, 2 * r)), np.zeros((nq, 1, r)), np.zeros((1, nq, nq)), z, dl,
                     np.empty(1), np.empty((1, 2 * r)))


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) the kernels once per process, so that the first interval of
    a filter does not carry it (:func:`warm_up_held`, :func:`warm_up_interval`, :func:`warm_up_maps`; the
    filter's sample loop: :func:`.loop.warm_up`)."""
    global _warm
    if _warm:
        return
    warm_up_held()
    warm_up_interval()
    warm_up_maps()
    _warm = True

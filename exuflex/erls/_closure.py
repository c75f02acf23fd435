"""Newton iteration of the loop-closure equations, compiled with numba when it is installed.

The cached observer evaluates the configuration about 30 times in 3 s, each time solving the closure from the
last solution (two or three Newton steps). In NumPy, each step is a dozen small array operations whose call
overhead is most of the cost (about 0.4 ms per solve); compiled, the same arithmetic takes a few
microseconds. :meth:`exuflex.erls.kinematics.Kinematics._newton_numpy` is the reference, and
``tests/test_kinematics.py`` checks that the two agree.

The equations are those of :class:`~exuflex.erls.kinematics.Kinematics`, described by a
:class:`ClosureArrays` of index arrays: position equations ``k`` (rows ``2k, 2k+1``) join point ``esa[k]`` of
link ``ea[k]`` to point ``esb[k]`` of link ``eb[k]`` (or to the ground point ``eg[k]`` where ``ebm[k] = 0``);
scalar equations ``j`` (rows after them) read

``cn[j] . p(ca[j], cs[j]) + cw[j] th[ca[j]] - cwr[j] th[cr[j]] - coff[j] - q[cq[j]] = 0``

with ``p(a, s)`` the point at station ``s`` of link ``a`` and no ``q`` term where ``cq[j] < 0``: an angle
coordinate (``cn = 0``, ``cw = 1``), a prismatic joint's line (``cn`` its normal, ``cw = 0``), a slide
coordinate (``cn`` its axis) or a weld's angle (``cw = cwr = 1``, no ``q``).

The Newton iteration and the pose are compiled into the kernels that call them (``_inline``; the ``*_inline``
twins of the public kernels are what :mod:`._assembly` and :mod:`exuflex.reduction._compiled` call): see
:mod:`exuflex.reduction._compiled` for why. The small helpers they call at several places (the residual, the
Jacobian, the solve, the norms) are compiled once and called there, not copied into each place.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

try:
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None
    HAVE_NUMBA = False

_xgesv = None  # numba's LAPACK helper, see _solve_lapack
if HAVE_NUMBA:
    try:
        from numba import types as _nbt
        from numba.np.linalg import F_INT_nbtype
        from numba.np.linalg import F_INT_nptype as _F_INT

        _KIND_D = ord("d")  # float64
        # int numba_xgesv(char kind, intp n, intp nrhs, double *a, intp lda, F_INT *ipiv, double *b, intp ldb)
        _xgesv = _nbt.ExternalFunction("numba_xgesv", _nbt.intc(_nbt.char, _nbt.intp, _nbt.intp,
                                                                 _nbt.CPointer(_nbt.float64), _nbt.intp,
                                                                 _nbt.CPointer(F_INT_nbtype),
                                                                 _nbt.CPointer(_nbt.float64), _nbt.intp))
    except ImportError:  # pragma: no cover - a numba without these names: _solve is np.linalg.solve
        _xgesv = None

__all__ = ["HAVE_NUMBA", "ClosureArrays", "closure_newton", "coordinate_rates", "pose_sensitivities"]


class ClosureArrays(NamedTuple):
    """The closure equations as arrays (see the module docstring); ``J0`` holds the Jacobian's constant entries
    and ``E = -dPhi/dq``."""

    ea: np.ndarray  # (n_pos,) int
    esa: np.ndarray  # (n_pos,)
    eb: np.ndarray  # (n_pos,) int (0 where the second point is the ground)
    ebm: np.ndarray  # (n_pos,) 1 where the second point is a link
    esb: np.ndarray  # (n_pos,)
    eg: np.ndarray  # (n_pos, 2)
    ca: np.ndarray  # (n_sc,) int
    cs: np.ndarray  # (n_sc,)
    cn: np.ndarray  # (n_sc, 2)
    cw: np.ndarray  # (n_sc,)
    cr: np.ndarray  # (n_sc,) int
    cwr: np.ndarray  # (n_sc,)
    coff: np.ndarray  # (n_sc,)
    cq: np.ndarray  # (n_sc,) int, -1: no coordinate
    J0: np.ndarray  # (n_eq, 3 n_links)
    E: np.ndarray  # (n_eq, nq)


def _residual(z, q, k, out):  # pragma: no cover
    ea, esa, eb, ebm, esb, eg = k.ea, k.esa, k.eb, k.ebm, k.esb, k.eg
    for i in range(ea.shape[0]):
        a, b, m = ea[i], eb[i], ebm[i]
        ta, tb = z[3 * a + 2], z[3 * b + 2]
        out[2 * i] = z[3 * a] + esa[i] * math.cos(ta) - m * (z[3 * b] + esb[i] * math.cos(tb)) - eg[i, 0]
        out[2 * i + 1] = z[3 * a + 1] + esa[i] * math.sin(ta) - m * (z[3 * b + 1] + esb[i] * math.sin(tb)) - eg[i, 1]
    base = 2 * ea.shape[0]
    for j in range(k.ca.shape[0]):
        a = k.ca[j]
        ta = z[3 * a + 2]
        v = (k.cn[j, 0] * (z[3 * a] + k.cs[j] * math.cos(ta)) + k.cn[j, 1] * (z[3 * a + 1] + k.cs[j] * math.sin(ta))
             + k.cw[j] * ta - k.cwr[j] * z[3 * k.cr[j] + 2] - k.coff[j])
        if k.cq[j] >= 0:
            v -= q[k.cq[j]]
        out[base + j] = v


def _jacobian(z, k, J):  # pragma: no cover
    J0 = k.J0
    for i in range(J0.shape[0]):
        for c in range(J0.shape[1]):
            J[i, c] = J0[i, c]
    ea, esa, eb, ebm, esb = k.ea, k.esa, k.eb, k.ebm, k.esb
    for i in range(ea.shape[0]):
        a = ea[i]
        ta = z[3 * a + 2]
        J[2 * i, 3 * a + 2] = -esa[i] * math.sin(ta)
        J[2 * i + 1, 3 * a + 2] = esa[i] * math.cos(ta)
        if ebm[i] > 0:
            b = eb[i]
            tb = z[3 * b + 2]
            J[2 * i, 3 * b + 2] = esb[i] * math.sin(tb)
            J[2 * i + 1, 3 * b + 2] = -esb[i] * math.cos(tb)
    base = 2 * ea.shape[0]
    for j in range(k.ca.shape[0]):
        if k.cs[j] != 0.0:
            a = k.ca[j]
            ta = z[3 * a + 2]
            J[base + j, 3 * a + 2] += k.cs[j] * (-k.cn[j, 0] * math.sin(ta) + k.cn[j, 1] * math.cos(ta))


def _max_abs(v):  # pragma: no cover
    m = 0.0
    for x in v:
        if not abs(x) <= m:  # a NaN wins
            m = abs(x)
    return m


def _solve_lapack(J, b):  # pragma: no cover - compiled
    """``J^-1 b`` by LAPACK's ``dgesv`` called as compiled ``np.linalg.solve`` calls it (numba's helper
    ``numba_xgesv``, the same copies in Fortran order: the same numbers), with its errors: LinAlgError for a
    non-finite or singular ``J``. ``np.linalg.solve`` itself copies ``b`` in by a slice assignment, whose
    compiled shape check brings numba's string-formatting code into every kernel that solves."""
    n = J.shape[0]
    a = np.empty((n, n)).T  # Fortran order: dgesv's column-major input, overwritten by the LU factors
    x = np.empty(n)
    for i in range(n):
        if not math.isfinite(b[i]):
            raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
        x[i] = b[i]
        for j in range(n):
            if not math.isfinite(J[i, j]):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
            a[i, j] = J[i, j]
    ipiv = np.empty(n, dtype=_F_INT)
    info = _xgesv(_KIND_D, n, 1, a.ctypes, n, ipiv.ctypes, x.ctypes, n)
    if info != 0 or a.shape[0] != n or ipiv.shape[0] != n:  # (a and ipiv used after the call: kept alive)
        raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
    return x


def _solve_columns_lapack(A, B):  # pragma: no cover - compiled
    """``A^-1 B`` for ``B`` with several columns, as :func:`_solve_lapack` (compiled ``np.linalg.solve``'s
    ``dgesv`` call on the same Fortran-order copies: the same numbers, and its result in Fortran order as that
    returns it), with its errors."""
    n = A.shape[0]
    m = B.shape[1]
    a = np.empty((n, n)).T
    x = np.empty((m, n)).T
    for i in range(n):
        for j in range(n):
            if not math.isfinite(A[i, j]):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
            a[i, j] = A[i, j]
    for i in range(n):
        for j in range(m):
            if not math.isfinite(B[i, j]):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
            x[i, j] = B[i, j]
    ipiv = np.empty(n, dtype=_F_INT)
    info = _xgesv(_KIND_D, n, m, a.ctypes, n, ipiv.ctypes, x.ctypes, n)
    if info != 0 or a.shape[0] != n or ipiv.shape[0] != n:  # (a and ipiv used after the call: kept alive)
        raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
    return x


def _solve_numpy(J, b):  # pragma: no cover - compiled where numba lacks the names _solve_lapack uses
    return np.linalg.solve(J, b)


def _closure_newton(z0, q, k, tol, max_iter):  # pragma: no cover
    """Newton from ``z0``; returns ``(z, ok)``: ``ok`` False where the kinematics' NumPy Newton returns None
    (non-finite iterate or no convergence). Converged: one more step polishes the solution to round-off.
    A singular Jacobian raises numpy's LinAlgError, as in NumPy."""
    z = z0.copy()
    n = z.shape[0]
    res = np.empty(k.J0.shape[0])
    J = np.empty(k.J0.shape)
    for _ in range(max_iter):
        _residual(z, q, k, res)
        _jacobian(z, k, J)
        if _max_abs(res) < tol:
            return z - _solve(J, res), True
        z += _solve(J, -res)
        for i in range(n):
            if not math.isfinite(z[i]):
                return z, False
    _residual(z, q, k, res)
    return z, _max_abs(res) < 1e3 * tol


def _norm1(A):  # pragma: no cover
    """The matrix 1-norm (largest column sum of |A|), as ``np.linalg.norm(A, 1)``."""
    m = 0.0
    for j in range(A.shape[1]):
        c = 0.0
        for i in range(A.shape[0]):
            c += abs(A[i, j])
        if not c <= m:
            m = c
    return m


def _pose_sensitivities(z, k, node_link, node_station):  # pragma: no cover
    """What :meth:`~exuflex.erls.kinematics.Kinematics.pose` computes after the closure is solved: the inverse
    of the closure Jacobian ``J``, its 1-norm condition number, ``S_z = J^-1 E`` and the nodal poses ``r`` and
    sensitivities ``S`` (rows x, y, theta per node). A singular ``J`` raises numpy's LinAlgError."""
    J = np.empty(k.J0.shape)
    _jacobian(z, k, J)
    Jinv = np.linalg.inv(J)
    cond = _norm1(J) * _norm1(Jinv)
    Sz = Jinv @ k.E
    nn = node_link.shape[0]
    nq = k.E.shape[1]
    r = np.empty(3 * nn)
    S = np.empty((3 * nn, nq))
    for m in range(nn):
        li = node_link[m]
        s = node_station[m]
        th = z[3 * li + 2]
        c, sn = math.cos(th), math.sin(th)
        r[3 * m] = z[3 * li] + s * c
        r[3 * m + 1] = z[3 * li + 1] + s * sn
        r[3 * m + 2] = th
        for j in range(nq):
            st = Sz[3 * li + 2, j]
            S[3 * m, j] = Sz[3 * li, j] - (s * sn) * st
            S[3 * m + 1, j] = Sz[3 * li + 1, j] + (s * c) * st
            S[3 * m + 2, j] = st
    return Jinv, cond, Sz, r, S


def _coordinate_rates(z, Sz, Jinv, k, node_link, node_station):  # pragma: no cover
    """``dS/dq_j`` for every coordinate j (nq, 3 n_nodes, nq): the formulas of
    :meth:`~exuflex.erls.kinematics.Kinematics.coordinate_rates`, with the sparse ``dPhi_z/dt`` applied
    directly (only the angle columns of the position equations and of the scalar equations on a point are
    nonzero)."""
    ea, esa, eb, ebm, esb = k.ea, k.esa, k.eb, k.ebm, k.esb
    nq = Sz.shape[1]
    n_eq = Jinv.shape[0]
    nn = node_link.shape[0]
    base = 2 * ea.shape[0]
    out = np.empty((nq, 3 * nn, nq))
    JdS = np.zeros((n_eq, nq))
    for j in range(nq):
        JdS[:] = 0.0
        for i in range(ea.shape[0]):
            a = ea[i]
            ta = z[3 * a + 2]
            wa = esa[i] * Sz[3 * a + 2, j]  # esa * (link a's angle rate along e_j)
            ca, sa = wa * math.cos(ta), wa * math.sin(ta)
            for c in range(nq):
                st = Sz[3 * a + 2, c]
                JdS[2 * i, c] -= ca * st
                JdS[2 * i + 1, c] -= sa * st
            if ebm[i] > 0:
                b = eb[i]
                tb = z[3 * b + 2]
                wb = esb[i] * Sz[3 * b + 2, j]
                cb, sb = wb * math.cos(tb), wb * math.sin(tb)
                for c in range(nq):
                    st = Sz[3 * b + 2, c]
                    JdS[2 * i, c] += cb * st
                    JdS[2 * i + 1, c] += sb * st
        for i in range(k.ca.shape[0]):
            if k.cs[i] != 0.0:
                a = k.ca[i]
                ta = z[3 * a + 2]
                w = k.cs[i] * Sz[3 * a + 2, j] * (-k.cn[i, 0] * math.cos(ta) - k.cn[i, 1] * math.sin(ta))
                for c in range(nq):
                    JdS[base + i, c] += w * Sz[3 * a + 2, c]
        Szd = -(Jinv @ JdS)
        for m in range(nn):
            li = node_link[m]
            s = node_station[m]
            th = z[3 * li + 2]
            c, sn = math.cos(th), math.sin(th)
            thd = Sz[3 * li + 2, j]
            for col in range(nq):
                std = Szd[3 * li + 2, col]
                st = Sz[3 * li + 2, col]
                out[j, 3 * m, col] = Szd[3 * li, col] - s * sn * std - s * c * thd * st
                out[j, 3 * m + 1, col] = Szd[3 * li + 1, col] + s * c * std - s * sn * thd * st
                out[j, 3 * m + 2, col] = std
    return out


if HAVE_NUMBA:
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy", no_cfunc_wrapper=True)
    _inline = numba.njit(inline="always", nogil=True, error_model="numpy")
    # the small helpers that the Newton iteration and the pose call more than once: compiled once per process and
    # linked where they are called, not copied into every call site (inline="always" copies them)
    _shared = numba.njit(nogil=True, error_model="numpy", no_cfunc_wrapper=True)
    _residual = _shared(_residual)
    _jacobian = _shared(_jacobian)
    _max_abs = _shared(_max_abs)
    _solve = _shared(_solve_lapack if _xgesv is not None else _solve_numpy)
    solve_columns = _shared(_solve_columns_lapack if _xgesv is not None else _solve_numpy)
    _norm1 = _shared(_norm1)
    closure_newton = _jit(_closure_newton)
    pose_sensitivities = _jit(_pose_sensitivities)
    coordinate_rates = _jit(_coordinate_rates)
    closure_newton_inline = _inline(_closure_newton)
    pose_sensitivities_inline = _inline(_pose_sensitivities)
    coordinate_rates_inline = _inline(_coordinate_rates)
else:  # pragma: no cover
    closure_newton = None
    solve_columns = None
    coordinate_rates = None
    pose_sensitivities = None

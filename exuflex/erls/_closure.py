"""Newton iteration of the loop-closure equations, compiled with numba when it is installed.

The cached observer evaluates the configuration about 30 times in 3 s, each time solving the closure from the
last solution (two or three Newton steps). In NumPy, each step is a dozen small array operations whose call
overhead is most of the cost (about 0.4 ms per solve); compiled, the same arithmetic takes a few
microseconds. :meth:`exuflex.erls.kinematics.Kinematics._newton_numpy` is the reference, and
``tests/test_kinematics.py`` checks that the two agree.

The equations are those of :class:`~exuflex.erls.kinematics.Kinematics` (its index arrays are passed in):
position equations ``k`` (rows ``2k, 2k+1``) join point ``esa[k]`` of link ``ea[k]`` to point ``esb[k]`` of link
``eb[k]`` (or to the ground point ``eg[k]`` where ``ebm[k] = 0``); angle equations ``j`` set
``th[ang_a[j]] - ang_rm[j] th[ang_r[j]] - ang_off[j]`` to ``q[j]``.
"""

from __future__ import annotations

import math

import numpy as np

try:
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None
    HAVE_NUMBA = False

__all__ = ["HAVE_NUMBA", "closure_newton", "coordinate_rates", "pose_sensitivities"]


def _residual(z, q, ea, esa, eb, ebm, esb, eg, ang_a, ang_r, ang_rm, ang_off, out):  # pragma: no cover
    for k in range(ea.shape[0]):
        a, b, m = ea[k], eb[k], ebm[k]
        ta, tb = z[3 * a + 2], z[3 * b + 2]
        out[2 * k] = z[3 * a] + esa[k] * math.cos(ta) - m * (z[3 * b] + esb[k] * math.cos(tb)) - eg[k, 0]
        out[2 * k + 1] = z[3 * a + 1] + esa[k] * math.sin(ta) - m * (z[3 * b + 1] + esb[k] * math.sin(tb)) - eg[k, 1]
    base = 2 * ea.shape[0]
    for j in range(ang_a.shape[0]):
        out[base + j] = z[3 * ang_a[j] + 2] - ang_rm[j] * z[3 * ang_r[j] + 2] - ang_off[j] - q[j]


def _jacobian(z, ea, esa, eb, ebm, esb, J0, J):  # pragma: no cover
    J[:] = J0
    for k in range(ea.shape[0]):
        a = ea[k]
        ta = z[3 * a + 2]
        J[2 * k, 3 * a + 2] = -esa[k] * math.sin(ta)
        J[2 * k + 1, 3 * a + 2] = esa[k] * math.cos(ta)
        if ebm[k] > 0:
            b = eb[k]
            tb = z[3 * b + 2]
            J[2 * k, 3 * b + 2] = esb[k] * math.sin(tb)
            J[2 * k + 1, 3 * b + 2] = -esb[k] * math.cos(tb)


def _max_abs(v):  # pragma: no cover
    m = 0.0
    for x in v:
        if not abs(x) <= m:  # a NaN wins
            m = abs(x)
    return m


def _closure_newton(z0, q, ea, esa, eb, ebm, esb, eg, ang_a, ang_r, ang_rm, ang_off, J0, tol, max_iter):  # pragma: no cover
    """Newton from ``z0``; returns ``(z, ok)``: ``ok`` False where the kinematics' NumPy Newton returns None
    (non-finite iterate or no convergence). Converged: one more step polishes the solution to round-off.
    A singular Jacobian raises numpy's LinAlgError, as in NumPy."""
    z = z0.copy()
    n = z.shape[0]
    res = np.empty(J0.shape[0])
    J = np.empty(J0.shape)
    for _ in range(max_iter):
        _residual(z, q, ea, esa, eb, ebm, esb, eg, ang_a, ang_r, ang_rm, ang_off, res)
        _jacobian(z, ea, esa, eb, ebm, esb, J0, J)
        if _max_abs(res) < tol:
            return z - np.linalg.solve(J, res), True
        z += np.linalg.solve(J, -res)
        for i in range(n):
            if not math.isfinite(z[i]):
                return z, False
    _residual(z, q, ea, esa, eb, ebm, esb, eg, ang_a, ang_r, ang_rm, ang_off, res)
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


def _pose_sensitivities(z, ea, esa, eb, ebm, esb, J0, E, node_link, node_station):  # pragma: no cover
    """What :meth:`~exuflex.erls.kinematics.Kinematics.pose` computes after the closure is solved: the inverse
    of the closure Jacobian ``J``, its 1-norm condition number, ``S_z = J^-1 E`` and the nodal poses ``r`` and
    sensitivities ``S`` (rows x, y, theta per node). A singular ``J`` raises numpy's LinAlgError."""
    J = np.empty(J0.shape)
    _jacobian(z, ea, esa, eb, ebm, esb, J0, J)
    Jinv = np.linalg.inv(J)
    cond = _norm1(J) * _norm1(Jinv)
    Sz = Jinv @ E
    nn = node_link.shape[0]
    nq = E.shape[1]
    r = np.empty(3 * nn)
    S = np.empty((3 * nn, nq))
    for k in range(nn):
        li = node_link[k]
        s = node_station[k]
        th = z[3 * li + 2]
        c, sn = math.cos(th), math.sin(th)
        r[3 * k] = z[3 * li] + s * c
        r[3 * k + 1] = z[3 * li + 1] + s * sn
        r[3 * k + 2] = th
        for j in range(nq):
            st = Sz[3 * li + 2, j]
            S[3 * k, j] = Sz[3 * li, j] - (s * sn) * st
            S[3 * k + 1, j] = Sz[3 * li + 1, j] + (s * c) * st
            S[3 * k + 2, j] = st
    return Jinv, cond, Sz, r, S


def _coordinate_rates(z, Sz, Jinv, ea, esa, eb, ebm, esb, node_link, node_station):  # pragma: no cover
    """``dS/dq_j`` for every coordinate j (nq, 3 n_nodes, nq): the formulas of
    :meth:`~exuflex.erls.kinematics.Kinematics.coordinate_rates`, with the sparse ``dPhi_z/dt`` applied
    directly (only the angle columns of the position equations are nonzero)."""
    nq = Sz.shape[1]
    n_eq = Jinv.shape[0]
    nn = node_link.shape[0]
    out = np.empty((nq, 3 * nn, nq))
    JdS = np.zeros((n_eq, nq))
    for j in range(nq):
        JdS[:] = 0.0
        for k in range(ea.shape[0]):
            a = ea[k]
            ta = z[3 * a + 2]
            wa = esa[k] * Sz[3 * a + 2, j]  # esa * (link a's angle rate along e_j)
            ca, sa = wa * math.cos(ta), wa * math.sin(ta)
            for c in range(nq):
                st = Sz[3 * a + 2, c]
                JdS[2 * k, c] -= ca * st
                JdS[2 * k + 1, c] -= sa * st
            if ebm[k] > 0:
                b = eb[k]
                tb = z[3 * b + 2]
                wb = esb[k] * Sz[3 * b + 2, j]
                cb, sb = wb * math.cos(tb), wb * math.sin(tb)
                for c in range(nq):
                    st = Sz[3 * b + 2, c]
                    JdS[2 * k, c] += cb * st
                    JdS[2 * k + 1, c] += sb * st
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
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy")
    _residual = _jit(_residual)
    _jacobian = _jit(_jacobian)
    _max_abs = _jit(_max_abs)
    _norm1 = _jit(_norm1)
    closure_newton = _jit(_closure_newton)
    pose_sensitivities = _jit(_pose_sensitivities)
    coordinate_rates = _jit(_coordinate_rates)
else:  # pragma: no cover
    closure_newton = None
    coordinate_rates = None
    pose_sensitivities = None

"""The nodal mass and stiffness matrices at a configuration, compiled with numba when it is installed.

:meth:`exuflex.erls.model.ErlsModel.configuration` rotates every element's local matrices with its link and
scatters them into the nodal matrices. The NumPy form (batched products and a ``bincount`` scatter) is the
reference; at the six-bar's size (9 elements, 42 nodal dofs) its call overhead is most of its cost, so the
cached observer's configuration evaluations use :func:`nodal_matrices`, the same arithmetic in one compiled
call (``tests/test_elements.py`` checks that the two agree).

:func:`configuration` goes one step further: the closure's Newton iteration, the pose sensitivities
(:mod:`._closure`), the nodal matrices and ``W = [S, T]`` in one compiled call, what
:meth:`exuflex.erls.model.ErlsModel.configuration` does through the kinematics' separate calls (the reference;
``tests/test_elements.py`` checks that the two agree). Inside a filter run, where the configuration is evaluated
only every few hundred samples and every separate call starts from cold caches, the Python between the calls
cost as much as their arithmetic.
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

from ._closure import closure_newton, closure_newton_inline, pose_sensitivities_inline

__all__ = ["HAVE_NUMBA", "configuration", "nodal_matrices"]


def _nodal_matrices(th, Ml, Kl, el_dofs, lumped):  # pragma: no cover - compiled twin of ErlsModel.configuration
    """``(R, M_N, K_N)``: element rotations (n_el, 6, 6) for element angles ``th`` and the assembled nodal mass
    (with the lumped masses on its diagonal) and stiffness, ``sum_e scatter_e(R_e X_e R_e^T)``."""
    n_el = th.shape[0]
    N = lumped.shape[0]
    R = np.zeros((n_el, 6, 6))
    M_N = np.zeros((N, N))
    K_N = np.zeros((N, N))
    for i in range(N):
        M_N[i, i] = lumped[i]
    for e in range(n_el):
        c, s = math.cos(th[e]), math.sin(th[e])
        for o in (0, 3):
            R[e, o, o] = c
            R[e, o, o + 1] = -s
            R[e, o + 1, o] = s
            R[e, o + 1, o + 1] = c
            R[e, o + 2, o + 2] = 1.0
        Re = R[e]
        Rt = np.ascontiguousarray(Re.T)
        Me = Re @ (Ml[e] @ Rt)
        Ke = Re @ (Kl[e] @ Rt)
        for a in range(6):
            ia = el_dofs[e, a]
            for b in range(6):
                ib = el_dofs[e, b]
                M_N[ia, ib] += Me[a, b]
                K_N[ia, ib] += Ke[a, b]
    return R, M_N, K_N


if HAVE_NUMBA:
    nodal_matrices = numba.njit(cache=True, nogil=True, error_model="numpy", no_cfunc_wrapper=True)(_nodal_matrices)
    _nodal_matrices_inline = numba.njit(inline="always", nogil=True, error_model="numpy")(_nodal_matrices)
else:  # pragma: no cover
    nodal_matrices = None


def _configuration(z0, q, k, tol, max_iter, node_link, node_station, el_link, Ml, Kl, el_dofs, lumped,
                   T):  # pragma: no cover - compiled
    """``(ok, z, J^-1, cond, S_z, r, S, R, M_N, K_N, W)`` at q from the Newton start ``z0``: the closure
    (:func:`._closure.closure_newton` with the closure arrays ``k``, tolerance ``tol`` absolute), the pose
    sensitivities (:func:`._closure.pose_sensitivities`), the nodal matrices at the element angles
    (:func:`nodal_matrices`) and ``W = [S, T]``. ``ok`` False (the rest empty): Newton did not converge, the
    caller takes the reference path."""
    z, ok = closure_newton_inline(z0, q, k, tol, max_iter)
    if not ok:
        e2, e3 = np.empty((0, 0)), np.empty((0, 0, 0))
        return False, z, e2, np.inf, e2, np.empty(0), e2, e3, e2, e2, e2
    Jinv, cond, Sz, r, S = pose_sensitivities_inline(z, k, node_link, node_station)
    th = np.empty(el_link.shape[0])
    for e in range(el_link.shape[0]):
        th[e] = z[3 * el_link[e] + 2]
    R, M_N, K_N = _nodal_matrices_inline(th, Ml, Kl, el_dofs, lumped)
    nq = S.shape[1]
    W = np.empty((S.shape[0], nq + T.shape[1]))
    for a in range(S.shape[0]):
        for j in range(nq):
            W[a, j] = S[a, j]
        for j in range(T.shape[1]):
            W[a, nq + j] = T[a, j]
    return True, z, Jinv, cond, Sz, r, S, R, M_N, K_N, W


if HAVE_NUMBA and closure_newton is not None:
    configuration = numba.njit(cache=True, nogil=True, error_model="numpy", no_cfunc_wrapper=True)(_configuration)
else:  # pragma: no cover
    configuration = None

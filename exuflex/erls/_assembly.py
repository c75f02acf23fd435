"""The nodal mass and stiffness matrices at a configuration, compiled with numba when it is installed.

:meth:`exuflex.erls.model.ErlsModel.configuration` rotates every element's local matrices with its link and
scatters them into the nodal matrices. The NumPy form (batched products and a ``bincount`` scatter) is the
reference; at the six-bar's size (9 elements, 42 nodal dofs) its call overhead is most of its cost, so the
cached observer's configuration evaluations use :func:`nodal_matrices`, the same arithmetic in one compiled
call (``tests/test_elements.py`` checks that the two agree).
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

__all__ = ["HAVE_NUMBA", "nodal_matrices"]


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
    nodal_matrices = numba.njit(cache=True, nogil=True, error_model="numpy")(_nodal_matrices)
else:  # pragma: no cover
    nodal_matrices = None

"""Two-node planar Euler-Bernoulli beam element (axial + bending, consistent mass).

Local dofs per element: ``(u1, v1, th1, u2, v2, th2)`` with ``u`` axial, ``v`` lateral, ``th`` the
cross-section rotation. Global = R local with R the block rotation by the element angle.
"""

from __future__ import annotations

import numpy as np

__all__ = ["GENERATOR", "beam_geometric_stiffness", "beam_gyroscopic", "beam_mass", "beam_stiffness", "hermite_curvature_row",
           "rotation"]


def beam_stiffness(EA: float, EI: float, L: float) -> np.ndarray:
    """Local 6x6 stiffness matrix."""
    k = np.zeros((6, 6))
    a = EA / L
    k[np.ix_([0, 3], [0, 3])] = a * np.array([[1.0, -1.0], [-1.0, 1.0]])
    b = EI / L**3
    kb = b * np.array(
        [
            [12.0, 6 * L, -12.0, 6 * L],
            [6 * L, 4 * L * L, -6 * L, 2 * L * L],
            [-12.0, -6 * L, 12.0, -6 * L],
            [6 * L, 2 * L * L, -6 * L, 4 * L * L],
        ]
    )
    k[np.ix_([1, 2, 4, 5], [1, 2, 4, 5])] = kb
    return k


def beam_geometric_stiffness(N: float, L: float) -> np.ndarray:
    """Local 6x6 consistent geometric stiffness of the axial force ``N`` (tension positive) on the cubic lateral
    field: ``N / (30 L) [[36, 3L, -36, 3L], [3L, 4L^2, -3L, -L^2], ...]`` on ``(v1, th1, v2, th2)``, from the
    virtual work ``N int v' dv' dx`` (the second-order strain). ``-K_G d`` is the force of an axial load acting
    across the lateral displacements ``d`` (the P-delta effect; a rigid tilt ``th`` of the element gets the couple
    ``N th L``), which the linear element leaves out."""
    k = np.zeros((6, 6))
    k[np.ix_([1, 2, 4, 5], [1, 2, 4, 5])] = N / (30.0 * L) * np.array(
        [
            [36.0, 3 * L, -36.0, 3 * L],
            [3 * L, 4 * L * L, -3 * L, -L * L],
            [-36.0, -3 * L, 36.0, -3 * L],
            [3 * L, -L * L, -3 * L, 4 * L * L],
        ]
    )
    return k


def beam_mass(rhoA: float, L: float) -> np.ndarray:
    """Local 6x6 consistent mass matrix (no rotary inertia of the section)."""
    m = np.zeros((6, 6))
    mt = rhoA * L
    m[np.ix_([0, 3], [0, 3])] = mt / 6 * np.array([[2.0, 1.0], [1.0, 2.0]])
    mb = mt / 420 * np.array(
        [
            [156.0, 22 * L, 54.0, -13 * L],
            [22 * L, 4 * L * L, 13 * L, -3 * L * L],
            [54.0, 13 * L, 156.0, -22 * L],
            [-13 * L, -3 * L * L, -22 * L, 4 * L * L],
        ]
    )
    m[np.ix_([1, 2, 4, 5], [1, 2, 4, 5])] = mb
    return m


def beam_gyroscopic(rhoA: float, L: float) -> np.ndarray:
    """Local 6x6 skew matrix ``A = int_0^L rhoA N^T G2 N ds`` (``G2 = [[0, -1], [1, 0]]``).

    ``N`` (2 x 6) interpolates the element's local displacement field: linear in the axial ``u``, cubic Hermite
    in the lateral ``v`` (with the rotations). ``A - m G`` (``m``: :func:`beam_mass`, ``G``: :data:`GENERATOR`)
    is the element's rotation-rate matrix of eq. 2's ``M_G`` (see :mod:`exuflex.erls.model`); it vanishes on
    rigid velocity fields, which ``N`` interpolates exactly (for them ``N G = G2 N``). Gauss-Legendre with three
    points, exact for the quartic integrand.
    """
    x, w = np.polynomial.legendre.leggauss(3)
    A = np.zeros((6, 6))
    for xi, wi in zip(0.5 * (x + 1.0), 0.5 * w * L):
        Nx = np.array([1 - xi, 0, 0, xi, 0, 0])
        Ny = np.array([0, 1 - 3 * xi**2 + 2 * xi**3, L * (xi - 2 * xi**2 + xi**3), 0, 3 * xi**2 - 2 * xi**3,
                       L * (-(xi**2) + xi**3)])
        A += wi * rhoA * (np.outer(Ny, Nx) - np.outer(Nx, Ny))  # N^T G2 N = Ny^T Nx - Nx^T Ny
    return A


# d R / d theta = R @ GENERATOR for the 6x6 element rotation
GENERATOR = np.zeros((6, 6))
GENERATOR[0, 1] = GENERATOR[3, 4] = -1.0
GENERATOR[1, 0] = GENERATOR[4, 3] = 1.0


def rotation(theta) -> np.ndarray:
    """Element rotation matrices for angles ``theta`` (shape (..., 6, 6))."""
    theta = np.asarray(theta, float)
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros(theta.shape + (6, 6))
    for o in (0, 3):
        R[..., o, o] = c
        R[..., o, o + 1] = -s
        R[..., o + 1, o] = s
        R[..., o + 1, o + 1] = c
        R[..., o + 2, o + 2] = 1.0
    return R


def hermite_curvature_row(L: float, xi: float) -> np.ndarray:
    """Row ``c`` with curvature = c @ local_dofs at ``xi`` in [0, 1] (d^2 v / ds^2 of the cubic)."""
    c = np.zeros(6)
    c[1] = (-6 + 12 * xi) / L**2
    c[2] = (-4 + 6 * xi) / L
    c[4] = (6 - 12 * xi) / L**2
    c[5] = (-2 + 6 * xi) / L
    return c

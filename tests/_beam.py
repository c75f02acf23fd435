"""Euler-Bernoulli beam frequencies from the exact frequency equation (test helper).

w(x) = a cos(kx) + b sin(kx) + c cosh(kx) + d sinh(kx), k^4 = rho A omega^2 / (E I), and the
boundary conditions (from the Lagrangian with hub inertia J_h, tip mass m_t, tip inertia J_t):

- root x = 0: w = 0 and either w' = 0 (clamped) or E I w'' = -J_h omega^2 w' (pinned to a hub);
- tip x = L: E I w'' = J_t omega^2 w',  E I w''' = -m_t omega^2 w.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import brentq


def _basis(k: float, x: float) -> np.ndarray:
    """Rows: w, w', w'', w''' of the four basis functions at x."""
    c, s, ch, sh = np.cos(k * x), np.sin(k * x), np.cosh(k * x), np.sinh(k * x)
    return np.array(
        [
            [c, s, ch, sh],
            [-k * s, k * c, k * sh, k * ch],
            [-k * k * c, -k * k * s, k * k * ch, k * k * sh],
            [k**3 * s, -(k**3) * c, k**3 * sh, k**3 * ch],
        ]
    )


def _det(beta: float, EI: float, rhoA: float, L: float, hub, m_t: float, J_t: float) -> float:
    k = beta / L
    w2 = k**4 * EI / rhoA
    B0, BL = _basis(k, 0.0), _basis(k, L)
    rows = [B0[0]]
    rows.append(B0[1] if hub == "clamped" else EI * B0[2] + hub * w2 * B0[1])
    rows.append(EI * BL[2] - J_t * w2 * BL[1])
    rows.append(EI * BL[3] + m_t * w2 * BL[0])
    A = np.array(rows)
    # scale the columns so the determinant stays O(1) for large beta
    A = A / np.linalg.norm(A, axis=0)
    return float(np.linalg.det(A))


def beam_frequencies(EI, rhoA, L, *, hub="clamped", m_t=0.0, J_t=0.0, n=3) -> np.ndarray:
    """First ``n`` non-zero natural frequencies (Hz); ``hub`` is "clamped" or a hub inertia (kg m^2).

    The roots beta = k L are bracketed on a grid (consecutive roots are about pi apart) and polished.
    """
    grid = np.linspace(1e-3, np.pi * (n + 1.5), 400 * (n + 2))
    vals = np.array([_det(b, EI, rhoA, L, hub, m_t, J_t) for b in grid])
    betas = []
    for a, b, fa, fb in zip(grid, grid[1:], vals, vals[1:]):
        if fa == 0.0 or np.sign(fa) != np.sign(fb):
            betas.append(brentq(_det, a, b, args=(EI, rhoA, L, hub, m_t, J_t), xtol=1e-14))
            if len(betas) == n:
                break
    betas = np.array(betas)
    return betas**2 / L**2 * np.sqrt(EI / rhoA) / (2 * np.pi)

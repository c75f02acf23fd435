"""Constrained eigenfrequencies and modal damping of the Exudyn model (motors free, at rest)."""

from __future__ import annotations

import logging

import numpy as np
import scipy.linalg as sla

from ..mechanism import Mechanism
from .builder import build_truth

__all__ = ["exudyn_frequencies", "modal_damping"]

log = logging.getLogger(__name__)

RIGID_TOL_HZ = 0.5  # the mechanism modes must come out below this (Hz), otherwise the model is inconsistent


def _drop_rigid(f: np.ndarray, nq: int, what: str) -> np.ndarray:
    f = np.sort(np.asarray(f, float))
    if np.any(f[:nq] > RIGID_TOL_HZ):
        raise RuntimeError(
            f"{what}: expected {nq} zero-frequency mechanism modes (motors free), got {np.round(f[:nq], 3).tolist()} Hz"
        )
    return f[nq:]


def exudyn_frequencies(
    mech: Mechanism, q=None, elements_per_link: int | None = 4, formulation: str = "ancf"
) -> np.ndarray:
    """Undamped eigenfrequencies (Hz, ascending) of the Exudyn model at rest at ``q``, motors free.

    The constraints (joints) are projected out by Exudyn (SVD null space of the constraint Jacobian);
    the mechanism's ``len(mech.coordinates)`` zero-frequency rigid modes are dropped.

    Parameters
    ----------
    mech : Mechanism
    q : array-like, optional
        Independent ERLS coordinates (default ``mech.q_ref``).
    elements_per_link, formulation : see :func:`exuflex.groundtruth.build_truth`.
    """
    tm = build_truth(mech, q, elements_per_link=elements_per_link, formulation=formulation, damping=None)
    f, _ = tm.mbs.ComputeODE2Eigenvalues(
        convert2Frequencies=True,
        useSparseSolver=False,
        ignoreAlgebraicEquations=False,
        useAbsoluteValues=True,
    )
    return _drop_rigid(f, len(mech.coordinates), f"Exudyn {formulation} model of {mech.name}")


def modal_damping(
    mech: Mechanism,
    q=None,
    elements_per_link: int | None = 4,
    formulation: str = "ancf",
    fmax: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Damped natural frequencies (Hz) and damping ratios of the Exudyn model with its damping.

    Linearises the constrained model at rest at ``q`` (``ComputeLinearizedSystem`` projected onto the
    constraint null space) and solves the quadratic eigenproblem ``(s^2 M + s D + K) phi = 0``.

    Returns
    -------
    f_hz, zeta : (n_modes,) arrays, ascending in frequency, rigid modes dropped, up to ``fmax``.
    """
    tm = build_truth(
        mech,
        q,
        elements_per_link=elements_per_link,
        formulation=formulation,
        damping="erls",
        explicit_damping=False,
    )
    M, K, D, *_ = tm.mbs.ComputeLinearizedSystem(projectIntoConstraintNullspace=True)
    M, K, D = (np.asarray(a) for a in (M, K, D))
    n = M.shape[0]
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-np.linalg.solve(M, K), -np.linalg.solve(M, D)]])
    s = sla.eigvals(A)
    s = s[s.imag > 1e-6]
    wn = np.abs(s)
    zeta = -s.real / wn
    order = np.argsort(wn)
    f, zeta = wn[order] / (2 * np.pi), zeta[order]
    # the nq rigid modes have s = 0 (or tiny): they were dropped with imag > 0 only if real; drop tiny ones too
    keep = f > RIGID_TOL_HZ
    f, zeta = f[keep], zeta[keep]
    if fmax is not None:
        keep = f <= fmax
        f, zeta = f[keep], zeta[keep]
    return f, zeta

"""Constrained eigenfrequencies and modal damping of the Exudyn model at rest (motors free or locked).

Motors locked means the ERLS coordinates q held: every coordinate (a tangent angle at a joint, absolute
or relative to another link, or a slider's position) gets a constraint ``A_j dc = 0``, its linearisation at
the build configuration (``A_j``: :meth:`~exuflex.groundtruth.TruthModel.point_rows`' angle row; on ANCF
``d atan2(y', x') = (x' dy' - y' dx') / |r'|^2`` of the node's slope, on geometrically exact beams the
rotation coordinate; a slider: its axis times the position rows), added as an ``ObjectConnectorCoordinateVector`` on the node(s) so that Exudyn's
own null-space projection removes it with the joints. Exact for the linearised analysis at rest.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.linalg as sla

from ..mechanism import Mechanism
from .builder import _exu, build_truth

__all__ = ["exudyn_frequencies", "lock_coordinates", "modal_damping"]

log = logging.getLogger(__name__)

RIGID_TOL_HZ = 0.5  # the mechanism modes must come out below this (Hz), otherwise the model is inconsistent


def _drop_rigid(f: np.ndarray, nq: int, what: str) -> np.ndarray:
    f = np.sort(np.asarray(f, float))
    if np.any(f[:nq] > RIGID_TOL_HZ):
        raise RuntimeError(
            f"{what}: expected {nq} zero-frequency mechanism modes (motors free), got {np.round(f[:nq], 3).tolist()} Hz"
        )
    return f[nq:]


def lock_coordinates(tm) -> None:
    """Add the linearised constraints that hold every ERLS coordinate q (motors locked), before ``Assemble``.

    Must be called on a model built with ``assemble`` done; it re-assembles. See the module docstring.
    """
    _, it = _exu()
    mech, mbs = tm.mech, tm.mbs
    c = tm.coordinates()
    for co in mech.coordinates:
        jt = mech.joint(co.joint)
        row = np.zeros(len(c))
        if co.kind == "slide":  # the slider's position along its axis: axis . (position rows)
            st = next(p.station for p in jt.points if p.link == co.link)
            row = np.asarray(jt.axis, float) @ tm.point_rows(co.link, st, c)[2]
        for link, sign in ((co.link, 1.0), (co.relative_to, -1.0)) if co.kind != "slide" else ():
            if link is None:
                continue
            st = next(p.station for p in jt.points if p.link == link)
            row += sign * tm.point_rows(link, st, c)[3]
        cols = np.flatnonzero(np.abs(row) > 1e-14 * np.max(np.abs(row)))
        nodes = sorted({int(i) // tm.node_size for i in cols})
        if len(nodes) > 2:  # pragma: no cover - an angle reads at most the two nodes at the joint
            raise RuntimeError(f"coordinate {co.name!r}: its angle depends on {len(nodes)} Exudyn nodes")
        markers, scalings = [], []
        for n in nodes:
            idx = np.arange(n * tm.node_size, (n + 1) * tm.node_size)
            markers.append(mbs.AddMarker(it.MarkerNodeCoordinates(nodeNumber=_node_number(tm, n))))
            scalings.append(row[idx][None, :])
        if len(markers) == 1:  # a connector needs two distinct markers: another node's with a zero row
            other = 1 if nodes[0] == 0 else 0
            markers.append(mbs.AddMarker(it.MarkerNodeCoordinates(nodeNumber=_node_number(tm, other))))
            scalings.append(np.zeros_like(scalings[0]))
        mbs.AddObject(  # Exudyn's constraint is X1 q1 - X0 q0: the first node's row enters with a minus
            it.ObjectConnectorCoordinateVector(
                markerNumbers=markers, scalingMarker0=-scalings[0], scalingMarker1=scalings[1], offset=[0.0]
            )
        )
    mbs.Assemble()


def _node_number(tm, k: int) -> int:
    """Exudyn node number of the k-th link node (link nodes come first in the ODE2 order, node by node)."""
    for lm in tm.links.values():
        for n, idx in zip(lm.nodes, lm.ode2):
            if idx[0] == k * tm.node_size:
                return n
    raise KeyError(k)  # pragma: no cover


def exudyn_frequencies(
    mech: Mechanism,
    q=None,
    elements_per_link: int | str | None = 4,
    formulation: str = "ancf",
    locked: bool = False,
    hub: str = "rigid",
) -> np.ndarray:
    """Undamped eigenfrequencies (Hz, ascending) of the Exudyn model at rest at ``q``, motors free or locked.

    The constraints (joints, and with ``locked`` the held coordinates, see the module docstring) are
    projected out by Exudyn (SVD null space of the constraint Jacobian); motors free, the mechanism's
    ``len(mech.coordinates)`` zero-frequency rigid modes are dropped.

    Parameters
    ----------
    mech : Mechanism
    q : array-like, optional
        Independent ERLS coordinates (default ``mech.q_ref``).
    elements_per_link, formulation, hub : see :func:`exuflex.groundtruth.build_truth`.
    locked : hold q (motors locked) instead of leaving it free.
    """
    tm = build_truth(
        mech, q, elements_per_link=elements_per_link, formulation=formulation, damping=None, hub=hub
    )
    if locked:
        lock_coordinates(tm)
    f, _ = tm.mbs.ComputeODE2Eigenvalues(
        convert2Frequencies=True,
        useSparseSolver=False,
        ignoreAlgebraicEquations=False,
        useAbsoluteValues=True,
    )
    what = f"Exudyn {formulation} model of {mech.name}"
    return _drop_rigid(f, 0, what) if locked else _drop_rigid(f, len(mech.coordinates), what)


def modal_damping(
    mech: Mechanism,
    q=None,
    elements_per_link: int | None = 4,
    formulation: str = "ancf",
    fmax: float | None = None,
    hub: str = "rigid",
    locked: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Damped natural frequencies (Hz) and damping ratios of the Exudyn model with its damping.

    Linearises the constrained model at rest at ``q`` (``ComputeLinearizedSystem`` projected onto the
    constraint null space; ``locked``: q held, :func:`lock_coordinates`) and solves the quadratic eigenproblem
    ``(s^2 M + s D + K) phi = 0``: ``f = |s| / 2 pi``, ``zeta = -Re s / |s|``. With the default damping the
    free modes' ``zeta`` is the model file's ``alpha / (2 w) + beta w / 2`` (:mod:`exuflex.groundtruth.builder`).

    Returns
    -------
    f_hz, zeta : (n_modes,) arrays, ascending in frequency, rigid modes dropped, up to ``fmax``.
    """
    tm = build_truth(
        mech,
        q,
        elements_per_link=elements_per_link,
        formulation=formulation,
        damping="rayleigh",
        explicit_damping=False,
        hub=hub,
    )
    if locked:
        lock_coordinates(tm)
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

"""Build an Exudyn model of a :class:`~exuflex.mechanism.Mechanism` (the independent "real mechanism").

This is the only module family of exuflex that imports :mod:`exudyn`. Every link becomes a chain of
planar flexible beams, independent of the ERLS mesh:

- ``formulation="ancf"`` (default): ``ObjectANCFCable2D`` elements (cubic Hermite, absolute nodal
  coordinates ``x, y, x', y'``; Euler-Bernoulli, like the ERLS elements);
- ``formulation="gebeam"``: ``ObjectBeamGeometricallyExact2D`` (linear, shear-deformable, nodes
  ``x, y, phi``): an independent cross-check that needs a fine mesh (16-32 elements per link).

Each link has its own nodes; the links' nodes at a joint coincide and are connected by
``ObjectJointRevolute2D`` (ground pins to an ``ObjectGround`` marker). A prismatic joint's node
keeps its coordinate normal to the axis (a global x or y direction) at its reference value
(``ObjectConnectorCoordinate`` to a ground node). A weld keeps the two nodes' tangents at their angle:
``ObjectConnectorCoordinate`` on the rotations (gebeam, exact) or, for ANCF, the linear constraint
``r'_b = R(angle) r'_a`` on the slopes (``ObjectConnectorCoordinateVector``), which also equates the
axial strains of the two links at the weld (one constraint more than a rigid angle; the bending modes
of a welded frame hardly load it). Lumped masses sit on the node at their station
(``ObjectGenericODE2``). A rotary inertia ``J`` (a hub, a motor rotor) or a mass at an offset
``(a, b)`` in the link frame must move with the node's rotation only:

- ``hub="rigid"`` (default): on ANCF such a mass gets a rigid body (``NodeRigidBody2D``,
  ``ObjectRigidBody2D`` with its mass and ``J``, centred at the mass point) welded to the node by an
  ``ObjectJointGeneric`` that ties position and rotation (x, y, rotation about z) of a body marker at
  the node (``MarkerBodyRigid`` at ``-(a, b)``) to the node's ``MarkerNodeRigid``, whose angle is the
  slope's ``atan2(y', x')``. The kinetic energy is then exactly that of a rigid body carried by the ERLS
  node, whatever the slope's length.
- ``hub="slopes"``: a constant mass matrix on the node's ``[x, y, x', y']``: the mass point at
  ``p + a r' + b (-y', x')``, ``m A^T A`` with ``A = [[1, 0, a, -b], [0, 1, b, a]]``, and J on both
  slope components. Exact for a unit slope, but it also gives the slope's *stretch* the inertia
  ``J + m (a^2 + b^2)``, which adds a spurious mode (slope stretch against the axial stiffness of the
  adjacent elements, ``~ sqrt(EA h / J)``) that falls into the band as the mesh is refined. Kept as the
  legacy model, for comparison.
On ``formulation="gebeam"`` J sits on the node's rotation coordinate (both choices are the same; an offset
mass needs ANCF). Motor torques act on the motor
link's node at the joint and, reversed, on the reaction link's node (nothing on ground), as the
generalized forces of a torque on that node's tangent angle, ``T d(atan2(y', x'))/dc``
(``T (-y', x') / |r'|^2`` on the ANCF slopes, ``T`` on a rotation coordinate). They sit, with the
alpha damper's forces, in the ``forceVector`` of one ``ObjectGenericODE2`` spanning all nodes,
which the simulation sets once per time step (``LoadTorqueVector`` on ``MarkerNodeRigid`` does the
same but costs the solver 60 % more time per step). The model is built directly in the closed, rigid configuration of
the ERLS at ``q`` (links straight, at rest), so no assembly step is needed.

The model's ``gravity`` ``g`` loads every mass the truth has, from its own bodies: each beam element by
``LoadMassProportional`` on a ``MarkerBodyMass`` (Exudyn integrates ``int S^T rho A g dx``), each hub body the
same way, and a constant mass matrix ``M_k`` on a node (point masses; the legacy slopes hub) by the generalized
force ``M_k t_g`` (``LoadCoordinate``), ``t_g`` the node's coordinates of a rigid translation by ``g``
(positions ``g``, slopes or rotation 0; the weight is the work of ``g`` on every mass point).

Damping (the model file's Rayleigh damping of the free elastic modes)
--------------------------------------------------------------------
The model file's ``alpha``, ``beta`` state that every free elastic mode (motors free) has the damping ratio
``alpha / (2 w) + beta w / 2``. The truth builds this from its own bodies only (it never reads the ERLS model):

- ``beta``: material damping of the beams: bending moment ``EI kappa + beta EI kappa'``, axial force
  ``EA eps + beta EA eps'`` (``bendingDamping``, ``axialDamping``); linearised, ``beta K`` with the truth's own
  stiffness ``K``.
- ``alpha`` (``damping="rayleigh"``, default): ``alpha M`` on the absolute coordinates would brake the rigid
  motion. The damper is the mass-proportional part with the rigid mechanism motions projected out,
  ``D = alpha (M - M R (R^T M R)^-1 R^T M)``, on all ODE2 coordinates (links and hub bodies): ``M`` the truth's
  own mass matrix (Exudyn's, constant for ANCF cables, geometrically exact beams and rigid bodies), ``R`` (n_c x
  n_q) the velocity fields of the rigid motions of the mechanism at the configuration ``c``: every link's rigid
  translations and rotation (its nodes' positions and slopes or rotations, and its hub bodies, turning with it),
  combined so that the joints hold (the null space of the truth's own constraint Jacobian ``G`` applied to them;
  ``G`` is Exudyn's, of the joints between links, which are linear in the coordinates; the hub bodies' welds hold
  by construction). The rigid motions are the null space of the linearised stiffness within the constraints and
  the elastic modes are M-orthogonal to them, so on the constraint null space ``phi_i^T D phi_j = alpha
  delta_ij`` and ``D R = 0``: with ``beta K`` every elastic mode has the stated ratio and no rigid motion is
  damped (``tests/test_damping.py`` checks the ratios from Exudyn's linearised system,
  :func:`exuflex.groundtruth.modal_damping`). ``R`` depends on the configuration and is refreshed during a
  simulation (:func:`exuflex.groundtruth.simulate_truth`). Between refreshes the damper is stale: a link turned
  by ``delta`` since the damper's configuration has a rigid velocity field that is no longer quite in the span
  of ``R``, and the damper brakes the rotation with the power ``~ -alpha delta^2 J q'^2``: a relative
  deceleration ``alpha delta^2`` (1/s), quadratic in ``delta``. The simulation therefore evaluates the damper at
  the configuration expected halfway through the coming interval (the mean of ``delta^2`` over it is then
  ``(omega dt)^2 / 12``) and sets the interval from the links' rotation rate ``omega`` so that this mean stays
  below a tolerance. In a simulation the damper force ``-D c'`` is applied explicitly, with the rates at the
  start of each step (``alpha h`` and ``zeta omega h`` are below 0.01 for the damped modes, so this is stable
  and its lag negligible; a dense implicit damping matrix would fill the sparse solver's system); for modal
  analysis ``D`` is the object's damping matrix.
- ``damping="corotational"``: ``D_l = alpha (M_l - M_l R_l (R_l^T M_l R_l)^-1 R_l^T M_l)`` per link (``R_l``:
  the link's own rigid velocity fields), which damps each link's deformation relative to its own mass-weighted
  rigid motion. It also damps the links' rigid motions relative to each other, so the mechanism's modes get
  other ratios than the stated ones; :func:`exuflex.groundtruth.modal_damping` measures either.
- ``damping="stiffness"``: ``beta`` only; ``None``: undamped (generalized-alpha still damps the
  highest frequencies numerically).
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
import sys
from dataclasses import dataclass, field

import numpy as np

from ..erls.kinematics import Kinematics
from ..mechanism import Mechanism
from ..mechanism.refine import split_segments

__all__ = [
    "DAMPINGS",
    "FORMULATIONS",
    "HUBS",
    "MESH_FILE",
    "LinkMesh",
    "TruthModel",
    "ancf_shape",
    "build_truth",
    "link_mesh_stations",
]

log = logging.getLogger(__name__)

FORMULATIONS = ("ancf", "gebeam")
DAMPINGS = ("rayleigh", "corotational", "stiffness", None)
HUBS = ("rigid", "slopes")
MESH_FILE = "file"  # elements_per_link: the mechanism's own element boundaries
SHEAR_CORRECTION = 0.9  # circular section (gebeam only)
POISSON = 0.33  # (gebeam only) shear modulus G = E / (2 (1 + nu))


FAST_ENV = "EXUFLEX_EXUDYN_FAST"


def _exu():
    """Import Exudyn; the first import selects its compiled module.

    Unless Exudyn is already imported, or the choice was made (``sys.exudynFast`` set, or Exudyn's
    own ``EXUDYN_MODULE`` variable), exuflex asks for Exudyn's documented fast module
    ``exudynCPPfast`` (AVX2, no range checks; Exudyn falls back to the regular one on a CPU without
    AVX2). On the paper's 3 s six-bar manoeuvre it made the solver about 15 % faster and changed the
    probes by less than 1e-8 (relative). ``EXUFLEX_EXUDYN_FAST=0`` keeps the regular module.
    Exudyn's import notice is kept off stdout.
    """
    undecided = "exudyn" not in sys.modules and not hasattr(sys, "exudynFast")
    if (
        undecided
        and not os.environ.get("EXUDYN_MODULE")
        and os.environ.get(FAST_ENV, "1").strip().lower() not in ("0", "false", "no", "off")
    ):
        sys.exudynFast = True
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            import exudyn as exu
            import exudyn.itemInterface as items
    except ImportError as err:  # pragma: no cover - exudyn is a declared dependency of this subpackage
        raise ImportError("exuflex.groundtruth needs exudyn (pip install exudyn)") from err
    return exu, items


@dataclass
class LinkMesh:
    """Exudyn mesh of one link: element boundaries (stations, m) and handles."""

    name: str
    stations: np.ndarray  # (n_nodes,) ascending, first 0, last length
    nodes: list[int] = field(default_factory=list)  # exudyn node numbers
    elements: list[int] = field(default_factory=list)  # exudyn object numbers
    ode2: np.ndarray | None = None  # (n_nodes, n_node_coords) global ODE2 indices (after Assemble)
    mass_matrix: np.ndarray | None = None  # (n_c, n_c) consistent + lumped mass on the link's coordinates

    def node_at(self, station: float, length: float) -> int:
        """Index (into ``nodes``) of the node at ``station``; raises if the station is not a node."""
        i = int(np.argmin(np.abs(self.stations - station)))
        if abs(self.stations[i] - station) > 1e-9 * max(1.0, length):
            raise KeyError(f"link {self.name!r} has no Exudyn node at station {station} m")
        return i

    def locate(self, station: float) -> list[tuple[int, float]]:
        """Element(s) and local xi in [0, 1] of a station; both neighbours at an interior node."""
        st = self.stations
        L = st[-1]
        tol = 1e-9 * max(1.0, L)
        if station < -tol or station > L + tol:
            raise KeyError(f"station {station} m is outside link {self.name!r} (length {L} m)")
        out = []
        for e in range(len(st) - 1):
            a, b = st[e], st[e + 1]
            if a - tol <= station <= b + tol:
                out.append((e, float(min(max((station - a) / (b - a), 0.0), 1.0))))
        return out


def ancf_shape(xi: float, L: float, d: int = 0) -> np.ndarray:
    """Cubic Hermite shape functions of ``ObjectANCFCable2D`` (or their d-th x-derivative), (4,).

    ``r(x) = S1 r0 + S2 r0' + S3 r1 + S4 r1'`` with ``xi = x / L``; ``r'`` are slopes d r / d x.
    """
    if d == 0:
        return np.array(
            [
                1 - 3 * xi**2 + 2 * xi**3,
                L * (xi - 2 * xi**2 + xi**3),
                3 * xi**2 - 2 * xi**3,
                L * (-(xi**2) + xi**3),
            ]
        )
    if d == 1:
        return (
            np.array(
                [
                    -6 * xi + 6 * xi**2,
                    L * (1 - 4 * xi + 3 * xi**2),
                    6 * xi - 6 * xi**2,
                    L * (-2 * xi + 3 * xi**2),
                ]
            )
            / L
        )
    if d == 2:
        return np.array([-6 + 12 * xi, L * (-4 + 6 * xi), 6 - 12 * xi, L * (-2 + 6 * xi)]) / L**2
    raise ValueError(f"derivative order must be 0, 1 or 2, got {d}")


@dataclass
class TruthModel:
    """An Exudyn model of a mechanism plus the handles needed to drive it and read probes."""

    mech: Mechanism
    q: np.ndarray
    formulation: str
    SC: object
    mbs: object
    links: dict[str, LinkMesh]
    motor_nodes: list[list[tuple[np.ndarray, float]]]  # per motor: (ODE2 indices of the node, sign)
    node_size: int  # coordinates per node (4 ancf, 3 gebeam)
    damping: str | None
    alpha: float
    beta: float
    forces: int  # ObjectGenericODE2 over all nodes: motor torques and alpha damper (forceVector)
    n_link_coordinates: int = 0  # coordinates of the link nodes (first in the ODE2 order; hub bodies after)
    hub: str = "rigid"
    explicit_damping: bool = True  # alpha damper as explicit force (simulation) or damping matrix (modal)
    D_alpha: np.ndarray | None = None  # current alpha damping matrix on all ODE2 coordinates
    mass_matrix: np.ndarray | None = None  # (n_c, n_c) Exudyn's mass matrix on all ODE2 coordinates ("rayleigh")
    joint_jacobian: np.ndarray | None = None  # (n_g, n_c) Exudyn's constraint Jacobian of the joints between links
    hub_bodies: dict = field(default_factory=dict)  # link name -> ODE2 indices (x, y, phi) of its hub bodies
    _q_last: np.ndarray | None = None
    _ref: np.ndarray | None = None
    _motor_map: tuple | None = None

    @property
    def n_coordinates(self) -> int:
        return self.mbs.systemData.ODE2Size()

    def coordinates(self) -> np.ndarray:
        """Current total ODE2 coordinates (reference + displacement)."""
        exu, _ = _exu()
        sd = self.mbs.systemData
        if self._ref is None:
            self._ref = np.asarray(sd.GetODE2Coordinates(exu.ConfigurationType.Reference))
        return np.asarray(sd.GetODE2Coordinates(exu.ConfigurationType.Current)) + self._ref

    def velocities(self) -> np.ndarray:
        """Current ODE2 coordinate rates."""
        exu, _ = _exu()
        return np.asarray(self.mbs.systemData.GetODE2Coordinates_t(exu.ConfigurationType.Current))

    def motor_map(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Rows of the motor torques: ODE2 indices of the slope x' and y' (ancf; the rotation twice for
        gebeam), sign (+1 motor link, -1 reaction link) and motor index, one entry per loaded node."""
        if self._motor_map is None:
            rows = [(idx, sign, j) for j, nodes in enumerate(self.motor_nodes) for idx, sign in nodes]
            self._motor_map = (
                np.array([r[0][2] for r in rows], dtype=int),  # slope x' (ancf) or rotation (gebeam)
                np.array([r[0][min(3, self.node_size - 1)] for r in rows], dtype=int),
                np.array([r[1] for r in rows], dtype=float),
                np.array([r[2] for r in rows], dtype=int),
            )
        return self._motor_map

    def generalized_forces(self, tau, c: np.ndarray, cd: np.ndarray | None = None) -> np.ndarray:
        """Generalized forces (all ODE2 coordinates) of motor torques ``tau`` at total coordinates ``c``,
        minus the explicit alpha-damper force ``D c'`` if ``cd`` is given."""
        ix, iy, sign, j = self.motor_map()
        T = sign * np.asarray(tau, float)[j]
        if cd is not None and self.explicit_damping and self.D_alpha is not None:
            f = -(self.D_alpha @ cd)
        else:
            f = np.zeros(len(c))
        if self.formulation == "ancf":
            rx, ry = c[ix], c[iy]
            n2 = rx * rx + ry * ry
            np.add.at(f, ix, -T * ry / n2)  # T d(atan2(y', x'))/d(x', y')
            np.add.at(f, iy, T * rx / n2)
        else:
            np.add.at(f, ix, T)
        return f

    def set_torques(self, tau) -> None:
        """Set the motor torques (N m, one per motor, in ``mech.motors`` order) for the current state.

        Also applies the explicit alpha-damper force for the current rates. Call once per time step.
        """
        c = self.coordinates()
        cd = self.velocities() if self.explicit_damping and self.D_alpha is not None else None
        f = self.generalized_forces(tau, c, cd)
        self.mbs.SetObjectParameter(self.forces, "forceVector", f)

    # ------------------------------------------------------------------ kinematic read-out
    def point_rows(self, link: str, station: float, c: np.ndarray):
        """Position (2,), tangent angle and the linear maps (2, nc), (nc,) at a link station.

        The maps give the first-order changes of position and tangent angle with the total ODE2
        coordinates ``c`` (used for the coordinate read-out and the locked modes); at an interior node the first
        adjacent element is used (position and slope are continuous there).
        """
        lm = self.links[link]
        e, xi = lm.locate(station)[0]
        L = lm.stations[e + 1] - lm.stations[e]
        nc = len(c)
        P = np.zeros((2, nc))
        A = np.zeros(nc)
        if self.formulation == "ancf":
            idx = lm.ode2[e : e + 2].ravel()  # [x0, y0, x0', y0', x1, y1, x1', y1']
            S0, S1 = ancf_shape(xi, L, 0), ancf_shape(xi, L, 1)
            for k in range(4):
                P[0, idx[2 * k]] = S0[k]
                P[1, idx[2 * k + 1]] = S0[k]
            ce = c[idx].reshape(4, 2)
            r = S0 @ ce
            rp = S1 @ ce
            n2 = rp @ rp
            # d atan2(ry', rx') = (rx' d ry' - ry' d rx') / |r'|^2
            for k in range(4):
                A[idx[2 * k]] += -rp[1] * S1[k] / n2
                A[idx[2 * k + 1]] += rp[0] * S1[k] / n2
            return r, float(np.arctan2(rp[1], rp[0])), P, A
        i0, i1 = lm.ode2[e], lm.ode2[e + 1]
        for comp in (0, 1):
            P[comp, i0[comp]], P[comp, i1[comp]] = 1 - xi, xi
        A[i0[2]], A[i1[2]] = 1 - xi, xi
        r = (1 - xi) * c[i0[:2]] + xi * c[i1[:2]]
        return r, float((1 - xi) * c[i0[2]] + xi * c[i1[2]]), P, A

    def coordinate_values(self, c: np.ndarray | None = None) -> np.ndarray:
        """The ERLS coordinates q read from the Exudyn state (slope angles at the coordinate joints, slider
        positions along their axes).

        Angles are put on the branch nearest to the last value (the build ``q`` at first).
        """
        c = self.coordinates() if c is None else c
        ref = self.q if self._q_last is None else self._q_last
        out = np.empty(len(self.mech.coordinates))
        for j, co in enumerate(self.mech.coordinates):
            jt = self.mech.joint(co.joint)
            st = next(p.station for p in jt.points if p.link == co.link)
            if co.kind == "slide":  # the slider's position along the axis
                p = self.point_rows(co.link, st, c)[0]
                out[j] = float(np.asarray(jt.axis) @ (p - np.asarray(jt.ground))) - co.offset
                continue
            th = self.point_rows(co.link, st, c)[1]
            if co.relative_to is not None:
                st2 = next(p.station for p in jt.points if p.link == co.relative_to)
                th -= self.point_rows(co.relative_to, st2, c)[1]
            v = th - co.offset
            out[j] = ref[j] + (v - ref[j] + np.pi) % (2 * np.pi) - np.pi
        return out

    def rotation_rate(self, c: np.ndarray, cd: np.ndarray) -> float:
        """The links' fastest rotation rate (rad/s): the largest tangent-angle rate at a link's first node (rigid
        rotation plus that node's elastic rotation rate)."""
        return max(abs(float(self.point_rows(name, 0.0, c)[3] @ cd)) for name in self.links)

    # ------------------------------------------------------------------ damping
    def update_dampers(self, c: np.ndarray | None = None) -> None:
        """Refresh the configuration-dependent alpha damper for the current (or given) coordinates."""
        if self.alpha == 0.0 or self.damping not in ("rayleigh", "corotational"):
            return
        c = self.coordinates() if c is None else np.asarray(c, float)
        if self.damping == "corotational":
            D = np.zeros((len(c), len(c)))
            for lm in self.links.values():
                idx = lm.ode2.ravel()
                D[np.ix_(idx, idx)] = _corotational_damping(lm, c[idx], self.alpha, self.formulation)
            self._set_damping(D)
            return
        M = self.mass_matrix
        R = self.rigid_motions(c)
        MR = M @ R
        D = self.alpha * (M - MR @ np.linalg.solve(R.T @ MR, MR.T))
        self._set_damping(0.5 * (D + D.T))

    def rigid_motions(self, c: np.ndarray) -> np.ndarray:
        """(n_c, n_q) velocity fields of the mechanism's rigid motions at the coordinates ``c``.

        Every link's rigid translations and rotation about the origin (its nodes' positions and slopes, or
        rotations, and its hub bodies turning with it), combined by the n_q right singular vectors of
        ``G L`` with the smallest singular values (``G``: the joints' constraint Jacobian, ``L`` the links'
        fields): exact at a configuration where the links are straight, first order in the strains otherwise.
        """
        n, links = len(c), list(self.links.values())
        L = np.zeros((n, 3 * len(links)))
        for i, lm in enumerate(links):
            idx = lm.ode2.ravel()
            L[idx, 3 * i : 3 * i + 3] = _rigid_fields(c[idx], self.formulation)
            for body in self.hub_bodies.get(lm.name, ()):
                x, y, ph = body
                L[x, 3 * i], L[y, 3 * i + 1] = 1.0, 1.0
                L[x, 3 * i + 2], L[y, 3 * i + 2], L[ph, 3 * i + 2] = -c[y], c[x], 1.0
        nq = len(self.mech.coordinates)
        _, _, Vt = np.linalg.svd(self.joint_jacobian @ L)
        return L @ Vt[-nq:].T if Vt.shape[0] >= nq else L

    def _set_damping(self, D: np.ndarray) -> None:
        self.D_alpha = D
        if not self.explicit_damping:
            self.mbs.SetObjectParameter(self.forces, "dampingMatrix", D)


def link_mesh_stations(
    mech: Mechanism, link: str, elements_per_link: int | str | None = 4, extra: tuple[float, ...] = ()
) -> np.ndarray:
    """Element boundaries of a link's Exudyn mesh.

    The stations of the link's joints and lumped masses (and ``extra``, e.g. gauges) are always
    element boundaries; between them, segments are split evenly so that no element is longer than
    ``length / elements_per_link`` (``None``: one element per segment; ``"file"``: the mechanism's
    own element boundaries, the ERLS mesh, e.g. as refined by
    :func:`~exuflex.mechanism.refine_mechanism` or :func:`~exuflex.mechanism.remesh_mechanism`).
    """
    lk = mech.link(link)
    L = lk.length
    req = {0.0, L}
    for j in mech.joints:
        for p in j.points:
            if p.link == link:
                req.add(float(p.station))
    for m in mech.all_masses():
        name, s = mech.node_location(m.node)
        if name == link:
            req.add(float(s))
    for s in extra:
        if not 0.0 <= s <= L:
            raise ValueError(f"station {s} m is outside link {link!r} (length {L} m)")
        req.add(float(s))
    if elements_per_link == MESH_FILE:
        req.update(float(s) for s in lk.stations)
    req = sorted(req)
    # merge stations closer than round-off
    base = [req[0]]
    for s in req[1:]:
        if s - base[-1] > 1e-9 * max(1.0, L):
            base.append(s)
    base[-1] = L
    if elements_per_link is None or elements_per_link == MESH_FILE:
        return np.array(base)
    if isinstance(elements_per_link, bool) or not isinstance(elements_per_link, int) or elements_per_link < 1:
        raise ValueError(f"elements_per_link must be an integer >= 1, {MESH_FILE!r} or None, got {elements_per_link!r}")
    return np.array(split_segments(base, L / elements_per_link))


def _hermite_mass(L: float) -> np.ndarray:
    """int_0^L S^T S dx for the cubic Hermite shape functions [S1, S2, S3, S4] (S2, S4 scaled by L)."""
    return (L / 420.0) * np.array(
        [
            [156, 22 * L, 54, -13 * L],
            [22 * L, 4 * L * L, 13 * L, -3 * L * L],
            [54, 13 * L, 156, -22 * L],
            [-13 * L, -3 * L * L, -22 * L, 4 * L * L],
        ]
    )


def _link_mass_matrix(
    lm: LinkMesh, rhoA: float, rhoI: float, lumped: dict[int, np.ndarray], form: str
):
    """Consistent mass of the link's beams plus its lumped masses, on the link's coordinates."""
    nn = len(lm.stations)
    if form == "ancf":
        nc = 4
        M = np.zeros((nn * nc, nn * nc))
        for e in range(nn - 1):
            L = lm.stations[e + 1] - lm.stations[e]
            Me = np.kron(rhoA * _hermite_mass(L), np.eye(2))  # dofs [x0, y0, x0', y0', x1, y1, x1', y1']
            M[e * nc : e * nc + 8, e * nc : e * nc + 8] += Me
        for i, Mi in lumped.items():
            M[i * nc : i * nc + 4, i * nc : i * nc + 4] += Mi
    else:
        nc = 3
        M = np.zeros((nn * nc, nn * nc))
        lin = np.array([[2.0, 1.0], [1.0, 2.0]]) / 6.0
        for e in range(nn - 1):
            L = lm.stations[e + 1] - lm.stations[e]
            idx = np.array([e * nc, e * nc + 1, e * nc + 2, e * nc + 3, e * nc + 4, e * nc + 5])
            Me = np.zeros((6, 6))
            for c, r in ((0, rhoA), (1, rhoA), (2, rhoI)):
                Me[np.ix_([c, 3 + c], [c, 3 + c])] = r * L * lin
            M[np.ix_(idx, idx)] += Me
        for i, Mi in lumped.items():
            M[i * nc : i * nc + 3, i * nc : i * nc + 3] += Mi
    return M


def _rigid_fields(c: np.ndarray, form: str) -> np.ndarray:
    """(n_c, 3) velocity fields of the link's rigid translations and rotation about the origin."""
    if form == "ancf":
        c = c.reshape(-1, 4)
        n = len(c)
        R = np.zeros((n, 4, 3))
        R[:, 0, 0] = 1.0
        R[:, 1, 1] = 1.0
        R[:, 0, 2], R[:, 1, 2] = -c[:, 1], c[:, 0]
        R[:, 2, 2], R[:, 3, 2] = -c[:, 3], c[:, 2]
        return R.reshape(4 * n, 3)
    c = c.reshape(-1, 3)
    n = len(c)
    R = np.zeros((n, 3, 3))
    R[:, 0, 0] = 1.0
    R[:, 1, 1] = 1.0
    R[:, 0, 2], R[:, 1, 2], R[:, 2, 2] = -c[:, 1], c[:, 0], 1.0
    return R.reshape(3 * n, 3)


def _corotational_damping(lm: LinkMesh, coords: np.ndarray, alpha: float, form: str) -> np.ndarray:
    M = lm.mass_matrix
    MR = M @ _rigid_fields(coords, form)
    P = MR @ np.linalg.solve(MR.T @ _rigid_fields(coords, form), MR.T)
    D = alpha * (M - P)
    return 0.5 * (D + D.T)


def build_truth(
    mech: Mechanism,
    q=None,
    elements_per_link: int | None = 4,
    formulation: str = "ancf",
    align_stations: tuple[tuple[str, float], ...] = (),
    damping: str | None = "rayleigh",
    explicit_damping: bool = True,
    reduced_integration: bool = True,
    hub: str = "rigid",
) -> TruthModel:
    """Build the Exudyn model of ``mech`` at rest in the closed rigid configuration at ``q``.

    Parameters
    ----------
    mech : Mechanism
    q : array-like, optional
        Independent ERLS coordinates of the initial configuration (default ``mech.q_ref``).
    elements_per_link : int, "file" or None
        Target number of elements per link (see :func:`link_mesh_stations`); joints and lumped
        masses always sit on element boundaries. ``None``: one element between such stations;
        ``"file"``: the mechanism's own mesh.
    formulation : "ancf" or "gebeam"
    align_stations : (link, station) pairs that must also be element boundaries (e.g. gauges).
    damping : "rayleigh", "corotational", "stiffness" or None
        How the model file's Rayleigh damping is reproduced (see module docstring).
    explicit_damping : bool
        Apply the alpha damper as an explicit force (for simulation, refreshed by
        :meth:`TruthModel.set_torques`) rather than as a damping matrix (for linearised analysis).
    reduced_integration : bool
        ANCF only: Exudyn's reduced Gauss order (7 for the axial, 3 for the bending virtual work
        instead of 9 and 5; ``useReducedOrderIntegration=1``). Exact for the linearised element about
        a straight reference; on the paper's 3 s manoeuvre it changed the probes by less than 1e-6
        (relative, curvature 4e-8) and made the solver about 10 % faster.
    hub : "rigid" or "slopes"
        How a lumped rotary inertia acts on an ANCF node (see module docstring): a rigid body welded
        to the node (no spurious mode) or the legacy ``diag(J, J)`` on the slopes.

    Returns
    -------
    TruthModel
        Assembled model (``mbs.Assemble()`` done) with handles for torques and probes.
    """
    if formulation not in FORMULATIONS:
        raise ValueError(f"formulation must be one of {FORMULATIONS}, got {formulation!r}")
    if damping not in DAMPINGS:
        raise ValueError(f"damping must be one of {DAMPINGS}, got {damping!r}")
    if hub not in HUBS:
        raise ValueError(f"hub must be one of {HUBS}, got {hub!r}")
    exu, it = _exu()
    q = np.asarray(mech.q_ref if q is None else q, float)
    pose = Kinematics(mech).pose(q)
    z = pose.z
    SC = exu.SystemContainer()
    mbs = SC.AddSystem()
    ground = mbs.AddObject(it.ObjectGround(referencePosition=[0.0, 0.0, 0.0]))
    alpha = mech.damping.alpha if damping in ("rayleigh", "corotational") else 0.0
    beta = mech.damping.beta if damping is not None else 0.0

    extra: dict[str, list[float]] = {}
    for name, s in align_stations:
        extra.setdefault(name, []).append(float(s))

    gravity = [float(mech.gravity[0]), float(mech.gravity[1]), 0.0]
    has_gravity = any(gravity)
    node_size = 4 if formulation == "ancf" else 3
    links: dict[str, LinkMesh] = {}
    for i, lk in enumerate(mech.links):
        x0, y0, th = z[3 * i : 3 * i + 3]
        th = float(th)
        c, s = math.cos(th), math.sin(th)
        st = link_mesh_stations(mech, lk.name, elements_per_link, tuple(extra.get(lk.name, ())))
        lm = LinkMesh(lk.name, st)
        for sj in st:
            px, py = float(x0 + sj * c), float(y0 + sj * s)
            if formulation == "ancf":
                node = it.NodePoint2DSlope1(referenceCoordinates=[px, py, c, s])
            else:
                node = it.NodeRigidBody2D(referenceCoordinates=[px, py, th])
            lm.nodes.append(mbs.AddNode(node))
        E, A, I = lk.material.E, lk.section.A, lk.section.I
        rhoA, EI, EA = lk.material.rho * A, E * I, E * A
        for e in range(len(st) - 1):
            Le = float(st[e + 1] - st[e])
            nodes = [lm.nodes[e], lm.nodes[e + 1]]
            if formulation == "ancf":
                obj = it.ObjectANCFCable2D(
                    nodeNumbers=nodes,
                    length=Le,
                    massPerLength=rhoA,
                    bendingStiffness=EI,
                    axialStiffness=EA,
                    bendingDamping=beta * EI,
                    axialDamping=beta * EA,
                    useReducedOrderIntegration=1 if reduced_integration else 0,
                )
            else:
                GA = SHEAR_CORRECTION * E / (2.0 * (1.0 + POISSON)) * A
                obj = it.ObjectBeamGeometricallyExact2D(
                    nodeNumbers=nodes,
                    length=Le,
                    massPerLength=rhoA,
                    crossSectionInertia=lk.material.rho * I,
                    bendingStiffness=EI,
                    axialStiffness=EA,
                    shearStiffness=GA,
                    bendingDamping=beta * EI,
                    axialDamping=beta * EA,
                    shearDamping=beta * GA,
                )
            lm.elements.append(mbs.AddObject(obj))
            if has_gravity:  # the element's distributed mass: int S^T rho A g dx, Exudyn's own quadrature
                mbs.AddLoad(it.LoadMassProportional(
                    markerNumber=mbs.AddMarker(it.MarkerBodyMass(bodyNumber=lm.elements[-1])), loadVector=gravity))
        links[lk.name] = lm

    # lumped masses and rotary inertias at their stations (mass matrices on the node's coordinates: the legacy
    # slopes model, also the link mass matrices of the corotational damper)
    lumped: dict[str, dict[int, np.ndarray]] = {name: {} for name in links}
    bodies: dict[str, dict[int, list]] = {name: {} for name in links}  # masses with J or an offset (hub rigid)
    body_nodes: dict[str, list[int]] = {name: [] for name in links}  # their rigid bodies' nodes, by link
    point_mass: dict[str, dict[int, float]] = {name: {} for name in links}  # the others' point masses
    for m in mech.all_masses():
        name, s = mech.node_location(m.node)
        lm = links[name]
        k = lm.node_at(s, mech.link(name).length)
        if m.inertia > 0.0 or m.offset != (0.0, 0.0):
            bodies[name].setdefault(k, []).append(m)
        else:
            point_mass[name][k] = point_mass[name].get(k, 0.0) + m.mass
        a, b = m.offset
        if formulation == "ancf":
            A = np.array([[1.0, 0.0, a, -b], [0.0, 1.0, b, a]])
            Mk = m.mass * A.T @ A + np.diag([0.0, 0.0, m.inertia, m.inertia])
        else:
            if a or b:
                raise ValueError(f"{mech.source or mech.name}: a mass at an offset ({m.label or m.node!r}) needs "
                                 "formulation='ancf' (a gebeam node's mass matrix would depend on its rotation)")
            Mk = np.diag([m.mass, m.mass, m.inertia])
        lumped[name][k] = lumped[name].get(k, 0.0) + Mk
    for name, d in lumped.items():
        for k, Mk in d.items():
            node = links[name].nodes[k]
            if formulation == "ancf" and hub == "rigid":
                # the node keeps its point masses; each rotary inertia or offset mass becomes a rigid body welded
                # to the node: its rotation is the slope angle atan2(y', x'), so J and the offset act on the
                # rotation only (no inertia on the slope's stretch)
                ref = mbs.GetNodeParameter(node, "referenceCoordinates")
                th = math.atan2(ref[3], ref[2])
                c, s_ = math.cos(th), math.sin(th)
                for m in bodies[name].get(k, ()):
                    a, b = m.offset
                    body_node = mbs.AddNode(it.NodeRigidBody2D(
                        referenceCoordinates=[ref[0] + c * a - s_ * b, ref[1] + s_ * a + c * b, th]))
                    body_nodes[name].append(body_node)
                    body = mbs.AddObject(it.ObjectRigidBody2D(nodeNumber=body_node, mass=m.mass, inertia=m.inertia))
                    m_body = mbs.AddMarker(it.MarkerBodyRigid(bodyNumber=body, localPosition=[-a, -b, 0.0]))
                    m_node = mbs.AddMarker(it.MarkerNodeRigid(nodeNumber=node))
                    mbs.AddObject(it.ObjectJointGeneric(markerNumbers=[m_node, m_body],
                                                        constrainedAxes=[1, 1, 0, 0, 0, 1]))
                    if has_gravity:
                        mbs.AddLoad(it.LoadMassProportional(
                            markerNumber=mbs.AddMarker(it.MarkerBodyMass(bodyNumber=body)), loadVector=gravity))
                Mk = point_mass[name].get(k, 0.0) * np.diag([1.0, 1.0, 0.0, 0.0])
                if not Mk.any():
                    continue
            mbs.AddObject(it.ObjectGenericODE2(nodeNumbers=[node], massMatrix=Mk))
            if has_gravity:
                # a constant mass matrix on the node: the weight's generalized force is Mk t_g, t_g the node's
                # coordinates of a rigid translation by g (positions g, slopes or rotation 0); for an offset mass
                # on the slopes this includes the moment of its weight about the node
                t_g = np.zeros(node_size)
                t_g[:2] = gravity[:2]
                for coord, f in enumerate(Mk @ t_g):
                    if f != 0.0:
                        mbs.AddLoad(it.LoadCoordinate(markerNumber=mbs.AddMarker(
                            it.MarkerNodeCoordinate(nodeNumber=node, coordinate=coord)), load=float(f)))

    # joints: revolute between coincident nodes; ground pins
    def node_marker(link: str, station: float) -> int:
        lm = links[link]
        k = lm.node_at(station, mech.link(link).length)
        return mbs.AddMarker(it.MarkerNodePosition(nodeNumber=lm.nodes[k]))

    ground_node = None

    def coordinate_marker(link: str, station: float, coordinate: int) -> int:
        lm = links[link]
        k = lm.node_at(station, mech.link(link).length)
        return mbs.AddMarker(it.MarkerNodeCoordinate(nodeNumber=lm.nodes[k], coordinate=coordinate))

    for jt in mech.joints:
        markers = [node_marker(p.link, p.station) for p in jt.points]
        if jt.kind == "prismatic":
            # pinned together; the first node's normal coordinate (displacement) stays at zero: on the axis
            for mk in markers[1:]:
                mbs.AddObject(it.ObjectJointRevolute2D(markerNumbers=[markers[0], mk]))
            if ground_node is None:
                ground_node = mbs.AddNode(it.NodePointGround(referenceCoordinates=[0.0, 0.0, 0.0]))
            gm = mbs.AddMarker(it.MarkerNodeCoordinate(nodeNumber=ground_node, coordinate=0))
            c = 0 if abs(jt.normal[0]) > 0.5 else 1
            p0 = jt.points[0]
            mbs.AddObject(it.ObjectConnectorCoordinate(markerNumbers=[gm, coordinate_marker(p0.link, p0.station, c)]))
        elif jt.kind == "weld":
            mbs.AddObject(it.ObjectJointRevolute2D(markerNumbers=markers))
            (pa, pb) = jt.points
            if formulation == "ancf":
                mk = []
                for p in (pa, pb):
                    lm = links[p.link]
                    mk.append(mbs.AddMarker(it.MarkerNodeCoordinates(
                        nodeNumber=lm.nodes[lm.node_at(p.station, mech.link(p.link).length)])))
                ca, sa = math.cos(jt.angle), math.sin(jt.angle)
                S0 = np.zeros((2, 4))
                S0[:, 2:] = np.array([[ca, -sa], [sa, ca]])  # Exudyn's c = X1 q1 - X0 q0: r'_b - R(angle) r'_a
                S1 = np.zeros((2, 4))
                S1[:, 2:] = np.eye(2)
                mbs.AddObject(it.ObjectConnectorCoordinateVector(markerNumbers=mk, scalingMarker0=S0,
                                                                 scalingMarker1=S1, offset=[0.0, 0.0]))
            else:
                mbs.AddObject(it.ObjectConnectorCoordinate(markerNumbers=[
                    coordinate_marker(pa.link, pa.station, 2), coordinate_marker(pb.link, pb.station, 2)]))
        elif jt.ground is not None:
            gm = mbs.AddMarker(
                it.MarkerBodyPosition(bodyNumber=ground, localPosition=[jt.ground[0], jt.ground[1], 0.0])
            )
            for mk in markers:
                mbs.AddObject(it.ObjectJointRevolute2D(markerNumbers=[gm, mk]))
        else:
            for mk in markers[1:]:
                mbs.AddObject(it.ObjectJointRevolute2D(markerNumbers=[markers[0], mk]))

    # motors: +T on the motor link's node at the joint, -T on the reaction link's node
    motor_at = []
    for mo in mech.motors:
        jt = mech.joint(mo.joint)
        at = []
        for lname, sign in ((mo.link, 1.0), (mo.reaction, -1.0)):
            if lname is None:
                continue
            st = next((p.station for p in jt.points if p.link == lname), None)
            if st is None:
                raise KeyError(f"motor {mo.name!r}: link {lname!r} is not at joint {mo.joint!r}")
            at.append((lname, links[lname].node_at(st, mech.link(lname).length), sign))
        motor_at.append(at)

    # one generic object over all nodes: motor torques and the alpha damper (filled after Assemble)
    all_nodes = [n for lm in links.values() for n in lm.nodes]
    for lk in mech.links:
        lm = links[lk.name]
        lm.mass_matrix = _link_mass_matrix(
            lm, lk.material.rho * lk.section.A, lk.material.rho * lk.section.I, lumped[lk.name], formulation
        )
    n_c = node_size * len(all_nodes)
    hub_nodes = [n for nodes in body_nodes.values() for n in nodes]
    n_all = n_c + 3 * len(hub_nodes)  # the hub bodies' coordinates follow the links' (NodeRigidBody2D: x, y, phi)
    forces = mbs.AddObject(
        it.ObjectGenericODE2(
            nodeNumbers=all_nodes + hub_nodes,
            massMatrix=np.zeros((n_all, n_all)) if not explicit_damping else None,
            dampingMatrix=np.zeros((n_all, n_all)) if not explicit_damping else None,
            forceVector=np.zeros(n_all),
        )
    )
    mbs.Assemble()
    for lm in links.values():
        lm.ode2 = np.array([mbs.GetNodeODE2Index(n) + np.arange(node_size) for n in lm.nodes], dtype=int)
    order = np.concatenate([lm.ode2.ravel() for lm in links.values()])
    order = np.concatenate([order] + [mbs.GetNodeODE2Index(n) + np.arange(3) for n in hub_nodes])
    if not np.array_equal(order, np.arange(len(order))) or len(order) != n_all or mbs.systemData.ODE2Size() != n_all:
        raise RuntimeError(
            "Exudyn numbered the node coordinates out of node order; the force object assumes it"
        )
    motor_nodes = [[(links[ln].ode2[k], sign) for ln, k, sign in at] for at in motor_at]
    tm = TruthModel(
        mech,
        q,
        formulation,
        SC,
        mbs,
        links,
        motor_nodes,
        node_size,
        damping,
        alpha,
        beta,
        forces,
        n_link_coordinates=n_c,
        hub=hub,
        explicit_damping=explicit_damping,
    )
    tm.hub_bodies = {name: [mbs.GetNodeODE2Index(n) + np.arange(3) for n in nodes]
                     for name, nodes in body_nodes.items()}
    if alpha != 0.0 and damping == "rayleigh":
        # the truth's own mass matrix and the Jacobian of its joints between links (rows on link nodes only: the
        # hub bodies' welds are nonlinear, the rigid fields of rigid_motions satisfy them by construction)
        lin = mbs.ComputeLinearizedSystem(returnConstraintJacobian=True)  # [M, K, D, C^T]
        M, G = lin[0], np.asarray(lin[3]).T
        hub_cols = np.arange(n_c, G.shape[1])
        tm.mass_matrix = np.asarray(M)
        tm.joint_jacobian = G[~np.any(G[:, hub_cols] != 0.0, axis=1)] if len(hub_cols) else G
    ref = np.asarray(mbs.systemData.GetODE2Coordinates(exu.ConfigurationType.Reference))
    tm.update_dampers(ref)
    log.debug(
        "built %s truth of %s at q=%s: %d ODE2 coordinates",
        formulation,
        mech.name,
        np.round(q, 4).tolist(),
        tm.n_coordinates,
    )
    return tm

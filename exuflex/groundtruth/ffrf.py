"""The FFRF truth: a mechanism of Exudyn floating-frame bodies reduced from solid meshes (a third, independent
formulation: 3D linear elasticity in each link's moving frame, no beam kinematics).

Each link is an ``ObjectFFRFreducedOrder`` (:mod:`exuflex.groundtruth.solid`: netgen mesh, quadratic tetrahedra,
Hurty-Craig-Bampton modes) whose floating frame is a ``NodeRigidBodyRxyz`` placed at the link's start in the
closed rigid configuration at ``q`` (link frame: axis along x, the mechanism's plane x-y).

Planarity without redundant constraints: every frame is held in the plane once, by three coordinate
constraints on its node (``z``, ``rot_x``, ``rot_y`` = 0); the joints then act in the plane only:

- revolute: ``ObjectJointSpherical`` with ``constrainedAxes = [1, 1, 0]`` between the joint markers of the links
  (``MarkerSuperElementRigid`` over a rigid interface's nodes, offset to the axis point), or to a ground point;
  the rotation about z and every out-of-plane deformation stay free. A closed loop of planar 3D bodies with 3D
  revolute joints would repeat the out-of-plane constraints around the loop; these do not;
- prismatic: pinned as above, and the first point's coordinate normal to the axis (a global x or y direction) held
  at the axis by a one-axis spherical joint to the ground;
- weld: not supported (its rigid rotation constraint would need the interface frame's orientation).

Out-of-plane deformation modes remain in the bodies' bases; no in-plane load excites them in a section
symmetric about the plane, and :func:`ffrf_frequencies` classifies the modes and reports the in-plane ones.

Masses: a point mass is an ``ObjectMassPoint`` pinned (3 axes) to the interface marker at its station; a mass
with a rotary inertia or an offset is an ``ObjectRigidBody2D`` held at its offset by an ``ObjectJointGeneric``
(x, y, rotation about z). Motors: ``LoadTorqueVector`` about z on the interface markers (+T on the motor's link,
-T on the reaction link), set once per step.

Damping (the model file's Rayleigh damping of the free elastic modes: each has ``alpha / (2 w) + beta w / 2``):

- ``beta K`` on each body's modal coordinates (``dampingMatrixReduced``): all stiffness is modal, so every
  elastic mode of the mechanism gets ``beta w / 2`` exactly and no rigid motion is damped.
- ``alpha``: the mass-proportional part with the mechanism's rigid motions projected out, as the beam truth
  does (:mod:`.builder`): ``D = alpha (M - M R (R^T M R)^-1 R^T M)`` on all ODE2 coordinates, ``M`` the truth's own
  mass matrix (Exudyn's, from ``ComputeLinearizedSystem`` at the build configuration) and ``R`` (n_c x n_q) the
  velocity fields of the mechanism's rigid motions (:meth:`FfrfModel.rigid_motions`): each body's frame
  translations and rotation, with the masses attached to it turning along and the modal rates zero, combined so
  that every joint's axis point moves alike on the links it joins (and stays on the ground or the slide axis).
  The elastic modes are M-orthogonal to the rigid motions (the null space of the stiffness within the
  constraints), so ``phi_i^T D phi_j = alpha delta_ij`` and ``D R = 0``: with ``beta K`` every elastic mode
  has the stated ratio. ``M`` depends on each frame's angle ``theta`` only through the rotation ``A(theta)`` of
  the frame's translation and rotation-parameter blocks (kinetic energy in body-frame velocities is invariant;
  Exudyn's Rxyz parameters at ``rx = ry = 0`` give body rates ``A_z^T`` times the parameter rates), so
  ``M(c) = S M_0 S^T`` with ``S`` those rotations by the angles turned since the build: exact for undeformed
  bodies, first order in the deformation otherwise, as ``R`` is (it uses the joints' undeformed stations). ``R``
  changes with the configuration, so the damper is refreshed during a simulation on the beam truth's schedule
  (:func:`exuflex.groundtruth.simulate_truth`'s ``damping_tol``) and applied as the explicit force ``-D c'`` of
  one ``ObjectGenericODE2`` over all nodes; for modal analysis ``D`` is that object's damping matrix
  (``exuflex modes --exudyn --beam ffrf --json`` reports the ratios of Exudyn's linearised system).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..mechanism import Mechanism
from ..probes import Probe, ProbeRecord, probes_for
from .builder import _exu
from .simulate import implicit_settings, step_grid
from .solid import MODE_FACTOR, SolidLink, solid_link, solid_specs

__all__ = ["FfrfBody", "FfrfModel", "build_ffrf", "ffrf_frequencies", "simulate_ffrf"]

log = logging.getLogger(__name__)


@dataclass
class FfrfBody:
    """One link's FFRF body: its solid model, Exudyn handles and ODE2 indices (frame x, y, rot_z; modes)."""

    link: str
    solid: SolidLink
    node_rigid: int
    node_modal: int
    obj: int
    markers: list[int]  # one MarkerSuperElementRigid per interface
    frame_idx: np.ndarray | None = None  # ODE2 indices of the frame's x, y, rot_z
    rot_idx: np.ndarray | None = None  # ODE2 indices of the frame's rot_x, rot_y (turned with rot_z in M)
    modal_idx: np.ndarray | None = None  # ODE2 indices of the modal coordinates


@dataclass
class FfrfModel:
    """An Exudyn FFRF model of a mechanism plus the handles to drive it and read its probes."""

    mech: Mechanism
    q: np.ndarray
    SC: object
    mbs: object
    bodies: dict[str, FfrfBody]
    motor_loads: list[list[tuple[int, float]]]  # per motor: (load number, sign)
    setup_s: float = 0.0
    cached: bool = True
    settings: dict = field(default_factory=dict)
    alpha: float = 0.0
    forces: int | None = None  # ObjectGenericODE2 over all nodes: the alpha damper (forceVector or dampingMatrix)
    explicit_damping: bool = True
    mass_ref: np.ndarray | None = None  # Exudyn's mass matrix at the build configuration (all ODE2 coordinates)
    angle_ref: dict[str, float] = field(default_factory=dict)  # each frame's angle at the build
    masses: list[tuple[str, np.ndarray, bool]] = field(default_factory=list)  # (link, ODE2 x, y[, phi], rigid)
    D_alpha: np.ndarray | None = None  # current alpha damper on all ODE2 coordinates

    # ------------------------------------------------------------------ alpha damper (module docstring)
    def mass_matrix(self, c: np.ndarray) -> np.ndarray:
        """Exudyn's mass matrix at total coordinates ``c``: the build's, each frame's translation and
        rotation-parameter blocks turned by the angle the frame turned since (``S M_0 S^T``)."""
        S = np.eye(len(c))
        for b in self.bodies.values():
            d = float(c[b.frame_idx[2]]) - self.angle_ref[b.link]
            A = np.array([[math.cos(d), -math.sin(d)], [math.sin(d), math.cos(d)]])
            for ij in (b.frame_idx[:2], b.rot_idx):
                S[np.ix_(ij, ij)] = A
        M = S @ self.mass_ref @ S.T
        return 0.5 * (M + M.T)

    def rigid_motions(self, c: np.ndarray) -> np.ndarray:
        """(n_c, n_q) velocity fields of the mechanism's rigid motions at total coordinates ``c``.

        Per body three fields (frame translations, rotation about the frame's origin; modal rates zero; its masses
        carried along), combined by the n_q right singular vectors with the smallest singular values of the
        joints' velocity conditions on them: a joint's axis point (its undeformed station, in each link's
        frame) moves alike on every link it joins; a ground pivot's is at rest, a slider's normal to its axis."""
        names = list(self.bodies)
        col = {n: 3 * i for i, n in enumerate(names)}
        L = np.zeros((len(c), 3 * len(names)))
        for n, b in self.bodies.items():
            ix, iy, ith = b.frame_idx
            L[ix, col[n]], L[iy, col[n] + 1], L[ith, col[n] + 2] = 1.0, 1.0, 1.0
        for link, idx, rigid in self.masses:
            b = self.bodies[link]
            j = col[link]
            L[idx[0], j], L[idx[1], j + 1] = 1.0, 1.0
            L[idx[0], j + 2] = -(c[idx[1]] - c[b.frame_idx[1]])
            L[idx[1], j + 2] = c[idx[0]] - c[b.frame_idx[0]]
            if rigid:
                L[idx[2], j + 2] = 1.0

        def point_rows(p):  # velocity (2 rows) of the link's axis point at p.station, on the 3 fields per body
            b = self.bodies[p.link]
            th = float(c[b.frame_idx[2]])
            dx, dy = math.cos(th) * p.station, math.sin(th) * p.station
            rows = np.zeros((2, L.shape[1]))
            j = col[p.link]
            rows[0, j], rows[0, j + 2] = 1.0, -dy
            rows[1, j + 1], rows[1, j + 2] = 1.0, dx
            return rows

        H = []
        for jt in self.mech.joints:
            r0 = point_rows(jt.points[0])
            H.extend(r0 - point_rows(p) for p in jt.points[1:])
            if jt.kind == "prismatic":
                H.append(r0[[0 if abs(jt.normal[0]) > 0.5 else 1]])
            elif jt.ground is not None:
                H.append(r0)
        nq = len(self.mech.coordinates)
        _, _, Vt = np.linalg.svd(np.vstack(H))
        return L @ Vt[-nq:].T

    def rotation_rate(self, c: np.ndarray, cd: np.ndarray) -> float:
        """The frames' fastest rotation rate (rad/s) at coordinates ``c`` and rates ``cd``."""
        return max(abs(float(cd[b.frame_idx[2]])) for b in self.bodies.values())

    def update_damper(self, c: np.ndarray) -> None:
        """Refresh the alpha damper ``D = alpha (M - M R (R^T M R)^-1 R^T M)`` at total coordinates ``c``."""
        if self.forces is None:
            return
        M = self.mass_matrix(c)
        R = self.rigid_motions(c)
        MR = M @ R
        D = self.alpha * (M - MR @ np.linalg.solve(R.T @ MR, MR.T))
        self.D_alpha = 0.5 * (D + D.T)
        if not self.explicit_damping:
            self.mbs.SetObjectParameter(self.forces, "dampingMatrix", self.D_alpha)

    def probe_values(self, probe: Probe, c: np.ndarray, cd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values and rates (n_t, width) of a probe from total ODE2 coordinates and rates (n_t, n_coords).

        ``p = r + R(phi) (s e_x + u_s)``, ``slope = phi + theta_s``, ``kappa = kappa_s`` with ``(r, phi)`` the frame
        and ``u_s, theta_s, kappa_s`` the section read-outs (linear in the modal coordinates)."""
        b = self.bodies[probe.link]
        rows = b.solid.section(probe.station)
        fr, frd = c[:, b.frame_idx], cd[:, b.frame_idx]
        qm, qmd = c[:, b.modal_idx], cd[:, b.modal_idx]
        u, ud = qm @ rows.T, qmd @ rows.T  # (n_t, 4)
        phi, phid = fr[:, 2], frd[:, 2]
        if probe.kind == "slope":
            return (phi + u[:, 2])[:, None], (phid + ud[:, 2])[:, None]
        if probe.kind == "curvature":
            return u[:, 3:4], ud[:, 3:4]
        co, si = np.cos(phi), np.sin(phi)
        lx, ly = probe.station + u[:, 0], u[:, 1]
        p = np.column_stack([fr[:, 0] + co * lx - si * ly, fr[:, 1] + si * lx + co * ly])
        v = np.column_stack([frd[:, 0] - phid * (si * lx + co * ly) + co * ud[:, 0] - si * ud[:, 1],
                             frd[:, 1] + phid * (co * lx - si * ly) + si * ud[:, 0] + co * ud[:, 1]])
        return p, v


def _probe_stations(mech: Mechanism, probes: Sequence[Probe]) -> dict[str, tuple[float, ...]]:
    st: dict[str, list[float]] = {}
    for p in probes:
        st.setdefault(p.link, []).append(p.station)
    return {k: tuple(sorted(set(v))) for k, v in st.items()}


def build_ffrf(mech: Mechanism, q=None, *, mesh_scale: float = 1.0, mode_factor: float = MODE_FACTOR,
               damping: bool = True, probes: Sequence[Probe] | None = None,
               progress: Callable[[str], None] | None = None, cache: bool = True,
               explicit_damping: bool = True) -> FfrfModel:
    """Build the FFRF model of ``mech`` at rest in the closed rigid configuration at ``q`` (default ``q_ref``).

    ``mesh_scale`` scales every link's mesh size (a convergence study), ``mode_factor`` the fixed-interface modes
    kept (up to ``mode_factor x band_hz``); ``damping``: the model file's Rayleigh damping on the modal
    coordinates and the rigid-motion-free alpha damper (see the module docstring), applied as an explicit force
    (``explicit_damping``, for simulation: :func:`simulate_ffrf` refreshes it) or as a damping matrix (for
    linearised analysis); ``probes`` (default :func:`~exuflex.probes.probes_for`) fixes the
    read-out stations; ``progress`` receives one-line messages of the meshing and modes (cached on disk)."""
    from ..erls.kinematics import Kinematics

    exu, it = _exu()
    t0 = time.perf_counter()
    for jt in mech.joints:
        if jt.kind == "weld":
            raise ValueError(f"{mech.source or mech.name}: joint {jt.name!r}: the FFRF truth does not support "
                             "weld joints (expected revolute or prismatic joints)")
    probes = tuple(probes_for(mech) if probes is None else probes)
    specs = solid_specs(mech, _probe_stations(mech, probes), mesh_scale=mesh_scale, mode_factor=mode_factor)
    solids = {name: solid_link(sp, progress, cache=cache) for name, sp in specs.items()}
    q = np.asarray(mech.q_ref if q is None else q, float)
    z = Kinematics(mech).pose(q).z
    SC = exu.SystemContainer()
    mbs = SC.AddSystem()
    ground = mbs.AddObject(it.ObjectGround(referencePosition=[0.0, 0.0, 0.0]))
    ground_node = mbs.AddNode(it.NodePointGround(referenceCoordinates=[0.0, 0.0, 0.0]))
    ground_coord = mbs.AddMarker(it.MarkerNodeCoordinate(nodeNumber=ground_node, coordinate=0))
    alpha = mech.damping.alpha if damping else 0.0
    beta = mech.damping.beta if damping else 0.0
    gravity = [float(mech.gravity[0]), float(mech.gravity[1]), 0.0]
    has_gravity = any(gravity)
    bodies: dict[str, FfrfBody] = {}
    for i, lk in enumerate(mech.links):
        sl = solids[lk.name]
        a = sl.arrays
        x0, y0, th = (float(v) for v in z[3 * i : 3 * i + 3])
        n_rigid = mbs.AddNode(it.NodeRigidBodyRxyz(referenceCoordinates=[x0, y0, 0.0, 0.0, 0.0, th]))
        nm = sl.n_modes
        n_modal = mbs.AddNode(it.NodeGenericODE2(numberOfODE2Coordinates=nm, referenceCoordinates=[0.0] * nm,
                                                 initialCoordinates=[0.0] * nm, initialCoordinates_t=[0.0] * nm))
        K = exu.MatrixContainer()
        K.SetWithDenseMatrix(a["stiffnessMatrixReduced"], useDenseMatrix=False)
        M = exu.MatrixContainer()
        M.SetWithDenseMatrix(a["massMatrixReduced"], useDenseMatrix=False)
        D = []
        if beta:
            D = exu.MatrixContainer()
            D.SetWithDenseMatrix(beta * a["stiffnessMatrixReduced"], useDenseMatrix=False)
        obj = mbs.AddObject(it.ObjectFFRFreducedOrder(
            nodeNumbers=[n_rigid, n_modal], stiffnessMatrixReduced=K, massMatrixReduced=M, dampingMatrixReduced=D,
            modeBasis=a["modeBasis"], referencePositions=a["xRef"], mass=float(a["totalMass"]),
            inertia=a["inertiaLocal"], centerOfMass=a["chiU"], mPsiTildePsi=a["mPsiTildePsi"],
            mPsiTildePsiTilde=a["mPsiTildePsiTilde"], mPhitTPsi=a["mPhitTPsi"], mPhitTPsiTilde=a["mPhitTPsiTilde"],
            mXRefTildePsi=a["mXRefTildePsi"], mXRefTildePsiTilde=a["mXRefTildePsiTilde"],
            computeFFRFterms=True, visualization=it.VObjectFFRFreducedOrder(show=False)))
        for coord in (2, 3, 4):  # the frame stays in the plane: z, rot_x, rot_y held (once per body)
            mk = mbs.AddMarker(it.MarkerNodeCoordinate(nodeNumber=n_rigid, coordinate=coord))
            mbs.AddObject(it.ObjectConnectorCoordinate(markerNumbers=[ground_coord, mk]))
        markers = [mbs.AddMarker(it.MarkerSuperElementRigid(bodyNumber=obj, meshNodeNumbers=nodes.tolist(),
                                                            weightingFactors=[1.0 / len(nodes)] * len(nodes),
                                                            offset=off.tolist()))
                   for nodes, off in sl.markers]
        if has_gravity:
            mbs.AddLoad(it.LoadMassProportional(markerNumber=mbs.AddMarker(it.MarkerBodyMass(bodyNumber=obj)),
                                                loadVector=gravity))
        bodies[lk.name] = FfrfBody(lk.name, sl, n_rigid, n_modal, obj, markers)

    def marker(link: str, station: float) -> int:
        b = bodies[link]
        return b.markers[b.solid.interface_index(station)]

    def ground_point(p) -> int:
        return mbs.AddMarker(it.MarkerBodyPosition(bodyNumber=ground, localPosition=[p[0], p[1], 0.0]))

    for jt in mech.joints:
        mks = [marker(p.link, p.station) for p in jt.points]
        for mk in mks[1:]:
            mbs.AddObject(it.ObjectJointSpherical(markerNumbers=[mks[0], mk], constrainedAxes=[1, 1, 0]))
        if jt.kind == "prismatic":
            axes = [1, 0, 0] if abs(jt.normal[0]) > 0.5 else [0, 1, 0]
            mbs.AddObject(it.ObjectJointSpherical(markerNumbers=[ground_point(jt.ground), mks[0]],
                                                  constrainedAxes=axes))
        elif jt.ground is not None:
            mbs.AddObject(it.ObjectJointSpherical(markerNumbers=[ground_point(jt.ground), mks[0]],
                                                  constrainedAxes=[1, 1, 0]))

    pose_of = {lk.name: z[3 * i : 3 * i + 3] for i, lk in enumerate(mech.links)}
    mass_nodes = []  # (link, node, rigid)
    for m in mech.all_masses():
        name, s = mech.node_location(m.node)
        x0, y0, th = (float(v) for v in pose_of[name])
        c, sn = math.cos(th), math.sin(th)
        a_, b_ = m.offset
        px, py = x0 + c * (s + a_) - sn * b_, y0 + sn * (s + a_) + c * b_
        mk = marker(name, s)
        if m.inertia > 0.0 or m.offset != (0.0, 0.0):
            node = mbs.AddNode(it.NodeRigidBody2D(referenceCoordinates=[px, py, th]))
            body = mbs.AddObject(it.ObjectRigidBody2D(nodeNumber=node, mass=m.mass, inertia=m.inertia))
            mb = mbs.AddMarker(it.MarkerBodyRigid(bodyNumber=body, localPosition=[-a_, -b_, 0.0]))
            mbs.AddObject(it.ObjectJointGeneric(markerNumbers=[mk, mb], constrainedAxes=[1, 1, 0, 0, 0, 1]))
            mass_nodes.append((name, node, True))
        elif m.mass > 0.0:
            node = mbs.AddNode(it.NodePoint(referenceCoordinates=[px, py, 0.0]))
            body = mbs.AddObject(it.ObjectMassPoint(nodeNumber=node, mass=m.mass))
            mb = mbs.AddMarker(it.MarkerBodyPosition(bodyNumber=body, localPosition=[0.0, 0.0, 0.0]))
            mbs.AddObject(it.ObjectJointSpherical(markerNumbers=[mk, mb], constrainedAxes=[1, 1, 1]))
            mass_nodes.append((name, node, False))
        else:
            continue
        if has_gravity:
            mbs.AddLoad(it.LoadMassProportional(markerNumber=mbs.AddMarker(it.MarkerBodyMass(bodyNumber=body)),
                                                loadVector=gravity))

    motor_loads = []
    for mo in mech.motors:
        jt = mech.joint(mo.joint)
        loads = []
        for lname, sign in ((mo.link, 1.0), (mo.reaction, -1.0)):
            if lname is None:
                continue
            st = next(p.station for p in jt.points if p.link == lname)
            loads.append((mbs.AddLoad(it.LoadTorqueVector(markerNumber=marker(lname, st), loadVector=[0.0, 0.0, 0.0])),
                          sign))
        motor_loads.append(loads)
    ode2_nodes = [(n, k) for b in bodies.values() for n, k in ((b.node_rigid, 6), (b.node_modal, b.solid.n_modes))]
    ode2_nodes += [(n, 3) for _, n, _ in mass_nodes]
    n_c = sum(k for _, k in ode2_nodes)
    forces = None
    if alpha:
        forces = mbs.AddObject(it.ObjectGenericODE2(
            nodeNumbers=[n for n, _ in ode2_nodes], forceVector=np.zeros(n_c),
            massMatrix=None if explicit_damping else np.zeros((n_c, n_c)),
            dampingMatrix=None if explicit_damping else np.zeros((n_c, n_c))))
    mbs.Assemble()
    for b in bodies.values():
        r0 = mbs.GetNodeODE2Index(b.node_rigid)
        m0 = mbs.GetNodeODE2Index(b.node_modal)
        b.frame_idx = np.array([r0, r0 + 1, r0 + 5])
        b.rot_idx = np.array([r0 + 3, r0 + 4])
        b.modal_idx = m0 + np.arange(b.solid.n_modes)
    starts = np.cumsum([0] + [k for _, k in ode2_nodes])
    if [mbs.GetNodeODE2Index(n) for n, _ in ode2_nodes] != starts[:-1].tolist() or mbs.systemData.ODE2Size() != n_c:
        raise RuntimeError("Exudyn numbered the node coordinates out of node order; the damper object assumes it")
    fm = FfrfModel(mech, q, SC, mbs, bodies, motor_loads, time.perf_counter() - t0,
                   all(s.cached for s in solids.values()), alpha=alpha, forces=forces,
                   explicit_damping=explicit_damping)
    if forces is not None:
        fm.mass_ref = np.asarray(mbs.ComputeLinearizedSystem()[0])  # the truth's own mass matrix at q
        ref = np.asarray(mbs.systemData.GetODE2Coordinates(exu.ConfigurationType.Reference))
        fm.angle_ref = {n: float(ref[b.frame_idx[2]]) for n, b in bodies.items()}
        fm.masses = [(link, mbs.GetNodeODE2Index(n) + np.arange(3 if rigid else 2), rigid)
                     for link, n, rigid in mass_nodes]
        fm.update_damper(ref)
    fm.settings = {
        "formulation": "FFRF reduced order (Exudyn ObjectFFRFreducedOrder), Hurty-Craig-Bampton modes, RBE2 interfaces",
        "mesh_order": 2,
        "mesh_scale": mesh_scale,
        "mode_factor": mode_factor,
        "links": {n: {"mesh_size_m": s.spec.mesh_size, "nodes": s.n_nodes, "tetrahedra": s.n_tets,
                      "setup_s": round(s.setup_s, 2), "from_cache": s.cached,
                      "modes": s.n_modes, "interfaces": list(s.spec.interfaces),
                      "fixed_interface_hz": np.round(s.fixed_interface_hz, 2).tolist()} for n, s in solids.items()},
        "damping": ("Rayleigh: beta K on each body's modal coordinates, alpha M with the mechanism's rigid motions "
                    "projected out (system level)") if damping else "none",
    }
    return fm


def _mode_planarity(fm: FfrfModel, vecs: np.ndarray) -> np.ndarray:
    """Per eigenvector (columns of ``vecs``, ODE2 coordinates): the fraction of its motion in the plane, from the
    frames and the bodies' interface and section read-outs against the modal coordinates' full 3D size."""
    inplane = np.zeros(vecs.shape[1])
    total = np.zeros(vecs.shape[1])
    for b in fm.bodies.values():
        L = b.solid.spec.length
        fr = vecs[b.frame_idx, :]
        qm = vecs[b.modal_idx, :]
        basis = b.solid.arrays["modeBasis"]
        u = basis @ qm  # (3 n_nodes, n_vec)
        ux, uy, uz = u[0::3], u[1::3], u[2::3]
        # in-plane: the frame and the displacement field's part even in z; out of plane: u_z and odd parts
        zc = b.solid.arrays["xRef"][2::3]
        odd = np.sign(zc)[:, None]
        fr_n = fr[0] ** 2 + fr[1] ** 2 + (L * fr[2]) ** 2
        n = max(len(zc), 1)
        ex = ((ux * odd).sum(0) ** 2 + (uy * odd).sum(0) ** 2) / n  # odd in z: out of plane
        ev = (ux.sum(0) ** 2 + uy.sum(0) ** 2) / n  # even in z: in plane
        ez = (uz.sum(0) ** 2) / n  # a mean u_z: out of plane
        etor = ((uz * np.sign(b.solid.arrays["xRef"][1::3])[:, None]).sum(0) ** 2) / n  # torsion
        inplane += fr_n * n + ev
        total += fr_n * n + ev + ex + ez + etor
    return inplane / np.maximum(total, 1e-300)


def ffrf_frequencies(mech: Mechanism, q=None, *, mesh_scale: float = 1.0, mode_factor: float = MODE_FACTOR,
                     progress: Callable[[str], None] | None = None, with_damping: bool = False,
                     fmax: float | None = None) -> dict:
    """Eigenfrequencies of the FFRF model at rest at ``q`` (motors free), in-plane modes separated from the
    out-of-plane ones (deformation odd in z, torsion) by :func:`_mode_planarity`.

    Returns a dict: ``frequencies_hz`` (in-plane elastic modes, ascending), ``out_of_plane_hz``, and with
    ``with_damping`` the ``damping_ratio`` of each in-plane mode from the linearised damped system
    (``ComputeLinearizedSystem``, the constraint null space)."""
    from .eigen import RIGID_TOL_HZ

    fm = build_ffrf(mech, q, mesh_scale=mesh_scale, mode_factor=mode_factor, damping=with_damping,
                    progress=progress, explicit_damping=False)
    zeta = None
    if with_damping:
        import scipy.linalg as sla

        M, K, D, *_ = fm.mbs.ComputeLinearizedSystem(projectIntoConstraintNullspace=True)
        M, K, D = (np.asarray(a) for a in (M, K, D))
        n = M.shape[0]
        Z = np.zeros((n, n))
        s = sla.eigvals(np.block([[Z, np.eye(n)], [-np.linalg.solve(M, K), -np.linalg.solve(M, D)]]))
        s = s[s.imag > 1e-6]
        zeta = (np.abs(s) / (2 * np.pi), -s.real / np.abs(s))
    f, vecs = fm.mbs.ComputeODE2Eigenvalues(convert2Frequencies=True, useSparseSolver=False,
                                            ignoreAlgebraicEquations=False, useAbsoluteValues=True)
    f, vecs = np.asarray(f, float), np.asarray(vecs, float)
    order = np.argsort(f)
    f, vecs = f[order], vecs[:, order]
    nq = len(mech.coordinates)
    if np.any(f[:nq] > RIGID_TOL_HZ):
        raise RuntimeError(f"FFRF model of {mech.name}: expected {nq} zero-frequency mechanism modes, got "
                           f"{np.round(f[:nq], 3).tolist()} Hz")
    f, vecs = f[nq:], vecs[:, nq:]
    plan = _mode_planarity(fm, vecs)
    keep = plan >= 0.5
    out = {"frequencies_hz": f[keep], "out_of_plane_hz": f[~keep], "planarity": plan[keep],
           "settings": fm.settings, "setup_s": fm.setup_s, "cached": fm.cached}
    if zeta is not None:  # each in-plane mode's ratio: the damped mode nearest in frequency
        fz, z = zeta
        out["damping_ratio"] = np.array([z[np.argmin(np.abs(fz - fi))] for fi in out["frequencies_hz"]])
    if fmax is not None:
        if zeta is not None:
            out["damping_ratio"] = out["damping_ratio"][out["frequencies_hz"] <= fmax]
        out["planarity"] = out["planarity"][out["frequencies_hz"] <= fmax]
        out["frequencies_hz"] = out["frequencies_hz"][out["frequencies_hz"] <= fmax]
        out["out_of_plane_hz"] = out["out_of_plane_hz"][out["out_of_plane_hz"] <= fmax]
    return out


def simulate_ffrf(mech: Mechanism, t_table, torque_table, duration: float, h: float = 1e-4,
                  output_dt: float | None = 1 / 500, q0=None, probes: Sequence[Probe] | None = None,
                  progress: Callable[[float], None] | None = None, messages: Callable[[str], None] | None = None,
                  mesh_scale: float = 1.0, mode_factor: float = MODE_FACTOR, damping: bool = True,
                  damping_update: float = 0.02, damping_tol: float | None = 1e-5,
                  newton_tol: float = 1e-4, spectral_radius: float = 0.9, stats: dict | None = None) -> ProbeRecord:
    """Simulate the FFRF model of ``mech`` from rest at ``q0`` under tabulated motor torques; record the probes.

    Same contract as :func:`exuflex.groundtruth.simulate_truth` (torque table in ``mech.motors`` order, its zero-order
    hold applied at each step's end as the ERLS engine's generalized-alpha does, :func:`.simulate.step_end_torques`:
    without lag, and a record holds nothing of a torque switched at its instant; probes every ``output_dt``; slopes
    on the branch of the ERLS pose at ``q0``). ``messages`` receives the meshing and modes' progress lines;
    ``mesh_scale``, ``mode_factor``, ``damping``: :func:`build_ffrf`; the alpha damper is refreshed on
    :class:`~exuflex.groundtruth.simulate.DamperSchedule` (``damping_update``, ``damping_tol``: as in
    :func:`~exuflex.groundtruth.simulate_truth`) and applied as the force ``-D c'`` with the rates at each step's
    start. ``stats`` (a dict) receives the solver's
    statistics and the setup time.
    """
    from .simulate import DamperSchedule, _interp_table, step_end_torques

    exu, _ = _exu()
    n_steps, every = step_grid(h, duration, output_dt)
    probes = tuple(probes_for(mech) if probes is None else probes)
    fm = build_ffrf(mech, q0, mesh_scale=mesh_scale, mode_factor=mode_factor, damping=damping, probes=probes,
                    progress=messages)
    mbs = fm.mbs
    nm = len(mech.motors)
    t_steps = np.arange(n_steps + 1) * h
    tau = _interp_table(t_table, torque_table, t_steps, nm) if nm else np.zeros((n_steps + 1, 0))
    tau_end = step_end_torques(t_table, torque_table, h, n_steps, every, nm)  # at the end t_k+1 of step k
    sd = mbs.systemData
    ref = np.asarray(sd.GetODE2Coordinates(exu.ConfigurationType.Reference))
    n_out = n_steps // every + 1
    C = np.empty((n_out, len(ref)))
    Cd = np.empty((n_out, len(ref)))
    T_out = np.empty(n_out)
    state = {"i": 0}
    rep_every = max(1, n_steps // 100)
    loads = [(ld, sign, j) for j, lds in enumerate(fm.motor_loads) for ld, sign in lds]
    cur = exu.ConfigurationType.Current

    def record(t):
        i = state["i"]
        if i < n_out:
            C[i] = sd.GetODE2Coordinates(cur)
            Cd[i] = sd.GetODE2Coordinates_t(cur)
            T_out[i] = t
            state["i"] = i + 1

    pre_time = [0.0]
    schedule = DamperSchedule(fm.alpha, h, damping_update, damping_tol)

    def pre_step(mbs_, t):
        t_in = time.perf_counter()
        k = int(round(t / h)) - 1  # Exudyn passes the step's end time; the state is still at t_k
        if k < 0 or k >= n_steps:
            return True
        if k % every == 0:
            record(k * h)
        if fm.forces is not None:
            cd = np.asarray(sd.GetODE2Coordinates_t(cur))
            if schedule.due(k):
                fm.update_damper(schedule.plan(k, np.asarray(sd.GetODE2Coordinates(cur)) + ref, cd,
                                               fm.rotation_rate))
            mbs_.SetObjectParameter(fm.forces, "forceVector", -(fm.D_alpha @ cd))
        row = tau_end[k]
        for ld, sign, j in loads:
            mbs_.SetLoadParameter(ld, "loadVector", [0.0, 0.0, sign * float(row[j])])
        if progress is not None and k % rep_every == 0:
            progress(k / n_steps)
        pre_time[0] += time.perf_counter() - t_in
        return True

    ss = implicit_settings(exu, n_steps, duration, newton_tol, spectral_radius)
    for ld, sign, j in loads:
        mbs.SetLoadParameter(ld, "loadVector", [0.0, 0.0, sign * float(tau[0, j])])
    mbs.SetPreStepUserFunction(pre_step)
    t0, c0 = time.perf_counter(), time.process_time()
    solver = exu.MainSolverImplicitSecondOrder()
    ok = solver.SolveSystem(mbs, ss)
    wall = time.perf_counter() - t0
    if not ok:
        raise RuntimeError(f"Exudyn FFRF solver failed before t = {duration} s (see Exudyn's messages)")
    if n_steps % every == 0:
        record(n_steps * h)
    if progress is not None:
        progress(1.0)
    if stats is not None:
        it = solver.it
        stats.update(wall_s=wall, cpu_s=time.process_time() - c0, setup_s=fm.setup_s, setup_cached=fm.cached,
                     pre_step_s=pre_time[0],
                     newton_per_step=it.newtonStepsCount / n_steps, jacobians_per_step=it.newtonJacobiCount / n_steps,
                     n_steps=n_steps, n_coordinates=len(ref), step_ms=1e3 * wall / n_steps, solid=fm.settings)
    n = state["i"]
    c_full = C[:n] + ref
    cd_full = Cd[:n]
    rec = ProbeRecord(T_out[:n].copy())
    from ..erls.kinematics import Kinematics

    pose = Kinematics(mech).pose(np.asarray(mech.q_ref if q0 is None else q0, float))
    link_angle = {lk.name: pose.z[3 * i + 2] for i, lk in enumerate(mech.links)}
    for p in probes:
        v, r = fm.probe_values(p, c_full, cd_full)
        if p.kind == "slope":
            v = v + 2 * np.pi * np.round((link_angle[p.link] - v[0]) / (2 * np.pi))
        rec.values[p.key] = v
        rec.rates[p.key] = r
    log.info("FFRF truth %s: %.3g s simulated in %.3g s wall (h = %g s, %.3g ms per step)", mech.name, duration,
             wall, h, 1e3 * wall / n_steps)
    return rec

"""Full-order ERLS model of a planar flexible-link mechanism (the paper's eq. 2).

Coordinates ``x = [q; u]``: the independent ERLS coordinates ``q`` and the elastic displacements
``u`` (global frame, relative to the ERLS, after the ERLS-defining constraints, see
:mod:`exuflex.mechanism.dofs`). Every node's absolute coordinates are ``b = r(q) + T u`` with
``r`` the ERLS nodal coordinates and ``T`` the 0/1 map from ``u`` to nodal displacements, so
``db/dt = S q' + T u' = W v`` with ``W = [S, T]`` and ``v = [q'; u']``.

Equations of motion: ``W^T M_N W v' + h(x, v) + C v + K x = W^T (B tau + f + M_N g)`` with
``W^T M_N W`` eq. 2's mass matrix, ``K = diag(0, K_uu)``, ``K_uu = T^T K_N T``, ``M_N`` and ``K_N``
assembled from the element matrices rotated with the ERLS (``R_e``: the element's block rotation by
its link's angle ``theta_e``).

Element kinematics (both forms start here). A point at station ``s`` of element ``e`` sits at
``p = R_e N(s) R_e^T b_e``: the element's nodal coordinates taken into its own frame, interpolated
(``N``, 2 x 6: linear axial, cubic Hermite lateral) and turned back. With ``R_e' = theta_e' R_e G``
(``G``: :data:`~exuflex.erls.elements.GENERATOR`, ``G2`` its 2 x 2 block)

``p' = R N R^T b' + theta' R (G2 N - N G) R^T u``.

``N`` interpolates rigid velocity fields exactly, for which ``N G = G2 N``, so the second term acts on
the elastic ``u`` only; it is the difference between rotating the elastic field with the element and
interpolating it in the global frame, and shrinks as O(h^2) with the element length h. The two forms
(``form=``) differ in how they treat it and in the damping's rows:

``form="lagrange"`` (energy-consistent)
    Lagrange's equations for ``T = b'^T M_N(q) b' / 2`` (the first term of ``p'`` only) and
    ``V = u^T K_uu(q) u / 2``:
    ``h = W^T (M_N S' q' + M_N' b') - [dT/dq; 0] + [dV/dq; 0]`` with the symmetric
    ``M_N' = sum_e theta_e' R_e (G m_e - m_e G) R_e^T`` (``S' = dS/dt``; the terms of ``dW/dq``
    cancel because ``d^2 r/dq_j dq_k`` is symmetric). The two q-row terms are second order in the
    elastic motion. ``C(x) = L^T (alpha P + beta K_N) L``: Rayleigh damping as the dissipation function
    ``v^T C v / 2`` of the strain rate ``s = L v`` (see "Damping" below; ``diag(0, alpha M_e + beta K_uu)`` at
    ``u = 0``). Exactly energy-consistent, ``dE/dt = -v^T C v + v^T Q`` (``tests/test_energy.py``).
    ``M_N' S q'`` is not zero under pure rigid motion.
``form="eq2"`` (the paper's eq. 2 as written)
    Virtual work with ``delta p = R N R^T delta b`` and the acceleration
    ``p'' = R N R^T b'' + 2 theta' R (G2 N - N G) R^T u' + (terms in theta'^2 u and theta'' u)``, the
    last left out as eq. 2 does: ``h = W^T (M_N S' q' + 2 M_G T u')`` with
    ``M_G = sum_e theta_e' R_e (A_e - m_e G) R_e^T``, ``A_e = int rhoA N^T G2 N ds`` (skew,
    :func:`~exuflex.erls.elements.beam_gyroscopic`), so ``M_G`` is not symmetric and ``M_G S = 0``.
    The damping is ``W^T C_N T u'`` with ``C_N = alpha M_N + beta K_N``: eq. 2's ``S^T C u'`` in the
    q rows (``K_N S = 0``, so only ``alpha S^T M_N T u'`` remains there). Neither ``M_G`` nor the q rows'
    damping derives from an energy or a dissipation function, so this form has no power balance identity.

Damping. The model file's ``alpha``, ``beta`` are the Rayleigh damping of the free elastic modes: each mode
of ``M(q) x'' + C x' + K x = 0`` at rest (motors free) has the damping ratio ``alpha / (2 w) + beta w / 2``.

The ``"lagrange"`` form damps the strain rate, not the global rate ``u'``. ``u`` is global, so ``d = T u``
turns with the links: with the element-frame displacement ``e = R^T d`` (``R`` the element's, i.e. its link's,
rotation), ``R e' = d' - theta' G d``. A bent link turning rigidly has ``e' = 0`` but ``d' = theta' G d != 0``:
a damping on ``u'`` would brake it, a joint damping that material damping (a law in the strain rate, invariant
under rigid rotation; Exudyn's beams' ``bendingDamping`` and ``axialDamping``) does not have. The strain rate in
global components, node by node with its link's rate ``theta_n' = S_n q'`` (the rotation rows of ``S``), is

``s = T u' - Y(u) q' = L v``, ``L = [-Y, T]``, ``Y[:, j] = (G3 T u) * S_theta[:, j]``

(:meth:`ErlsModel.turned_rates`; ``G3`` turns each node's translation by 90 degrees and leaves its rotation
alone; ``Y`` is linear in ``u``). The dissipation function is

``D = beta/2 s^T K_N s + alpha/2 min_a |S a + s|^2_{M_N} = v^T C(x) v / 2``,
``C(x) = L^T (alpha P + beta K_N) L``, ``P = M_N - M_N S (S^T M_N S)^-1 S^T M_N``,

``beta s^T K_N s = beta sum_e e_e'^T K_e e_e'``: the element strain energy's form in the element-frame rates,
the Kelvin-Voigt law of the beam elements. ``alpha``: the kinetic energy of the strain rates relative to the rigid
mechanism motion that carries their momentum (the ERLS counter-rotates against the deformation; ``alpha M_uu``
on ``u'`` would damp that rigid counter-rotation). The generalized damping force is ``-dD/dv = -C(x) v`` on all
coordinates: the q rows get ``Y^T (alpha P + beta K_N) s`` (the rotation rate is part of the strain rate). ``C``
is symmetric positive semidefinite, so the damping only dissipates, and ``s = 0``, ``C v = 0`` for the rates of
a rigid turning with every link's deflection held (``T u' = Y q'``). Its change with ``u`` at fixed ``v`` is
:meth:`ErlsModel.damping_position_jacobian` (the implicit engine's iteration matrix and the state matrix
use it).

At rest (``u = 0``) ``L = [0, T]`` and ``C = diag(0, alpha M_e + beta K_uu)`` with the Schur complement ``M_e =
M_uu - M_uq M_qq^-1 M_qu`` (:meth:`ErlsModel.elastic_mass`), so the free modes' ratios are Rayleigh's: ``K =
diag(0, K_uu)`` has the rigid mechanism motions ``E = [I; 0]`` as its null space, the elastic modes are
M-orthogonal to them (``M_qq phi_q + M_qu phi_u = 0``), a mode's kinetic energy is ``phi_u^T M_e phi_u``, and
``C = alpha (M - M E (E^T M E)^-1 E^T M) + beta K`` gives ``phi_i^T C phi_j = (alpha + beta w_i^2) delta_ij`` on
the mass-normalised elastic modes and ``C E = 0``. ``"eq2"`` keeps eq. 2's ``W^T C_N T u'`` (``C = alpha M [0; I]
+ beta K`` in the u columns, on the global ``u'``): also the Rayleigh ratios (its state matrix is
block-triangular in rigid and elastic modal coordinates), but with forces in the q rows that no dissipation
function gives. ``tests/test_damping.py`` checks both forms' ratios against the formula from the state matrix's
eigenvalues; ``tests/test_damping_strain.py`` the strain-rate law against element-frame rates by differences.

Geometric stiffness (``geometric=True``, the default). Linear elasticity in the links' frames leaves out the work
of an axial force ``N`` across the lateral displacements, ``N int v'^2 / 2 dx`` (the second-order strain), whose
second variation is the geometric stiffness ``K_G(N)`` (:func:`~exuflex.erls.elements.beam_geometric_stiffness`):
a link in compression softens (the P-delta effect of a weight along an upright link), one in tension stiffens (the
centrifugal stiffening of a spinning link). The elastic rows take the axial forces of the rigid motion's loads
(:meth:`ErlsModel.rigid_loads`: motors, weight and the d'Alembert forces of the rigid accelerations and rates, in
equilibrium), each element's from the links' quasi-static axial response (:meth:`ErlsModel.axial_forces`), so the
elastic rows' stiffness is ``K_uu + T^T K_G(N(q, q', tau)) T``: linear in ``u``, first order in the loads. The
coordinate rows already hold the P-delta's share: the rotated stiffness's ``dV/dq`` above is the moment of the
elastic axial force across the tilt (``tests/test_pdelta.py``). The weight's static part, ``K_G`` of the weight
with the holding torques, is the configuration's (:meth:`ErlsModel.static_geometric`): the linearised models and
the reduction hold it. ``K_G(q, q', tau)`` derives from no potential: its power ``-u'^T K_G u`` enters the energy
balance (``tests/test_energy.py``).

On rigid motion (``u = u' = 0``) the q rows of the two forms coincide (``M_N'`` and the ``dT/dq`` term
cancel on rigid fields). On a uniformly spinning link the elastic rows of ``"eq2"`` are exactly the
consistent nodal load of the centrifugal force; ``"lagrange"`` adds ``T^T M_N' S q'``, whose largest
entry falls as h^2 (``tests/test_erls_forms.py`` checks these, ``M_G S = 0`` and both forms' ``dh/dv``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mechanism import ElasticDofs, Mechanism, elastic_dofs
from ._assembly import configuration as compiled_configuration
from ._assembly import nodal_matrices
from .elements import (
    GENERATOR,
    beam_geometric_stiffness,
    beam_gyroscopic,
    beam_mass,
    beam_stiffness,
    hermite_curvature_row,
    rotation,
)
from .kinematics import Kinematics, Pose

__all__ = ["FORMS", "Configuration", "ErlsModel"]

FORMS = ("lagrange", "eq2")  # the velocity forces and damping of the equations of motion (module docstring)


@dataclass(frozen=True)
class Configuration:
    """Everything that depends on q only: the pose, rotated and assembled nodal matrices, W."""

    pose: Pose
    R: np.ndarray  # (n_el, 6, 6) element rotations
    M_N: np.ndarray  # (N, N) nodal mass (elements + lumped)
    K_N: np.ndarray  # (N, N) nodal stiffness (linear elastic)
    W: np.ndarray  # (N, n) = [S, T]
    #: the nodal geometric stiffness of the static axial loads at q (``ErlsModel.static_geometric``; None: none,
    #: no gravity or ``geometric=False``)
    K_G: np.ndarray | None = None
    N_static: np.ndarray | None = None  # (n_el,) the elements' static axial forces (N, tension positive) of K_G

    @property
    def q(self) -> np.ndarray:
        return self.pose.q


class ErlsModel:
    """Full-order ERLS model: assembly, equations of motion, outputs.

    Parameters
    ----------
    mech : Mechanism
        The mechanism (e.g. from :func:`exuflex.mechanism.load_mechanism`).
    form : "lagrange" or "eq2"
        The velocity-dependent forces and damping: the energy-consistent Lagrange form (default: on the six-bar's
        manoeuvre it agrees with the Exudyn truth, eq. 2 as written does not, and on the spin-up benchmark the two
        are equal; ``docs/validity.md``) or the paper's eq. 2 as written (see the module docstring).
    geometric : bool
        The geometric stiffness of the links' axial loads in the elastic rows (default; module docstring,
        "Geometric stiffness"); False: linear elasticity alone.
    """

    def __init__(self, mech: Mechanism, form: str = "lagrange", geometric: bool = True):
        if form not in FORMS:
            raise ValueError(f"ErlsModel: form must be one of {FORMS}, got {form!r}")
        self.form = form
        self.geometric = bool(geometric)
        self._locate_cache: dict = {}
        self.mech = mech
        self.kin = Kinematics(mech)
        self.dofs: ElasticDofs = elastic_dofs(mech)
        self.nq = len(mech.coordinates)
        self.ne = self.dofs.n
        self.n = self.nq + self.ne
        nodes = list(mech.node_ids)
        self.n_nodes = len(nodes)
        self.N = 3 * self.n_nodes
        T = np.zeros((self.N, self.ne))
        for d, k in enumerate(self.dofs.nodal_to_u):
            if k >= 0:
                T[d, k] = 1.0
        self.T = T
        # T by rows: the elastic coordinate of every nodal dof (-1: none; at most one per row), for the compiled
        # products with W = [S, T] that skip T's zeros (:mod:`exuflex.reduction._compiled`)
        self.t_index = np.asarray(self.dofs.nodal_to_u, dtype=np.int64)
        # elements
        link_index = {lk.name: i for i, lk in enumerate(mech.links)}
        el_link, el_dofs, Kl, Ml, Al, el_len, el_station = [], [], [], [], [], [], []
        for lk in mech.links:
            EA = lk.material.E * lk.section.A
            EI = lk.material.E * lk.section.I
            rhoA = lk.material.rho * lk.section.A
            for a in range(lk.n_elements):
                L = lk.stations[a + 1] - lk.stations[a]
                na, nb = nodes.index(lk.node_ids[a]), nodes.index(lk.node_ids[a + 1])
                el_link.append(link_index[lk.name])
                el_dofs.append([3 * na, 3 * na + 1, 3 * na + 2, 3 * nb, 3 * nb + 1, 3 * nb + 2])
                Kl.append(beam_stiffness(EA, EI, L))
                Ml.append(beam_mass(rhoA, L))
                Al.append(beam_gyroscopic(rhoA, L))
                el_len.append(L)
                el_station.append(lk.stations[a])
        # masses at an offset from their node: one-node "elements" that rotate with the node's link, local mass
        # m [[1, 0, -b], [0, 1, a], [-b, a, a^2 + b^2]] + J e3 e3^T on (u, v, theta) for the offset (a, b) in the
        # link frame (the mass point's velocity in that frame is (u' - b theta', v' + a theta') = N_p d', so the mass is
        # m N_p^T N_p + J e3 e3^T and eq. 2's gyroscopic matrix m N_p^T G2 N_p, as beam_gyroscopic for a point), no
        # stiffness, zero length (no station: sensors never locate them). The element's second node is a neighbour
        # on the link with a zero block, so that no element lists a nodal dof twice.
        for lm in mech.all_masses():
            if lm.offset == (0.0, 0.0):
                continue
            a, b = lm.offset
            k = nodes.index(lm.node)
            lname = lm.link or mech.node_location(lm.node)[0]
            ids = mech.link(lname).node_ids
            i = ids.index(lm.node)
            k2 = nodes.index(ids[i + 1] if i + 1 < len(ids) else ids[i - 1])
            Np = np.zeros((2, 6))
            Np[:, :3] = [[1.0, 0.0, -b], [0.0, 1.0, a]]
            Me = lm.mass * Np.T @ Np
            Me[2, 2] += lm.inertia
            # plus m N_p^T (a, b) e3^T: with it A - M G annihilates the rigid rotation about the node, (0, 0, 1), as
            # it does translations (a beam's N interpolates rigid fields with N G = G2 N; an offset point does not)
            e3 = np.zeros(6)
            e3[2] = 1.0
            Al.append(lm.mass * (Np.T @ np.array([[0.0, -1.0], [1.0, 0.0]]) @ Np + np.outer(Np.T @ [a, b], e3)))
            el_link.append(link_index[lname])
            el_dofs.append([3 * k, 3 * k + 1, 3 * k + 2, 3 * k2, 3 * k2 + 1, 3 * k2 + 2])
            Kl.append(np.zeros((6, 6)))
            Ml.append(Me)
            el_len.append(0.0)
            el_station.append(mech.node_location(lm.node)[1])
        self.el_link = np.array(el_link)
        self.el_dofs = np.array(el_dofs)
        self.el_len = np.array(el_len)
        self.el_station = np.array(el_station)
        self.Kl = np.array(Kl)
        self.Ml = np.array(Ml)
        self.Gl = GENERATOR @ self.Ml - self.Ml @ GENERATOR  # dM/dtheta in local form
        self.KGl = GENERATOR @ self.Kl - self.Kl @ GENERATOR
        # the geometric stiffness per unit axial force and the axial stiffness EA / L of each beam element (zero for
        # the offset masses' one-node elements)
        self.el_KG1 = np.array([beam_geometric_stiffness(1.0, L) if L > 0 else np.zeros((6, 6)) for L in el_len])
        self.el_axial = np.array([k[3, 3] for k in Kl])  # EA / L of the local stiffness' axial block
        self.MGl = np.array(Al) - self.Ml @ GENERATOR  # eq. 2's M_G per unit element rate, local form
        self.n_el = len(el_link)
        lump = np.zeros(self.N)
        for lm in mech.all_masses():
            if lm.offset == (0.0, 0.0):
                i = nodes.index(lm.node)
                lump[3 * i : 3 * i + 3] += (lm.mass, lm.mass, lm.inertia)
        self.lumped = lump
        self._diag_idx = np.diag_indices(self.N)
        # motors: nodal moment pattern
        B = np.zeros((self.N, len(mech.motors)))
        for j, m in enumerate(mech.motors):
            B[self._joint_node_dof(m.joint, m.link, 2), j] += 1.0
            if m.reaction is not None:
                B[self._joint_node_dof(m.joint, m.reaction, 2), j] -= 1.0
        self.B_N = B
        g = np.zeros(self.N)
        g[0::3], g[1::3] = mech.gravity
        self.g_N = g
        self.alpha, self.beta = mech.damping.alpha, mech.damping.beta
        self.names = tuple(mech.coordinate_names) + self.dofs.names
        # scatter indices for assembly
        self._rows = np.repeat(self.el_dofs, 6, axis=1).ravel()
        self._cols = np.tile(self.el_dofs, (1, 6)).ravel()
        self._flat = self._rows * self.N + self._cols
        self._el_flat = self.el_dofs.ravel()
        # (N, 6 n_el) 0/1 map scattering stacked element vectors into nodal vectors
        self.scatter = np.zeros((self.N, 6 * self.n_el))
        self.scatter[self._el_flat, np.arange(6 * self.n_el)] = 1.0
        # configuration(): the rotated, assembled nodal matrices in one compiled call where numba is installed
        # (_assembly); False: the NumPy expressions (the reference)
        self.compiled = nodal_matrices is not None

    # ------------------------------------------------------------------ helpers
    def _joint_node_dof(self, joint: str, link: str, comp: int) -> int:
        j = self.mech.joint(joint)
        st = next(p.station for p in j.points if p.link == link)
        node = self.mech.node_at(link, st)
        return 3 * list(self.mech.node_ids).index(node) + comp

    def index(self, name: str) -> int:
        """Index in x of a coordinate (``q1``) or elastic dof (``x25``, ``node14.x``)."""
        if name in self.mech.coordinate_names:
            return self.mech.coordinate_names.index(name)
        return self.nq + self.dofs.index(name)

    def _assemble(self, Ke: np.ndarray) -> np.ndarray:
        return np.bincount(self._flat, Ke.reshape(-1), minlength=self.N * self.N).reshape(self.N, self.N)

    # ------------------------------------------------------------------ configuration
    def configuration(self, q, z0=None) -> Configuration:
        """Everything that depends on q only (closure warm-started from ``z0`` or the last solution); in one compiled
        call (:func:`._assembly.configuration`) where numba is installed and Newton converges from the start. With
        gravity (and ``geometric``) with the geometric stiffness of the static axial loads at q
        (:meth:`static_geometric`)."""
        cfg = self._material_configuration(q, z0)
        if self.geometric and np.any(self.g_N):
            return self.static_geometric(cfg)
        return cfg

    def _material_configuration(self, q, z0=None) -> Configuration:
        """:meth:`configuration` with the material stiffness only."""
        kin = self.kin
        if self.compiled and kin.compiled and compiled_configuration is not None:
            q, start = kin.start(q, z0)
            try:
                ok, z, Jinv, cond, Sz, r, S, R, M_N, K_N, W = compiled_configuration(
                    np.asarray(start, float), q, kin.arrays, 1e-12 * kin.newton_scale, 30, kin.node_link,
                    kin.node_station, self.el_link, self.Ml, self.Kl, self.el_dofs, self.lumped, self.T)
            except np.linalg.LinAlgError:  # a singular closure Jacobian: the reference path reports it
                ok = False
            if ok:
                kin.accept(q, z)
                kin.check_condition(q, cond)
                return Configuration(Pose(q, z, Sz, r, S, cond, Jinv), R, M_N, K_N, W)
        pose = kin.pose(q, z0)
        th = pose.link_angles[self.el_link]
        if self.compiled:
            R, M_N, K_N = nodal_matrices(np.ascontiguousarray(th, dtype=float), self.Ml, self.Kl, self.el_dofs,
                                         self.lumped)
            return Configuration(pose, R, M_N, K_N, np.hstack([pose.S, self.T]))
        R = rotation(th)
        Rt = np.swapaxes(R, 1, 2)
        M_N = self._assemble(R @ self.Ml @ Rt)
        M_N[self._diag_idx] += self.lumped
        K_N = self._assemble(R @ self.Kl @ Rt)
        W = np.hstack([pose.S, self.T])
        return Configuration(pose, R, M_N, K_N, W)

    def mass(self, cfg: Configuration) -> np.ndarray:
        """M(q) of eq. 2 (n x n)."""
        return cfg.W.T @ cfg.M_N @ cfg.W

    def stiffness(self, cfg: Configuration) -> np.ndarray:
        """K(q) of eq. 2: zero q rows and columns, ``K_uu = T^T K_N T`` with the static axial loads' geometric
        stiffness where the model has it (:meth:`elastic_stiffness`)."""
        K = np.zeros((self.n, self.n))
        K[self.nq :, self.nq :] = self.elastic_stiffness(cfg)
        return K

    def damping(self, cfg: Configuration, x: np.ndarray | None = None) -> np.ndarray:
        """The damping matrix C (n x n) of the form at the configuration ``cfg`` and state ``x`` (``None``: the
        elastic coordinates zero). ``"lagrange"``: ``C(x) = L^T (alpha P + beta K_N) L`` with the strain-rate map
        ``L = [-Y(x), T]`` (:meth:`turned_rates`) and ``P`` the mass relative to the rigid motion, so that ``v^T C
        v / 2`` is the dissipation function of the link-relative rates; at ``u = 0``: ``diag(0, alpha M_e + beta
        K_uu)`` (:meth:`elastic_mass`). ``"eq2"``: ``W^T (alpha M_N + beta K_N) T`` in the u columns (module
        docstring, "Damping")."""
        C = np.zeros((self.n, self.n))
        if self.form == "eq2":
            C[:, self.nq :] = cfg.W.T @ (self.alpha * (cfg.M_N @ self.T) + self.beta * (cfg.K_N @ self.T))
            return C
        if x is None or not np.any(x[self.nq :]):
            Tt = self.T.T
            C[self.nq :, self.nq :] = self.alpha * self.elastic_mass(cfg) + self.beta * (Tt @ cfg.K_N @ self.T)
            return C
        L = np.hstack([-self.turned_rates(cfg, x), self.T])
        return L.T @ self.damping_products(cfg, L)

    def turned_rates(self, cfg: Configuration, x: np.ndarray) -> np.ndarray:
        """``Y`` (N, nq): the nodal rates of the elastic displacements ``d = T u`` turned with their links per unit
        ``q'``, ``Y q' = Omega d`` with ``Omega`` the block-diagonal ``theta_n' G3`` over the nodes (``theta_n'``
        the rate of node n's link, ``G3 = [[0, -1, 0], [1, 0, 0], [0, 0, 0]]``). The strain rate in the global frame
        is ``s = T u' - Y q' = R d(R^T d)/dt`` (module docstring, "Damping"); ``Y`` is linear in ``u``."""
        d = self.T @ x[self.nq :]
        Gd = np.zeros(self.N)
        Gd[0::3], Gd[1::3] = -d[1::3], d[0::3]
        return Gd[:, None] * self._node_rates(cfg)

    def _node_rates(self, cfg: Configuration) -> np.ndarray:
        """(N, nq): the rate of every nodal dof's link angle per unit ``q'`` (the rigid rotation rows of ``S``)."""
        return np.repeat(cfg.pose.S[2::3], 3, axis=0)

    def damping_products(self, cfg: Configuration, s: np.ndarray) -> np.ndarray:
        """``(alpha P + beta K_N) s`` for nodal rates ``s`` (N,) or (N, k), ``P = M_N - M_N S (S^T M_N S)^-1 S^T
        M_N``."""
        S = cfg.pose.S
        MS = cfg.M_N @ S
        f = self.beta * (cfg.K_N @ s)
        if self.alpha:
            f = f + self.alpha * (cfg.M_N @ s - MS @ np.linalg.solve(S.T @ MS, MS.T @ s))
        return f

    def damping_forces(self, cfg: Configuration, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``C(x) v`` (n,) as products (:meth:`damping`), the gradient in ``v`` of the dissipation function ``v^T
        C(x) v / 2`` (the generalized damping force is its negative). ``"lagrange"``: ``L^T (alpha P + beta K_N) s``
        with the strain rate ``s = T u' - Y q'``; ``"eq2"``: ``W^T (alpha M_N + beta K_N) T u'``."""
        nq = self.nq
        Tud = self.T @ v[nq:]
        if self.form == "eq2":
            return cfg.W.T @ (self.alpha * (cfg.M_N @ Tud) + self.beta * (cfg.K_N @ Tud))
        out = np.zeros(self.n)
        if np.any(x[nq:]):
            Y = self.turned_rates(cfg, x)
            f = self.damping_products(cfg, Tud - Y @ v[:nq])
            out[:nq] = -Y.T @ f
        else:
            f = self.damping_products(cfg, Tud)
        out[nq:] = self.T.T @ f
        return out

    def damping_position_jacobian(self, cfg: Configuration, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``d(C(x) v)/du`` (n, ne) of the ``"lagrange"`` form's damping forces, exact (they are bilinear in ``u``
        and ``v`` at a configuration): with ``s = T u' - Y q'``, ``ds/du = -diag(w) G3 T`` (``w``: every nodal dof's
        link rate) and ``f = (alpha P + beta K_N) s``, ``d(L^T f)/du = L^T (alpha P + beta K_N) ds/du`` plus the
        change of ``-Y^T`` in the q rows, ``-(diag(f) Sigma)^T G3 T`` (``Sigma``: :meth:`_node_rates`). Their change
        with ``q`` (through ``S``, ``P``, ``K_N``) is not part of it; the eq2 form: zero (its damping does not depend
        on ``u``)."""
        nq = self.nq
        if self.form == "eq2" or not (self.alpha or self.beta):
            return np.zeros((self.n, self.ne))
        Sig = self._node_rates(cfg)
        w = Sig @ v[:nq]
        GT = np.zeros((self.N, self.ne))
        GT[0::3], GT[1::3] = -self.T[1::3], self.T[0::3]
        dsdu = -w[:, None] * GT
        Y = self.turned_rates(cfg, x)
        s = self.T @ v[nq:] - Y @ v[:nq]
        f = self.damping_products(cfg, s)
        Zd = self.damping_products(cfg, dsdu)
        out = np.empty((self.n, self.ne))
        out[:nq] = -Y.T @ Zd - (Sig * f[:, None]).T @ GT
        out[nq:] = self.T.T @ Zd
        return out

    def elastic_mass(self, cfg: Configuration) -> np.ndarray:
        """``M_e = M_uu - M_uq M_qq^-1 M_qu`` (ne x ne): the mass of the elastic rates relative to the rigid
        mechanism motion that carries their momentum, ``u'^T M_e u' = min_a |S a + T u'|^2_{M_N}`` (the
        ``"lagrange"`` form's mass-proportional damping; module docstring, "Damping")."""
        MS = cfg.M_N @ cfg.pose.S
        MT = cfg.M_N @ self.T
        X = self.T.T @ MS  # M_uq
        return self.T.T @ MT - X @ np.linalg.solve(cfg.pose.S.T @ MS, X.T)

    def input_matrix(self, cfg: Configuration) -> np.ndarray:
        """Generalised forces of unit motor torques, W^T B (n x n_motors)."""
        return cfg.W.T @ self.B_N

    def nodal_load_vector(self, cfg: Configuration, f_nodal: np.ndarray) -> np.ndarray:
        """Generalised forces W^T f of nodal loads (N,) in the global frame."""
        return cfg.W.T @ f_nodal

    def velocity_forces(self, cfg: Configuration, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """h(x, v): the velocity-dependent forces of the form (``"lagrange"`` with the q-row geometric
        term; see the module docstring)."""
        if self.form == "eq2":
            return self._velocity_forces_eq2(cfg, v)
        nq = self.nq
        qd, ud = v[:nq], v[nq:]
        _, Sd = self.kin.rates(cfg.pose, qd)
        bd = cfg.pose.S @ qd + self.T @ ud
        f = cfg.M_N @ (Sd @ qd)
        th_d = (cfg.pose.Sz[2::3] @ qd)[self.el_link]  # element angular rates
        R = cfg.R
        Rt = np.swapaxes(R, 1, 2)
        bl = np.einsum("eij,ej->ei", Rt, bd[self.el_dofs])  # element velocities in local frames
        Gb = np.einsum("eij,ej->ei", self.Gl, bl)
        fe = np.einsum("eij,ej->ei", R, Gb) * th_d[:, None]  # M_N' b'
        f += np.bincount(self._el_flat, fe.reshape(-1), minlength=self.N)
        h = cfg.W.T @ f
        # q rows: -dT/dq (explicit) + dV/dq, both through the element angles
        d = self.T @ x[nq:]
        dl = np.einsum("eij,ej->ei", Rt, d[self.el_dofs])
        gT = 0.5 * np.einsum("ei,ei->e", bl, Gb)
        gV = 0.5 * np.einsum("ei,eij,ej->e", dl, self.KGl, dl)
        S_th = cfg.pose.Sz[2::3][self.el_link]  # (n_el, nq)
        h[:nq] += S_th.T @ (gV - gT)
        return h

    def coriolis_matrix(self, cfg: Configuration, qd: np.ndarray) -> np.ndarray:
        """Eq. 2's ``M_G = sum_e theta_e' R_e (A_e - m_e G) R_e^T`` (N x N, nodal) at the rates ``q'``."""
        th_d = (cfg.pose.Sz[2::3] @ qd)[self.el_link]
        R = cfg.R
        return self._assemble((R @ self.MGl @ np.swapaxes(R, 1, 2)) * th_d[:, None, None])

    def _velocity_forces_eq2(self, cfg: Configuration, v: np.ndarray) -> np.ndarray:
        """``W^T (M_N S' q' + 2 M_G T u')``: eq. 2's velocity terms without the damping."""
        nq = self.nq
        qd = v[:nq]
        _, Sd = self.kin.rates(cfg.pose, qd)
        f = cfg.M_N @ (Sd @ qd)
        th_d = (cfg.pose.Sz[2::3] @ qd)[self.el_link]
        R = cfg.R
        ul = np.einsum("eji,ej->ei", R, (self.T @ v[nq:])[self.el_dofs])  # R^T u' per element
        fe = np.einsum("eij,ej->ei", R, np.einsum("eij,ej->ei", self.MGl, ul)) * (2.0 * th_d[:, None])
        f += np.bincount(self._el_flat, fe.reshape(-1), minlength=self.N)
        return cfg.W.T @ f

    def velocity_force_jacobian(self, cfg: Configuration, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """dh/dv (n x n) of :meth:`velocity_forces`, exact (h is a quadratic form in v)."""
        if self.form == "eq2":
            return self._velocity_force_jacobian_eq2(cfg, v)
        nq = self.nq
        qd = v[:nq]
        W = cfg.W
        S_th = cfg.pose.Sz[2::3][self.el_link]  # (n_el, nq)
        th_d = S_th @ qd
        R = cfg.R
        Rt = np.swapaxes(R, 1, 2)
        bd = W @ v
        RGR = R @ self.Gl @ Rt  # (n_el, 6, 6) dM_N/dtheta_e in global form
        ye = np.einsum("eij,ej->ei", RGR, bd[self.el_dofs])  # (n_el, 6)
        Md = self._assemble(RGR * th_d[:, None, None])  # M_N'
        dfdv = Md @ W
        _, Sd = self.kin.rates(cfg.pose, qd)
        Y = np.zeros((self.N, nq))
        for j in range(nq):
            e = np.zeros(nq)
            e[j] = 1.0
            _, Sdj = self.kin.rates(cfg.pose, e)
            Y[:, j] = cfg.M_N @ (Sdj @ qd + Sd @ e)
            Y[:, j] += np.bincount(self._el_flat, (ye * S_th[:, j][:, None]).reshape(-1), minlength=self.N)
        dfdv[:, :nq] += Y
        Jh = W.T @ dfdv
        # q rows: -d(gT)/dv, gT_e = 1/2 bd_e' (R Gl R') bd_e
        Yall = np.zeros((self.n_el, self.N))
        Yall[np.arange(self.n_el)[:, None], self.el_dofs] = ye
        Jh[:nq] -= S_th.T @ (Yall @ W)
        return Jh

    def _velocity_force_jacobian_eq2(self, cfg: Configuration, v: np.ndarray) -> np.ndarray:
        nq = self.nq
        qd = v[:nq]
        W = cfg.W
        dfdv = np.zeros((self.N, self.n))
        dfdv[:, nq:] = 2.0 * self.coriolis_matrix(cfg, qd) @ self.T
        _, Sd = self.kin.rates(cfg.pose, qd)
        S_th = cfg.pose.Sz[2::3][self.el_link]  # (n_el, nq)
        R = cfg.R
        ul = np.einsum("eji,ej->ei", R, (self.T @ v[nq:])[self.el_dofs])
        ye = 2.0 * np.einsum("eij,ej->ei", R, np.einsum("eij,ej->ei", self.MGl, ul))  # 2 M_G per unit rate, on u'
        for j in range(nq):
            e = np.zeros(nq)
            e[j] = 1.0
            _, Sdj = self.kin.rates(cfg.pose, e)
            dfdv[:, j] = cfg.M_N @ (Sdj @ qd + Sd @ e)
            dfdv[:, j] += np.bincount(self._el_flat, (ye * S_th[:, j][:, None]).reshape(-1), minlength=self.N)
        return W.T @ dfdv

    def state_matrix(self, cfg: Configuration, x: np.ndarray | None = None,
                     v: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(A, M^-1)``: the state matrix of eq. 2 linearised at ``cfg``, ``[[0, I], [-M^-1 (K + dCv/du), -M^-1 (C
        + dh/dv)]]`` (2n x 2n), with the damping at ``x`` and the velocity forces' and damping forces' Jacobians at
        ``(x, v)`` if given (none at rest; ``dCv/du``: :meth:`damping_position_jacobian`, in the u columns)."""
        n = self.n
        Minv = np.linalg.inv(self.mass(cfg))
        C = self.damping(cfg, x)
        K = self.stiffness(cfg)
        if v is not None:
            C = C + self.velocity_force_jacobian(cfg, x, v)
            K[:, self.nq :] += self.damping_position_jacobian(cfg, x, v)
        A = np.zeros((2 * n, 2 * n))
        A[:n, n:] = np.eye(n)
        A[n:, :n] = -Minv @ K
        A[n:, n:] = -Minv @ C
        return A, Minv

    def element_rotation_term(self, cfg: Configuration, WJ: np.ndarray) -> np.ndarray:
        """``SE[k] = sum_e (dtheta_e/dq_k) (W J)_e^T R_e G R_e^T (W J)_e`` (nq, r, r): the change of ``(W J)^T M_N
        (W J)`` with q through the rotation of the element masses with their links (shared by the velocity
        force tensor and ``d M_r / dq``)."""
        nq = self.nq
        r = WJ.shape[1]
        R = cfg.R
        RGR = R @ self.Gl @ np.swapaxes(R, 1, 2)
        S_th = cfg.pose.Sz[2::3][self.el_link]  # (n_el, nq)
        WJe = WJ[self.el_dofs]  # (n_el, 6, r)
        E = np.swapaxes(WJe, 1, 2) @ (RGR @ WJe)  # (n_el, r, r)
        return (S_th.T @ E.reshape(len(E), -1)).reshape(nq, r, r)  # [k, i, j] = sum_e S_th[e, k] E[e, i, j]

    def velocity_force_tensor(self, cfg: Configuration, J: np.ndarray, Sd: list | None = None,
                              WJ: np.ndarray | None = None, SE: np.ndarray | None = None) -> np.ndarray:
        """``T[k] = J^T (dh/dv)(J e_k) J`` for a velocity map ``v = J w`` whose first ``nq`` rows are ``[I 0]``.

        Since ``h`` is a quadratic form in ``v``, ``J^T h(J w) = 1/2 sum_k w_k T[k] w`` (the position-dependent
        ``dV/dq`` term aside). Batched over all k (a few einsums instead of ``r`` Jacobian evaluations).
        ``Sd``: ``dS/dq_j`` for every coordinate (:meth:`coordinate_derivatives`), ``WJ = W J`` and ``SE``
        (:meth:`element_rotation_term`), if already computed. The ``"lagrange"`` form's ``h`` only.
        """
        if self.form != "lagrange":
            raise ValueError(f"velocity_force_tensor: the {self.form!r} form has none (the 'lagrange' form's only)")
        nq = self.nq
        r = J.shape[1]
        if WJ is None:
            WJ = cfg.W @ J
        if SE is None:
            SE = self.element_rotation_term(cfg, WJ)
        T = np.zeros((r, r, r))
        T[:nq] += SE  # M_N' b' through the element rates
        T[:, :, :nq] += np.transpose(SE, (2, 1, 0))  # ... through b'
        T[:, :nq, :] -= np.transpose(SE, (2, 0, 1))  # q rows: -d(gT)/dv
        if Sd is None:
            Sd = self.coordinate_derivatives(cfg)
        # T[k, :, j] += (W J)^T M_N (dS/dq_j e_k + dS/dq_k e_j) for all k, j < nq in one product
        Sd3 = np.stack(Sd)  # [j, :, k] = dS/dq_j e_k
        X = (np.transpose(Sd3, (2, 0, 1)) + np.transpose(Sd3, (0, 2, 1))).reshape(nq * nq, -1)  # [k nq + j, :]
        T[:nq, :, :nq] += ((X @ cfg.M_N) @ WJ).reshape(nq, nq, r).transpose(0, 2, 1)
        return T

    def coordinate_derivatives(self, cfg: Configuration) -> list[np.ndarray]:
        """``dS/dq_j`` (N, nq) for every coordinate j (the rate of S along ``q' = e_j``)."""
        return list(self.kin.coordinate_rates(cfg.pose))

    # ------------------------------------------------------------------ geometric stiffness
    def rigid_loads(self, cfg: Configuration, qd: np.ndarray | None = None, tau: np.ndarray | None = None,
                    qdd: np.ndarray | None = None) -> np.ndarray:
        """The nodal loads (N,) that the rigid mechanism's motion puts on its links, in equilibrium.

        ``f = B tau + M_N g - M_N (S q'' + S' q')``: the motors, the weight and the d'Alembert forces of the rigid
        motion (the nodes moving with the ERLS, ``b' = S q'``). ``q''`` is the rigid acceleration the loads give,
        ``(S^T M_N S) q'' = S^T (B tau + M_N g - M_N S' q')``, so that ``S^T f = 0``: no load on the rigid
        mechanism's motions, the loads balance through the links' internal forces and the ground. With ``qdd``
        (a prescribed motion) ``q''`` is that and ``tau`` the torques the motion needs, by least squares
        from ``S^T B tau = S^T (M_N (S q'' + S' q') - M_N g)`` (what the motors do not span is left to the
        acceleration, as above); ``tau=None`` without ``qdd``: the torques that hold the configuration, the same
        with ``q'' = 0``. ``q' = None``: at rest."""
        S, B = cfg.pose.S, self.B_N
        f = cfg.M_N @ self.g_N
        if qd is not None and np.any(qd):
            f = f - cfg.M_N @ (self.kin.rates(cfg.pose, qd)[1] @ qd)
        if qdd is not None:
            f = f - cfg.M_N @ (S @ np.asarray(qdd, float))
        if tau is None or qdd is not None:
            tau = -np.linalg.lstsq(S.T @ B, S.T @ f, rcond=None)[0] if B.shape[1] else np.zeros(0)
        f = f + B @ tau
        MS = cfg.M_N @ S
        return f - MS @ np.linalg.solve(S.T @ MS, S.T @ f)

    def axial_forces(self, cfg: Configuration, f: np.ndarray) -> np.ndarray:
        """Each element's axial force ``N_e`` (n_el,; N, tension positive; zero for the offset masses) under the
        nodal loads ``f`` in equilibrium (:meth:`rigid_loads`): the elastic rows' static response ``K_uu u = T^T f``
        (the linear elastic stiffness, the coordinates held: the loads balance, so the joints that fix the coordinates
        carry none of them and the internal forces are those of the moving mechanism), ``N_e = (EA / L) (u_2 -
        u_1)`` along the element (its frame). First order: the axial modes lie far above the loads' frequencies,
        so the links' axial strain follows the loads quasi-statically. ``f`` (N, k): k load cases at once, the
        forces (n_el, k)."""
        T = self.T
        d = T @ np.linalg.solve(T.T @ cfg.K_N @ T, T.T @ f)
        de = d[self.el_dofs]  # (n_el, 6) or (n_el, 6, k)
        R = cfg.R
        cx, cy = (R[:, 0, 0], R[:, 1, 0]) if d.ndim == 1 else (R[:, 0, 0, None], R[:, 1, 0, None])
        ax = cx * (de[:, 3] - de[:, 0]) + cy * (de[:, 4] - de[:, 1])  # (R^T d)_3 - (R^T d)_0
        return (self.el_axial if d.ndim == 1 else self.el_axial[:, None]) * ax

    def geometric_stiffness(self, cfg: Configuration, N: np.ndarray) -> np.ndarray:
        """The nodal geometric stiffness ``sum_e N_e R_e K_G1 R_e^T`` (N, N) of the elements' axial forces ``N``
        (``K_G1``: :func:`.elements.beam_geometric_stiffness` per unit force): the second variation of the axial
        forces' work ``sum_e N_e int (v'^2 / 2) dx`` across the lateral displacements ``v`` (each element's
        frame), the P-delta effect that linear elasticity leaves out."""
        R = cfg.R
        return self._assemble((R @ self.el_KG1 @ np.swapaxes(R, 1, 2)) * N[:, None, None])

    def geometric_forces(self, cfg: Configuration, N: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``-T^T K_G(N) T u`` (ne,): the elastic rows' forces of the axial forces ``N`` across the elastic
        displacements ``u`` (:meth:`geometric_stiffness`, element by element without assembly)."""
        R = cfg.R
        dl = np.einsum("eji,ej->ei", R, (self.T @ u)[self.el_dofs])  # R^T d per element
        fe = np.einsum("eij,ej->ei", R, np.einsum("eij,ej->ei", self.el_KG1, dl)) * N[:, None]
        return -self.T.T @ np.bincount(self._el_flat, fe.reshape(-1), minlength=self.N)

    def static_geometric(self, cfg: Configuration) -> Configuration:
        """``cfg`` with the geometric stiffness of the static axial loads: the elements' axial forces ``N_s`` of the
        weight with the torques that hold the configuration (:meth:`rigid_loads` at rest) and ``K_G(N_s)``.

        The elastic rows' stiffness about the static sag (:meth:`elastic_stiffness`), which the linearised models
        (:meth:`stiffness`) and the reduction's ``K_r`` hold as they hold ``K_N``; the equations of motion take the
        axial forces of the motion itself (:meth:`rigid_axial_forces`, :meth:`net_forces`)."""
        from dataclasses import replace

        N_s = self.axial_forces(cfg, self.rigid_loads(cfg))
        return replace(cfg, K_G=self.geometric_stiffness(cfg, N_s), N_static=N_s)

    def rigid_axial_forces(self, cfg: Configuration, qd: np.ndarray | None, tau: np.ndarray | None = None,
                           qdd: np.ndarray | None = None) -> np.ndarray:
        """The elements' axial forces (n_el,) under the rigid motion's loads at ``q'`` under ``tau``, or with the
        prescribed ``q''`` (:meth:`rigid_loads`, :meth:`axial_forces`): those of :meth:`net_forces`' ``K_G(q, q',
        tau)``. Zeros without ``geometric``."""
        if not self.geometric:
            return np.zeros(self.n_el)
        return self.axial_forces(cfg, self.rigid_loads(cfg, qd, tau, qdd))

    def elastic_stiffness(self, cfg: Configuration) -> np.ndarray:
        """The elastic rows' stiffness at rest ``K_uu + T^T K_G(N_s) T`` (ne x ne): linear elastic and the static
        axial loads' geometric stiffness (:meth:`static_geometric`; none without it)."""
        K = self.T.T @ cfg.K_N @ self.T
        return K if cfg.K_G is None else K + self.T.T @ cfg.K_G @ self.T

    # ------------------------------------------------------------------ dynamics
    def generalized_forces(self, cfg: Configuration, tau: np.ndarray, f_nodal: np.ndarray | None = None):
        F = cfg.W.T @ (self.B_N @ tau + cfg.M_N @ self.g_N)
        if f_nodal is not None:
            F = F + cfg.W.T @ f_nodal
        return F

    def net_forces(self, cfg: Configuration, x: np.ndarray, v: np.ndarray, tau: np.ndarray,
                   qdd: np.ndarray | None = None) -> np.ndarray:
        """Right-hand side of eq. 2, ``W^T (B tau + M_N g) - h(x, v) - C v - K x``, so that ``M v' = net_forces``
        (``h`` and ``C`` of the model's form). With ``geometric`` the elastic rows' ``K_uu`` holds the geometric
        stiffness of the links' axial forces under the rigid motion's loads, ``K_G(q, q', tau)``
        (:meth:`rigid_axial_forces`); ``qdd``: a prescribed motion's acceleration, whose loads give the axial forces
        instead of ``tau``'s."""
        nq = self.nq
        rhs = self.generalized_forces(cfg, tau) - self.velocity_forces(cfg, x, v)
        T, Tt = self.T, self.T.T
        # K_uu u = T^T K_N T u and the damping as matrix-vector products
        rhs[nq:] -= Tt @ (cfg.K_N @ (T @ x[nq:]))
        if self.geometric:
            rhs[nq:] += self.geometric_forces(cfg, self.rigid_axial_forces(cfg, v[:nq], tau, qdd), x[nq:])
        if self.alpha or self.beta:
            rhs -= self.damping_forces(cfg, x, v)
        return rhs

    def accelerations(self, x: np.ndarray, v: np.ndarray, tau: np.ndarray, cfg: Configuration | None = None):
        """v' from eq. 2 at state (x, v) under motor torques tau."""
        if cfg is None:
            cfg = self.configuration(x[: self.nq])
        return np.linalg.solve(self.mass(cfg), self.net_forces(cfg, x, v, tau))

    def prescribed_accelerations(self, x: np.ndarray, v: np.ndarray, qdd: np.ndarray,
                                 cfg: Configuration | None = None) -> np.ndarray:
        """u'' under a prescribed motion of the ERLS coordinates (``q, q'`` in ``x, v``, ``q'' = qdd``): the
        elastic rows of eq. 2, ``M_uu u'' = F_u - h_u - (C v)_u - K_uu u - M_uq q''`` (no motor torques; the
        q rows give the torques that the motion needs and are not solved)."""
        if cfg is None:
            cfg = self.configuration(x[: self.nq])
        nq = self.nq
        M = self.mass(cfg)
        rhs = self.net_forces(cfg, x, v, np.zeros(len(self.mech.motors)), qdd=qdd)
        return np.linalg.solve(M[nq:, nq:], rhs[nq:] - M[nq:, :nq] @ np.asarray(qdd, float))

    def prescribed_jacobian(self, x: np.ndarray, v: np.ndarray, cfg: Configuration | None = None,
                            qdd: np.ndarray | None = None) -> np.ndarray:
        """``[d u''/d u, d u''/d u']`` (ne x 2 ne) of :meth:`prescribed_accelerations` at the prescribed ``q''``
        ``qdd`` (exact: under a prescribed motion the elastic rows are linear in ``u`` and ``u'``; ``qdd=None``:
        the geometric stiffness of the motion's axial loads at zero acceleration)."""
        if cfg is None:
            cfg = self.configuration(x[: self.nq])
        nq = self.nq
        M_uu = self.mass(cfg)[nq:, nq:]
        D = (self.damping(cfg, x) + self.velocity_force_jacobian(cfg, x, v))[nq:, nq:]
        K_uu = self.T.T @ cfg.K_N @ self.T + self.damping_position_jacobian(cfg, x, v)[nq:]
        if self.geometric:
            N = self.rigid_axial_forces(cfg, v[:nq], None, np.zeros(nq) if qdd is None else qdd)
            K_uu = K_uu + self.T.T @ self.geometric_stiffness(cfg, N) @ self.T
        return -np.linalg.solve(M_uu, np.hstack([K_uu, D]))

    def rhs(self, t: float, y: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """First-order form y = [x; v] -> y'."""
        n = self.n
        return np.concatenate([y[n:], self.accelerations(y[:n], y[n:], tau)])

    def energy(self, y: np.ndarray) -> float:
        """Kinetic + strain energy (no gravity)."""
        n = self.n
        cfg = self.configuration(y[: self.nq])
        v = y[n:]
        u = y[self.nq : n]
        return 0.5 * v @ self.mass(cfg) @ v + 0.5 * u @ (self.T.T @ cfg.K_N @ self.T) @ u

    # ------------------------------------------------------------------ outputs
    def nodal_displacements(self, u: np.ndarray) -> np.ndarray:
        """Elastic nodal displacement vector d = T u (N,)."""
        return self.T @ u

    def locate(self, link: str, station: float) -> tuple[tuple[int, float], ...]:
        """Element(s) and xi of a link station; two entries at an interior node (both sides). Cached: the
        observer asks for its sensors' stations at every configuration evaluation."""
        hit = self._locate_cache.get((link, station))
        if hit is None:
            hit = self._locate_cache[(link, station)] = self._locate(link, station)
        return hit

    def _locate(self, link: str, station: float) -> tuple[tuple[int, float], ...]:
        li = [lk.name for lk in self.mech.links].index(link)
        els = np.flatnonzero((self.el_link == li) & (self.el_len > 0))  # beam elements (not offset masses)
        out = []
        for e in els:
            a, L = self.el_station[e], self.el_len[e]
            xi = (station - a) / L
            if -1e-9 <= xi <= 1 + 1e-9:
                out.append((int(e), float(min(max(xi, 0.0), 1.0))))
        if len(out) > 1:
            out = [o for o in out if o[1] in (0.0, 1.0)] or out[:1]
        if not out:
            raise KeyError(f"link {link!r} has no station {station}")
        return tuple(out)

    def curvature_row(self, cfg: Configuration, link: str, station: float) -> np.ndarray:
        """Row c (ne,) with bending curvature (1/m) at a link station = c @ u (configuration dependent).

        At an interior node the curvature of the two adjacent cubic elements is averaged.
        """
        row = np.zeros(self.N)
        locs = self.locate(link, station)
        for e, xi in locs:
            cl = hermite_curvature_row(self.el_len[e], xi)
            row[self.el_dofs[e]] += (cl @ cfg.R[e].T) / len(locs)
        return row @ self.T

    def point_displacement_rows(self, cfg: Configuration, link: str, station: float,
                                rate: bool = False) -> np.ndarray:
        """(2, ne) map from u to the global elastic displacement of a link point: ``r N R^T`` on the element's
        dofs, with ``N`` the element-frame shape functions (linear axially, Hermite transversely), ``R`` the
        element rotation and ``r`` its 2x2 block. With ``rate`` the derivative of that map in the link's angle:
        ``dR/dtheta = R W`` (``W`` the 90-degree rotation's generator ``[[0, -1], [1, 0]]`` on each node's
        translations), so ``d(r N R^T)/dtheta = r (w N - N W) R^T`` with ``w = [[0, -1], [1, 0]]``."""
        e, xi = self.locate(link, station)[0]
        L = self.el_len[e]
        N = np.zeros((2, 6))
        N[0, 0], N[0, 3] = 1 - xi, xi
        N[1, 1] = 1 - 3 * xi**2 + 2 * xi**3
        N[1, 2] = L * (xi - 2 * xi**2 + xi**3)
        N[1, 4] = 3 * xi**2 - 2 * xi**3
        N[1, 5] = L * (-(xi**2) + xi**3)
        if rate:  # w N - N W: rows (-N_y, N_x) minus N's translation columns turned the other way
            NW = np.zeros((2, 6))
            NW[:, [0, 3]], NW[:, [1, 4]] = N[:, [1, 4]], -N[:, [0, 3]]
            N = np.array([-N[1], N[0]]) - NW
        r2 = cfg.R[e][:2, :2]
        rows = np.zeros((2, self.N))
        rows[:, self.el_dofs[e]] = r2 @ N @ cfg.R[e].T
        return rows @ self.T

    def rotation_row(self, link: str, joint: str) -> np.ndarray:
        """(ne,) map from u to the elastic rotation of ``link``'s node at ``joint``."""
        return self.T[self._joint_node_dof(joint, link, 2)]

    def coordinate_reading_rows(self) -> np.ndarray:
        """(nq, ne) map ``G`` from u to what each coordinate's encoder reads beyond ``q``: the encoder of an angle
        coordinate of ``link`` at ``joint`` reads ``q + G u``, the tangents' angle difference at the joint
        (``theta_link - theta_ref`` of the two nodes there, ERLS frame plus elastic rotation, minus the offset).
        The coordinate's own node turns with its frame (:func:`exuflex.mechanism.elastic_dofs`), so an absolute
        angle's and a slide's rows are zero and a relative angle's is minus the other link's elastic rotation at
        the joint. ``G`` is constant: rotations are the same in every planar frame."""
        G = np.zeros((self.nq, self.ne))
        for j, co in enumerate(self.mech.coordinates):
            if co.kind == "slide":
                continue
            G[j] = self.rotation_row(co.link, co.joint)
            if co.relative_to is not None:
                G[j] -= self.rotation_row(co.relative_to, co.joint)
        return G

"""The reduced model ``M_r p'' + C_r p' + K_r p = F_r`` (the paper's eq. 7) with ``x = H(q, q*) p``.

Two forms:

- ``consistent=True`` (default): the velocity transformation is exact. Since ``H`` depends on ``q``,
  ``x' = J p'`` with ``J = H + [d(H p)/dq, 0]`` (the slave displacements follow the links as they turn and
  the static shapes change with the configuration), and the reduced equations are those of Lagrange on
  the constrained coordinates: ``M_r = J^T M J``, ``C_r = J^T C(H p) J`` (the damping of the strain rate,
:meth:`~exuflex.erls.model.ErlsModel.damping`), ``K_r p -> J^T K H p`` and
  ``F_r = J^T (F - h(H p, J p') - M a_b)`` with the bias acceleration ``a_b = (dJ/dt) p' = 2 d(H p')/dq q' +
  d^2(H p)/dq^2 [q', q']`` (the second term quadratic in ``q'``, linear in the elastic coordinates:
  :meth:`ReducedModel.basis_curvature`).
- ``consistent=False``: the paper's eq. 7 as printed, ``x' ~ H p'`` (``J = H``, no bias term).

What the tests show (``tests/test_reduced_derivatives.py``): ``J`` equals the finite-difference derivative of
``H(q) p`` to 1e-6; ``a_b`` equals the finite-difference rate of ``J p'`` entry by entry on deformed moving
states. Over the first 0.1 s of the six-bar's manoeuvre (RK4, 0.1 ms, the same computed torques
and start), the consistent form's coordinates stay within 3e-5 rad of the full-order model's and the paper's
form drifts by 2.5-3.2e-4 rad (the neglected terms are Coriolis forces of the elastic rates in the rotating
links); exuflex therefore defaults to the consistent form.

``h`` holds the full model's velocity-dependent terms
(:meth:`exuflex.erls.model.ErlsModel.velocity_forces`, its energy-consistent ``"lagrange"`` form, the one the
compiled force model reduces). State ``z = [p; p']`` with ``p = [q; u_m; eta]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..erls.model import ErlsModel
from ..mechanism import parse_mechanism
from . import _compiled
from .basis import CraigBampton, ReducedConfiguration

__all__ = ["ReducedMatrices", "ReducedModel", "motion_coefficients", "warm_up"]

#: the central differences' step (rad) of :meth:`ReducedModel.basis_curvature` and :meth:`ReducedModel.basis_hessian`
CURVATURE_STEP = 1e-5


@dataclass(frozen=True)
class ReducedMatrices:
    """Reduced matrices at a state: ``Mr p'' + Cr p' + Kr p = Gr tau + fr``."""

    rc: ReducedConfiguration
    J: np.ndarray  # (n, r) velocity transformation x' = J p'
    Mr: np.ndarray
    Kr: np.ndarray
    Cr: np.ndarray
    Gr: np.ndarray  # (r, n_motors) generalised forces of unit motor torques
    fr: np.ndarray  # (r,) gravity minus velocity-dependent forces at the state


def motion_coefficients(tau: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """``c = [1, tau, (q'_a q'_b)_{a <= b}]`` (pairs row-major): :meth:`ReducedModel.motion_geometric`'s form is
    ``sum_k c_k KGd[k]``."""
    nq = len(qd)
    a, b = np.triu_indices(nq)
    return np.concatenate([[1.0], np.asarray(tau, float), np.asarray(qd, float)[a] * np.asarray(qd, float)[b]])


class QuadraticForces:
    """``fr(p, p') = fg - 1/2 sum_k p'_k T_k p' - [p^T V_i p]_i - J^T M a_b(q', p')`` at a held configuration.

    Stored flattened so that one evaluation is three small matrix-vector products. ``dMr2``, ``dKr2``: the
    q-gradients of ``M_r`` and of ``H_u^T K_uu H_u`` (``K_r``'s elastic rows; its q rows' ``d(H p)/dq``
    part, linear in the elastic coordinates, is not differentiated) at the held configuration, flattened
    (nq, r*r), for the cached step; both equal central differences to 1e-6 on undeformed states
    (``tests/test_reduced_derivatives.py``). ``Wg``: the weight's gradient in the positions
    (:meth:`ReducedModel.weight_gradient`; empty without gravity).
    """

    def __init__(self, nq: int, fg: np.ndarray, Tk: np.ndarray, V: np.ndarray, dHdq: np.ndarray | None,
                 JtM: np.ndarray | None, dMr: np.ndarray | None = None, dKr: np.ndarray | None = None,
                 C2: np.ndarray | None = None, symmetrised: tuple | None = None, Wg: np.ndarray | None = None):
        r = len(fg)
        self.nq, self.r = nq, r
        self.fg = fg
        #: the weight's gradient in the positions, ``Wg[c, m] = d fg_c / dp_m`` (r, r; empty (0, 0) without
        #: gravity: :meth:`ReducedModel.weight_gradient`)
        self.Wg = np.zeros((0, 0)) if Wg is None else Wg
        self.dMr2 = None if dMr is None else dMr.reshape(nq, r * r)
        self.dKr2 = None if dKr is None else dKr.reshape(nq, r * r)
        self._tensors = None
        self._symmetrised = symmetrised  # (Ts, Vs) of jacobian_tensors, if computed already (compiled paths)
        self.T2 = Tk.reshape(r, r * r)
        self.V2 = V.reshape(nq * r, r)
        self.C2 = C2  # the flattened bias form, if computed already (:func:`._compiled.force_terms`)
        self.elastic = None  # (pM, pK, pC, pG, p2C) of :meth:`ReducedModel.elastic_forms`, with the gradients
        self.dHdq = None  # d(H e_k)/dq (r, n, nq) of :meth:`ReducedModel.held` (the measurement rows' change)
        #: the motion's geometric stiffness as a linear form, flattened (k, r*r) (:meth:`ReducedModel.motion_geometric`
        #: of the configuration undeformed; empty (0, 0): none), set by :meth:`ReducedModel.held`
        self.KGd = np.zeros((0, 0))
        #: its q-gradient under gravity, flattened (k, nq*r*r) (:meth:`ReducedModel.motion_geometric_gradient`; empty
        #: (0, 0): none)
        self.dKGd = np.zeros((0, 0))
        if C2 is None and dHdq is not None:
            C = np.swapaxes(JtM @ dHdq, 1, 2)  # (r, nq, r): [k, j, :] = J^T M dH/dq_j e_k
            self.C2 = 2.0 * C.reshape(r * nq, r)

    def __call__(self, p: np.ndarray, pd: np.ndarray) -> np.ndarray:
        nq, r = self.nq, self.r
        f = self.fg - 0.5 * ((pd @ self.T2).reshape(r, r) @ pd)
        f[:nq] -= (self.V2 @ p).reshape(nq, r) @ p
        if self.C2 is not None:
            f -= np.outer(pd, pd[:nq]).ravel() @ self.C2
        return f

    def jacobian_tensors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(Ts, Vs, C3)``: the symmetrised forms whose contractions with ``p'`` and ``p`` are the forces'
        derivatives, ``Ts[m, i, j] = T[m,i,j] + T[j,i,m]`` (r, r, r), ``Vs[i, a, b] = V[i,a,b] + V[i,b,a]``
        (nq, r, r) and ``C3[k, j, c]`` (r, nq, r; empty without the bias term). Built once per held
        configuration."""
        if self._tensors is None:
            nq, r = self.nq, self.r
            C3 = np.zeros((0, nq, r)) if self.C2 is None else self.C2.reshape(r, nq, r)
            if self._symmetrised is None:
                T3 = self.T2.reshape(r, r, r)  # [k, i, j]
                V3 = self.V2.reshape(nq, r, r)  # [i, a, b]
                Ts = np.ascontiguousarray(T3 + np.transpose(T3, (2, 1, 0)))
                Vs = np.ascontiguousarray(V3 + np.swapaxes(V3, 1, 2))
            else:
                Ts, Vs = self._symmetrised
            self._tensors = (Ts, Vs, np.ascontiguousarray(C3))
        return self._tensors

    def jacobian(self, p: np.ndarray, pd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(df/dp, df/dp')`` (r, r) each, of the forces at the held configuration (exact: quadratic forms)."""
        nq, r = self.nq, self.r
        Ts, Vs, C3 = self.jacobian_tensors()
        Gpd = -0.5 * (Ts @ pd).T
        Gp = np.zeros((r, r))
        Gp[:nq] = -(Vs @ p)
        if len(C3):
            Gpd -= np.tensordot(pd[:nq], C3, axes=(0, 1)).T  # d/dp'_m of p'_m p'_j terms, j < nq
            Gpd[:, :nq] -= np.tensordot(pd, C3, axes=(0, 0)).T  # ... of p'_k p'_m, m < nq
        return Gp, Gpd


class ReducedModel:
    """Reduced ERLS model on a :class:`CraigBampton` basis.

    Parameters
    ----------
    cb : CraigBampton
    consistent : exact velocity transformation (default) or the paper's ``x' ~ H p'`` (see module docstring).
    compiled : the per-configuration arithmetic (:meth:`matrices` without forces, :meth:`force_model`) in compiled
        calls (:mod:`._compiled`); default: where numba is installed. False: the NumPy expressions, the reference.
    """

    def __init__(self, cb: CraigBampton, consistent: bool = True, compiled: bool | None = None):
        if cb.model.form != "lagrange":
            raise ValueError(f"ReducedModel: the full-order model's form must be 'lagrange' (the reduced forces are "
                             f"its quadratic forms), got {cb.model.form!r}")
        self.cb = cb
        # the force model's arithmetic in one compiled call (:mod:`._compiled`) where numba is installed;
        # False: the NumPy expressions below (the reference)
        self.compiled = _compiled.HAVE_NUMBA if compiled is None else bool(compiled and _compiled.HAVE_NUMBA)
        # compiled: :meth:`held` in one call (:meth:`_held_compiled`); False: the piecewise compiled calls
        self.one_call = self.compiled
        self.model = cb.model
        self.nq = cb.nq
        self.r = cb.r
        self.nx = 2 * cb.r
        self.names = cb.names
        self.consistent = consistent
        self._hessian = (None, None)  # the last configuration's basis_hessian: (its key, the array)

    # ------------------------------------------------------------------ matrices
    def matrices(self, p, pd=None, *, forces: bool = True, dHdq: np.ndarray | None = None,
                 rc: ReducedConfiguration | None = None) -> ReducedMatrices:
        """Reduced matrices and state-dependent forces at (p, p'); ``pd=None``: at rest.

        ``forces=False`` leaves ``fr`` out (``None``: the cached observer step takes the forces from
        :meth:`force_model`); ``dHdq`` (``d(H e_k)/dq`` for every reduced coordinate) and ``rc`` (the basis
        at ``p``'s configuration) if already computed.
        """
        model, cb, nq = self.model, self.cb, self.nq
        p = np.asarray(p, float)
        if p.shape == (nq,):  # a configuration: undeformed
            p = np.concatenate([p, np.zeros(self.r - nq)])
        pd = np.zeros(self.r) if pd is None else np.asarray(pd, float)
        if rc is None:
            rc = cb.at(p[:nq])
        cfg, H = rc.cfg, rc.H
        if self.compiled and not forces and (dHdq is not None or not self.consistent):
            J, Mr, Kr, Cr, Gr = _compiled.reduced_matrices(
                p, pd, H, np.zeros((0, 1, 1)) if dHdq is None else np.ascontiguousarray(dHdq), cfg.W, cfg.M_N,
                cfg.K_N, rc.Kuu, model.t_index, model.B_N, float(model.alpha), float(model.beta), nq, self.consistent)
            return ReducedMatrices(rc, J, Mr, Kr + self.geometric_stiffness(rc, J), Cr, Gr, None)
        J = H
        a_b = None
        if self.consistent:
            if dHdq is None:
                D = cb.basis_derivative(rc, np.column_stack([p, pd]))  # (2, n, nq)
            else:
                D = (np.column_stack([p, pd]).T @ dHdq.reshape(self.r, -1)).reshape(2, -1, nq)
            J = H.copy()
            J[:, :nq] += D[0]
            if np.any(pd[:nq]):
                a_b = 2.0 * (D[1] @ pd[:nq]) + self.basis_curvature(p, pd[:nq], at_q=D[0] @ pd[:nq])
        WJ = cfg.W @ J
        Mr = WJ.T @ cfg.M_N @ WJ
        Hu, Ju = H[nq:], J[nq:]
        T = model.T
        Kuu = rc.Kuu
        JtK = Ju.T @ Kuu
        Kr = JtK @ Hu + self.geometric_stiffness(rc, J)
        if model.alpha or model.beta:  # J^T C(H p) J: the dissipation of the strain rate T J_u p' - Y q'
            TJ = T @ Ju
            turned = self.consistent and np.any(p[nq:])
            if turned:  # the elastic displacement turned with the links is no strain rate (ErlsModel.damping)
                TJ[:, :nq] -= model.turned_rates(cfg, H @ p)
            MS = cfg.M_N @ cfg.pose.S
            X = TJ.T @ MS  # M_e = T^T M_N T - M_uq M_qq^-1 M_qu (ErlsModel.elastic_mass)
            Cr = (model.alpha * (TJ.T @ (cfg.M_N @ TJ) - X @ np.linalg.solve(cfg.pose.S.T @ MS, X.T))
                  + model.beta * (TJ.T @ (cfg.K_N @ TJ) if turned else JtK @ Ju))
        else:
            Cr = np.zeros((self.r, self.r))
        Gr = WJ.T @ model.B_N
        if not forces:
            return ReducedMatrices(rc, J, Mr, Kr, Cr, Gr, None)
        f = cfg.M_N @ model.g_N
        fr = WJ.T @ f - J.T @ model.velocity_forces(cfg, H @ p, J @ pd)
        if a_b is not None:
            fr -= (WJ.T @ cfg.M_N @ cfg.W) @ a_b  # J^T M a_b
        return ReducedMatrices(rc, J, Mr, Kr, Cr, Gr, fr)

    def basis_curvature(self, p: np.ndarray, qd: np.ndarray, at_q: np.ndarray | None = None) -> np.ndarray:
        """``d^2(H p)/dq^2 [q', q']`` (n,): the bias acceleration's part quadratic in the joint rates.

        ``x = H(q) p`` gives ``x'' = J p'' + (dJ/dt) p'`` with ``(dJ/dt) p' = 2 d(H p')/dq q' + d^2(H p)/dq^2 [q',
        q']``; the second term is the curvature of the slave displacements ``H p`` along the joint motion (zero on
        undeformed states: ``H p`` depends on ``q`` through the elastic coordinates only). It is the derivative of
        the exact first derivative ``D(q) = d(H p)/dq`` (:meth:`CraigBampton.basis_derivative`) along ``u = q' /
        |q'|``: with ``at_q = D(q) q'`` given (:meth:`matrices` has it), the forward difference ``(D(q + d u) q' -
        at_q) / d |q'|`` over ``d = CURVATURE_STEP / 10`` (one configuration more; error ``d/2`` of the third
        derivative, some 1e-6 relative), else the central difference over ``CURVATURE_STEP`` (two; error
        ``d^2/6``, some 1e-10). The configurations are the material ones (the basis is that of ``K_uu``; the
        static ``K_G`` does not enter it)."""
        nq = self.nq
        p = np.asarray(p, float)
        s = float(np.linalg.norm(qd))
        if s == 0.0 or not np.any(p[nq:]):
            return np.zeros(nq + self.model.ne)
        u = np.asarray(qd, float) / s
        P = p[:, None]

        def along(d):
            rc = self.cb.at(self.model._material_configuration(p[:nq] + d * u))
            return self.cb.basis_derivative(rc, P)[0] @ qd

        if at_q is not None:
            d = 0.1 * CURVATURE_STEP
            return (along(d) - at_q) * (s / d)
        d = CURVATURE_STEP
        return (along(d) - along(-d)) * (s / (2.0 * d))

    def basis_hessian(self, q: np.ndarray) -> np.ndarray:
        """``d^2(H e_m)/dq_i dq_j`` (r - nq, n, nq, nq) for every elastic coordinate ``m``: the second derivatives
        whose contraction with ``p_m q'_i q'_j`` is :meth:`basis_curvature`, by central differences of the exact
        first derivative (:meth:`CraigBampton.basis_derivative`) over ``+-1e-5`` rad in each ``q_i`` (error some
        1e-10 relative; :meth:`basis_curvature` says why). The cached observer step holds it at an undeformed
        configuration for the bias force's first order in the elastic coordinates (the nominal model and the payload
        estimator's increment alike: the last configuration's is kept, read-only)."""
        nq, r = self.nq, self.r
        q = np.asarray(q, float)
        key = (q.tobytes(), self.cb.compiled, self.model.kin.compiled)  # (the basis derivative's own arithmetic)
        if self._hessian[0] == key:
            return self._hessian[1]
        d = CURVATURE_STEP
        E = np.eye(r)[:, nq:]
        out = np.empty((r - nq, nq + self.model.ne, nq, nq))
        for i in range(nq):
            e = np.zeros(nq)
            e[i] = d
            Dp = self.cb.basis_derivative(self.cb.at(self.model._material_configuration(q + e)), E)
            Dm = self.cb.basis_derivative(self.cb.at(self.model._material_configuration(q - e)), E)
            out[:, :, :, i] = (Dp - Dm) / (2.0 * d)
        self.model.configuration(q)  # leave the closure solver warm-started at q
        out.flags.writeable = False
        self._hessian = (key, out)
        return out

    def held(self, p, pd, *, fr: bool = False, gradients: bool = True) -> tuple[ReducedMatrices, QuadraticForces]:
        """The reduced matrices and :meth:`force_model` at a configuration, computed once with shared terms
        (one basis derivative for both). The cached observer step holds them with the q-gradients of ``M_r``
        and ``K_r`` (``fr`` left out); the frozen step needs ``fr`` and the forces' Jacobian only
        (``fr=True, gradients=False``). Without ``fr``, where the piecewise compiled calls would run, in one compiled
        call after the configuration's (:meth:`_held_compiled`)."""
        p = np.asarray(p, float)
        if not fr and self.one_call and self.compiled and self.cb.compiled and self.model.kin.compiled:
            mats, fm = self._held_compiled(p, gradients)
        else:
            rc = self.cb.at(p[: self.nq])
            dHdq = self.cb.basis_derivative(rc, np.eye(self.r))
            mats = self.matrices(p, pd, forces=fr, dHdq=dHdq if self.consistent else None, rc=rc)
            fm = self.force_model(mats, p, dHdq=dHdq, gradients=gradients)
            fm.dHdq = dHdq
            if gradients:
                fm.elastic = self.elastic_forms(rc, dHdq)
        if gradients and mats.rc.cfg.K_G is not None:
            fm.dKr2 = fm.dKr2 + self.geometric_gradient(mats.rc, fm.dHdq).reshape(self.nq, -1)
        KGd = self.motion_geometric(mats.rc)
        if KGd.shape[0]:
            fm.KGd = np.ascontiguousarray(KGd.reshape(len(KGd), -1))
            if gradients and mats.rc.cfg.K_G is not None:  # under gravity: the form follows q with the static part
                fm.dKGd = np.ascontiguousarray(self.motion_geometric_gradient(mats.rc).reshape(len(KGd), -1))
        curved_mass = self.consistent and fm.dMr2 is not None
        if fr and np.any(p[self.nq :]) and (fm.C2 is not None or curved_mass or (self.consistent and fm.Wg.shape[0])):
            Zp = np.tensordot(p[self.nq :], self.basis_hessian(p[: self.nq]), axes=(0, 0))  # d^2(H p)/dq^2
            if fm.C2 is not None:
                fm.C2 = self._curved_bias_form(mats, fm.C2, p, Zp)
            if self.consistent and fm.Wg.shape[0]:
                fm.Wg = self._curved_weight_gradient(mats, fm.Wg, p, Zp)
            if curved_mass:  # the mass matrix's q-gradient of the deformed state (the reference step's, under gravity)
                fm.dMr2 = self._curved_mass_gradient(mats, fm.dMr2, Zp)
        return mats, fm

    def _curved_weight_gradient(self, mats: ReducedMatrices, Wg: np.ndarray, p: np.ndarray,
                                Zp: np.ndarray | None = None) -> np.ndarray:
        """The weight's gradient :meth:`weight_gradient` of a deformed state with the basis's second derivatives
        times the elastic coordinates in it: the q rows' weight ``(W J_q)^T M_N g`` with ``J_q = H_q + d(H p)/dq``
        changes with ``q_i`` by ``(W d^2(H p)/dq_i dq_j)^T M_N g`` as well (:meth:`basis_hessian`), the weight
        turning the sag's displacement with the links. Under gravity the sag is always there, and the term is of the
        weight's moment across it: on the crane arm (``benchmarks/models/crane_arm.toml``) 0.013 N m of the
        shoulder's 12 N m/rad, which the small boom inertia behind the elbow turns into a fifth of ``dq2''/dq1``
        (docs/gravity.md). ``Zp``: ``d^2(H p)/dq^2`` (n, nq, nq) if computed already."""
        nq = self.nq
        cfg = mats.rc.cfg
        if Zp is None:
            Zp = np.tensordot(p[nq:], self.basis_hessian(p[:nq]), axes=(0, 0))  # (n, nq, nq): d^2(H p)/dq_i dq_j
        wg = cfg.W.T @ (cfg.M_N @ self.model.g_N)  # (n,)
        out = np.array(Wg, float)
        out[:nq, :nq] += np.einsum("xij,x->ji", Zp, wg)
        return out

    def _curved_bias_form(self, mats: ReducedMatrices, C2: np.ndarray, p: np.ndarray,
                          Zp: np.ndarray | None = None) -> np.ndarray:
        """The bias form ``C2`` (r nq, r: the force ``-sum p'_k p'_j C2[k, j]``, ``j < nq``) of a deformed state
        with the bias acceleration's curvature term in it: at the state's ``p``, ``-(W J)^T M_N W d^2(H p)/dq_k dq_j
        q'_k q'_j`` is a bilinear form in the joint rates, added to the entries ``k < nq``
        (:meth:`basis_hessian`), so that the force model equals ``fr`` at the state. ``Zp``: ``d^2(H p)/dq^2``
        (n, nq, nq) if computed already (it depends on the basis only, not on the masses)."""
        nq, r = self.nq, self.r
        cfg = mats.rc.cfg
        if Zp is None:
            Zp = np.tensordot(p[nq:], self.basis_hessian(p[:nq]), axes=(0, 0))  # (n, nq, nq)
        JtMW = (cfg.W @ mats.J).T @ (cfg.M_N @ cfg.W)  # (r, n)
        out = np.array(C2, float).reshape(r, nq, r)
        out[:nq] += np.einsum("cx,xkj->kjc", JtMW, Zp)
        return out.reshape(r * nq, r)

    def _forms(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(T2, V2, C2)`` of :meth:`force_model` at ``p`` (``C2`` empty (0, 0) in the paper's form), without the
        gradients and the geometric forms :meth:`held` adds."""
        nq, r = self.nq, self.r
        if self.one_call and self.compiled and self.cb.compiled and self.model.kin.compiled:
            _, fm = self._held_compiled(p, False)
        else:
            rc = self.cb.at(p[:nq])
            dHdq = self.cb.basis_derivative(rc, np.eye(r))
            mats = self.matrices(p, None, forces=False, dHdq=dHdq if self.consistent else None, rc=rc)
            fm = self.force_model(mats, p, dHdq=dHdq, gradients=False)
        return fm.T2, fm.V2, np.zeros((0, 0)) if fm.C2 is None else fm.C2

    def velocity_forms_gradient(self, q: np.ndarray, h: float = 1e-6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(dT2, dV2, dC2)``: the forces' quadratic forms of :class:`QuadraticForces` at the configuration ``q``
        undeformed (``T2`` (r, r*r) of the velocity forces, ``V2`` (nq*r, r) of the q rows' term of the elastic
        forces turned with the elements, ``C2`` (r*nq, r) of the bias force) differentiated in each ``q_i`` and
        stacked over ``i``: (nq*r, r*r), (nq*nq*r, r), (nq*r*nq, r) (``dC2`` empty (0, 0) in the paper's form); by
        central differences over ``h`` (rad or m; the forms are smooth in q, the differences' error some 1e-10 of
        them).

        Why: the forces of the rates (centrifugal, Coriolis, the bias acceleration's) and the elastic forces turned
        with the elements change with the configuration as the weight does, and under gravity the step Jacobian's
        q columns carry every force's q-gradient (:func:`exuflex.observer.expansion.position_forces`): at a sagged
        state the weight's and the elastic stiffness's gradients can cancel to a remainder smaller than the rates'
        forces' gradient (a relative joint's ``dq1''/dq2`` on the crane arm, ``benchmarks/models/crane_arm.toml``;
        docs/step_jacobian.md measures it). The cached step holds the forms at its configuration and follows ``q``
        by these gradients to first order (:func:`exuflex.observer.expansion._held_model`)."""
        nq, r = self.nq, self.r
        q = np.asarray(q, float)
        dT2 = np.empty((nq * r, r * r))
        dV2 = np.empty((nq * nq * r, r))
        dC2 = np.empty((nq * r * nq, r)) if self.consistent else np.zeros((0, 0))
        for i in range(nq):
            p = np.zeros(r)
            p[:nq] = q
            p[i] += h
            Tp, Vp, Cp = self._forms(p)
            p[i] -= 2 * h
            Tm, Vm, Cm = self._forms(p)
            dT2[i * r : (i + 1) * r] = (Tp - Tm) / (2 * h)
            dV2[i * nq * r : (i + 1) * nq * r] = (Vp - Vm) / (2 * h)
            if self.consistent:
                dC2[i * r * nq : (i + 1) * r * nq] = (Cp - Cm) / (2 * h)
        self.model.configuration(q)  # leave the closure solver warm-started at q
        return dT2, dV2, dC2

    def velocity_force_gradient(self, p: np.ndarray, pd: np.ndarray, h: float = 1e-6) -> np.ndarray:
        """``d f_v / dq`` (r, nq) at the state ``(p, p')``: the forces ``f_r`` (:meth:`matrices`) less the weight
        ``(W J)^T M_N g`` (whose gradient is :meth:`weight_gradient`'s), the forces of the rates and the q rows' term
        of the elastic forces turned with the elements, differentiated in q at fixed elastic coordinates and rates,
        by central differences over ``h`` (the reference step's Jacobian under gravity: :meth:`velocity_forms_gradient`
        says why)."""
        nq, r = self.nq, self.r
        p = np.asarray(p, float)
        pd = np.asarray(pd, float)
        g_N = self.model.g_N
        out = np.empty((r, nq))

        def fv(x):
            m = self.matrices(x, pd)
            cfg = m.rc.cfg
            return m.fr - (cfg.W @ m.J).T @ (cfg.M_N @ g_N)

        for i in range(nq):
            e = np.zeros(r)
            e[i] = h
            out[:, i] = (fv(p + e) - fv(p - e)) / (2 * h)
        self.model.configuration(p[:nq])  # leave the closure solver warm-started at q
        return out

    def geometric_gradient(self, rc: ReducedConfiguration, dHdq: np.ndarray) -> np.ndarray:
        """``d(H_u^T K_Guu H_u)/dq_i`` (nq, r, r): the q-gradient of :meth:`geometric_stiffness`'s elastic rows, as
        ``dKr2`` holds the linear elastic stiffness's (its q rows' ``d(H p)/dq`` part not differentiated): the
        basis turning with the links, ``dH_u^T K_Guu H_u`` and its transpose (``K_Guu = T^T K_G T``), and the
        nodal ``K_G``'s own change, the elements turning and their static axial forces changing with the
        configuration, by central differences of :meth:`~exuflex.erls.model.ErlsModel.static_geometric` over
        ``1e-6`` (rad or m; ``K_G`` is smooth in q, the differences' error some 1e-10 of it). The cached step holds
        ``K_r`` to first order in q with it (second along its secant), as it holds the linear elastic part; the
        holding torques' change with q that ``N_s(q)`` carries the motion's form takes back at the torques applied
        (:meth:`motion_geometric_gradient`)."""
        model, nq = self.model, self.nq
        T, H, q = model.T, rc.H, rc.cfg.q
        TH = T @ H[nq:]
        KH = (T.T @ (rc.cfg.K_G @ TH))  # K_Guu H_u
        out = np.swapaxes(np.swapaxes(dHdq[:, nq:, :], 1, 2) @ KH, 0, 1)  # dH_u^T K_Guu H_u per q_i
        out = out + np.swapaxes(out, 1, 2)
        h = 1e-6
        for i in range(nq):
            e = np.zeros(nq)
            e[i] = h
            dK = (model.configuration(q + e).K_G - model.configuration(q - e).K_G) / (2 * h)
            out[i] += TH.T @ (dK @ TH)
        model.configuration(q)  # leave the closure solver warm-started at q
        return out

    def motion_geometric_gradient(self, rc: ReducedConfiguration) -> np.ndarray:
        """``dKGd`` (k, nq, r, r): :meth:`motion_geometric`'s form (``J = H``) differentiated in q, by central
        differences of the form at ``q +- 1e-6`` (rad or m: the basis, the elements' rotations, the axial response
        and the static part ``N_s(q)`` all follow; the differences' error some 1e-10 of the form).

        Why: the equations of motion carry ``K_G`` of the axial forces under the torques applied, ``N(q, q', tau)``
        (:meth:`~exuflex.erls.model.ErlsModel.net_forces`). The held ``K_r`` carries the static part ``N_s(q)``, under
        the torques that hold each q, with its q-gradient (:meth:`geometric_gradient`); at fixed torques the holding
        torques' change with q is not there, and the motion's part ``N - N_s`` takes it back: held at ``q0`` without
        its own gradient, it cannot, and the sum follows q by the static gradient alone. On the crane arm
        (``benchmarks/models/crane_arm.toml``) at its sag the two differ by the whole change of the mast's ``K_G``
        with the shoulder angle (the elastic rows' force ``dK_G/dq1 p``, 0.03-0.07 N, which the mass matrix's coupling
        turns into a sixth of ``dq2''/dq1``: docs/gravity.md). With this gradient the cached step's ``K_G`` follows q
        at the interval's torques and rates, ``sum_k c_k (KGd_k + dKGd_k . dl)``, to first order, as its static part
        does. Empty (0, nq, r, r) without geometric stiffness."""
        model, nq, r = self.model, self.nq, self.r
        if not model.geometric:
            return np.zeros((0, nq, r, r))
        q = rc.cfg.q
        h = 1e-6
        out = None
        for i in range(nq):
            e = np.zeros(nq)
            e[i] = h
            d = (self.motion_geometric(self.cb.at(q + e)) - self.motion_geometric(self.cb.at(q - e))) / (2 * h)
            if out is None:
                out = np.empty((d.shape[0], nq, r, r))
            out[:, i] = d
        self.model.configuration(q)  # leave the closure solver warm-started at q
        return out

    def geometric_stiffness(self, rc: ReducedConfiguration, J: np.ndarray) -> np.ndarray:
        """``J_u^T T^T K_G T H_u`` (r, r): the geometric stiffness of the static axial loads at the configuration
        (:meth:`~exuflex.erls.model.ErlsModel.static_geometric`: the weight with the holding torques) reduced as
        ``K_uu`` is, ``K_r = J_u^T (K_uu + T^T K_G T) H_u``; zero without (no gravity, or a model built with
        ``geometric=False``). The basis stays that of ``K_uu`` (the Craig-Bampton shapes of the linear elastic
        links; the static corrections take the model's stiffness with ``K_G``, :mod:`.static`). The change of the
        axial loads with the motion (the rest of the full model's ``K_G(q, q', tau)``,
        :meth:`~exuflex.erls.model.ErlsModel.net_forces`) is :meth:`motion_geometric`'s; the static part's
        q-gradient is :meth:`geometric_gradient`."""
        K_G = rc.cfg.K_G
        if K_G is None:
            return np.zeros((self.r, self.r))
        nq, T = self.nq, self.model.T
        TH = T @ rc.H[nq:]
        return (T @ J[nq:]).T @ (K_G @ TH)

    def motion_geometric(self, rc: ReducedConfiguration, J: np.ndarray | None = None) -> np.ndarray:
        """``KGd`` (k, r, r): the geometric stiffness of the motion's axial loads beyond the static ones,
        ``J_u^T T^T K_G(N(q, q', tau) - N_s) T H_u`` (reduced as :meth:`geometric_stiffness`; ``J=None``: ``H``, the
        configuration undeformed), as a linear form in ``c = [1, tau, (q'_a q'_b)_{a <= b}]`` (``k = 1 + n_motors
        + nq (nq + 1) / 2``, the pairs row-major): the stiffness is ``sum_k c_k KGd[k]`` (:func:`motion_coefficients`).

        The full model's elastic rows carry ``K_G`` of the axial forces of the rigid motion's loads
        (:meth:`~exuflex.erls.model.ErlsModel.net_forces`): ``f = P (M_N g + B tau - M_N S' q')`` with ``P`` the
        projection that leaves the rigid motions unloaded (:meth:`~exuflex.erls.model.ErlsModel.rigid_loads`), and
        ``N = A f`` the links' quasi-static axial response, linear in ``f`` (:meth:`~exuflex.erls.model.ErlsModel.
        axial_forces`). ``S' q' = sum_ab q'_a q'_b dS/dq_a e_b``, so at a configuration ``N`` is affine in ``tau``
        and quadratic in ``q'``, and ``K_G`` is linear in ``N``. The static part (the weight with the holding
        torques, ``N_s``) is :meth:`geometric_stiffness`'s; the rest, under the motors' torques beyond holding and
        the rates' centripetal loads, is this one: on a slider-crank with a heavy slider the rod's axial force is
        some percent of its buckling load and changes the rod's stiffness by as much, against gauge readings of
        tens of noise standard deviations. The cached observer step holds the form with its configuration (its
        change with q over the refresh radius left out: first order there, where ``K_r``'s is second) and contracts
        it with each interval's torques and start rates (:func:`exuflex.observer.expansion.motion_stiffness`).
        Empty (0, r, r) for a model built with ``geometric=False``."""
        model, nq, r = self.model, self.nq, self.r
        if not model.geometric:
            return np.zeros((0, r, r))
        cfg = rc.cfg
        S = cfg.pose.S
        Sd = model.coordinate_derivatives(cfg)
        nm = model.B_N.shape[1]
        pairs = [(a, b) for a in range(nq) for b in range(a, nq)]
        F = np.empty((model.N, 1 + nm + len(pairs)))
        F[:, 0] = cfg.M_N @ model.g_N
        F[:, 1 : 1 + nm] = model.B_N
        for k, (a, b) in enumerate(pairs):  # the coefficient of q'_a q'_b in -M_N S' q'
            acc = Sd[a][:, b] + Sd[b][:, a] if a != b else Sd[a][:, a]
            F[:, 1 + nm + k] = -(cfg.M_N @ acc)
        MS = cfg.M_N @ S
        F -= MS @ np.linalg.solve(S.T @ MS, S.T @ F)
        N = model.axial_forces(cfg, F)  # (n_el, k)
        if cfg.N_static is not None:
            N[:, 0] -= cfg.N_static
        TH = model.T @ rc.H[nq:]
        TJ = TH if J is None else model.T @ J[nq:]
        return np.stack([TJ.T @ (model.geometric_stiffness(cfg, N[:, k]) @ TH) for k in range(N.shape[1])])

    def motion_stiffness(self, rc: ReducedConfiguration, J: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """``J_u^T T^T K_G(N(q, q', tau) - N_s) T H_u`` (r, r) at one state and torque: :meth:`motion_geometric`'s
        stiffness evaluated directly (the full model's axial forces, :meth:`~exuflex.erls.model.ErlsModel.
        rigid_axial_forces`); zeros without geometric stiffness."""
        model, nq = self.model, self.nq
        if not model.geometric:
            return np.zeros((self.r, self.r))
        cfg = rc.cfg
        N = model.rigid_axial_forces(cfg, np.asarray(qd, float), np.asarray(tau, float))
        if cfg.N_static is not None:
            N = N - cfg.N_static
        TH = model.T @ rc.H[nq:]
        return (model.T @ J[nq:]).T @ (model.geometric_stiffness(cfg, N) @ TH)

    def elastic_forms(self, rc: ReducedConfiguration, dHdq: np.ndarray) -> tuple | None:
        """``(pM, pK, pC, pG, p2C)``: the change of the reduced matrices with the elastic coordinates at a
        configuration: per unit elastic coordinate ``p_k`` (``k >= nq``) the first-order rows, flattened ``[k - nq,
        i * ncol + j]`` over the ``nq`` rigid rows ``i``, and the damping's second-order rigid block, ``sum_kl p_k
        p_l X_kl``, packed by its symmetries: column ``c`` the pair ``k <= l`` (row-major, of
        the elastic coordinates) with ``X_kl + X_lk`` (``X_kk`` where ``k = l``), row ``t`` the entry ``i <= j``
        (row-major). None in the paper's form (``J = H`` does not depend on ``p``).

        ``J = H + [d(H p)/dq, 0]`` is linear in ``p`` and changes only the rigid columns: with ``A_k = T d(H_u
        e_k)/dq`` (N, nq) the rigid columns of ``W J`` gain ``sum_k p_k A_k``, so to first order ``M_r`` gains
        ``pM_k = A_k^T M_N W J`` in its rigid rows and the transpose in its rigid columns, ``K_r = J_u^T K_uu
        H_u`` gains ``pK_k = (d(H_u e_k)/dq)^T K_uu H_u`` in its rigid rows, and ``G_r = (W J)^T B_N`` and the
        weight ``(W J)^T M_N g`` gain ``pG_k = A_k^T [B_N, M_N g]`` (the weight the last column). The damping acts
        on the strain rate (:meth:`~exuflex.erls.model.ErlsModel.damping`), ``T J_u p' - Y(H p) q'`` with ``Y``
        the deflection's rates turned with the links, linear in ``p``: per unit ``p_k`` its rigid columns gain
        ``A_k - E_k``, ``E_k = Y(H e_k)`` (:meth:`~exuflex.erls.model.ErlsModel.turned_rates`). So ``C_r = (T J_u
        - [Y, 0])^T (alpha P + beta K_N) (T J_u - [Y, 0])`` (``P = M_N - M_N S (S^T M_N S)^-1 S^T M_N``, the mass
        relative to the rigid motion, :meth:`~exuflex.erls.model.ErlsModel.elastic_mass`) gains in its rigid rows
        ``pC_k = alpha (A_k - E_k)^T P T H_u - beta E_k^T K_N T H_u`` (and the transpose; its remaining ``beta
        A_k^T K_N T H_u`` is ``beta pK_k``, which the kernel adds with ``K_r``), and, being quadratic, its rigid
        block ``p_k p_l X_kl`` with ``X_kl = (A_k - E_k)^T (alpha P + beta K_N) (A_l - E_l)``. Where the basis
        turns with its links, ``E_k`` holds most of ``A_k``: what is damped is the shapes' change with the
        configuration, not the deflection turned with its link. ``K_r = J_u^T K_uu H_u``, ``G_r`` and the weight
        are linear in ``J``; ``M_r``'s second order, ``p_k p_l A_k^T M_N A_l``, is left out
        (:func:`exuflex.observer.expansion._elastic_terms` says why). The cached observer step holds its
        configurations undeformed and adds these terms."""
        if not self.consistent:
            return None
        model, nq, r = self.model, self.nq, self.r
        cfg = rc.cfg
        H = rc.H
        dHu = dHdq[nq:, nq:, :]  # (r - nq, ne, nq): d(H_u e_k)/dq of the elastic coordinates
        A = model.T @ dHu  # (r - nq, N, nq)
        # the strain rate's rigid columns: A_k minus the turned rates of H e_k (ErlsModel.turned_rates)
        x_k = np.zeros(model.n)
        E = np.empty_like(A)
        for k in range(r - nq):
            x_k[nq:] = H[nq:, nq + k]
            E[k] = model.turned_rates(cfg, x_k)
        At = np.swapaxes(A, 1, 2)
        As = A - E
        Ast = np.swapaxes(As, 1, 2)
        WH = cfg.W @ H
        S = cfg.pose.S
        MS = cfg.M_N @ S
        TH = model.T @ H[nq:]
        PTH = cfg.M_N @ TH - MS @ np.linalg.solve(S.T @ MS, MS.T @ TH)
        BG = np.column_stack([model.B_N, cfg.M_N @ model.g_N])
        pC = model.alpha * (Ast @ PTH) - model.beta * (np.swapaxes(E, 1, 2) @ (cfg.K_N @ TH))
        Kel = rc.Kuu if cfg.K_G is None else rc.Kuu + model.T.T @ cfg.K_G @ model.T  # K_r's stiffness (with K_G)
        out = (At @ (cfg.M_N @ WH), np.swapaxes(dHu, 1, 2) @ (Kel @ H[nq:]), pC, At @ BG)
        # the damping's second order as a Gram matrix over (k, i)
        n = r - nq
        A2 = As.transpose(1, 0, 2).reshape(-1, n * nq)  # column k * nq + i: (A_k - E_k) e_i
        MA2 = cfg.M_N @ A2
        PA2 = MA2 - MS @ np.linalg.solve(S.T @ MS, MS.T @ A2)
        GC = model.alpha * (A2.T @ PA2) + model.beta * (A2.T @ (cfg.K_N @ A2))
        k, l = np.triu_indices(n)
        i, j = np.triu_indices(nq)
        kl = ((k * nq)[None, :] + i[:, None], (l * nq)[None, :] + j[:, None])  # X_kl's entry i <= j
        lk = ((l * nq)[None, :] + i[:, None], (k * nq)[None, :] + j[:, None])  # X_lk's (k < l)
        out = tuple(np.ascontiguousarray(x.reshape(n, -1)) for x in out)
        return (*out, np.ascontiguousarray(GC[kl] + (k != l) * GC[lk]))

    def _held_compiled(self, p: np.ndarray, gradients: bool) -> tuple[ReducedMatrices, QuadraticForces]:
        """:meth:`held` without ``fr`` through :func:`._compiled.held_evaluation`: the basis, its derivative, the
        reduced matrices and the force model at ``p``'s configuration in one call (the same formulas as the
        piecewise path, with ``W J`` and ``M_N W J`` shared)."""
        cb, model, nq = self.cb, self.model, self.nq
        kin = model.kin
        cfg = model.configuration(p[:nq])
        pose = cfg.pose
        (Kuu, B, Kinv, Psi, H, J, Mr, Kr, Cr, Gr, fg, Tk, V, dMr, dKr, C2, Ts, Vs, Wg, dHdq) = _compiled.held_evaluation(
            p, cfg.K_N, cfg.M_N, cfg.R, cfg.W, pose.z, pose.Sz, pose.r, pose.S, pose.Jinv, kin.arrays,
            kin.node_link, kin.node_station, model.t_index, cb.im, cb.is_, cb._Phi_u, cb._px,
            cb._py, cb._pnode, cb._plocal, cb._keep, cb._theta_star, model.B_N, model.g_N, model.Gl, model.KGl,
            model.el_dofs, model.el_link, float(model.alpha), float(model.beta), nq, cb.rotate, cb.has_local,
            self.consistent, gradients)
        rc = ReducedConfiguration(cfg, B, Psi, H, Kuu, Kinv)
        mats = ReducedMatrices(rc, J, Mr, Kr + self.geometric_stiffness(rc, J), Cr, Gr, None)
        fm = self._compiled_forces(fg, Tk, V, dMr, dKr, C2, Ts, Vs, Wg, gradients)
        fm.dHdq = dHdq
        if gradients:
            fm.elastic = self.elastic_forms(mats.rc, dHdq)
        return mats, fm

    def reduced_mass(self, p: np.ndarray) -> np.ndarray:
        """``M_r = J^T M J`` at (the configuration of) ``p`` alone."""
        nq = self.nq
        rc = self.cb.at(p[:nq])
        J = rc.H
        if self.consistent:
            J = rc.H.copy()
            J[:, :nq] += self.cb.basis_derivative(rc, p[:, None])[0]
        WJ = rc.cfg.W @ J
        return WJ.T @ rc.cfg.M_N @ WJ

    def mass_derivative(self, mats: ReducedMatrices, p: np.ndarray, delta: float = 1e-6) -> np.ndarray:
        """``d M_r / d q_i`` (nq, r, r) by forward differences (``M_r`` is smooth in q; error ~ delta)."""
        out = np.empty((self.nq, self.r, self.r))
        for i in range(self.nq):
            pp = np.array(p, float)
            pp[i] += delta
            out[i] = (self.reduced_mass(pp) - mats.Mr) / delta
        self.cb.at(p[: self.nq])  # leave the closure solver warm-started at p
        return out

    def force_model(self, mats: ReducedMatrices, p: np.ndarray, dHdq: np.ndarray | None = None,
                    gradients: bool = True) -> QuadraticForces:
        """The state-dependent forces ``fr(p, p')`` at ``mats``' configuration as explicit quadratic forms.

        With the configuration (and ``J``) held, every velocity-dependent term is a quadratic form in ``p'``
        (``h_2``: ``J^T h_2(J p') = 1/2 sum_k p'_k T_k p'`` with ``T_k = J^T (dh/dv)(J e_k) J``), the bias
        acceleration is bilinear in ``q'`` and ``p'``, and the q-row geometric term of the elastic
        displacements is a quadratic form in ``p``. Evaluating them costs a few tensor contractions instead of
        a kinematic and finite-element evaluation, which is what makes the cached observer step cheap.
        ``gradients=False`` leaves out the q-derivatives of ``M_r`` and ``K_r`` (``dMr2``, ``dKr2`` None).
        """
        model, cb, nq, r = self.model, self.cb, self.nq, self.r
        rc, J = mats.rc, mats.J
        cfg = rc.cfg
        if dHdq is None:
            dHdq = cb.basis_derivative(rc, np.eye(r))  # (r, n, nq)
        if self.compiled:
            return self._force_model_compiled(mats, dHdq, gradients)
        Sd = model.coordinate_derivatives(cfg)
        WJ = cfg.W @ J
        SE = model.element_rotation_term(cfg, WJ)
        Tk = model.velocity_force_tensor(cfg, J, Sd, WJ, SE)
        # per element A_e = R_e^T (T H)_e: the element's displacements in its own frame per reduced coordinate;
        # E_e = A_e^T K_G A_e, summed with the element rotation rates, is both the q-row geometric term and the
        # element part of d K_r / dq
        TH = model.T @ rc.H[nq:]  # (N, r)
        Ae = np.swapaxes(cfg.R, 1, 2) @ TH[model.el_dofs]  # (n_el, 6, r)
        Ee = np.swapaxes(Ae, 1, 2) @ (model.KGl @ Ae)  # (n_el, r, r)
        S_th = cfg.pose.Sz[2::3][model.el_link]  # (n_el, nq)
        SEe = (S_th.T @ Ee.reshape(len(Ee), -1)).reshape(nq, r, r)
        # q-row geometric term h_V(p) = S_th^T gV(u): the quadratic form in p of the symmetric part of K_G
        V = 0.25 * (SEe + np.swapaxes(SEe, 1, 2))  # J's q rows are [I 0]
        JtM = WJ.T @ cfg.M_N @ cfg.W if self.consistent else None
        fg = WJ.T @ (cfg.M_N @ model.g_N)
        Wg = self.weight_gradient(mats, dHdq, Sd, WJ)
        if not gradients:
            return QuadraticForces(nq, fg, Tk, V, dHdq if self.consistent else None, JtM, Wg=Wg)
        # d K_r / d q_i with K_r = H_u^T K_uu H_u: stiffness rotated with the elements, basis with the links;
        # per element (T H)_e^T R K_G R^T (T H)_e = A_e^T K_G A_e, so no assembly is needed
        KH = rc.Kuu @ rc.H[nq:]
        dHK = np.swapaxes(np.swapaxes(dHdq[:, nq:, :], 1, 2) @ KH, 0, 1)  # dH_u^T K_uu H_u per q_i
        dKr = SEe + dHK + np.swapaxes(dHK, 1, 2)
        dMr = self.mass_derivative_analytic(mats, dHdq, Sd, WJ, SE)
        return QuadraticForces(nq, fg, Tk, V, dHdq if self.consistent else None, JtM, dMr, dKr, Wg=Wg)

    def _force_model_compiled(self, mats: ReducedMatrices, dHdq: np.ndarray, gradients: bool) -> QuadraticForces:
        """:meth:`force_model` through :func:`._compiled.force_terms` (the same formulas, one call)."""
        model, nq = self.model, self.nq
        cfg = mats.rc.cfg
        fg, Tk, V, _JtM, dMr, dKr, C2, Ts, Vs, Wg = _compiled.force_terms(
            cfg.W, np.ascontiguousarray(mats.J), mats.rc.H, cfg.M_N, model.t_index, np.ascontiguousarray(mats.rc.Kuu),
            model.g_N, cfg.R, model.Gl, model.KGl, model.el_dofs, np.ascontiguousarray(cfg.pose.Sz[2::3][model.el_link]),
            model.kin.coordinate_rates(cfg.pose), np.ascontiguousarray(dHdq), nq, self.consistent, gradients)
        return self._compiled_forces(fg, Tk, V, dMr, dKr, C2, Ts, Vs, Wg, gradients)

    def _compiled_forces(self, fg, Tk, V, dMr, dKr, C2, Ts, Vs, Wg, gradients: bool) -> QuadraticForces:
        """The force model from a compiled evaluation's terms, whose bias form ``C2``, symmetrised forms
        ``Ts, Vs`` and weight gradient ``Wg`` are computed there (``C2`` is used by the consistent form only,
        ``dMr, dKr`` with ``gradients`` only)."""
        return QuadraticForces(self.nq, fg, Tk, V, None, None, dMr if gradients else None,
                               dKr if gradients else None, C2=C2 if self.consistent else None, symmetrised=(Ts, Vs),
                               Wg=Wg)

    def mass_derivative_analytic(self, mats: ReducedMatrices, dHdq: np.ndarray, Sd: list | None = None,
                                 WJ: np.ndarray | None = None, SE: np.ndarray | None = None) -> np.ndarray:
        """``d M_r / d q_i`` (nq, r, r) from the element rotations, ``dS/dq_i`` and ``dH/dq_i``.

        ``M_r = (W J)^T M_N (W J)``; the second derivatives of the basis in q times the elastic coordinates
        (``d D0 / dq``, consistent form only) are left out here: exact on undeformed states, 3e-4 relative on the
        six-bar at elastic coordinates 1e-4 (``tests/test_reduced_derivatives.py``, central differences). Where a
        deformed state's gradient is wanted (the reference step under gravity, :meth:`held` with ``fr``) they are
        added (:meth:`_curved_mass_gradient`); the cached step holds them per unit elastic coordinate
        (:meth:`mass_curvature`). ``Sd`` (``dS/dq_i``), ``WJ = W J`` and
        ``SE`` (:meth:`~exuflex.erls.model.ErlsModel.element_rotation_term`) if already computed.
        """
        model = self.model
        rc, J = mats.rc, mats.J
        cfg = rc.cfg
        if Sd is None:
            Sd = model.coordinate_derivatives(cfg)
        if WJ is None:
            WJ = cfg.W @ J
        if SE is None:  # W J^T dM_N/dq_i W J: the element masses rotate with their links
            SE = model.element_rotation_term(cfg, WJ)
        dWJ = self._velocity_map_gradient(mats, dHdq, Sd)
        A = np.swapaxes(dWJ, 1, 2) @ (cfg.M_N @ WJ)
        return A + np.swapaxes(A, 1, 2) + SE

    def _velocity_map_gradient(self, mats: ReducedMatrices, dHdq: np.ndarray, Sd: list) -> np.ndarray:
        """``d(W J)/dq_i = dS/dq_i J_q + W dH/dq_i`` (nq, N, r): the nodal velocity map's change with q (the second
        derivatives of the basis times the elastic coordinates left out, see :meth:`mass_derivative_analytic`)."""
        nq, J, W = self.nq, mats.J, mats.rc.cfg.W
        r, n = J.shape[1], dHdq.shape[1]
        WdH = (W @ dHdq.transpose(1, 0, 2).reshape(n, r * nq)).reshape(-1, r, nq)
        return np.stack([Sdi @ J[:nq] + WdH[:, :, i] for i, Sdi in enumerate(Sd)])

    def weight_gradient(self, mats: ReducedMatrices, dHdq: np.ndarray, Sd: list | None = None,
                        WJ: np.ndarray | None = None) -> np.ndarray:
        """``Wg[c, m] = d fg_c / dp_m`` (r, r): the weight ``fg = (W J)^T M_N g`` (:meth:`force_model`) differentiated
        in the positions at ``mats``' state; empty (0, 0) without gravity.

        In q (columns ``m < nq``), ``d fg/dq_i = (d(W J)/dq_i)^T M_N g + (W J)^T (dM_N/dq_i) g``: the velocity map
        turns with the links (:meth:`_velocity_map_gradient`) and the element masses with them
        (``dM_N/dq_i = sum_e dtheta_e/dq_i R_e G_e R_e^T``, ``G_e`` the local mass rotation rate: the offset
        masses' weight moves with their link). In the elastic coordinates (columns ``m >= nq``, consistent form
        only), ``J = H + [d(H p)/dq, 0]`` changes the q rows: ``d fg_i / dp_m = (W dH/dq_i e_m)^T M_N g``, the
        last column of :meth:`elastic_forms`' ``pG``. Exact where the elastic coordinates are zero (the second
        derivatives of the basis times them are left out, as in :meth:`mass_derivative_analytic`); central
        differences of ``fr`` at rest agree entry by entry (``tests/test_step_jacobian.py``)."""
        model, nq, r = self.model, self.nq, self.r
        if not np.any(model.g_N):
            return np.zeros((0, 0))
        cfg = mats.rc.cfg
        if Sd is None:
            Sd = model.coordinate_derivatives(cfg)
        if WJ is None:
            WJ = cfg.W @ mats.J
        dW = self._velocity_map_gradient(mats, dHdq, Sd).transpose(0, 2, 1) @ (cfg.M_N @ model.g_N)  # (nq, r)
        RGR = cfg.R @ model.Gl @ np.swapaxes(cfg.R, 1, 2)  # dM_N/dtheta_e per element
        Ee = np.einsum("eaj,eab,eb->ej", WJ[model.el_dofs], RGR, model.g_N[model.el_dofs])  # (n_el, r)
        S_th = cfg.pose.Sz[2::3][model.el_link]  # (n_el, nq)
        Wg = np.zeros((r, r))
        Wg[:, :nq] = (dW + S_th.T @ Ee).T
        if self.consistent:
            Wg[:nq, nq:] = dW[:, nq:]
        return Wg

    def weight_curvature(self, mats: ReducedMatrices, dHdq: np.ndarray, hess: np.ndarray) -> np.ndarray:
        """``We`` (r - nq, nq * nq): the weight's q rows differentiated in ``q`` and in an elastic coordinate,
        ``We[m, i * nq + j] = d^2 fg_i / dq_j dp_m`` (i, j < nq) at ``mats``' configuration (undeformed); empty
        (0, 0) without gravity or in the paper's form (``J = H``: ``fg`` does not depend on ``p``).

        ``fg_q = (S + T d(H_u p)/dq)^T M_N g`` is linear in the elastic coordinates, so its q-gradient at a deformed
        state is the undeformed one's (:meth:`weight_gradient`) plus ``sum_m p_m We[m]``: per unit ``p_m`` the basis's
        second derivative ``(W d^2(H e_m)/dq_i dq_j)^T M_N g`` (``hess``, :meth:`basis_hessian`) and the element masses
        turning with the links against the sag's velocity map, ``sum_e dtheta_e/dq_i (W d(H e_m)/dq_j)_e^T R_e G_e
        R_e^T g_e`` (:meth:`weight_gradient`'s rotation term with ``W A_m`` for ``W J``). The cached observer step
        holds the configuration undeformed and follows the elastic coordinates to first order; under gravity the
        sag is always there, and the weight's moment across it changes with q by ``We p``: on the crane arm
        (``benchmarks/models/crane_arm.toml``) 0.013 N m/rad of the shoulder's 12 N m/rad, which the boom's small
        inertia behind the elbow turns into a fifth of ``dq2''/dq1`` (docs/gravity.md)."""
        model, nq, r = self.model, self.nq, self.r
        if not (self.consistent and np.any(model.g_N)) or r == nq:
            return np.zeros((0, 0))
        cfg = mats.rc.cfg
        wg = cfg.W.T @ (cfg.M_N @ model.g_N)  # (n,)
        out = np.einsum("mxij,x->mij", hess, wg)  # (r - nq, nq, nq): [m, i, j], symmetric in i, j
        RGR = cfg.R @ model.Gl @ np.swapaxes(cfg.R, 1, 2)  # dM_N/dtheta_e per element
        S_th = cfg.pose.Sz[2::3][model.el_link]  # (n_el, nq)
        ge = np.einsum("eab,eb->ea", RGR, model.g_N[model.el_dofs])  # (n_el, 6)
        for m in range(r - nq):
            WA = cfg.W @ dHdq[nq + m]  # (N, nq): W d(H e_m)/dq_j
            Ee = np.einsum("eaj,ea->ej", WA[model.el_dofs], ge)  # (n_el, nq) [e, j]
            out[m] += (S_th.T @ Ee).T  # row i = j of the q rows (the velocity map's column), column the angle's q
        return np.ascontiguousarray(out.reshape(r - nq, nq * nq))

    def mass_curvature(self, mats: ReducedMatrices, dHdq: np.ndarray, hess: np.ndarray) -> np.ndarray:
        """``Me`` (r - nq, nq * nq * r): the reduced mass matrix differentiated in ``q`` and in an elastic coordinate
        at ``mats``' configuration (undeformed), ``d^2 M_r / dq_i dp_m = X_mi + X_mi^T`` with ``X_mi`` (r, r) zero but
        in its first ``nq`` rows, which ``Me[m, (i * nq + a) * r + b]`` holds (``a < nq``); empty (0, 0) in the
        paper's form (``J = H``: ``M_r`` does not depend on ``p``) or without elastic coordinates.

        ``M_r = (W J)^T M_N (W J)`` with ``J = H + [d(H p)/dq, 0]``: per unit ``p_m`` the rigid columns of ``W J`` gain
        ``W A_m``, ``A_m = d(H e_m)/dq`` (its q rows zero, so ``dS/dq_i`` does not act on it), and ``M_r``'s rigid rows
        ``pM_m = (W A_m)^T M_N W J`` (:meth:`elastic_forms`). Its q-gradient is ``X_mi = (W d^2(H e_m)/dq_. dq_i)^T M_N W
        J + (W A_m)^T (dM_N/dq_i) W J + (W A_m)^T M_N d(W J)/dq_i``: the basis's second derivatives (``hess``,
        :meth:`basis_hessian`), the element masses turning with the links (``dM_N/dq_i = sum_e dtheta_e/dq_i R_e G_e
        R_e^T``, as in :meth:`weight_gradient`) and the velocity map turning (:meth:`_velocity_map_gradient`). So at a
        deformed state (the sag under gravity) ``d M_r/dq_i = dMr_i + sum_m p_m Me[m, i]`` to first order in ``p``
        (``M_r``'s second order in ``p``, ``p_k p_l A_k^T M_N A_l``, is left out of the held model altogether,
        :func:`exuflex.observer.expansion._elastic_terms`). The cached observer step holds it under gravity, where the
        sag is always there (docs/step_jacobian.md)."""
        model, nq, r = self.model, self.nq, self.r
        if not self.consistent or r == nq:
            return np.zeros((0, 0))
        cfg = mats.rc.cfg
        Sd = model.coordinate_derivatives(cfg)
        WJ = cfg.W @ mats.J  # (N, r)
        MWJ = cfg.M_N @ WJ
        dWJ = self._velocity_map_gradient(mats, dHdq, Sd)  # (nq, N, r)
        MdWJ = np.einsum("xy,iyc->ixc", cfg.M_N, dWJ)  # (nq, N, r): M_N d(W J)/dq_i
        RGR = cfg.R @ model.Gl @ np.swapaxes(cfg.R, 1, 2)  # dM_N/dtheta_e per element
        S_th = cfg.pose.Sz[2::3][model.el_link]  # (n_el, nq)
        RWJ = np.einsum("eab,ebc->eac", RGR, WJ[model.el_dofs])  # (n_el, 6, r)
        out = np.empty((r - nq, nq, nq, r))  # [m, i, a, b]
        for m in range(r - nq):
            WA = cfg.W @ dHdq[nq + m]  # (N, nq): W d(H e_m)/dq_a
            WZ = np.einsum("Nx,xai->iNa", cfg.W, hess[m])  # (nq, N, nq): W d^2(H e_m)/dq_a dq_i
            X = np.einsum("iNa,Nb->iab", WZ, MWJ) + np.einsum("Na,iNb->iab", WA, MdWJ)
            X += np.einsum("ei,eca,ecb->iab", S_th, WA[model.el_dofs], RWJ)
            out[m] = X
        return np.ascontiguousarray(out.reshape(r - nq, nq * nq * r))

    def _curved_mass_gradient(self, mats: ReducedMatrices, dMr: np.ndarray, Zp: np.ndarray) -> np.ndarray:
        """``dMr`` (nq, r*r, :meth:`mass_derivative_analytic` at a deformed state) with the basis's second derivatives
        times the elastic coordinates in it: ``d(W J)/dq_i`` gains ``W [d^2(H p)/dq dq_i, 0]`` (``Zp``, (n, nq, nq)),
        so ``d M_r/dq_i`` gains ``Y_i + Y_i^T``, ``Y_i`` the rigid rows ``(W Zp[:, :, i])^T M_N W J``."""
        nq, r = self.nq, self.r
        cfg = mats.rc.cfg
        WZ = np.einsum("Nx,xai->iNa", cfg.W, Zp)  # (nq, N, nq)
        Y = np.zeros((nq, r, r))
        Y[:, :nq, :] = np.einsum("iNa,Nb->iab", WZ, cfg.M_N @ (cfg.W @ mats.J))
        return (dMr.reshape(nq, r, r) + Y + np.swapaxes(Y, 1, 2)).reshape(nq, r * r)

    def accelerations(self, p: np.ndarray, pd: np.ndarray, tau: np.ndarray, mats: ReducedMatrices | None = None):
        """``p''`` of ``M_r p'' + C_r p' + (K_r + K_Gd) p = G_r tau + f_r`` at ``(p, p')`` under ``tau``, ``K_Gd`` the
        motion's geometric stiffness (:meth:`motion_stiffness`)."""
        if mats is None:
            mats = self.matrices(p, pd)
        F = mats.Gr @ tau + mats.fr - (mats.Kr + self.motion_stiffness(mats.rc, mats.J, pd[: self.nq], tau)) @ p \
            - mats.Cr @ pd
        return np.linalg.solve(mats.Mr, F)

    def quasi_static(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray, passes: int = 2) -> np.ndarray:
        """The elastic coordinates (r - nq,) at which the reduced equations hold at ``q, q'`` under ``tau`` with the
        elastic rates and accelerations zero: ``M_r[:, :nq] q'' + (K_r + K_Gd) p = G_r tau + f_r - C_r p'``
        (:meth:`accelerations`' terms; every row, ``q''`` and ``p_e`` the unknowns), solved with the matrices at the
        undeformed state, then again at the solution (``J`` and the forces change with ``p_e``: each pass moves it by
        the sag's square relative). Under gravity the links' quasi-static sag under the weight, the torques and the
        rates' loads, about which the elastic coordinates vibrate."""
        nq, r = self.nq, self.r
        p = np.zeros(r)
        p[:nq] = q
        pd = np.zeros(r)
        pd[:nq] = qd
        tau = np.asarray(tau, float)
        for _ in range(passes):
            m = self.matrices(p, pd)
            K = m.Kr + self.motion_stiffness(m.rc, m.J, pd[:nq], tau)
            A = np.hstack([m.Mr[:, :nq], K[:, nq:]])
            b = m.Gr @ tau + m.fr - K[:, :nq] @ p[:nq] - m.Cr @ pd
            p[nq:] = np.linalg.solve(A, b)[nq:]
        return p[nq:].copy()

    def rhs(self, t: float, z: np.ndarray, tau: np.ndarray) -> np.ndarray:
        r = self.r
        return np.concatenate([z[r:], self.accelerations(z[:r], z[r:], tau)])

    # ------------------------------------------------------------------ states
    def full_state(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Full coordinates and velocities (x, v) = (H p, J p') of a reduced state."""
        r = self.r
        rc = self.cb.at(z[: self.nq])
        J = rc.H
        if self.consistent:
            J = rc.H.copy()
            J[:, : self.nq] += self.cb.basis_derivative(rc, z[:r])[0]
        return rc.H @ z[:r], J @ z[r:]

    def reduce_state(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The reduced state closest to a full state (masters exact, eta by mass-weighted least squares)."""
        cb, nq = self.cb, self.nq
        rc = cb.at(x[:nq])
        M = self.model.mass(rc.cfg)
        H = rc.H
        nm = cb.n_m
        p = np.linalg.solve(H.T @ M @ H, H.T @ M @ x)
        p[:nq] = x[:nq]
        p[nq:nm] = cb.master_values(rc.cfg, x[nq:])
        J = H
        if self.consistent:
            J = H.copy()
            J[:, :nq] += cb.basis_derivative(rc, p)[0]
        pd = np.linalg.solve(J.T @ M @ J, J.T @ M @ v)
        # master rates: the rows of J at the masters, v_m = (Q^T (J p')_u)_m, solved for the master block
        pd[:nq] = v[:nq]
        Jm = cb.master_values(rc.cfg, J[nq:])  # (me, r)
        pd[nq:nm] = np.linalg.solve(Jm[:, nq:nm], cb.master_values(rc.cfg, v[nq:]) - Jm[:, :nq] @ pd[:nq]
                                    - Jm[:, nm:] @ pd[nm:])
        return np.concatenate([p, pd])

    def rest_state(self, q) -> np.ndarray:
        """Undeformed state at rest at q."""
        z = np.zeros(self.nx)
        z[: self.nq] = q
        return z

    def energy(self, z: np.ndarray) -> float:
        r = self.r
        p, pd = z[:r], z[r:]
        mats = self.matrices(p, pd)
        Hu = mats.rc.H[self.nq :]
        return 0.5 * pd @ mats.Mr @ pd + 0.5 * p @ (Hu.T @ mats.rc.Kuu @ Hu) @ p


#: a clamped steel rod of two elements, one master: the smallest model whose reduction runs every kernel of the
#: held evaluation (:func:`warm_up`)
_WARM_UP_MODEL = {
    "model": {"name": "warm_up_rod", "q_ref": [0.0]},
    "materials": [{"name": "steel", "E": 2.0e11, "rho": 7800.0}],
    "links": [{"name": "rod", "length": 1.0, "material": "steel", "diameter": 0.02, "n_elements": 2}],
    "joints": [{"name": "hub", "points": [{"link": "rod", "station": 0.0}], "ground": [0.0, 0.0]}],
    "coordinates": [{"name": "q1", "link": "rod", "joint": "hub"}],
    "reduction": {"masters": ["node3.transverse"], "q_star": [0.0], "n_interior": 1},
}


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) the kernels that building a reduced model and its held
    evaluation run (the closure's, the full-order configuration, :mod:`._compiled`; the held evaluation with the
    frozen step's forces too), by building the reduction of a two-element
    rod and evaluating it once: the kernels see arguments of the very types a mechanism's model passes (the
    closure arrays, the Fortran-ordered inverses that compiled code returns)."""
    if not _compiled.HAVE_NUMBA:
        return
    rm = ReducedModel(CraigBampton(ErlsModel(parse_mechanism(_WARM_UP_MODEL, "warm_up"))))
    rm.held(np.zeros(rm.r), np.zeros(rm.r))
    rm.held(np.zeros(rm.r), np.zeros(rm.r), fr=True, gradients=False)  # the frozen step's forces

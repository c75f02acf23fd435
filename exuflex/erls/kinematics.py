"""ERLS kinematics of a planar closed chain of revolute, prismatic and welded joints.

The equivalent rigid-link system (ERLS) places every link rigidly; its pose is
``z = [x_1, y_1, th_1, ..., x_L, y_L, th_L]`` (origin and absolute angle of each link), fixed by
the independent ERLS coordinates ``q`` through the closure equations ``Phi(z, q) = 0``:

- each joint: the link points it joins coincide (or sit at the ground position);
- each prismatic joint: its point lies on its axis, ``n . (p - g) = 0`` (``n`` the axis' normal);
- each weld: ``th_b - th_a - angle = 0``;
- each coordinate: ``th_link - th_ref - offset - q_j = 0`` (``th_ref = 0`` for an absolute angle), or for a
  slide coordinate ``d . (p - g) - offset - q_j = 0`` (``d`` the axis).

Given ``q`` the closure is solved by Newton's method; the sensitivity ``S_z = dz/dq`` and its time
derivative follow exactly from the closure's Jacobian (no finite differences):
``Phi_z S_z = E`` and ``Phi_z dS_z/dt = -(dPhi_z/dt) S_z``.
The nodal rigid coordinates ``r`` (x, y, theta of every FE node) and their sensitivity
``S = dr/dq`` (the paper's S in eq. 2) are then direct.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from ..mechanism import Mechanism
from ._closure import ClosureArrays, closure_newton, coordinate_rates, pose_sensitivities

__all__ = ["Kinematics", "KinematicsError", "Pose"]

log = logging.getLogger(__name__)


class KinematicsError(ValueError):
    """The closure cannot be solved, or the configuration is at or near a singularity."""


@dataclass(frozen=True)
class Pose:
    """The ERLS at ``q``: link poses, nodal rigid coordinates and their sensitivities."""

    q: np.ndarray  # (nq,)
    z: np.ndarray  # (3 n_links,) link origin x, y and angle
    Sz: np.ndarray  # (3 n_links, nq) dz/dq
    r: np.ndarray  # (3 n_nodes,) nodal x, y, theta of the ERLS
    S: np.ndarray  # (3 n_nodes, nq) dr/dq
    cond: float  # condition number (1-norm) of the closure Jacobian
    Jinv: np.ndarray | None = None  # inverse of the closure Jacobian (reused by ``rates``)

    @property
    def link_angles(self) -> np.ndarray:
        return self.z[2::3]

    def node_xy(self, index: int) -> np.ndarray:
        return self.r[3 * index : 3 * index + 2]


class Kinematics:
    """Closure solver and sensitivities for a mechanism.

    Parameters
    ----------
    mech : Mechanism
    cond_max : float
        Closure Jacobians with a larger condition number are reported as singular.
    """

    def __init__(self, mech: Mechanism, cond_max: float = 1e8):
        self.mech = mech
        self.cond_max = cond_max
        self.compiled = True  # the Newton iteration in compiled code where numba is installed (_closure)
        self.link_names = [lk.name for lk in mech.links]
        li = {n: i for i, n in enumerate(self.link_names)}
        self.nl = len(mech.links)
        self.nq = len(mech.coordinates)
        # position equations: rows of (link a, station a, link b or -1, station b, ground xy)
        eqs = []
        # scalar equations: (link a, station a, direction n (2,), weight of th_a, link r, weight of th_r, offset,
        # coordinate index or -1), read n . p(a, s) + w th_a - wr th_r - offset - q = 0
        sc = []
        for j in mech.joints:
            pts = [(li[p.link], p.station) for p in j.points]
            if j.kind == "revolute" and j.ground is not None:
                for a, sa in pts:
                    eqs.append((a, sa, -1, 0.0, np.asarray(j.ground, float)))
            else:
                a0, s0 = pts[0]
                for b, sb in pts[1:]:
                    eqs.append((b, sb, a0, s0, np.zeros(2)))
            if j.kind == "prismatic":
                n = np.asarray(j.normal, float)
                sc.append((a0, s0, n, 0.0, 0, 0.0, float(n @ np.asarray(j.ground, float)), -1))
            elif j.kind == "weld":
                sc.append((pts[1][0], 0.0, np.zeros(2), 1.0, a0, 1.0, j.angle, -1))
        self._pos_eqs = eqs
        for k, c in enumerate(mech.coordinates):
            if c.kind == "slide":
                jt = mech.joint(c.joint)
                d = np.asarray(jt.axis, float)
                p0 = jt.points[0]
                sc.append((li[p0.link], p0.station, d, 0.0, 0, 0.0, float(d @ np.asarray(jt.ground)) + c.offset, k))
            else:
                rel = c.relative_to is not None
                sc.append((li[c.link], 0.0, np.zeros(2), 1.0, li[c.relative_to] if rel else 0, 1.0 if rel else 0.0,
                           c.offset, k))
        self._sc_eqs = sc
        self.n_eq = 2 * len(eqs) + len(sc)
        if self.n_eq != 3 * self.nl:
            raise KinematicsError(
                f"{mech.source or mech.name}: {self.n_eq} closure equations for {3 * self.nl} link coordinates"
            )
        E = np.zeros((self.n_eq, self.nq))
        for i, e in enumerate(sc):
            if e[7] >= 0:
                E[2 * len(eqs) + i, e[7]] = 1.0
        self._E = E
        # nodes: link index and station of every node, in mech.node_ids order
        self.node_ids = mech.node_ids
        self.node_link = np.empty(len(self.node_ids), int)
        self.node_station = np.empty(len(self.node_ids))
        for k, n in enumerate(self.node_ids):
            name, s = mech.node_location(n)
            self.node_link[k] = li[name]
            self.node_station[k] = s
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        self._vectorise()

    # ------------------------------------------------------------------ closure
    def _vectorise(self):
        """Index arrays for the position equations, so residual and Jacobians need no Python loops."""
        eqs = self._pos_eqs
        self._ea = np.array([e[0] for e in eqs], int)
        self._esa = np.array([e[1] for e in eqs], float)
        self._eb = np.array([max(e[2], 0) for e in eqs], int)
        self._ebm = np.array([1.0 if e[2] >= 0 else 0.0 for e in eqs])  # 1 where the second point is a link
        self._esb = np.array([e[3] for e in eqs], float) * self._ebm
        self._eg = np.array([e[4] for e in eqs], float).reshape(-1, 2)
        sc = self._sc_eqs
        self._ca = np.array([e[0] for e in sc], int)
        self._cs = np.array([e[1] for e in sc], float)
        self._cn = np.array([e[2] for e in sc], float).reshape(-1, 2)
        self._cw = np.array([e[3] for e in sc], float)
        self._cr = np.array([e[4] for e in sc], int)
        self._cwr = np.array([e[5] for e in sc], float)
        self._coff = np.array([e[6] for e in sc], float)
        self._cq = np.array([e[7] for e in sc], int)
        npos = len(eqs)
        self._rx = 2 * np.arange(npos)
        self._ry = self._rx + 1
        J0 = np.zeros((self.n_eq, 3 * self.nl))
        for k, (a, _, b, _, _) in enumerate(eqs):
            J0[2 * k : 2 * k + 2, 3 * a : 3 * a + 2] += np.eye(2)
            if b >= 0:
                J0[2 * k : 2 * k + 2, 3 * b : 3 * b + 2] -= np.eye(2)
        base = 2 * npos
        for j, (a, _, n, w, r, wr, _, _) in enumerate(self._sc_eqs):
            J0[base + j, 3 * a : 3 * a + 2] += n
            J0[base + j, 3 * a + 2] += w
            J0[base + j, 3 * r + 2] -= wr
        self._J0 = J0
        self._pca = 3 * self._ea + 2  # angle columns of the position equations
        self._pcb = 3 * self._eb + 2
        self._link_eq = self._ebm > 0
        self._sc_rows = base + np.flatnonzero(self._cs != 0.0)  # scalar equations on a point off the origin
        self._sc_pt = np.flatnonzero(self._cs != 0.0)
        self.arrays = ClosureArrays(self._ea, self._esa, self._eb, self._ebm, self._esb, self._eg, self._ca,
                                    self._cs, self._cn, self._cw, self._cr, self._cwr, self._coff, self._cq,
                                    self._J0, self._E)

    def residual(self, z: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Phi(z, q) (n_eq,); batched over leading axes of ``z`` (..., 3 n_links) and ``q`` (..., nq)."""
        x, y, th = z[..., 0::3], z[..., 1::3], z[..., 2::3]
        a, b = self._ea, self._eb
        out = np.empty(np.shape(z)[:-1] + (self.n_eq,))
        m = self._ebm
        ca, sa_ = np.cos(th[..., a]), np.sin(th[..., a])
        cb, sb_ = np.cos(th[..., b]), np.sin(th[..., b])
        out[..., self._rx] = x[..., a] + self._esa * ca - m * (x[..., b] + self._esb * cb) - self._eg[:, 0]
        out[..., self._ry] = y[..., a] + self._esa * sa_ - m * (y[..., b] + self._esb * sb_) - self._eg[:, 1]
        base = 2 * len(self._pos_eqs)
        ta = th[..., self._ca]
        q = np.asarray(q, float)
        q_term = np.where(self._cq >= 0, q[..., np.maximum(self._cq, 0)], 0.0)
        out[..., base:] = (self._cn[:, 0] * (x[..., self._ca] + self._cs * np.cos(ta))
                           + self._cn[:, 1] * (y[..., self._ca] + self._cs * np.sin(ta))
                           + self._cw * ta - self._cwr * th[..., self._cr] - self._coff - q_term)
        return out

    def jacobian(self, z: np.ndarray) -> np.ndarray:
        """Phi_z (n_eq, 3 n_links); batched over leading axes of ``z``."""
        th = z[..., 2::3]
        J = np.broadcast_to(self._J0, th.shape[:-1] + self._J0.shape).copy()
        a, b = self._ea, self._eb
        J[..., self._rx, self._pca] = -self._esa * np.sin(th[..., a])
        J[..., self._ry, self._pca] = self._esa * np.cos(th[..., a])
        lk = self._link_eq
        J[..., self._rx[lk], self._pcb[lk]] = self._esb[lk] * np.sin(th[..., b[lk]])
        J[..., self._ry[lk], self._pcb[lk]] = -self._esb[lk] * np.cos(th[..., b[lk]])
        i = self._sc_pt
        ta = th[..., self._ca[i]]
        J[..., self._sc_rows, 3 * self._ca[i] + 2] += self._cs[i] * (-self._cn[i, 0] * np.sin(ta)
                                                                     + self._cn[i, 1] * np.cos(ta))
        return J

    def _jacobian_rate(self, z: np.ndarray, zd: np.ndarray) -> np.ndarray:
        """d(Phi_z)/dt along the velocity zd; batched over leading axes of ``z`` and ``zd``."""
        th, thd = z[..., 2::3], zd[..., 2::3]
        J = np.zeros(th.shape[:-1] + (self.n_eq, 3 * self.nl))
        a, b = self._ea, self._eb
        J[..., self._rx, self._pca] = -self._esa * thd[..., a] * np.cos(th[..., a])
        J[..., self._ry, self._pca] = -self._esa * thd[..., a] * np.sin(th[..., a])
        lk = self._link_eq
        bl = b[lk]
        J[..., self._rx[lk], self._pcb[lk]] = self._esb[lk] * thd[..., bl] * np.cos(th[..., bl])
        J[..., self._ry[lk], self._pcb[lk]] = self._esb[lk] * thd[..., bl] * np.sin(th[..., bl])
        i = self._sc_pt
        ai = self._ca[i]
        J[..., self._sc_rows, 3 * ai + 2] = self._cs[i] * thd[..., ai] * (-self._cn[i, 0] * np.cos(th[..., ai])
                                                                         - self._cn[i, 1] * np.sin(th[..., ai]))
        return J

    def jacobian_rate_product(self, z: np.ndarray, zd: np.ndarray) -> np.ndarray:
        """``(dPhi_z/dt) z'`` (n_eq,) without forming the matrix; batched over leading axes of ``z`` and ``zd``."""
        th, thd = z[..., 2::3], zd[..., 2::3]
        a, b = self._ea, self._eb
        wa = self._esa * thd[..., a] ** 2
        wb = self._ebm * self._esb * thd[..., b] ** 2
        out = np.zeros(np.shape(z)[:-1] + (self.n_eq,))
        out[..., self._rx] = -wa * np.cos(th[..., a]) + wb * np.cos(th[..., b])
        out[..., self._ry] = -wa * np.sin(th[..., a]) + wb * np.sin(th[..., b])
        i = self._sc_pt  # scalar equations on a point: s (-n_x cos - n_y sin) th'^2
        ai = self._ca[i]
        out[..., self._sc_rows] = self._cs[i] * thd[..., ai] ** 2 * (-self._cn[i, 0] * np.cos(th[..., ai])
                                                                    - self._cn[i, 1] * np.sin(th[..., ai]))
        return out

    def initial_guess(self, q: np.ndarray) -> np.ndarray:
        """Link poses from the angle guesses, placed by walking the joints from the ground."""
        mech = self.mech
        li = {n: i for i, n in enumerate(self.link_names)}
        th = np.zeros(self.nl)
        for i, lk in enumerate(mech.links):
            if lk.angle_guess is not None:
                th[i] = lk.angle_guess
        for j, c in enumerate(mech.coordinates):
            if c.kind == "angle" and c.relative_to is None:
                th[li[c.link]] = q[j] + c.offset
        for j, c in enumerate(mech.coordinates):
            if c.kind == "angle" and c.relative_to is not None:
                th[li[c.link]] = th[li[c.relative_to]] + q[j] + c.offset
        for jt in mech.joints:
            if jt.kind == "weld" and mech.link(jt.points[1].link).angle_guess is None:
                th[li[jt.points[1].link]] = th[li[jt.points[0].link]] + jt.angle
        z = np.zeros(3 * self.nl)
        z[2::3] = th
        placed = set()
        for j, c in enumerate(mech.coordinates):  # a slider at its coordinate
            if c.kind == "slide":
                jt = mech.joint(c.joint)
                pos = np.asarray(jt.ground) + (q[j] + c.offset) * np.asarray(jt.axis)
                for p in jt.points:
                    i = li[p.link]
                    z[3 * i : 3 * i + 2] = pos - p.station * np.array([np.cos(th[i]), np.sin(th[i])])
                    placed.add(i)
        for jt in mech.joints:
            if jt.kind == "revolute" and jt.ground is not None:
                for p in jt.points:
                    i = li[p.link]
                    z[3 * i : 3 * i + 2] = np.asarray(jt.ground) - p.station * np.array([np.cos(th[i]), np.sin(th[i])])
                    placed.add(i)
        changed = True
        while changed:
            changed = False
            for jt in mech.joints:
                done = [p for p in jt.points if li[p.link] in placed]
                if not done:
                    continue
                p0 = done[0]
                i0 = li[p0.link]
                pos = z[3 * i0 : 3 * i0 + 2] + p0.station * np.array([np.cos(th[i0]), np.sin(th[i0])])
                for p in jt.points:
                    i = li[p.link]
                    if i not in placed:
                        z[3 * i : 3 * i + 2] = pos - p.station * np.array([np.cos(th[i]), np.sin(th[i])])
                        placed.add(i)
                        changed = True
        return z

    def reset_warm_start(self) -> None:
        """Forget the last solution, so that the next :meth:`solve` without ``z0`` starts from the initial guess:
        a computation that must not depend on what this solver did before (a new observer run, in whatever
        process it lands) calls this first. Newton converges to the same closure either way, but the last bits
        of the solution depend on where it started."""
        self._last = None

    @property
    def warm_start(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The last solution ``(q, z)`` that :meth:`solve` starts from (None: the initial guess). Saved and set
        back by a computation that shares this solver with another but must neither disturb nor depend on the
        other's history (the observer's post-processing of a record between two chunks of its filter run)."""
        return self._last

    @warm_start.setter
    def warm_start(self, value: tuple[np.ndarray, np.ndarray] | None) -> None:
        self._last = value

    def start(self, q, z0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(q, z0)``: q checked as a float array and the Newton start of :meth:`solve` (``z0`` if given, else the
        last solution if it lies within 0.5 rad, else :meth:`initial_guess`)."""
        q = np.asarray(q, float)
        if q.shape != (self.nq,):
            raise KinematicsError(f"q must have {self.nq} entries ({list(self.mech.coordinate_names)}), got {q.shape}")
        if z0 is None:
            last = self._last
            if last is not None and np.max(np.abs(last[0] - q)) < 0.5:
                z0 = last[1]
            else:
                z0 = self.initial_guess(q)
        return q, z0

    def accept(self, q: np.ndarray, z: np.ndarray) -> None:
        """Keep the closure's solution z at q as the next :meth:`solve`'s warm start."""
        self._last = (q.copy(), z.copy())

    @property
    def newton_scale(self) -> float:
        """The length scale of the closure residual's tolerance (the longest link)."""
        return max(lk.length for lk in self.mech.links)

    def solve(self, q, z0: np.ndarray | None = None, tol: float = 1e-12, max_iter: int = 30) -> np.ndarray:
        """Solve the closure for the link poses z at q (Newton, warm-started from the last solution)."""
        q, z0 = self.start(q, z0)
        z = self._newton(z0, q, tol, max_iter)
        if z is None:
            # continuation from the guess configuration towards q
            z = self._continuation(q, tol, max_iter)
        self.accept(q, z)
        return z

    def _newton(self, z, q, tol, max_iter):
        """Newton from z at q; None if it does not converge (compiled where numba is installed, see
        :mod:`._closure`; :meth:`_newton_numpy` is the reference)."""
        if closure_newton is None or not self.compiled:
            return self._newton_numpy(z, q, tol, max_iter)
        scale = self.newton_scale
        try:
            z, ok = closure_newton(np.asarray(z, float), np.asarray(q, float), self.arrays, tol * scale, max_iter)
        except np.linalg.LinAlgError:  # a singular closure Jacobian on the way
            return None
        return z if ok else None

    def _newton_numpy(self, z, q, tol, max_iter):
        z = np.array(z, float)
        scale = max(lk.length for lk in self.mech.links)
        for _ in range(max_iter):
            res = self.residual(z, q)
            J = self.jacobian(z)
            if np.max(np.abs(res)) < tol * scale:
                # one more step polishes the solution to round-off (quadratic convergence)
                return z - np.linalg.solve(J, res)
            try:
                dz = np.linalg.solve(J, -res)
            except np.linalg.LinAlgError:
                return None
            z += dz
            if not np.all(np.isfinite(z)):
                return None
        return z if np.max(np.abs(self.residual(z, q))) < 1e3 * tol * scale else None

    def _continuation(self, q, tol, max_iter):
        start_q = self._last[0] if self._last is not None else np.asarray(self.mech.q_ref or q, float)
        z = self._last[1] if self._last is not None else self.initial_guess(start_q)
        z = self._newton(z, start_q, tol, max_iter)
        if z is None:
            raise KinematicsError(
                f"{self.mech.source or self.mech.name}: the loop cannot close at q = {np.round(q, 6).tolist()} "
                "(check the link lengths, joints and angle guesses)"
            )
        for lam in np.linspace(0.0, 1.0, 41)[1:]:
            z_new = self._newton(z, start_q + lam * (q - start_q), tol, max_iter)
            if z_new is None:
                raise KinematicsError(
                    f"{self.mech.source or self.mech.name}: the loop cannot close at q = {np.round(q, 6).tolist()}"
                    " (no assembly, or a singular configuration on the way)"
                )
            z = z_new
        return z

    # ------------------------------------------------------------------ sensitivities
    def pose(self, q, z0: np.ndarray | None = None) -> Pose:
        """Solve the closure and return the ERLS pose with S_z and the nodal S."""
        q = np.asarray(q, float)
        z = self.solve(q, z0)
        Jinv, cond, Sz, r, S = self._sensitivities(z)
        self.check_condition(q, cond)
        return Pose(q, z, Sz, r, S, cond, Jinv)

    def check_condition(self, q: np.ndarray, cond: float) -> None:
        """Raise :class:`KinematicsError` if the closure Jacobian's condition number at q marks a singularity."""
        if not math.isfinite(cond) or cond > self.cond_max:
            raise KinematicsError(
                f"{self.mech.source or self.mech.name}: configuration q = {np.round(q, 6).tolist()} is at or near a "
                f"singularity (closure Jacobian condition number {cond:.3g} > {self.cond_max:.0e})"
            )

    def _sensitivities(self, z: np.ndarray) -> tuple:
        """``(J^-1, cond, S_z, r, S)`` at the solved poses z: the closure Jacobian's inverse and 1-norm condition
        number, ``S_z = J^-1 E`` and the nodal poses and sensitivities (compiled where numba is installed,
        :func:`._closure.pose_sensitivities`). A singular Jacobian gives ``(None, inf, None, None, None)``."""
        try:
            if pose_sensitivities is not None and self.compiled:
                Jinv, cond, Sz, r, S = pose_sensitivities(z, self.arrays, self.node_link, self.node_station)
                return Jinv, float(cond), Sz, r, S
            J = self.jacobian(z)
            Jinv = np.linalg.inv(J)
        except np.linalg.LinAlgError:
            return None, np.inf, None, None, None
        Sz = Jinv @ self._E
        return (Jinv, float(np.linalg.norm(J, 1) * np.linalg.norm(Jinv, 1)), Sz, *self._nodal(z, Sz))

    def _nodal(self, z, Sz):
        li, s = self.node_link, self.node_station
        th = z[2::3][li]
        c, sn = np.cos(th), np.sin(th)
        nn = len(li)
        r = np.empty(3 * nn)
        r[0::3] = z[0::3][li] + s * c
        r[1::3] = z[1::3][li] + s * sn
        r[2::3] = th
        S = np.empty((3 * nn, self.nq))
        Sx, Sy, St = Sz[0::3][li], Sz[1::3][li], Sz[2::3][li]
        S[0::3] = Sx - (s * sn)[:, None] * St
        S[1::3] = Sy + (s * c)[:, None] * St
        S[2::3] = St
        return r, S

    def rates(self, pose: Pose, qd) -> tuple[np.ndarray, np.ndarray]:
        """dS_z/dt and dS/dt (nodal) at ``pose`` for the coordinate rates ``qd`` (exact)."""
        qd = np.asarray(qd, float)
        zd = pose.Sz @ qd
        Jd = self._jacobian_rate(pose.z, zd)
        if pose.Jinv is not None:
            Szd = -pose.Jinv @ (Jd @ pose.Sz)
        else:
            Szd = -np.linalg.solve(self.jacobian(pose.z), Jd @ pose.Sz)
        li, s = self.node_link, self.node_station
        th = pose.z[2::3][li]
        thd = zd[2::3][li]
        c, sn = np.cos(th), np.sin(th)
        St = pose.Sz[2::3][li]
        Sxd, Syd, Std = Szd[0::3][li], Szd[1::3][li], Szd[2::3][li]
        Sd = np.empty_like(pose.S)
        Sd[0::3] = Sxd - (s * sn)[:, None] * Std - (s * c * thd)[:, None] * St
        Sd[1::3] = Syd + (s * c)[:, None] * Std - (s * sn * thd)[:, None] * St
        Sd[2::3] = Std
        return Szd, Sd

    def coordinate_rates(self, pose: Pose, links: np.ndarray | None = None,
                         stations: np.ndarray | None = None) -> np.ndarray:
        """``dS/dq_j`` for every coordinate j at once: array (nq, 3 n_nodes, nq), entry j the nodal ``dS/dt`` of
        :meth:`rates` along ``q' = e_j`` (the same formulas, batched over j). With ``links`` and ``stations``
        (int and float arrays of one length) the same of those link points instead of the nodes: entry ``j`` row
        ``3 k + c`` is ``d^2 x_c / dq_j dq`` of point k's ``(x, y, angle)``, the second derivatives of its pose."""
        li = self.node_link if links is None else np.asarray(links, dtype=np.int64)
        s = self.node_station if stations is None else np.asarray(stations, dtype=float)
        if coordinate_rates is not None and self.compiled and pose.Jinv is not None:
            return coordinate_rates(pose.z, np.ascontiguousarray(pose.Sz), pose.Jinv, self.arrays, li, s)
        Sz = pose.Sz
        th = pose.z[2::3]
        thd = Sz[2::3].T  # (nq, n_links): link angle rates along each e_j
        nq = Sz.shape[1]
        a, b = self._ea, self._eb
        Jd = np.zeros((nq, self.n_eq, 3 * self.nl))
        Jd[:, self._rx, self._pca] = -self._esa * thd[:, a] * np.cos(th[a])
        Jd[:, self._ry, self._pca] = -self._esa * thd[:, a] * np.sin(th[a])
        lk = self._link_eq
        bl = b[lk]
        Jd[:, self._rx[lk], self._pcb[lk]] = self._esb[lk] * thd[:, bl] * np.cos(th[bl])
        Jd[:, self._ry[lk], self._pcb[lk]] = self._esb[lk] * thd[:, bl] * np.sin(th[bl])
        i = self._sc_pt
        ai = self._ca[i]
        Jd[:, self._sc_rows, 3 * ai + 2] = self._cs[i] * thd[:, ai] * (-self._cn[i, 0] * np.cos(th[ai])
                                                                      - self._cn[i, 1] * np.sin(th[ai]))
        JdS = Jd @ Sz  # (nq, n_eq, nq)
        if pose.Jinv is not None:
            Szd = -(pose.Jinv @ JdS)
        else:
            Szd = -np.linalg.solve(self.jacobian(pose.z), JdS)
        c, sn = np.cos(th[li]), np.sin(th[li])
        thn = thd[:, li][:, :, None]  # (nq, nn, 1)
        St = Sz[2::3][li][None]  # (1, nn, nq)
        Sxd, Syd, Std = Szd[:, 0::3][:, li], Szd[:, 1::3][:, li], Szd[:, 2::3][:, li]
        sc, ss = (s * c)[:, None], (s * sn)[:, None]
        Sd = np.empty((nq, 3 * len(li), nq))
        Sd[:, 0::3] = Sxd - ss * Std - sc * thn * St
        Sd[:, 1::3] = Syd + sc * Std - ss * thn * St
        Sd[:, 2::3] = Std
        return Sd

    def point(self, pose: Pose, link: str, station: float) -> tuple[np.ndarray, np.ndarray]:
        """Position of a point on a link's axis and its sensitivity (2,), (2, nq)."""
        i = self.link_names.index(link)
        x, y, th = pose.z[3 * i : 3 * i + 3]
        c, sn = np.cos(th), np.sin(th)
        p = np.array([x + station * c, y + station * sn])
        Sp = pose.Sz[3 * i : 3 * i + 2] + station * np.outer([-sn, c], pose.Sz[3 * i + 2])
        return p, Sp

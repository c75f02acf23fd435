"""The reduced model ``M_r p'' + C_r p' + K_r p = F_r`` (the paper's eq. 7) with ``x = H(q, q*) p``.

``M_r = H^T M H``, ``K_r = H^T K H``, ``C_r = H^T C H`` and ``F_r = H^T (F - h(H p, H p'))``, where ``h``
holds the same velocity-dependent (Coriolis, centrifugal and geometric) terms as the full model
(:meth:`exuflex.erls.model.ErlsModel.velocity_forces`). Like the paper, the time derivative of the
basis is left out of the velocities (``x' ~ H p'``): ``H`` changes with ``q`` only through the rotation
of the links, slowly against the elastic vibration.

State ``z = [p; p']`` with ``p = [q; u_m; eta]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .basis import CraigBampton, ReducedConfiguration

__all__ = ["ReducedModel", "ReducedMatrices"]


@dataclass(frozen=True)
class ReducedMatrices:
    rc: ReducedConfiguration
    WH: np.ndarray  # (N, r) nodal velocities per unit p'
    Mr: np.ndarray
    Kr: np.ndarray
    Cr: np.ndarray
    Gr: np.ndarray  # (r, n_motors) generalised forces of unit motor torques
    fr0: np.ndarray  # (r,) generalised gravity forces


class ReducedModel:
    """Reduced ERLS model on a :class:`CraigBampton` basis.

    Parameters
    ----------
    cb : CraigBampton
    """

    def __init__(self, cb: CraigBampton):
        self.cb = cb
        self.model = cb.model
        self.nq = cb.nq
        self.r = cb.r
        self.nx = 2 * cb.r
        self.names = cb.names
        self._z0 = None

    # ------------------------------------------------------------------ matrices
    def matrices(self, q, z0=None) -> ReducedMatrices:
        """Configuration-dependent reduced matrices at q."""
        model, cb = self.model, self.cb
        rc = cb.at(q, z0)
        cfg = rc.cfg
        H = rc.H
        WH = cfg.W @ H
        Mr = WH.T @ cfg.M_N @ WH
        Hu = H[self.nq :]
        T = model.T
        Kuu = T.T @ cfg.K_N @ T
        Kr = Hu.T @ Kuu @ Hu
        if model.alpha or model.beta:
            Muu = T.T @ cfg.M_N @ T
            Cr = model.alpha * (Hu.T @ Muu @ Hu) + model.beta * Kr
        else:
            Cr = np.zeros_like(Kr)
        Gr = WH.T @ model.B_N
        fr0 = WH.T @ (cfg.M_N @ model.g_N)
        return ReducedMatrices(rc, WH, Mr, Kr, Cr, Gr, fr0)

    def velocity_forces(self, mats: ReducedMatrices, p: np.ndarray, pd: np.ndarray) -> np.ndarray:
        """H^T h(H p, H p'): the full model's velocity-dependent forces, projected."""
        H = mats.rc.H
        return H.T @ self.model.velocity_forces(mats.rc.cfg, H @ p, H @ pd)

    def accelerations(self, p: np.ndarray, pd: np.ndarray, tau: np.ndarray, mats: ReducedMatrices | None = None):
        if mats is None:
            mats = self.matrices(p[: self.nq])
        F = mats.Gr @ tau + mats.fr0 - self.velocity_forces(mats, p, pd) - mats.Kr @ p - mats.Cr @ pd
        return np.linalg.solve(mats.Mr, F)

    def rhs(self, t: float, z: np.ndarray, tau: np.ndarray) -> np.ndarray:
        r = self.r
        return np.concatenate([z[r:], self.accelerations(z[:r], z[r:], tau)])

    # ------------------------------------------------------------------ states
    def full_state(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Full coordinates and velocities (x, v) = (H p, H p') of a reduced state."""
        r = self.r
        H = self.cb.at(z[: self.nq]).H
        return H @ z[:r], H @ z[r:]

    def reduce_state(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The reduced state closest to a full state (masters exact, eta by mass-weighted least squares)."""
        cb = self.cb
        rc = cb.at(x[: self.nq])
        M = self.model.mass(rc.cfg)
        H = rc.H
        A = H.T @ M @ H
        p = np.linalg.solve(A, H.T @ M @ x)
        pd = np.linalg.solve(A, H.T @ M @ v)
        nm = cb.n_m
        p[:nm], pd[:nm] = x[np.r_[0 : self.nq, self.nq + cb.im]], v[np.r_[0 : self.nq, self.nq + cb.im]]
        return np.concatenate([p, pd])

    def rest_state(self, q) -> np.ndarray:
        """Undeformed state at rest at q."""
        z = np.zeros(self.nx)
        z[: self.nq] = q
        return z

    def energy(self, z: np.ndarray) -> float:
        r = self.r
        mats = self.matrices(z[: self.nq])
        p, pd = z[:r], z[r:]
        return 0.5 * pd @ mats.Mr @ pd + 0.5 * p @ mats.Kr @ p

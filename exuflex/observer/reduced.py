"""The reduced flexible-multibody model as a discrete-time state-space model for the observers (eqs. 8-9).

State ``z = [p; p']`` with ``p = [q; u_m; eta]`` (:class:`exuflex.reduction.ReducedModel`); input the
measured motor torques, held over each measurement interval; output any of the mechanism's sensor
channels (encoders, curvature gauges, tip position) as the nonlinear functions of the state they are.

Step map over one interval ``dt`` (``n = dt / h`` RK4 sub-steps, ``h = 0.1 ms`` by default):

- ``method="cached"`` (fast; the observer's default): the configuration (pose, basis, reduced matrices and
  the velocity-dependent forces as explicit quadratic forms, :meth:`ReducedModel.force_model`) is
  evaluated only when q leaves ``refresh_rad`` (1e-2 rad) of the last evaluation; in between, ``M_r`` and
  ``K_r`` follow the links to first order in q (their q-derivatives are part of the evaluation) and the
  step map below is rebuilt from them whenever q moved by ``remap_rad`` (2e-3 rad). Measured on the
  six-bar's manoeuvre: estimates differ from ``frozen``'s by at most 12 % of the estimation error
  (RMS), at about a third of its cost (``tests/test_observer.py``).
- ``method="frozen"``: the configuration-dependent matrices ``M_r, K_r, C_r, G_r`` and the
  velocity-dependent forces are evaluated once at the start of the interval; the remaining linear
  system ``z' = A z + b`` is advanced by exactly what ``n`` RK4 steps would do,
  ``z_n = P^n z_0 + (sum_k P^k) Q b`` with ``P, Q`` the RK4 polynomials of ``h A`` (computed by
  repeated doubling, a few 26x26 products). The Jacobian of this step is ``F = P^n``.
- ``method="rk4"`` (reference): the paper's scheme, every RK4 stage with the matrices at its own state;
  ``F`` is the same linearisation about the interval start.

``F`` leaves out the derivatives of the configuration-dependent matrices with respect to ``q`` and of the
velocity forces with respect to the state (small on this time scale; the NEES test of the observer checks
that the covariance stays consistent).

Process noise: the measured torques carry white noise of std ``sigma`` (the motors' ``noise_std``),
held over the interval, so ``Q = L diag(sigma^2) L^T`` with ``L`` the interval's response to a unit
torque step (exact for the frozen system), plus an optional diagonal for unmodelled dynamics.

Measurement Jacobians: exact in ``p`` for every channel and in ``q`` for the rigid part (link angles,
rigid tip position); the dependence of the curvature and elastic-displacement rows on ``q`` is left out
(it is of the order of the measured elastic quantity per radian, far below the sensor noise).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..reduction import CraigBampton, ReducedModel
from ..reduction.model import ReducedMatrices
from .rows import sensor, sensor_rows

__all__ = ["ReducedObserverModel", "power_sum", "METHODS"]

METHODS = ("cached", "frozen", "rk4")


def power_sum(P: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``P^n`` and ``sum_{k<n} P^k`` by binary doubling (O(log n) products)."""
    m = P.shape[0]
    I = np.eye(m)
    Pk, Sk = P.copy(), I.copy()  # P^1, S_1 = I
    Pn, Sn = I.copy(), np.zeros((m, m))  # accumulators for n = 0
    bits = n
    while bits:
        if bits & 1:
            Sn = Sn + Pn @ Sk  # S_{a+b} = S_a + P^a S_b
            Pn = Pn @ Pk
        bits >>= 1
        if bits:
            Sk = Sk + Pk @ Sk
            Pk = Pk @ Pk
    return Pn, Sn


@dataclass
class _Interval:
    q0: np.ndarray
    mats: ReducedMatrices
    Pn: np.ndarray
    L: np.ndarray  # (nx, n_motors) response to a unit torque held over the interval
    Sz_theta: np.ndarray  # (n_links, nq) link-angle sensitivity at q0
    theta0: np.ndarray  # link angles at q0
    serial: int = 0  # identifies the interval in the measurement-row cache
    SQM: np.ndarray | None = None  # (nx, r) response to a unit generalised force held over the interval
    forces: object = None  # QuadraticForces at the held configuration (cached method)
    Q: np.ndarray | None = None
    dt: float = 0.0
    q_map: np.ndarray | None = None  # configuration of the current step map (cached method)


class ReducedObserverModel:
    """:class:`~exuflex.observer.base.DiscreteModel` of a reduced ERLS model.

    Parameters
    ----------
    reduced : ReducedModel or CraigBampton
    h : RK4 sub-step (s), default 1e-4 (the paper's).
    method : ``"cached"`` (fast), ``"frozen"`` or ``"rk4"`` (the paper's scheme, reference); see the module
        docstring. The observer session uses ``"cached"``.
    torque_std : std of the measured torques (N m) per motor; default the motors' ``noise_std``.
    q_extra : optional (nx,) diagonal added to Q per interval (unmodelled dynamics).
    """

    def __init__(self, reduced, h: float = 1e-4, method: str = "frozen", torque_std=None, q_extra=None,
                 refresh_rad: float = 1e-2, remap_rad: float = 2e-3):
        if isinstance(reduced, CraigBampton):
            reduced = ReducedModel(reduced)
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.rm = reduced
        self.model = reduced.model
        self.mech = self.model.mech
        self.nq = reduced.nq
        self.r = reduced.r
        self.nx = 2 * reduced.r
        self.h = float(h)
        self.method = method
        self.refresh_rad = float(refresh_rad)
        self.remap_rad = float(remap_rad)
        self.n_refresh = 0
        self.n_remap = 0
        sig = [m.noise_std for m in self.mech.motors] if torque_std is None else list(torque_std)
        self.torque_var = np.asarray(sig, float) ** 2
        self.q_extra = None if q_extra is None else np.asarray(q_extra, float)
        self._last: _Interval | None = None
        self._channel_cache: dict = {}
        self._serial = 0
        self.link_names = [lk.name for lk in self.mech.links]
        self.sensors = {s.name: s for s in self.mech.sensors}
        self.n_evaluations = 0

    def reset(self) -> None:
        """Forget the held interval and the cached measurement rows (a new run starts clean)."""
        self._last = None
        self._channel_cache = {}

    # ------------------------------------------------------------------ step
    def _step_maps(self, Minv, Kr, Cr, Gr, dt):
        """Pn, SQM (response to held generalised forces) and L (to held torques) of n RK4 steps of the
        linear system with these matrices."""
        r = self.r
        A = np.zeros((self.nx, self.nx))
        A[:r, r:] = np.eye(r)
        A[r:, :r] = -Minv @ Kr
        A[r:, r:] = -Minv @ Cr
        hA = self.h * A
        hA2 = hA @ hA
        hA3 = hA2 @ hA
        I = np.eye(self.nx)
        P = I + hA + hA2 / 2 + hA3 / 6 + hA3 @ hA / 24
        Qm = self.h * (I + hA / 2 + hA2 / 6 + hA3 / 24)
        n = int(round(dt / self.h))
        if n < 1 or abs(n * self.h - dt) > 1e-9 * dt:
            raise ValueError(f"measurement interval {dt:g} s is not a multiple of the RK4 step {self.h:g} s")
        Pn, Sn = power_sum(P, n)
        SQM = (Sn @ Qm[:, r:]) @ Minv
        return Pn, SQM, SQM @ Gr

    def _configuration(self, z: np.ndarray) -> _Interval:
        """Evaluate the configuration at the state z (reduced matrices, pose data); no step map yet."""
        mats = self.rm.matrices(z[: self.r], z[self.r :])
        self.n_evaluations += 1
        pose = mats.rc.cfg.pose
        self._serial += 1
        return _Interval(z[: self.nq].copy(), mats, None, None, pose.Sz[2::3].copy(), pose.z[2::3].copy(),
                         self._serial)

    def _interval(self, z: np.ndarray, u: np.ndarray, dt: float) -> tuple[_Interval, np.ndarray]:
        """The frozen step: configuration at the interval's start, its step map, and the state at the end."""
        iv = self._configuration(z)
        mats = iv.mats
        iv.Pn, iv.SQM, iv.L = self._step_maps(np.linalg.inv(mats.Mr), mats.Kr, mats.Cr, mats.Gr, dt)
        return iv, iv.Pn @ z + iv.L @ u + iv.SQM @ mats.fr

    def _cached_step(self, z: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """Configuration evaluated only when q leaves ``refresh_rad`` of the last one; in between, the
        stiffness follows the links to first order and the step map is rebuilt from it (cheap, 26x26);
        the state-dependent forces come from the held quadratic forms."""
        r, nq = self.r, self.nq
        iv = self._last
        if iv is None or iv.forces is None or np.max(np.abs(z[:nq] - iv.q0)) > self.refresh_rad or iv.dt != dt:
            iv = self._configuration(z)  # its step map is built just below
            iv.forces = self.rm.force_model(iv.mats, z[:r])
            iv.dt = dt
            self.n_refresh += 1
            self._last = iv
        if iv.q_map is None or np.max(np.abs(z[:nq] - iv.q_map)) > self.remap_rad:
            dK = iv.forces.stiffness_change(z[:nq])
            m = iv.mats
            Minv = np.linalg.inv(m.Mr + iv.forces.mass_change(z[:nq]))
            Pn, SQM, L = self._step_maps(Minv, m.Kr + dK, m.Cr + self.model.beta * dK, m.Gr, dt)
            iv.Pn, iv.SQM, iv.L = Pn, SQM, L
            iv.Q = (L * self.torque_var) @ L.T + (np.diag(self.q_extra) if self.q_extra is not None else 0.0)
            iv.q_map = z[:nq].copy()
            self.n_remap += 1
        return iv.Pn @ z + iv.L @ u + iv.SQM @ iv.forces(z[:r], z[r:])

    def step(self, x: np.ndarray, u, dt: float) -> tuple[np.ndarray, np.ndarray]:
        u = np.zeros(len(self.mech.motors)) if u is None else np.asarray(u, float)
        if self.method == "cached":
            return self._cached_step(np.asarray(x, float), u, dt), self._last.Pn
        iv, z_frozen = self._interval(x, u, dt)
        self._last = iv
        if self.method == "frozen":
            return z_frozen, iv.Pn
        z = np.array(x, float)
        n = int(round(dt / self.h))
        f, h = self.rm.rhs, self.h
        for k in range(n):
            k1 = f(0.0, z, u)
            k2 = f(0.0, z + h / 2 * k1, u)
            k3 = f(0.0, z + h / 2 * k2, u)
            k4 = f(0.0, z + h * k3, u)
            z = z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        return z, iv.Pn

    def process_noise(self, x: np.ndarray, u, dt: float) -> np.ndarray:
        iv = self._last
        if self.method == "cached" and iv is not None and iv.Q is not None:
            return iv.Q
        if iv is None or not np.array_equal(iv.q0, np.asarray(x)[: self.nq]):
            iv, _ = self._interval(np.asarray(x, float), np.zeros(len(self.mech.motors)) if u is None else u, dt)
        Q = (iv.L * self.torque_var) @ iv.L.T
        if self.q_extra is not None:
            Q = Q + np.diag(self.q_extra)
        return Q

    # ------------------------------------------------------------------ measurements
    def _rows(self, iv: _Interval, channel: str):
        """(rigid link angle combination or point, row in p) for a channel, cached per interval."""
        key = (iv.serial, channel)
        hit = self._channel_cache.get(key)
        if hit is not None:
            return hit
        if len(self._channel_cache) > 64:
            self._channel_cache = {k: v for k, v in self._channel_cache.items() if k[0] == iv.serial}
        s = sensor(self.mech, self.sensors, channel)
        kind, rigid, urow = sensor_rows(self.model, iv.mats.rc.cfg, s, self.link_names)
        out = (kind, rigid, urow @ iv.mats.rc.H[self.nq :])
        self._channel_cache[key] = out
        return out

    def measure(self, x: np.ndarray, channels: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, float)
        iv = self._last
        if iv is None or np.max(np.abs(x[: self.nq] - iv.q0)) > 1.5 * max(self.refresh_rad, 0.01):
            # no held configuration near x (first sample of a run): evaluate one at x
            iv = self._configuration(x)
            self._last = iv
        key = (iv.serial, tuple(channels))
        lin = self._channel_cache.get(key)
        if lin is None:
            lin = self._affine(iv, channels)
            self._channel_cache[key] = lin
        c0, Hm = lin
        return c0 + Hm @ x, Hm

    def _affine(self, iv: _Interval, channels: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """``y = c0 + Hm x`` for the channels, about the interval's configuration (rigid parts to first
        order in q, elastic parts exact in p)."""
        nq, r = self.nq, self.r
        c0 = np.zeros(len(channels))
        Hm = np.zeros((len(channels), self.nx))
        for i, ch in enumerate(channels):
            kind, rigid, prow = self._rows(iv, ch)
            Hm[i, :r] = prow
            if kind == "angle":
                row = rigid @ iv.Sz_theta
                c0[i] = rigid @ iv.theta0 - row @ iv.q0
                Hm[i, :nq] += row
            elif kind == "point":
                p0, Sp = rigid
                c0[i] = p0 - Sp @ iv.q0
                Hm[i, :nq] += Sp
        return c0, Hm

    # ------------------------------------------------------------------ physical states
    def initial_state(self, q, qd=None) -> np.ndarray:
        z = self.rm.rest_state(q)
        if qd is not None:
            z[self.r : self.r + self.nq] = qd
        return z

    def tip_rows(self, q, link: str, station: float) -> np.ndarray:
        """(2, r) map from p to the tip elastic displacement (global frame) at configuration q."""
        rc = self.rm.cb.at(q)
        return self.model.point_displacement_rows(rc.cfg, link, station) @ rc.H[self.nq :]

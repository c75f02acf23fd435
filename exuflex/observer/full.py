"""The full-order ERLS model as a discrete-time state-space model for the observers (the reference the
reduced observer is measured against).

State ``x = [q; u; q'; u']`` (:meth:`exuflex.erls.model.ErlsModel.rhs` layout, ``2 n`` entries); input
the measured motor torques, held over each measurement interval; output any of the mechanism's sensor
channels, as in :mod:`exuflex.observer.reduced` (which this module mirrors, with the identity as the
reduction basis).

Step map over one interval ``dt``: ``n = dt / h`` RK4 sub-steps of the full nonlinear ``ErlsModel.rhs``
(``h = 0.1 ms``, the paper's). Its Jacobian is taken from the linearisation frozen at the interval start,

``A = [[0, I], [-M^-1 K, -M^-1 (C + dh/dv)]]``, ``F = P^n``,

with ``P`` the RK4 polynomial of ``h A`` (what ``n`` RK4 steps do to the frozen linear system). ``F`` leaves
out the derivatives of the configuration-dependent matrices with respect to q (the reduced model now has
them, :mod:`exuflex.observer.reduced`; this comparison model is kept as it was measured).

Process noise: the measured torques carry white noise of std ``sigma`` (the motors' ``noise_std``)
held over the interval, ``Q = L diag(sigma^2) L^T`` with ``L = (sum_k P^k) Q_h [0; M^-1 W^T B]`` the
frozen system's response to a unit torque held over the interval.

Stability: the full model keeps the stiff axial modes that the reduction removes (about 4.5 kHz on the
six-bar, ``omega h`` near RK4's stability limit 2.83 at 0.1 ms); their Rayleigh damping keeps the
sub-steps stable here. :meth:`FullObserverModel.rk4_stability` reports RK4's amplification of the
decaying modes and the largest ``|h lambda|``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..erls.model import Configuration, ErlsModel
from ..erls.simulate import rk4_amplification, rk4_step
from .base import Measurement, Prediction
from .expansion import power_sum
from .rows import sensor, sensor_rows

__all__ = ["FullObserverModel"]

log = logging.getLogger(__name__)


@dataclass
class _Interval:
    q0: np.ndarray
    cfg: Configuration
    Pn: np.ndarray
    L: np.ndarray  # (nx, n_motors)
    Sz_theta: np.ndarray  # (n_links, nq)
    theta0: np.ndarray  # (n_links,)
    A: np.ndarray | None = None
    serial: int = 0


class FullObserverModel:
    """:class:`~exuflex.observer.base.DiscreteModel` of the full-order ERLS model.

    Parameters
    ----------
    model : ErlsModel
    h : RK4 sub-step (s), default 1e-4 (the paper's).
    torque_std : std of the measured torques (N m) per motor; default the motors' ``noise_std``.
    q_extra : optional (nx,) diagonal added to Q per interval.
    """

    def __init__(self, model: ErlsModel, h: float = 1e-4, torque_std=None, q_extra=None):
        self.model = model
        self.mech = model.mech
        self.n = model.n
        self.nq = model.nq
        self.nx = 2 * model.n
        self.h = float(h)
        sig = [m.noise_std for m in self.mech.motors] if torque_std is None else list(torque_std)
        self.torque_var = np.asarray(sig, float) ** 2
        self.q_extra = None if q_extra is None else np.asarray(q_extra, float)
        self.link_names = [lk.name for lk in self.mech.links]
        self.sensors = {s.name: s for s in self.mech.sensors}
        self._last: _Interval | None = None
        self._z = None  # last pose guess for the kinematics
        self._serial = 0
        self._rows_cache: dict = {}
        self.n_evaluations = 0

    # ------------------------------------------------------------------ step
    def _n_sub(self, dt: float) -> int:
        """Sub-steps over ``dt``, each at most ``h`` long (``dt / n`` each)."""
        return max(1, int(np.ceil(dt / self.h - 1e-9)))

    def _interval(self, x: np.ndarray, dt: float) -> _Interval:
        m, n, nq = self.model, self.n, self.nq
        cfg = m.configuration(x[:nq], self._z)
        self._z = cfg.pose.z
        self.n_evaluations += 1
        A, Minv = m.state_matrix(cfg, x[:n], x[n:])
        hA = (dt / self._n_sub(dt)) * A
        hA2 = hA @ hA
        hA3 = hA2 @ hA
        I = np.eye(self.nx)
        P = I + hA + hA2 / 2 + hA3 / 6 + hA3 @ hA / 24
        Qh = (dt / self._n_sub(dt)) * (I + hA / 2 + hA2 / 6 + hA3 / 24)
        Pn, Sn = power_sum(P, self._n_sub(dt))
        L = (Sn @ Qh)[:, n:] @ (Minv @ m.input_matrix(cfg))
        pose = cfg.pose
        self._serial += 1
        return _Interval(
            x[:nq].copy(), cfg, Pn, L, pose.Sz[2::3].copy(), pose.z[2::3].copy(), A, self._serial
        )

    def predict(self, x: np.ndarray, u, dt: float, u_next=None) -> Prediction:
        x = np.asarray(x, float)
        u = np.zeros(len(self.mech.motors)) if u is None else np.asarray(u, float)
        iv = self._interval(x, dt)
        self._last = iv
        z = x.copy()
        n_sub = self._n_sub(dt)
        f, h = self.model.rhs, dt / n_sub
        for k in range(n_sub):
            z = rk4_step(f, k * h, z, h, u)
        Q = (iv.L * self.torque_var) @ iv.L.T
        if self.q_extra is not None:
            Q = Q + np.diag(self.q_extra)
        return Prediction(z, iv.Pn, Q)

    def rk4_stability(self, x: np.ndarray) -> tuple[float, float]:
        """RK4 stability of the linearisation at ``x``: ``(max |R(h lambda)|, max |h lambda|)``.

        ``R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24`` is RK4's amplification per sub-step; the maximum is over
        the eigenvalues ``lambda`` of ``A`` with ``Re lambda <= 0`` (modes that do not grow physically), so a
        value above 1 means the sub-step makes a decaying mode grow. RK4 is stable on the imaginary axis up
        to ``|h lambda| = 2.83``.
        """
        lam = np.linalg.eigvals(self._interval(np.asarray(x, float), 10 * self.h).A)
        R = rk4_amplification(self.h * lam[lam.real <= 0])
        return float(np.max(np.abs(R))), float(np.max(np.abs(self.h * lam)))

    # ------------------------------------------------------------------ measurements
    def _rows(self, iv: _Interval, channel: str):
        key = (iv.serial, channel)
        hit = self._rows_cache.get(key)
        if hit is not None:
            return hit
        if len(self._rows_cache) > 64:
            self._rows_cache = {k: v for k, v in self._rows_cache.items() if k[0] == iv.serial}
        s = sensor(self.mech, self.sensors, channel)
        out = sensor_rows(self.model, iv.cfg, s, self.link_names)
        self._rows_cache[key] = out
        return out

    def measure(self, x: np.ndarray, channels: Sequence[str]) -> Measurement:
        x = np.asarray(x, float)
        iv = self._last
        if iv is None:
            iv = self._interval(x, 10 * self.h)
            self._last = iv
        nq, n = self.nq, self.n
        dq = x[:nq] - iv.q0
        y = np.empty(len(channels))
        H = np.zeros((len(channels), self.nx))
        for i, ch in enumerate(channels):
            kind, rigid, urow = self._rows(iv, ch)
            y[i] = urow @ x[nq:n]
            H[i, nq:n] = urow
            if kind == "angle":
                y[i] += rigid @ (iv.theta0 + iv.Sz_theta @ dq)
                H[i, :nq] += rigid @ iv.Sz_theta
            elif kind == "point":
                p0, Sp = rigid
                y[i] += p0 + Sp @ dq
                H[i, :nq] += Sp
        return Measurement(y, H)

    # ------------------------------------------------------------------ physical states
    def initial_state(self, q, qd=None) -> np.ndarray:
        x = np.zeros(self.nx)
        x[: self.nq] = q
        if qd is not None:
            x[self.n : self.n + self.nq] = qd
        return x

"""Manoeuvres: time laws, path planning by exact inverse kinematics, and rigid computed torque.

The paper (Sec. 4.1) drives the mechanism along a 3 s semicircle of the tip under *open-loop computed
torque from the rigid-body model*. This module turns a :class:`~exuflex.mechanism.Manoeuvre` into

- a :class:`Plan`: the ERLS coordinates ``q(t)`` and their exact rates ``q'(t)``, ``q''(t)`` on a
  uniform time grid (:func:`plan`);
- the motor torques of the rigid inverse dynamics along the plan (:func:`computed_torque`).

Time laws map ``t`` in ``[0, T]`` to the path parameter ``s`` in ``[0, 1]`` (:func:`time_law`);
before 0 and after ``T`` the law holds ``s`` at 0 or 1 with zero rates.

Path kinds
----------
``tip_arc``
    The point ``tip`` follows ``p(s) = centre + radius [cos phi, sin phi]`` with
    ``phi = phi_start + (phi_end - phi_start) s``; the coordinates named in ``rules`` follow
    ``q = start + (end - start) s``; the remaining coordinates (as many as the tip has components,
    two) come from inverse kinematics: Newton's method on the ERLS closure ``Phi(z, q) = 0`` together
    with the tip equations ``p_tip(z) = p(s)``, unknowns the link poses ``z`` and the free ``q``.
``joint``
    Every coordinate follows its rule.

Rates are exact (no finite differences): with the tip Jacobian ``J = dp_tip/dq`` (from
:meth:`Kinematics.point`), ``J q' = p_s s'`` and ``J q'' = p_ss s'^2 + p_s s'' - (dJ/dt) q'``, where
``(dJ/dt) q'`` follows from :meth:`Kinematics.rates`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lu_factor, lu_solve

from .erls.kinematics import Kinematics, KinematicsError
from .erls.model import ErlsModel
from .mechanism import Manoeuvre, Mechanism

__all__ = ["TIME_LAWS", "ActuationError", "Plan", "computed_torque", "plan", "time_law"]

log = logging.getLogger(__name__)

TIME_LAWS = ("trapezoid", "quintic", "cycloidal")


class ActuationError(ValueError):
    """The motors cannot produce the generalised forces the plan needs (rank-deficient input matrix)."""


# ---------------------------------------------------------------------------------------- time laws
def time_law(
    law: str, t, duration: float, ramp_time: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Path parameter ``s(t)`` in [0, 1] and its rates ``s'``, ``s''``.

    Parameters
    ----------
    law : {"trapezoid", "quintic", "cycloidal"}
        ``trapezoid``: trapezoidal velocity profile, constant acceleration during ``ramp_time`` at both
        ends, constant speed ``1 / (T - ramp_time)`` in between (``s''`` jumps at the ramp ends; the
        value at a jump is the one of the later phase).
        ``quintic``: ``s = 10 tau^3 - 15 tau^4 + 6 tau^5`` (zero velocity and acceleration at both ends).
        ``cycloidal``: ``s = tau - sin(2 pi tau) / (2 pi)`` (zero velocity and acceleration at both ends).
    t : float or array
        Time (s). Outside ``[0, duration]`` the law is at rest at s = 0 or 1.
    duration : float
        ``T`` (s), positive.
    ramp_time : float
        Acceleration time of the trapezoid (s), in ``(0, T/2]``; ignored by the other laws.

    Returns
    -------
    s, sd, sdd : arrays shaped like ``t``
    """
    if law not in TIME_LAWS:
        raise ValueError(f"time law must be one of {list(TIME_LAWS)}, got {law!r}")
    if not duration > 0:
        raise ValueError(f"time law duration must be positive, got {duration}")
    t = np.asarray(t, float)
    T = float(duration)
    tc = np.clip(t, 0.0, T)
    inside = (t >= 0.0) & (t <= T)
    if law == "trapezoid":
        ta = float(ramp_time)
        if not 0.0 < ta <= T / 2:
            raise ValueError(f"trapezoid ramp_time must be in (0, duration/2 = {T / 2:g}] s, got {ta}")
        v = 1.0 / (T - ta)
        a = v / ta
        # at a jump the later phase's value (as documented): the ramps are [0, ta) and [T - ta, T], so a
        # sample grid through T - ta sees the deceleration start at that sample, as it sees the cruise at ta
        acc = tc < ta
        dec = tc >= T - ta
        s = np.where(
            acc,
            0.5 * a * tc**2,
            np.where(dec, 1.0 - 0.5 * a * (T - tc) ** 2, 0.5 * a * ta**2 + v * (tc - ta)),
        )
        sd = np.where(acc, a * tc, np.where(dec, a * (T - tc), v))
        sdd = np.where(acc, a, np.where(dec, -a, 0.0))
    elif law == "quintic":
        u = tc / T
        s = u**3 * (10 - 15 * u + 6 * u**2)
        sd = 30 * u**2 * (1 - u) ** 2 / T
        sdd = 60 * u * (1 - u) * (1 - 2 * u) / T**2
    else:  # cycloidal
        u = tc / T
        w = 2 * np.pi
        s = u - np.sin(w * u) / w
        sd = (1 - np.cos(w * u)) / T
        sdd = w * np.sin(w * u) / T**2
    sd = np.where(inside, sd, 0.0)
    sdd = np.where(inside, sdd, 0.0)
    return s, sd, sdd


# ---------------------------------------------------------------------------------------- planning
@dataclass(frozen=True)
class Plan:
    """A planned motion on a uniform grid: time-first arrays, columns named by ``names``."""

    t: np.ndarray  # (n_t,)
    q: np.ndarray  # (n_t, nq)
    qd: np.ndarray  # (n_t, nq)
    qdd: np.ndarray  # (n_t, nq)
    names: tuple[str, ...] = ()  # coordinate names
    s: np.ndarray | None = None  # (n_t,) path parameter

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0]) if len(self.t) > 1 else 0.0


def _arc(man: Manoeuvre, s, sd, sdd):
    """Tip target p, and dp/dt, d2p/dt2 from the arc and the time law."""
    c = np.asarray(man.centre, float)[:, None]
    R = float(man.radius)
    dphi = float(man.phi_end - man.phi_start)
    phi = man.phi_start + dphi * s
    e = np.array([np.cos(phi), np.sin(phi)])
    et = np.array([-np.sin(phi), np.cos(phi)])
    p = c + R * e
    p_s = R * dphi * et
    p_ss = -R * dphi**2 * e
    return p, p_s * sd, p_ss * sd**2 + p_s * sdd


class _TipIK:
    """Newton on the closure plus the tip equations; unknowns the link poses z and the free coordinates.

    The same augmented Jacobian ``A = [[Phi_z, -E_free], [P_z, 0]]`` gives the exact rates:
    ``A [z'; q'_free] = [E_ruled q'_ruled; p']`` and
    ``A [z''; q''_free] = [E_ruled q''_ruled - (dPhi_z/dt) z'; p'' - (dP_z/dt) z']``.
    """

    def __init__(self, kin: Kinematics, man: Manoeuvre, free: list[int], ruled: list[int]):
        self.kin, self.free, self.ruled = kin, free, ruled
        self.li = kin.link_names.index(man.tip.link)
        self.st = man.tip.station
        self.scale = max(lk.length for lk in kin.mech.links)
        self.nz = 3 * kin.nl

    def tip(self, z):
        i, s = self.li, self.st
        return np.array([z[3 * i] + s * np.cos(z[3 * i + 2]), z[3 * i + 1] + s * np.sin(z[3 * i + 2])])

    def jacobian(self, z) -> np.ndarray:
        kin, i, nz = self.kin, self.li, self.nz
        J = np.zeros((kin.n_eq + 2, nz + len(self.free)))
        J[: kin.n_eq, :nz] = kin.jacobian(z)
        J[: kin.n_eq, nz:] = -kin._E[:, self.free]  # dPhi/dq = -E
        th = z[3 * i + 2]
        J[kin.n_eq :, 3 * i : 3 * i + 2] = np.eye(2)
        J[kin.n_eq :, 3 * i + 2] = self.st * np.array([-np.sin(th), np.cos(th)])
        return J

    def _fail(self, p, msg):
        kin = self.kin
        return KinematicsError(
            f"{kin.mech.source or kin.mech.name}: inverse kinematics {msg} for tip target {p.round(6).tolist()}"
            " (is the path reachable, away from singular configurations?)"
        )

    def solve(
        self, q_guess: np.ndarray, z_guess: np.ndarray, p: np.ndarray, tol: float = 1e-13, max_iter: int = 30
    ):
        kin, nz = self.kin, self.nz
        q = q_guess.copy()
        z = z_guess.copy()
        for it in range(max_iter):
            res = np.concatenate([kin.residual(z, q), self.tip(z) - p])
            if it > 0 and np.max(np.abs(res)) < tol * self.scale:
                return q, z
            try:
                dx = np.linalg.solve(self.jacobian(z), -res)
            except np.linalg.LinAlgError:
                raise self._fail(p, "is singular") from None
            z = z + dx[:nz]
            q[self.free] += dx[nz:]
        res = np.concatenate([kin.residual(z, q), self.tip(z) - p])
        if np.max(np.abs(res)) < 1e3 * tol * self.scale:
            return q, z
        raise self._fail(p, f"did not converge (residual {np.max(np.abs(res)):.3g})")

    def rates(self, z, qd_r, qdd_r, pd, pdd):
        """Exact (q'_free, q''_free) at the solved pose z."""
        kin, nz, i = self.kin, self.nz, self.li
        lu = lu_factor(self.jacobian(z))
        E_r = kin._E[:, self.ruled]
        sol = lu_solve(lu, np.concatenate([E_r @ qd_r, pd]))
        zd, qd_f = sol[:nz], sol[nz:]
        th, thd = z[3 * i + 2], zd[3 * i + 2]
        tip_bias = -self.st * thd**2 * np.array([np.cos(th), np.sin(th)])
        rhs = np.concatenate([E_r @ qdd_r - kin._jacobian_rate(z, zd) @ zd, pdd - tip_bias])
        return qd_f, lu_solve(lu, rhs)[nz:]


def plan(
    mech: Mechanism,
    manoeuvre: Manoeuvre | None = None,
    dt: float = 1e-4,
    *,
    t_end: float | None = None,
    q_guess=None,
    progress: Callable[[float], None] | None = None,
) -> Plan:
    """Plan the manoeuvre: q, q', q'' on the grid ``t = 0, dt, ..., t_end``.

    Parameters
    ----------
    mech : Mechanism
    manoeuvre : Manoeuvre, optional
        Defaults to ``mech.manoeuvre``.
    dt : float
        Grid step (s).
    t_end : float, optional
        Last time (s); defaults to the manoeuvre's duration. Beyond the duration the plan is at rest.
    q_guess : array, optional
        Starting guess of q for the first inverse-kinematics solve (selects the assembly branch);
        defaults to ``mech.q_ref`` with the ruled coordinates at their start values.
    progress : callable, optional
        Called with the fraction done.

    Returns
    -------
    Plan
    """
    man = manoeuvre if manoeuvre is not None else mech.manoeuvre
    src = mech.source or mech.name
    if man is None:
        raise ValueError(f"{src}: the model has no [manoeuvre] and none was given")
    if not dt > 0:
        raise ValueError(f"plan: dt must be positive, got {dt}")
    t_end = man.duration if t_end is None else float(t_end)
    n = round(t_end / dt) + 1
    t = np.arange(n) * dt
    s, sd, sdd = time_law(man.time_law, t, man.duration, man.ramp_time)
    names = mech.coordinate_names
    nq = len(names)
    ruled = {names.index(c): (a, b) for c, a, b in man.rules}
    kin = Kinematics(mech)
    q = np.empty((n, nq))
    qd = np.empty((n, nq))
    qdd = np.empty((n, nq))
    idx = np.array(sorted(ruled))
    if len(idx):
        a = np.array([ruled[k][0] for k in idx])
        b = np.array([ruled[k][1] for k in idx])
        q[:, idx] = a + np.outer(s, b - a)
        qd[:, idx] = np.outer(sd, b - a)
        qdd[:, idx] = np.outer(sdd, b - a)
    report = max(1, n // 100)
    if man.kind == "joint":
        if len(ruled) != nq:
            raise ValueError(f"{src}: a 'joint' manoeuvre needs one rule per coordinate {list(names)}")
        for k in range(n):  # check assembly along the way (raises KinematicsError)
            if k % max(1, n // 50) == 0 or k == n - 1:
                kin.pose(q[k])
        if progress is not None:
            progress(1.0)
        return Plan(t, q, qd, qdd, names, s)
    if man.kind != "tip_arc":
        raise ValueError(f"{src}: manoeuvre kind must be 'tip_arc' or 'joint', got {man.kind!r}")
    free = [k for k in range(nq) if k not in ruled]
    if len(free) != 2:
        raise ValueError(
            f"{src}: a 'tip_arc' manoeuvre needs exactly 2 coordinates without rules (the tip has 2 components); "
            f"free: {[names[k] for k in free]}"
        )
    p, pd, pdd = _arc(man, s, sd, sdd)
    ik = _TipIK(kin, man, free, list(idx))
    qg = np.array(q_guess if q_guess is not None else (mech.q_ref or np.zeros(nq)), float)
    if len(idx):
        qg[idx] = q[0, idx]
    z = kin.pose(qg).z
    qk = qg
    for k in range(n):
        qk = qk.copy()
        if len(idx):
            qk[idx] = q[k, idx]
        if k > 0:  # predict the free coordinates from the last rates
            qk[free] += qd[k - 1, free] * dt + 0.5 * qdd[k - 1, free] * dt**2
        qk, z = ik.solve(qk, z, p[:, k])
        q[k] = qk
        qd[k, free], qdd[k, free] = ik.rates(z, qd[k, idx], qdd[k, idx], pd[:, k], pdd[:, k])
        if progress is not None and ((k + 1) % report == 0 or k == n - 1):
            progress((k + 1) / n)
    # the end configurations must be regular (the loop itself stays on the branch by continuation)
    for k in (0, n - 1):
        kin.pose(q[k])
    return Plan(t, q, qd, qdd, names, s)


# ---------------------------------------------------------------------------------------- inverse dynamics
def computed_torque(
    mech: Mechanism,
    plan: Plan,
    *,
    model: ErlsModel | None = None,
    progress: Callable[[float], None] | None = None,
) -> np.ndarray:
    """Open-loop motor torques from the rigid-body inverse dynamics along ``plan``.

    The ERLS model with the elastic displacements and rates held at zero (``u = u' = 0``) is the rigid
    mechanism with the full mass distribution (consistent beam masses plus lumped masses). Its q rows of
    eq. 2 give, at every time,

    ``M_qq(q) q'' + h_q(q, q') - (W^T M_N g)_q = (W^T B)_q tau``.

    With as many independent motors as coordinates the system is solved exactly; with more motors the
    minimum-norm least-squares torques are returned.

    Parameters
    ----------
    mech : Mechanism
        Its masses (including the nominal payload) define the model the controller knows.
    plan : Plan
    model : ErlsModel, optional
        Reuse an existing model of ``mech``.

    Returns
    -------
    tau : (n_t, n_motors) array, columns in ``mech.motor_names`` order (N m)

    Raises
    ------
    ActuationError
        If the motors cannot actuate every coordinate (``rank (W^T B)_q < nq``).
    """
    model = model if model is not None else ErlsModel(mech)
    nq, n = model.nq, model.n
    nm = len(mech.motors)
    tau = np.empty((len(plan.t), nm))
    x = np.zeros(n)
    v = np.zeros(n)
    zero_tau = np.zeros(nm)
    report = max(1, len(plan.t) // 100)
    for k in range(len(plan.t)):
        x[:nq] = plan.q[k]
        v[:nq] = plan.qd[k]
        cfg = model.configuration(plan.q[k])
        M = model.mass(cfg)[:nq, :nq]
        h = model.velocity_forces(cfg, x, v)[:nq]
        g = model.generalized_forces(cfg, zero_tau)[:nq]  # gravity only
        A = model.input_matrix(cfg)[:nq]
        b = M @ plan.qdd[k] + h - g
        if k == 0:
            rank = np.linalg.matrix_rank(A)
            if rank < nq:
                raise ActuationError(
                    f"{mech.source or mech.name}: the motors {list(mech.motor_names)} actuate only {rank} of the "
                    f"{nq} coordinates {list(mech.coordinate_names)}; computed torque needs rank {nq}"
                )
        tau[k] = np.linalg.solve(A, b) if nm == nq else np.linalg.lstsq(A, b, rcond=None)[0]
        if progress is not None and ((k + 1) % report == 0 or k == len(plan.t) - 1):
            progress((k + 1) / len(plan.t))
    return tau

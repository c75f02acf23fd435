"""Manoeuvres: time laws, path planning by exact inverse kinematics, and rigid computed torque.

The paper (Sec. 4.1) drives the mechanism along a 3 s semicircle of the tip under *open-loop computed
torque from the rigid-body model*. This module turns a :class:`~exuflex.mechanism.Manoeuvre` into

- a :class:`Plan`: the ERLS coordinates ``q(t)`` and their exact rates ``q'(t)``, ``q''(t)`` on a
  uniform time grid (:func:`plan`);
- the motor torques of the rigid inverse dynamics along the plan (:func:`computed_torque`), evaluated
  link by link with the link poses' motion, all time points at once.

Time laws map ``t`` in ``[0, T]`` to the path parameter ``s`` in ``[0, 1]`` (:func:`time_law`);
before 0 and after ``T`` the law holds ``s`` at 0 or 1 with zero rates.

Path kinds
----------
``tip_arc``, ``tip_line``, ``tip_polyline``
    The point ``tip`` follows the path: ``p(s) = centre + radius [cos phi, sin phi]`` with
    ``phi = phi_start + (phi_end - phi_start) s``, or the polyline's segments one after the other, each with
    the time law over its share of the duration (resting at every corner); the coordinates named in ``rules``
    follow ``q = start + (end - start) s``; the remaining coordinates (as many as the tip has components,
    two) come from inverse kinematics: Newton's method on the ERLS closure ``Phi(z, q) = 0`` together
    with the tip equations ``p_tip(z) = p``, unknowns the link poses ``z`` and the free ``q``.
``joint``
    Every coordinate follows its rule.
``waypoints``
    Every coordinate through its waypoints: quintic segments resting at each, or a C2 cubic spline resting at
    both ends.
``trajectory``
    Samples of every coordinate, or of the tip and the other coordinates (inverse kinematics as for the tip
    paths): quintic Hermite through values, rates and accelerations where given, else a C2 cubic spline.
``torque``
    Measured torques (:func:`torque_table`); the plan is rest at the starting configuration.

The closure is solved along the whole path in batches (:func:`_solve_path`): point by point on a coarse
subset, then every other point at once from an interpolated start.

Rates are exact (no finite differences): with the tip Jacobian ``J = dp_tip/dq`` (from
:meth:`Kinematics.point`), ``J q' = p_s s'`` and ``J q'' = p_ss s'^2 + p_s s'' - (dJ/dt) q'``, where
``(dJ/dt) q'`` follows from :meth:`Kinematics.rates`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .erls.kinematics import Kinematics, KinematicsError
from .erls.model import ErlsModel
from .mechanism import Manoeuvre, Mechanism, ModelFileError
from .mechanism.loader import position_columns

__all__ = ["KINDS", "TIME_LAWS", "ActuationError", "Plan", "computed_torque", "open_loop_torque", "plan",
           "start_configuration", "time_law", "torque_table", "trajectory_csv", "write_trajectory"]

log = logging.getLogger(__name__)

TIME_LAWS = ("trapezoid", "quintic", "cycloidal")
KINDS = ("joint", "tip_arc", "tip_line", "tip_polyline", "waypoints", "trajectory", "torque")


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
    z: np.ndarray | None = None  # (n_t, 3 n_links) link poses x, y, angle of the rigid mechanism
    zd: np.ndarray | None = None  # (n_t, 3 n_links) their rates
    zdd: np.ndarray | None = None  # (n_t, 3 n_links) their accelerations

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


class _PathIK:
    """Newton on the closure plus the path equations, batched over time points.

    Unknowns per point: the link poses ``z`` and the free coordinates ``q_f``; equations: the closure
    ``Phi(z, q) = 0`` (with the other coordinates given) and, for a tip path, ``p_tip(z) = p``. The
    augmented Jacobian ``A = [[Phi_z, -E_f], [P_z, 0]]`` also gives the exact rates:
    ``A [z'; q_f'] = [E_r q_r'; p']`` and ``A [z''; q_f''] = [E_r q_r'' - (dPhi_z/dt) z'; p'' - (dP_z/dt) z']``
    (``E_r``, ``E_f``: the columns of ``E = -dPhi/dq`` of the given and free coordinates). Without a tip
    path and free coordinates, these are the closure and its rates alone.
    """

    def __init__(self, kin: Kinematics, free: list[int], tip: tuple[int, float] | None):
        self.kin = kin
        self.free = np.asarray(free, dtype=int)
        self.given = np.array([k for k in range(kin.nq) if k not in set(free)], dtype=int)
        self.tip = tip
        self.nz = 3 * kin.nl
        self.nf = len(free)
        self.n_eq = kin.n_eq + (2 if tip is not None else 0)
        if self.n_eq != self.nz + self.nf:
            raise ValueError(f"{self.n_eq} path equations for {self.nz + self.nf} unknowns")
        self.scale = kin.newton_scale

    def point(self, z: np.ndarray) -> np.ndarray:
        i, st = self.tip
        return np.stack([z[:, 3 * i] + st * np.cos(z[:, 3 * i + 2]), z[:, 3 * i + 1] + st * np.sin(z[:, 3 * i + 2])], 1)

    def residual(self, z: np.ndarray, q: np.ndarray, p: np.ndarray | None) -> np.ndarray:
        r = self.kin.residual(z, q)
        return r if self.tip is None else np.concatenate([r, self.point(z) - p], axis=1)

    def jacobian(self, z: np.ndarray) -> np.ndarray:
        kin, nz, ne = self.kin, self.nz, self.kin.n_eq
        J = np.zeros((len(z), self.n_eq, nz + self.nf))
        J[:, :ne, :nz] = kin.jacobian(z)
        J[:, :ne, nz:] = -kin._E[:, self.free]  # dPhi/dq = -E
        if self.tip is not None:
            i, st = self.tip
            th = z[:, 3 * i + 2]
            J[:, ne, 3 * i] = 1.0
            J[:, ne + 1, 3 * i + 1] = 1.0
            J[:, ne, 3 * i + 2] = -st * np.sin(th)
            J[:, ne + 1, 3 * i + 2] = st * np.cos(th)
        return J

    def newton(self, z, q, p, tol: float = 1e-13, max_iter: int = 30):
        """Newton from ``(z, q)`` at every point at once (at least one step, then until the residual is below
        ``tol`` times the longest link). Returns ``z, q, ok``; ``ok`` False where it did not converge or the
        Jacobian is singular."""
        z, q = z.copy(), q.copy()
        nz, free = self.nz, self.free
        todo = np.arange(len(z))
        lim = tol * self.scale
        for it in range(max_iter + 1):
            res = self.residual(z[todo], q[todo], None if p is None else p[todo])
            if it > 0:
                keep = ~(np.max(np.abs(res), axis=1) < lim)
                todo, res = todo[keep], res[keep]
            if not len(todo) or it == max_iter:
                break
            try:
                dx = np.linalg.solve(self.jacobian(z[todo]), -res[:, :, None])[:, :, 0]
            except np.linalg.LinAlgError:
                dx = np.full((len(todo), self.n_eq), np.nan)  # which one is singular: the caller's fallback
            z[todo] += dx[:, :nz]
            if self.nf:
                q[todo[:, None], free] += dx[:, nz:]
        ok = np.ones(len(z), bool)
        if len(todo):  # the last iterate is good enough if near the tolerance (as a single solve would accept)
            res = self.residual(z[todo], q[todo], None if p is None else p[todo])
            ok[todo] = np.max(np.abs(res), axis=1) < 1e3 * lim
        ok &= np.all(np.isfinite(z), axis=1)
        return z, q, ok

    def rates(self, z, qd, qdd, pd, pdd):
        """Exact ``z', z''`` and the free columns of ``q', q''`` (written into ``qd``, ``qdd``) at the solved poses."""
        kin, nz, g = self.kin, self.nz, self.given
        A = self.jacobian(z)
        E_g = kin._E[:, g]
        rhs = qd[:, g] @ E_g.T
        if self.tip is not None:
            rhs = np.concatenate([rhs, pd], axis=1)
        sol = np.linalg.solve(A, rhs[:, :, None])[:, :, 0]
        zd = sol[:, :nz]
        qd[:, self.free] = sol[:, nz:]
        rhs = qdd[:, g] @ E_g.T - kin.jacobian_rate_product(z, zd)
        if self.tip is not None:
            i, st = self.tip
            th, thd = z[:, 3 * i + 2], zd[:, 3 * i + 2]
            bias = -st * thd[:, None] ** 2 * np.stack([np.cos(th), np.sin(th)], 1)
            rhs = np.concatenate([rhs, pdd - bias], axis=1)
        sol = np.linalg.solve(A, rhs[:, :, None])[:, :, 0]
        qdd[:, self.free] = sol[:, nz:]
        return zd, sol[:, :nz]

    def fail(self, t: float, p: np.ndarray | None, msg: str) -> KinematicsError:
        kin = self.kin
        what = f"tip target {p.round(6).tolist()}" if p is not None else "the planned coordinates"
        return KinematicsError(
            f"{kin.mech.source or kin.mech.name}: inverse kinematics {msg} at t = {t:.6g} s for {what}"
            " (is the path reachable, away from singular configurations?)"
        )


def _hermite(t0, t1, y0, y1, d0, d1, t):
    """Cubic Hermite interpolation between (t0, y0, y0') and (t1, y1, y1') at times t (rows)."""
    h = (t1 - t0)[:, None]
    u = (t[:, None] - t0[:, None]) / h
    h00 = (1 + 2 * u) * (1 - u) ** 2
    h10 = u * (1 - u) ** 2
    h01 = u**2 * (3 - 2 * u)
    h11 = u**2 * (u - 1)
    return h00 * y0 + h10 * h * d0 + h01 * y1 + h11 * h * d1


# coarse points at most this far apart (grid points) are solved one after the other; the rest in one batch
_COARSE_POINTS = 200
_CHUNK = 2048  # points per batched solve


# largest closure-Jacobian condition number (1-norm) allowed along a planned path: the configuration check's
# (:func:`exuflex.validate.check_configurations`); the gallery's paths stay below 30
PATH_COND_MAX = 1e6


def _solve_path(ik: _PathIK, t, q, qd, qdd, p, pd, pdd, q0: np.ndarray, progress=None):
    """Fill the free columns of ``q, q', q''`` and return the link motion ``z, z', z''`` along the path.

    Continuation as a single sequential solve would do it, at a fraction of the cost: Newton point after
    point (each started from the last point's Taylor prediction) on a coarse subset of at most
    :data:`_COARSE_POINTS` grid points, then Newton at every other point at once (batched), started from the
    cubic Hermite interpolation of the coarse solutions and their exact rates. A point whose batched Newton
    fails, or which does not continue its predecessor (the trapezoidal rule over the step, violated by a change
    of assembly branch), is solved from its predecessor instead, as a sequential solve would, and so on until
    the path rejoins the batch's.
    """
    kin, nz, free = ik.kin, ik.nz, ik.free
    n = len(t)
    has_p = p is not None
    stride = max(1, -(-(n - 1) // _COARSE_POINTS))
    coarse = np.unique(np.r_[np.arange(0, n, stride), n - 1])
    z = np.empty((n, nz))
    zd = np.empty((n, nz))
    zdd = np.empty((n, nz))
    solved = np.zeros(n, bool)

    def sequential(ks, qk, zk, prev):
        """Solve the points ``ks`` in order, each from the prediction of the point ``prev`` before it."""
        for k in ks:
            qk = q[k].copy()
            if prev is not None:
                h = t[k] - t[prev]
                qk[free] = q[prev, free] + qd[prev, free] * h + 0.5 * qdd[prev, free] * h**2
                zk = z[prev] + zd[prev] * h + 0.5 * zdd[prev] * h**2
            else:
                qk[free] = q0[free]
            pk = p[k : k + 1] if has_p else None
            zs, qs, ok = ik.newton(zk[None], qk[None], pk)
            if not ok[0]:
                bad = np.max(np.abs(ik.residual(zs, qs, pk))) if np.all(np.isfinite(zs)) else np.nan
                raise ik.fail(t[k], None if pk is None else pk[0],
                              "is singular" if not np.isfinite(bad) else f"did not converge (residual {bad:.3g})")
            q[k] = qs[0]
            z[k] = zs[0]
            zd[k : k + 1], zdd[k : k + 1] = ik.rates(z[k : k + 1], qd[k : k + 1], qdd[k : k + 1],
                                                     pd[k : k + 1] if has_p else None,
                                                     pdd[k : k + 1] if has_p else None)
            solved[k] = True
            prev = k
        return prev

    z_start = kin.pose(np.where(np.isin(np.arange(kin.nq), free), q0, q[0])).z
    sequential(coarse[:1], None, z_start, None)
    prev = coarse[0]
    for k in coarse[1:]:
        try:
            prev = sequential([k], None, None, prev)
        except KinematicsError:  # too far for one step: every grid point in between, as a sequential solve
            prev = sequential(range(prev + 1, k + 1), None, None, prev)
    if progress is not None:
        progress(0.3)
    rest = np.flatnonzero(~solved)
    for c0 in range(0, len(rest), _CHUNK):  # in chunks: the batched arrays stay in cache
        r = rest[c0 : c0 + _CHUNK]
        right = np.searchsorted(coarse, r)  # the coarse points around each remaining point
        k0, k1 = coarse[right - 1], coarse[right]
        tt = t[r]
        zg = _hermite(t[k0], t[k1], z[k0], z[k1], zd[k0], zd[k1], tt)
        qg = q[r].copy()
        qg[:, free] = _hermite(t[k0], t[k1], q[k0][:, free], q[k1][:, free], qd[k0][:, free], qd[k1][:, free], tt)
        zs, qs, ok = ik.newton(zg, qg, p[r] if has_p else None)
        qdr, qddr = qd[r], qdd[r]
        z[r], q[r] = zs, qs
        zd[r], zdd[r] = ik.rates(zs, qdr, qddr, pd[r] if has_p else None, pdd[r] if has_p else None)
        qd[r], qdd[r] = qdr, qddr
        solved[r] = ok
    # every point must continue its predecessor: the trapezoidal rule over a step, z_k - z_k-1 = (z'_k-1 + z'_k) h / 2,
    # holds to h^2 |z''| / 8 (z'' may jump), a change of assembly branch breaks it; such points and those whose
    # Newton failed are solved from their predecessor, one after the other, until the path rejoins the batch
    k = 1
    while k < n:
        j = np.arange(k, min(n, k + _CHUNK))
        h = (t[j] - t[j - 1])[:, None]
        gap = np.abs(z[j] - z[j - 1] - 0.5 * h * (zd[j] + zd[j - 1]))
        bad = ~solved[j] | np.any(gap > 0.5 * h**2 * (np.abs(zdd[j]) + np.abs(zdd[j - 1])) + 1e-9, axis=1)
        if not bad.any():
            k = j[-1] + 1
            continue
        k = j[np.argmax(bad)]
        sequential([k], None, None, k - 1)
        k += 1
    if progress is not None:
        progress(0.9)
    # the path's equations must be regular at every point: a toggle position between two coarse points (a rocker
    # stretched in line with its coupler, a slider-crank's dead centre under a slider path) passes continuation but
    # gives the truth unbounded rates, and so does an open chain's reach limit under a tip path (the arm stretched
    # out): the closure's Jacobian, with the tip equations and the free coordinates where the path has them
    if len(z) and z.shape[1] and nz:
        A = ik.jacobian(z) if (ik.tip is not None or ik.nf) else kin.jacobian(z)
        cond = np.linalg.cond(A, 1)
        bad = np.flatnonzero(~(cond <= PATH_COND_MAX))
        if len(bad):
            k = int(bad[np.argmax(cond[bad])]) if np.all(np.isfinite(cond[bad])) else int(bad[0])
            src = kin.mech.source or kin.mech.name
            raise KinematicsError(
                f"{src}: the manoeuvre's path reaches a singular configuration at t = {t[k]:.6g} s, q = "
                f"{np.round(q[k], 6).tolist()} (path Jacobian condition number {cond[k]:.3g} > {PATH_COND_MAX:.0e}; "
                f"{len(bad)} grid point(s) from t = {t[bad[0]]:.6g} to {t[bad[-1]]:.6g} s): change the manoeuvre or "
                "the geometry to stay away from it")
    return z, zd, zdd


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
        With the link motion ``z, z', z''`` that :func:`computed_torque` uses.
    """
    man = manoeuvre if manoeuvre is not None else mech.manoeuvre
    src = mech.source or mech.name
    if man is None:
        raise ValueError(f"{src}: the model has no [manoeuvre] and none was given")
    src = man.source or src
    if not dt > 0:
        raise ValueError(f"plan: dt must be positive, got {dt}")
    if man.kind not in KINDS:
        raise ModelFileError(src, "manoeuvre.kind", f"one of {list(KINDS)}", man.kind)
    t_end = man.duration if t_end is None else float(t_end)
    n = round(t_end / dt) + 1
    t = np.arange(n) * dt
    names = mech.coordinate_names
    nq = len(names)
    kin = Kinematics(mech)
    kin.compiled = False  # its few single solves need no compiled kernels (nor their loading time)
    q = np.zeros((n, nq))
    qd = np.zeros((n, nq))
    qdd = np.zeros((n, nq))
    given: set[int] = set()
    p = pd = pdd = None
    q0 = np.array(q_guess if q_guess is not None else (mech.q_ref or np.zeros(nq)), float)
    if man.kind in ("waypoints", "trajectory", "torque"):
        s = np.clip(t / man.duration, 0.0, 1.0)
    else:
        s, sd, sdd = time_law(man.time_law, t, man.duration, man.ramp_time)
    if man.kind == "torque":  # no planned motion: rest at the starting configuration
        q[:] = np.asarray(man.q0, float) if man.q0 else q0
        given = set(range(nq))
    elif man.kind == "waypoints":
        q[:], qd[:], qdd[:] = _waypoints(man, t)
        given = set(range(nq))
    elif man.kind == "trajectory":
        cols, y, yd, ydd = _trajectory(man, names, t)
        for j, c in enumerate(cols):
            if c in names:
                k = names.index(c)
                q[:, k], qd[:, k], qdd[:, k] = y[:, j], yd[:, j], ydd[:, j]
                given.add(k)
        if "tip_x" in cols:
            j = [cols.index("tip_x"), cols.index("tip_y")]
            p, pd, pdd = y[:, j], yd[:, j], ydd[:, j]
    else:
        for c, a, b in man.rules:
            k = names.index(c)
            q[:, k], qd[:, k], qdd[:, k] = a + (b - a) * s, (b - a) * sd, (b - a) * sdd
            given.add(k)
        if man.kind == "tip_arc":
            p, pd, pdd = (x.T for x in _arc(man, s, sd, sdd))
        elif man.kind in ("tip_line", "tip_polyline"):
            p, pd, pdd = _polyline(man, t, src)
    free = [k for k in range(nq) if k not in given]
    if p is None and free:
        raise ModelFileError(src, "manoeuvre.rules", f"one rule per coordinate {list(names)} (a {man.kind!r} "
                             "manoeuvre)", [names[k] for k in sorted(given)])
    if p is not None and len(free) != 2:
        raise ModelFileError(src, "manoeuvre.rules", f"exactly 2 coordinates without rules (the tip has 2 "
                             f"components; a {man.kind!r} manoeuvre on {list(names)}); free", [names[k] for k in free])
    tip = None if p is None else (kin.link_names.index(man.tip.link), man.tip.station)
    ik = _PathIK(kin, free, tip)
    z, zd, zdd = _solve_path(ik, t, q, qd, qdd, p, pd, pdd, q0, progress)
    if progress is not None:
        progress(1.0)
    return Plan(t, q, qd, qdd, names, s, z, zd, zdd)


# ---------------------------------------------------------------------------------------- paths and samples
_QUINTIC = np.array([  # quintic Hermite basis on u in [0, 1]: coefficients of u^0..u^5 of the weights of
    [1, 0, 0, -10, 15, -6],  # y0
    [0, 1, 0, -6, 8, -3],  # h y0'
    [0, 0, 0.5, -1.5, 1.5, -0.5],  # h^2 y0''
    [0, 0, 0, 0.5, -1, 0.5],  # h^2 y1''
    [0, 0, 0, -4, 7, -3],  # h y1'
    [0, 0, 0, 10, -15, 6],  # y1
], float)


def start_configuration(mech: Mechanism) -> np.ndarray:
    """The configuration an observer starts from: the planned manoeuvre's first (the model's ``q_ref`` without a
    manoeuvre, or where the plan fails, with a warning)."""
    if mech.manoeuvre is not None:
        try:
            p = plan(mech, dt=mech.manoeuvre.duration, t_end=0.0)
            return np.asarray(p.q[0], float)
        except Exception as exc:  # noqa: BLE001 - fall back to q_ref, with a note
            log.warning("could not plan the manoeuvre's start (%s); starting the observer at q_ref", exc)
    return np.asarray(mech.q_ref, float)


def _hermite5(ts, Y, dY, ddY, t):
    """Piecewise quintic Hermite interpolation of samples ``(ts, Y, Y', Y'')`` (rows) at times ``t``: the
    values, rates and accelerations, exact at the samples and continuous (C2) between them. Beyond the last
    sample the last value at rest."""
    ts = np.asarray(ts, float)
    i = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 2)
    h = (ts[i + 1] - ts[i])[:, None]
    u = np.clip((t - ts[i]) / h[:, 0], 0.0, 1.0)
    P = np.stack([u**k for k in range(6)], 1)
    dP = np.stack([k * u ** max(k - 1, 0) if k else np.zeros_like(u) for k in range(6)], 1)
    ddP = np.stack([k * (k - 1) * u ** max(k - 2, 0) if k > 1 else np.zeros_like(u) for k in range(6)], 1)
    terms = (Y[i], h * dY[i], h**2 * ddY[i], h**2 * ddY[i + 1], h * dY[i + 1], Y[i + 1])
    y = sum((P @ c)[:, None] * v for c, v in zip(_QUINTIC, terms, strict=True))
    yd = sum((dP @ c)[:, None] * v for c, v in zip(_QUINTIC, terms, strict=True)) / h
    ydd = sum((ddP @ c)[:, None] * v for c, v in zip(_QUINTIC, terms, strict=True)) / h**2
    after = t > ts[-1]
    y[after], yd[after], ydd[after] = Y[-1], 0.0, 0.0
    return y, yd, ydd


def _spline(ts, Y, t, bc_type):
    """C2 cubic spline through the samples (rows of Y) at times t; the last sample at rest beyond it."""
    from scipy.interpolate import CubicSpline

    ts = np.asarray(ts, float)
    sp = CubicSpline(ts, Y, axis=0, bc_type=bc_type)
    tc = np.minimum(t, ts[-1])
    y, yd, ydd = sp(tc), sp(tc, 1), sp(tc, 2)
    # at a sample's own time the sample itself: the piecewise polynomial's value there can differ by an ulp
    # (which piece evaluates a knot depends on the SciPy version)
    k = np.clip(np.searchsorted(ts, tc), 0, len(ts) - 1)
    on = ts[k] == tc
    if np.ndim(tc) == 0:
        y = np.asarray(Y, float)[k].copy() if on else y
    else:
        y[on] = np.asarray(Y, float)[k[on]]
    after = t > ts[-1]
    yd[after], ydd[after] = 0.0, 0.0
    return y, yd, ydd


def _waypoints(man: Manoeuvre, t):
    """q, q', q'' through the waypoints: quintic segments resting at every waypoint, or a C2 cubic spline with
    zero rates at both ends (``clamped``)."""
    W = np.asarray(man.waypoints, float)
    if man.interpolation == "spline":
        return _spline(man.times, W, t, "clamped")
    zero = np.zeros_like(W)
    return _hermite5(man.times, W, zero, zero, t)


def _trajectory(man: Manoeuvre, names, t):
    """The position columns of a trajectory's samples and their values, rates and accelerations at t: quintic
    Hermite through the samples' values, rates (``d<name>``) and accelerations (``dd<name>``) if the file
    gives them (exact at the samples, so a plan written with its rates reads back equal), else a C2 cubic
    spline through the values (not-a-knot ends)."""
    cols = list(man.columns)
    pos = position_columns(cols, names)
    S = np.asarray(man.samples, float)
    ts = S[:, 0]
    col = {c: j + 1 for j, c in enumerate(cols)}
    Y = S[:, [col[c] for c in pos]]
    if all("d" + c in col for c in pos):  # the loader admits rates only with accelerations
        dY = S[:, [col["d" + c] for c in pos]]
        ddY = S[:, [col["dd" + c] for c in pos]]
        y, yd, ydd = _hermite5(ts, Y, dY, ddY, t)
    else:
        y, yd, ydd = _spline(ts, Y, t, "not-a-knot")
    return pos, y, yd, ydd


def _polyline(man: Manoeuvre, t, src: str):
    """Tip target p, p', p'' along the polyline: segment j runs during its share of the duration (in
    proportion to its length) with the time law, resting at both ends: ``p = P_0 + sum_j (P_j+1 - P_j)
    s(t - T_j; d_j)``."""
    P = np.asarray(man.points, float)
    seg = np.diff(P, axis=0)
    L = np.hypot(seg[:, 0], seg[:, 1])
    d = man.duration * L / L.sum()
    T0 = np.r_[0.0, np.cumsum(d)[:-1]]
    if man.time_law == "trapezoid" and man.ramp_time > d.min() / 2:
        raise ModelFileError(src, "manoeuvre.ramp_time", f"at most half the shortest segment's "
                             f"time {d.min():g} s (segments share the duration in proportion to their lengths)",
                             man.ramp_time)
    p = np.tile(P[0], (len(t), 1))
    pd = np.zeros((len(t), 2))
    pdd = np.zeros((len(t), 2))
    for j in range(len(seg)):
        s, sd, sdd = time_law(man.time_law, t - T0[j], d[j], man.ramp_time)
        p += np.outer(s, seg[j])
        pd += np.outer(sd, seg[j])
        pdd += np.outer(sdd, seg[j])
    return p, pd, pdd


def torque_table(mech: Mechanism, man: Manoeuvre, t) -> np.ndarray:
    """The measured torques of a ``torque`` manoeuvre at times t: (n_t, n_motors) in ``mech.motor_names`` order,
    linear between the samples, the last sample held beyond them."""
    if man.kind != "torque":
        raise ValueError(f"{mech.source or mech.name}: a torque table needs a 'torque' manoeuvre, got {man.kind!r}")
    S = np.asarray(man.samples, float)
    cols = list(man.columns)
    return np.stack([np.interp(t, S[:, 0], S[:, 1 + cols.index(m)]) for m in mech.motor_names], axis=1)


def open_loop_torque(mech: Mechanism, plan: Plan, manoeuvre: Manoeuvre | None = None, **kwargs) -> np.ndarray:
    """The motor torques that drive the manoeuvre open loop on ``plan.t``: the measured torques of a ``torque``
    manoeuvre (:func:`torque_table`), else the rigid computed torque along the plan (:func:`computed_torque`,
    ``kwargs`` passed to it)."""
    man = manoeuvre if manoeuvre is not None else mech.manoeuvre
    if man is not None and man.kind == "torque":
        return torque_table(mech, man, plan.t)
    return computed_torque(mech, plan, **kwargs)


def trajectory_csv(plan: Plan, *, rates: bool = True) -> str:
    """A plan as the text of a trajectory CSV (``t``, the coordinates, and with ``rates`` their ``d<name>`` and
    ``dd<name>``), every number in full precision: a ``trajectory`` manoeuvre of it plans the same q, q', q''
    on the same grid."""
    names = list(plan.names)
    header = ["t"] + names + ([f"d{c}" for c in names] + [f"dd{c}" for c in names] if rates else [])
    data = np.hstack([plan.t[:, None], plan.q] + ([plan.qd, plan.qdd] if rates else []))
    return ",".join(header) + "\n" + "".join(",".join(repr(float(v)) for v in row) + "\n" for row in data)


def write_trajectory(path, plan: Plan, *, rates: bool = True) -> None:
    """Write :func:`trajectory_csv` of ``plan`` to ``path``."""
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(trajectory_csv(plan, rates=rates))


# ---------------------------------------------------------------------------------------- inverse dynamics
def _link_bodies(model: ErlsModel, q: np.ndarray, z: np.ndarray):
    """Rigid-body mass properties of every link about its origin, in its own frame: mass ``m``, first moment
    ``(S_x, S_y)`` and moment of inertia ``J`` (each (n_links,)), from the model's nodal mass matrix.

    With ``u = 0`` the nodal coordinates are ``r(z)`` with ``G = dr/dz``; the kinetic energy
    ``z'^T G^T M_N G z' / 2`` is a sum over links of ``w^T P w / 2``, ``w = [R^T v_origin; omega]``,
    ``P = [[m, 0, -S_y], [0, m, S_x], [-S_y, S_x, J]]`` constant in the link frame (element and lumped masses
    rotate with their link). ``P`` is read off ``G^T M_N G`` at the configuration ``q`` (poses ``z``) and rotated
    into the link frame.
    """
    kin = model.kin
    cfg = model.configuration(q, z0=z)
    zc = cfg.pose.z
    li, st = kin.node_link, kin.node_station
    th = zc[2::3][li]
    nn, nl = len(li), kin.nl
    G = np.zeros((3 * nn, 3 * nl))
    k = np.arange(nn)
    G[3 * k, 3 * li] = 1.0
    G[3 * k + 1, 3 * li + 1] = 1.0
    G[3 * k, 3 * li + 2] = -st * np.sin(th)
    G[3 * k + 1, 3 * li + 2] = st * np.cos(th)
    G[3 * k + 2, 3 * li + 2] = 1.0
    Mz = G.T @ cfg.M_N @ G
    m, Sx, Sy, J = (np.empty(nl) for _ in range(4))
    for i in range(nl):
        c, s = np.cos(zc[3 * i + 2]), np.sin(zc[3 * i + 2])
        R3 = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        P = R3.T @ Mz[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] @ R3
        m[i], Sx[i], Sy[i], J[i] = P[0, 0], P[1, 2], -P[0, 2], P[2, 2]
        if abs(P[1, 1] - P[0, 0]) > 1e-9 * P[0, 0] or abs(P[0, 1]) > 1e-9 * P[0, 0]:
            raise ValueError(f"{model.mech.source or model.mech.name}: link {kin.link_names[i]!r}: its nodal masses "
                             f"are not a rigid body's (translational mass matrix {P[:2, :2].round(12).tolist()})")
    return m, Sx, Sy, J


def _link_forces(kin: Kinematics, z: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Generalised forces ``G(z)^T f`` on the link poses of constant nodal loads ``f`` (N, c): (n_t, 3 n_links, c)."""
    li, st = kin.node_link, kin.node_station
    L = np.zeros((kin.nl, len(li)))
    L[li, np.arange(len(li))] = 1.0  # sums over each link's nodes
    fx, fy, ft = f[0::3], f[1::3], f[2::3]
    th = z[:, 2::3, None]
    out = np.empty((len(z), 3 * kin.nl, f.shape[1]))
    out[:, 0::3] = L @ fx
    out[:, 1::3] = L @ fy
    out[:, 2::3] = L @ ft - np.sin(th) * (L @ (st[:, None] * fx)) + np.cos(th) * (L @ (st[:, None] * fy))
    return out


def _rigid_rows(mech: Mechanism, model: ErlsModel, bodies, z, zd, zdd):
    """``b = S_z^T Q_z`` (n_t, nq) and ``A = S_z^T G^T B`` (n_t, nq, n_motors) of the rigid inverse dynamics
    (:func:`computed_torque`) at the link motions ``z, z', z''``."""
    kin = model.kin
    m, Sx, Sy, J = bodies
    th, w, al = z[:, 2::3], zd[:, 2::3], zdd[:, 2::3]
    c, s = np.cos(th), np.sin(th)
    Sgx, Sgy = c * Sx - s * Sy, s * Sx + c * Sy
    ax = zdd[:, 0::3] - mech.gravity[0]
    ay = zdd[:, 1::3] - mech.gravity[1]
    rhs = np.empty((len(z), 3 * kin.nl, 1 + len(mech.motors)))
    rhs[:, 0::3, 0] = m * ax - al * Sgy - w**2 * Sgx
    rhs[:, 1::3, 0] = m * ay + al * Sgx - w**2 * Sgy
    rhs[:, 2::3, 0] = J * al + Sgx * ay - Sgy * ax
    rhs[:, :, 1:] = _link_forces(kin, z, model.B_N)
    Y = kin._E.T @ np.linalg.solve(np.swapaxes(kin.jacobian(z), 1, 2), rhs)  # S_z^T [Q_z, G^T B]
    return Y[:, :, 0], Y[:, :, 1:]


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

    They are evaluated link by link: each link is a rigid body (mass properties from the model's nodal mass,
    :func:`_link_bodies`) whose Newton-Euler forces on its pose ``z = (x, y, theta)`` follow from the plan's
    link motion ``z, z', z''``,

    ``Q_x = m a_x - theta'' S_gy - theta'^2 S_gx``, ``Q_y = m a_y + theta'' S_gx - theta'^2 S_gy``,
    ``Q_theta = J theta'' + S_gx a_y - S_gy a_x``,

    with ``a`` the origin's acceleration less gravity and ``S_g = R(theta) S`` the first moment in the global
    frame; the coordinates' share is ``S_z^T Q_z = E^T Phi_z^-T Q_z`` (virtual power, ``z' = S_z q'``), and the
    motors' ``S_z^T G^T B`` alike. All time points at once (batched solves).

    With as many independent motors as coordinates the system is solved exactly; with more motors the
    minimum-norm least-squares torques are returned.

    Parameters
    ----------
    mech : Mechanism
        Its masses (including the nominal payload) define the model the controller knows.
    plan : Plan
        A plan without the link motion (built by hand) has it solved from its ``q, q', q''``.
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
    if model is None:
        model = ErlsModel(mech)
        model.compiled = model.kin.compiled = False  # one configuration: no compiled kernels (nor their loading)
    kin = model.kin
    nq = model.nq
    nm = len(mech.motors)
    if plan.z is None or plan.zd is None or plan.zdd is None:
        q, qd, qdd = plan.q.copy(), plan.qd.copy(), plan.qdd.copy()
        z, zd, zdd = _solve_path(_PathIK(kin, [], None), plan.t, q, qd, qdd, None, None, None, q[0])
    else:
        z, zd, zdd = plan.z, plan.zd, plan.zdd
    if progress is not None:
        progress(0.2)
    bodies = _link_bodies(model, plan.q[0], z[0])
    tau = np.empty((len(z), nm))
    for c0 in range(0, len(z), _CHUNK):  # in chunks: the batched arrays stay in cache
        c = slice(c0, c0 + _CHUNK)
        b, A = _rigid_rows(mech, model, bodies, z[c], zd[c], zdd[c])
        if c0 == 0:
            rank = np.linalg.matrix_rank(A[0])
            if rank < nq:
                raise ActuationError(
                    f"{mech.source or mech.name}: the motors {list(mech.motor_names)} actuate only {rank} of the "
                    f"{nq} coordinates {list(mech.coordinate_names)}; computed torque needs rank {nq}"
                )
        tau[c] = np.linalg.solve(A, b[:, :, None])[:, :, 0] if nm == nq else (np.linalg.pinv(A) @ b[:, :, None])[:, :, 0]
    if progress is not None:
        progress(1.0)
    return tau

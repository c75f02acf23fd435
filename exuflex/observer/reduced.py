"""The reduced flexible-multibody model as a discrete-time state-space model for the observers (eqs. 8-9).

State ``z = [p; p']`` with ``p = [q; u_m; eta]`` (:class:`exuflex.reduction.ReducedModel`); input the
measured motor torques, held over each measurement interval; output any of the mechanism's sensor
channels (encoders, curvature gauges, tip position) as the nonlinear functions of the state they are.

Step map over one interval ``dt`` (``n = dt / h`` RK4 sub-steps, ``h = 0.1 ms`` by default):

- ``method="cached"`` (fast; the observer's default): the configuration (pose, basis, reduced matrices, the
  velocity-dependent forces as explicit quadratic forms and the q-gradients of ``M_r`` and ``K_r``,
  :meth:`ReducedModel.held`) is evaluated only when q leaves a refresh radius around the held one. In
  between, the model follows the links: ``M_r`` and ``K_r`` to second order in q (gradients at the held
  configuration, their change since the previous one along the line joining the two), damping, input
  matrix, forces and sensor rows along that secant to first order; every interval is then advanced by its
  RK4 steps with the matrices at the interval's start (compiled, :mod:`.held`). The radius adapts like an
  ODE step size: at each evaluation the previous held model's prediction of ``M_r`` and ``K_r`` is compared
  with the exact ones, and the next radius keeps that error near ``refresh_tol`` (3e-2, relative in the
  mass metric; radius within 2e-3 .. 4e-2 rad). A new configuration is evaluated ``lookahead`` (0.8) radii
  ahead of q along its motion, since the held model serves as well behind its centre as ahead of it. The
  Jacobian and process noise are rebuilt when q moved by ``remap_rad`` (2e-3 rad) from where they were
  built, ``remap_ahead`` (1.0) remap radii ahead of q along its motion (:func:`.held.map_lookahead`): a map
  then serves twice the path for the same largest and mean distance, 251 rebuilds in 3 s instead of 442,
  with estimates as close to ``frozen``'s (mean over 10 noise seeds of the worst quantity's RMS difference
  over the RMS estimation error 0.078, against 0.077 with the maps built at q). Measured on the
  six-bar's 3 s manoeuvre (``tests/test_observer.py``): 29 evaluations instead of 1500 (45 without the
  look-ahead, 39 with a whole radius, where the centre often ends up too far ahead), estimates within 5 %
  of the estimation error of ``frozen``'s (RMS, worst quantity dq3). A fixed radius does not work: the
  prediction error over 2e-2 rad falls from 0.6 at the start of the manoeuvre to 5e-3 later, and a
  first-order ``M_r`` held over 2e-2 rad loses positive definiteness there.
- ``method="frozen"``: the configuration-dependent matrices ``M_r, K_r, C_r, G_r`` and the
  velocity-dependent forces are evaluated once at the start of the interval; the remaining linear
  system ``z' = A z + b`` is advanced by exactly what ``n`` RK4 steps would do,
  ``z_n = P^n z_0 + (sum_k P^k) Q b`` with ``P, Q`` the RK4 polynomials of ``h A`` (computed by
  repeated doubling, a few 26x26 products).
- ``method="rk4"`` (reference): the paper's scheme, every RK4 stage with the matrices at its own state;
  ``F`` is the same linearisation about the interval start.

Jacobian (every method): ``F = P^n + SQM dF/dz``: the held linear system's map plus the response to the
change of the held generalised forces with the start state (the velocity-dependent forces, exactly, and
``M_r``, ``K_r`` through their q-gradients), see :meth:`ReducedObserverModel._jacobian`. ``P^n`` alone let the
filter diverge in the start-up transient on some noise realisations.

Process noise: the measured torques carry white noise of std ``sigma`` (the motors' ``noise_std``),
held over the interval, so ``Q = L diag(sigma^2) L^T`` with ``L`` the interval's response to a unit
torque step (exact for the frozen system), plus an optional diagonal for unmodelled dynamics. A torque jump
between two samples (two successive samples differing by more than their noise, :meth:`input_jump`) adds the mean
and covariance of its effect at an unknown instant of the interval (:meth:`input_jump_moments`).

Measurement Jacobians: exact in ``p`` for every channel and in ``q`` for the rigid part (link angles,
rigid tip position); the dependence of the curvature and elastic-displacement rows on ``q`` is left out
(it is of the order of the measured elastic quantity per radian, far below the sensor noise).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from ..erls.kinematics import KinematicsError
from ..reduction import CraigBampton, ReducedModel
from ..reduction.model import ReducedMatrices
from .fused import DONE, REFRESH, cached_run, cached_sample, pack_arguments
from .fused import warm_up as fused_warm_up
from .held import (
    HAVE_NUMBA,
    held_step_loops,
    held_step_numpy,
    held_system_loops,
    held_system_numpy,
    map_lookahead,
    power_sum,
    prediction_error,
    prediction_error_loops,
    step_jacobian_loops,
    step_maps,
    step_maps_held,
    step_maps_held_numpy,
)
from .held import warm_up as held_warm_up
from .rows import channel_rows, sensor

__all__ = ["METHODS", "ReducedObserverModel", "power_sum"]

METHODS = ("cached", "frozen", "rk4")


def _max_abs(v: np.ndarray) -> float:
    """max |v_i| of a short vector (a few coordinates: cheaper in Python than two NumPy reductions)."""
    return max(map(abs, v.tolist()))


def _secant_factor(iv: _Interval, dl: np.ndarray) -> float:
    """``s = (dl . d) / (d . d)``: how far along the secant to the previous held configuration q has moved.

    Zero (first order only) without a partner or when q moves away from the secant's line (cosine below
    0.7): the secant's differences then say nothing about the change, and extrapolating them along a
    different direction is what broke the filter during the start-up transient, where the estimate jitters
    in every direction while it converges."""
    if iv.old is None:
        return 0.0
    a = float(dl @ iv.d)
    n2 = float(dl @ dl)
    if a * a < 0.49 * n2 * iv.dd:
        return 0.0
    return a / iv.dd


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
    Ca: np.ndarray | None = None  # C_r - beta K_r at the held configuration (cached method)
    old: _Interval | None = None  # secant partner: the previous held configuration (cached method)
    d: np.ndarray | None = None  # q0 - old.q0
    dd: float = 0.0  # d . d
    rad: float = 0.0  # refresh radius while held (cached method)
    err: float = float("nan")  # prediction error of the previous held model at q0 (cached method)
    kargs: tuple | None = None  # held arguments of the step kernel (cached method)
    fused: tuple | None = None  # (channels, fixed arguments of the fused sample kernel) (cached method)


class ReducedObserverModel:
    """:class:`~exuflex.observer.base.DiscreteModel` of a reduced ERLS model.

    Parameters
    ----------
    reduced : ReducedModel or CraigBampton
    h : RK4 sub-step (s), default 1e-4 (the paper's).
    method : ``"cached"`` (fast), ``"frozen"`` or ``"rk4"`` (the paper's scheme, reference); see the module
        docstring. The observer session uses ``"cached"``.
    refresh_tol, refresh_min, refresh_rad : error target and radius limits (rad) of the cached method's
        configuration evaluations; remap_rad : when its Jacobian and process noise are rebuilt;
        lookahead : how many radii ahead of q along its motion a new configuration is evaluated (0: at q);
        remap_ahead, remap_horizon : how many remap radii ahead of q along its motion, but no further than
        its motion over ``remap_horizon`` seconds, the Jacobian and process noise are built (0: at q).
    kernel : ``"numba"`` (compiled cached step), ``"numpy"`` (its reference twin) or ``"auto"``.

    Attributes
    ----------
    full_jacobian : bool
        ``F = Pn + SQM dF/dz`` (default, see :meth:`_jacobian`) or the held system's ``Pn`` alone.
    n_refresh, n_remap, n_rescue : counters of configuration evaluations, step-map rebuilds and evaluations
        forced by a held mass matrix that lost positive definiteness.
    torque_std : std of the measured torques (N m) per motor; default the motors' ``noise_std``.
    jump_p : false-alarm probability per interval of the torque-jump test (:meth:`input_jump`); None: no test.
    q_extra : optional (nx,) diagonal added to Q per interval (unmodelled dynamics).
    """

    def __init__(self, reduced, h: float = 1e-4, method: str = "frozen", torque_std=None, q_extra=None,
                 refresh_rad: float = 4e-2, remap_rad: float = 2e-3, kernel: str = "auto",
                 refresh_tol: float = 3e-2, refresh_min: float = 2e-3, lookahead: float = 0.8,
                 jump_p: float | None = None, remap_ahead: float = 1.0, remap_horizon: float = 0.02):
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
        self.refresh_tol = float(refresh_tol)
        self.refresh_min = float(refresh_min)
        self.n_rescue = 0
        self.full_jacobian = True
        self.lookahead = float(lookahead)
        self.remap_rad = float(remap_rad)
        self.remap_ahead = float(remap_ahead)
        self.remap_horizon = float(remap_horizon)
        self.n_refresh = 0
        self.n_remap = 0
        sig = [m.noise_std for m in self.mech.motors] if torque_std is None else list(torque_std)
        self.torque_var = np.asarray(sig, float) ** 2
        self.q_extra = None if q_extra is None else np.asarray(q_extra, float)
        self.jump_p = jump_p
        nu = len(self.mech.motors)
        self._jump_threshold = math.inf if jump_p is None else float(chi2.ppf(1.0 - jump_p, nu))
        self._step_matrices = None
        self._last: _Interval | None = None
        self._channel_cache: dict = {}
        self._serial = 0
        self.link_names = [lk.name for lk in self.mech.links]
        self.sensors = {s.name: s for s in self.mech.sensors}
        self.n_evaluations = 0
        if kernel not in ("auto", "numba", "numpy"):
            raise ValueError(f"kernel must be 'auto', 'numba' or 'numpy', got {kernel!r}")
        if kernel == "numba" and not HAVE_NUMBA:
            raise ValueError("kernel='numba' needs the numba package (pip install numba)")
        self.kernel_name = "numba" if (kernel == "numba" or (kernel == "auto" and HAVE_NUMBA)) else "numpy"
        self.kernel = held_step_loops if self.kernel_name == "numba" else held_step_numpy
        if self.kernel_name == "numba" and method == "cached":
            held_warm_up()
        self._noC2 = np.zeros((0, self.r))
        self._noQ = np.zeros(0)
        self._channel_rows: dict = {}  # configuration-independent parts of the sensor rows, per channel tuple
        self._noRows = np.zeros((0, self.nx))
        self.fused = self.kernel_name == "numba"
        self._u_shape = (len(self.mech.motors),)
        self.n_declined = 0
        if self.fused and method == "cached":
            fused_warm_up()
        if method == "cached":  # compile (or load) the evaluation's kernels now, not in a run's first interval
            z = self.rm.rest_state(np.asarray(self.rm.cb.q_star, float))
            self.rm.held(z[: self.r], z[self.r :])
            self.model.kin.reset_warm_start()

    def reset(self) -> None:
        """Forget the held interval, the cached measurement rows and the closure solver's warm start (a new run
        starts clean: its estimates do not depend on what the model evaluated before, e.g. in a study worker)."""
        self._last = None
        self._channel_cache = {}
        self.model.kin.reset_warm_start()

    # ------------------------------------------------------------------ step
    def _n_steps(self, dt: float) -> int:
        n = int(round(dt / self.h))
        if n < 1 or abs(n * self.h - dt) > 1e-9 * dt:
            raise ValueError(f"measurement interval {dt:g} s is not a multiple of the RK4 step {self.h:g} s")
        return n

    def _step_maps(self, Minv, Kr, Cr, Gr, dt):
        """Pn, SQM (response to held generalised forces) and L (to held torques) of n RK4 steps of the
        linear system with these matrices."""
        return step_maps(Minv, Kr, Cr, Gr, self.h, self._n_steps(dt))

    def _configuration(self, z: np.ndarray, held: bool = False, frozen_forces: bool = False) -> _Interval:
        """Evaluate the configuration at the state z (reduced matrices, pose data); no step map yet. With
        ``held`` also the force model and the q-derivatives of the cached step; with ``frozen_forces`` the
        forces at z and their force model without q-derivatives (the frozen step and its Jacobian)."""
        forces = None
        if held:
            mats, forces = self.rm.held(z[: self.r], z[self.r :])
        elif frozen_forces:
            mats, forces = self.rm.held(z[: self.r], z[self.r :], fr=True, gradients=False)
        else:
            mats = self.rm.matrices(z[: self.r], z[self.r :])
        self.n_evaluations += 1
        pose = mats.rc.cfg.pose
        self._serial += 1
        return _Interval(z[: self.nq].copy(), mats, None, None, pose.Sz[2::3].copy(), pose.z[2::3].copy(),
                         self._serial, forces=forces)

    def _interval(self, z: np.ndarray, u: np.ndarray, dt: float, jacobian: bool = False) -> tuple[_Interval, np.ndarray]:
        """The frozen step: configuration at the interval's start, its step map, and the state at the end
        (with ``jacobian`` the force model for :meth:`_jacobian`, from the same evaluation)."""
        iv = self._configuration(z, frozen_forces=jacobian)
        mats = iv.mats
        iv.Pn, iv.SQM, iv.L = self._step_maps(np.linalg.inv(mats.Mr), mats.Kr, mats.Cr, mats.Gr, dt)
        return iv, iv.Pn @ z + iv.L @ u + iv.SQM @ mats.fr

    def _refresh(self, z: np.ndarray, dt: float) -> _Interval:
        """Evaluate and hold the configuration at z. The previous held one becomes its secant partner if it
        lies far enough away to give a usable direction, and how well it predicted this configuration sets
        the next refresh radius (see :meth:`_radius`)."""
        old = self._last
        iv = None
        if self.lookahead and old is not None and old.forces is not None:
            # evaluate ahead of q along its motion: the held model is as good behind its centre as ahead of
            # it, so a centre placed ahead covers (lookahead + 1) radii of the path instead of one
            qd = z[self.r : self.r + self.nq]
            vmax = _max_abs(qd)
            if vmax > 0.0:
                zc = z.copy()
                zc[: self.nq] += (self.lookahead * old.rad / vmax) * qd
                try:
                    iv = self._configuration(zc, held=True)
                except KinematicsError:  # ahead lies beyond the workspace: evaluate here
                    iv = None
        if iv is None:
            iv = self._configuration(z, held=True)
        iv.dt = dt
        iv.Ca = iv.mats.Cr - self.model.beta * iv.mats.Kr
        iv.rad = self.refresh_min
        if old is not None and old.forces is not None and old.dt == dt:
            iv.err = self._prediction_error(old, iv)
            dist = _max_abs(iv.q0 - old.q0)
            iv.rad = self._radius(old, dist, iv.err)
            if dist >= 0.5 * iv.rad:  # extrapolate at most about twice the partner's distance
                d = iv.q0 - old.q0
                iv.old, iv.d, iv.dd = old, d, float(d @ d)
            old.old = None  # keep one partner only (no chain of held configurations)
        iv.kargs = self._held_args(iv)
        self.n_refresh += 1
        self._last = iv
        return iv

    def _radius(self, old: _Interval, dist: float, err: float) -> float:
        """Next refresh radius from the prediction error ``err`` of the last held model after ``dist`` rad:
        the error of the held model grows as ``dist^3`` (second order, with a secant partner) or ``dist^2``,
        so the radius that keeps it at ``refresh_tol`` is ``dist (tol / err)^(1/p)`` (with a 0.9 margin, at
        most twice the last radius, within ``[refresh_min, refresh_rad]``). The model's curvature in q varies
        along a path (on the six-bar's manoeuvre the error over 2e-2 rad falls from 0.6 at the start to 5e-3),
        and a fixed radius would be either wasteful or unsafe."""
        if not err > 0:
            return min(2.0 * old.rad, self.refresh_rad)
        p = 3.0 if old.old is not None else 2.0
        rad = 0.9 * dist * (self.refresh_tol / err) ** (1.0 / p)
        return float(min(max(rad, self.refresh_min), 2.0 * old.rad, self.refresh_rad))

    def _prediction_error(self, old: _Interval, iv: _Interval) -> float:
        """How well the previously held model predicted the new configuration: the relative error of ``M_r``
        and ``K_r`` predicted by ``old`` at ``iv.q0``, in the metric of the new ``M_r`` (an error near 1 allows
        an indefinite mass matrix; ``K_r``'s relative to its own size in that metric)."""
        dl = iv.q0 - old.q0
        oo = old.old
        s = float(dl @ old.d) / old.dd if oo is not None else 0.0
        fo = old.forces
        po = (fo.dMr2, fo.dKr2) if oo is None else (oo.forces.dMr2, oo.forces.dKr2)
        kernel = prediction_error_loops if self.kernel_name == "numba" else prediction_error
        # largest entry of the whitened differences (within a factor r of the spectral norm, and a tenth of
        # its cost: this runs at every evaluation)
        return float(kernel(dl, s, oo is not None, old.mats.Mr, old.mats.Kr, fo.dMr2, fo.dKr2, *po, iv.mats.Mr,
                            iv.mats.Kr))

    def _held_args(self, iv: _Interval) -> tuple:
        """The arguments of :func:`.held.held_step_loops` after ``(z, u, dl, s)``: fixed while iv is held."""
        fm, m = iv.forces, iv.mats
        old = iv.old
        o, om, oCa = (fm, m, iv.Ca) if old is None else (old.forces, old.mats, old.Ca)
        return (old is not None, self.nq, float(self.model.beta), self.h, self._n_steps(iv.dt),
                m.Mr, m.Kr, iv.Ca, m.Gr, fm.dMr2, fm.dKr2, fm.fg, fm.T2, fm.V2, self._c2(fm),
                o.dMr2, o.dKr2, oCa, om.Gr, o.fg, o.T2, o.V2, self._c2(o))

    @staticmethod
    def _system_args(k: tuple) -> tuple:
        """The arguments of :func:`.held.held_system_loops` after ``(dl, s)``, from :meth:`_held_args`' ``k``:
        has_old, beta, the held ``M_r, K_r, C_a, G_r`` and q-gradients of ``M_r, K_r``, and the partner's
        gradients, ``C_a`` and ``G_r``."""
        return (k[0], k[2], *k[5:11], *k[15:19])

    def _c2(self, fm) -> np.ndarray:
        return self._noC2 if fm.C2 is None else fm.C2

    def _cached_step(self, z: np.ndarray, u: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Configuration held while q stays within the held radius of it (:meth:`_radius`); the model at z
        follows from it to second order (:mod:`.held`) and is advanced by the RK4 steps of the interval; the
        Jacobian and process noise are rebuilt when q moved by ``remap_rad``."""
        q = z[: self.nq]
        iv = self._last
        if iv is None or iv.kargs is None or iv.dt != dt or _max_abs(q - iv.q0) > iv.rad:
            iv = self._refresh(z, dt)
        dl = q - iv.q0
        s = _secant_factor(iv, dl)
        z_next, Mr, Kr, Cr, Gr = self.kernel(z, u, dl, s, *iv.kargs)
        if not math.isfinite(z_next[0]) and (s or any(dl)):
            # the held model broke down before the radius said so (M_r not positive definite): evaluate here
            self.n_rescue += 1
            iv = self._refresh(z, dt)
            dl = q - iv.q0
            z_next, Mr, Kr, Cr, Gr = self.kernel(z, u, dl, 0.0, *iv.kargs)
        self._step_matrices = (Mr, Kr, Cr, Gr)
        if iv.q_map is None or not _max_abs(q - iv.q_map) <= self.remap_rad:  # NaN: no map yet
            # the map is built ahead of q along its motion (map_lookahead), from the held model there
            # (not beyond the held model's measurement radius)
            lim = self._measurement_radius(iv)
            dla = np.clip(dl + map_lookahead(z, self.nq, self.remap_rad, self.remap_ahead, self.remap_horizon),
                          -lim, lim)
            numba_kernel = self.kernel_name == "numba"
            system = held_system_loops if numba_kernel else held_system_numpy
            Mr, Kr, Cr, Gr = system(dla, _secant_factor(iv, dla), *self._system_args(iv.kargs))
            maps = step_maps_held if numba_kernel else step_maps_held_numpy
            iv.Pn, iv.SQM, iv.L, iv.Q = maps(Mr, Kr, Cr, Gr, self.h, self._n_steps(dt), self.torque_var)
            if self.q_extra is not None:
                iv.Q = iv.Q + np.diag(self.q_extra)
            iv.q_map = iv.q0 + dla
            iv.fused = None  # new map arrays
            self.n_remap += 1
        if not self.full_jacobian:
            return z_next, iv.Pn
        if self.kernel_name == "numba":
            F = step_jacobian_loops(z, *iv.forces.jacobian_tensors(), iv.Pn, iv.SQM)
        else:
            F = self._jacobian(iv.forces, z, iv.Pn, iv.SQM)
        return z_next, F

    def _jacobian(self, fm, z, Pn, SQM) -> np.ndarray:
        """The step's Jacobian with the state dependence of the held forces.

        ``Pn`` is the Jacobian of the interval's RK4 steps with the matrices and forces held. The forces
        held over the interval depend on the start state (the velocity-dependent forces and the geometric
        q-row term: exact derivatives of their quadratic forms), and ``SQM`` is the interval's response to a
        held generalised force, so ``F = Pn + SQM dF/dz``, exact in the velocities (``tests/test_held.py``).
        Leaving it out (the earlier ``F = Pn``) let the filter diverge in the start-up transient, where the
        elastic rates are large, on some noise realisations (measured: one seed in 100 with the Exudyn truth,
        at every payload level). The q-dependence of ``M_r`` and ``K_r`` is left out: adding it through
        their gradients made the q/dq block overconfident (NEES on the filter's own model 6.17 instead of
        5.96 for 6 dof, 20 runs) without improving F against finite differences.
        """
        r = self.r
        Gp, Gpd = fm.jacobian(z[:r], z[r:])
        return Pn + SQM @ np.hstack([Gp, Gpd])

    def _input(self, u) -> np.ndarray:
        """The motor torques as an array of the model's motor count (zeros for None); a clear error else (the
        compiled kernels would read past a short one)."""
        n = len(self.mech.motors)
        if u is None:
            return np.zeros(n)
        u = np.asarray(u, float)
        if u.shape != (n,):
            raise ValueError(f"input has shape {u.shape}, expected ({n},): one torque per motor "
                             f"{list(self.mech.motor_names)}")
        return u

    def step(self, x: np.ndarray, u, dt: float) -> tuple[np.ndarray, np.ndarray]:
        u = self._input(u)
        if self.method == "cached":
            return self._cached_step(np.asarray(x, float), u, dt)
        x = np.asarray(x, float)
        iv, z_frozen = self._interval(x, u, dt, jacobian=self.full_jacobian)
        self._last = iv
        F = self._jacobian(iv.forces, x, iv.Pn, iv.SQM) if self.full_jacobian else iv.Pn
        if self.method == "frozen":
            return z_frozen, F
        z = np.array(x, float)
        n = int(round(dt / self.h))
        f, h = self.rm.rhs, self.h
        for k in range(n):
            k1 = f(0.0, z, u)
            k2 = f(0.0, z + h / 2 * k1, u)
            k3 = f(0.0, z + h / 2 * k2, u)
            k4 = f(0.0, z + h * k3, u)
            z = z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        return z, F

    def input_jump(self, u0, u1):
        """The increment ``u1 - u0`` of two successive torque samples if it is a jump: beyond what the sample noise
        explains (chi-square test against twice the noise variance, false-alarm probability ``jump_p`` per
        interval); else (and with ``jump_p`` None) None. See :meth:`input_jump_moments`."""
        if self.jump_p is None:
            return None
        thr, w = self._jump_test()
        a, b = np.asarray(u1, float).tolist(), np.asarray(u0, float).tolist()
        # once per sample: Python floats for three motors cost a third of the NumPy expression
        if not sum((x - y) * (x - y) * c for x, y, c in zip(a, b, w)) > thr:
            return None
        return np.subtract(a, b)

    def _jump_test(self) -> tuple[float, list]:
        """Threshold and per-motor weights of :meth:`input_jump`'s chi-square test (inf: no test). The weights
        follow ``torque_var``, which the observer session may rescale after construction."""
        return self._jump_threshold, (0.5 / self.torque_var).tolist()

    def input_jump_moments(self, d: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Mean and covariance of the effect of a torque jump ``d`` at an unknown instant of the last interval.

        The torques a controller applies change at the simulation's (or its own) steps, not at the sensor
        samples: a jump between two samples is held at its old value for part of the interval, a deterministic
        error the held-input step map cannot see (on the six-bar the manoeuvre's torque stepped by 14 N m 0.1 ms
        after a sample: run-averaged NEES up to 43 for ~80 ms). The jump is taken at one of the interval's
        sub-step boundaries ``j = 1..n`` with equal probability (``j = n``: at the next sample, no effect), and
        ``R_j``, the response at the interval's end to ``d`` applied from sub-step ``j`` on (RK4 of the held
        linear system, matrices of the last :meth:`step`), is moment-matched: the prediction is shifted by the
        mean of the ``R_j`` and their covariance is added to the process noise.
        """
        if self.method == "cached":
            Mr, Kr, Cr, Gr = self._step_matrices
        else:
            m = self._last.mats
            Mr, Kr, Cr, Gr = m.Mr, m.Kr, m.Cr, m.Gr
        n = self._n_steps(dt)
        P1, _, L1 = step_maps(np.linalg.inv(Mr), Kr, Cr, Gr, self.h, 1)
        R = np.zeros((n, self.nx))  # row j - 1: the jump at sub-step boundary j (row n - 1: none)
        v = L1 @ d  # one sub-step's response, carried to the interval's end by the later sub-steps
        for j in range(n - 1, 0, -1):
            R[j - 1] = R[j] + v
            v = P1 @ v
        mean = R.mean(axis=0)
        D = R - mean
        return mean, (D.T @ D) / n

    def input_jacobian(self) -> np.ndarray:
        """``d x_next / d u`` (nx, n_motors) of the last :meth:`step`: its response ``L`` to a unit torque held over
        the interval (the map its process noise is built from; :class:`.hold.LinearHoldModel`)."""
        return self._last.L

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
    def _measurement_radius(self, iv: _Interval) -> float:
        """How far from the held configuration its measurement rows are still used (beyond: evaluate anew)."""
        return 1.5 * max(iv.rad, self.refresh_min)

    def _measurement_interval(self, x: np.ndarray) -> _Interval:
        """The held configuration the measurement rows at x are taken about (evaluated at x if none is near)."""
        iv = self._last
        if iv is None or _max_abs(x[: self.nq] - iv.q0) > self._measurement_radius(iv):
            # no held configuration near x (first sample of a run): evaluate one at x
            iv = self._configuration(x)
            self._last = iv
        return iv

    def _secant_rows(self, iv: _Interval, channels: tuple) -> tuple:
        """``(c0, Hm, dH)``: ``y = c0 + (Hm + s dH) x`` about iv, with ``s`` the secant coordinate of x
        (``dH`` None without a secant partner); cached per held configuration."""
        key = (iv.serial, "secant", channels)
        lin = self._channel_cache.get(key)
        if lin is None:
            c0, Hm = self._linear(iv, channels)
            if iv.old is None:
                lin = (c0, Hm, None)
            else:
                # the elastic rows follow the configuration along the secant (the gauges' rows change with
                # H(q)); the rigid parts stay the exact first-order expansion about q0: a secant of their
                # intercepts would make y depend on q through s, which the Jacobian below leaves out, and
                # that inconsistency breaks the filter during the start-up transient
                H1 = self._linear(iv.old, channels)[1]
                dH = np.zeros_like(Hm)
                dH[:, self.nq : self.r] = (Hm[:, self.nq : self.r] - H1[:, self.nq : self.r]) / iv.dd
                lin = (c0, Hm, dH)
            self._channel_cache[key] = lin
        return lin

    def measure(self, x: np.ndarray, channels: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, float)
        iv = self._measurement_interval(x)
        c0, Hm, dH = self._secant_rows(iv, tuple(channels))
        if dH is not None:
            s = _secant_factor(iv, x[: self.nq] - iv.q0) * iv.dd
            if s:
                Hm = Hm + s * dH
        return c0 + Hm @ x, Hm

    # ------------------------------------------------------------------ one compiled sample
    def fused_sample(self, x: np.ndarray, P: np.ndarray, u, y: np.ndarray, channels: tuple, Rd: np.ndarray,
                     floor: np.ndarray, dt: float, bufs: tuple, u_next=None) -> tuple | None:
        """Predict over one interval and update with every channel in one compiled call
        (:func:`.fused.cached_sample`), for :class:`~exuflex.observer.ekf.MultirateEKF`'s ``numba`` back-end.

        Same arithmetic as :meth:`step`, :meth:`process_noise` and :meth:`measure` followed by the filter's
        update and end-of-sample settling, in the same order (``tests/test_fused.py``). Returns None where
        the fused path does not apply or declines the sample (a rescue evaluation, a predicted state far from
        the held configuration, an indefinite innovation covariance): the filter then takes its step-by-step
        path, and nothing of its state has changed. Otherwise ``(x_post, P_post, innovation, S, nis,
        finite)``, with ``P_post`` written into ``bufs[0]``.

        ``bufs``: ``(P_out, P_pred, work, HP)`` scratch of the filter. ``u_next``: the input sample that ends
        the interval; the kernel declines the sample if it is a jump from ``u`` (:meth:`input_jump`; None or
        ``jump_p`` None: no test).
        """
        if not self._fusable():
            return None
        if u.__class__ is not np.ndarray or u.shape != self._u_shape or u.dtype != np.float64:
            u = self._input(u)  # (the filter passes its stored input: a float array, checked once here)
        if u_next is not None and (u_next.__class__ is not np.ndarray or u_next.shape != self._u_shape
                                   or u_next.dtype != np.float64):
            u_next = self._input(u_next)  # the kernel reads it without bounds checks
        m = len(channels)
        x_out, r, S = np.empty(self.nx), np.empty(m), np.empty((m, m))
        iv = self._last
        if iv is None or iv.kargs is None or iv.dt != dt:
            iv = self._refresh(x, dt)
        for attempt in range(2):
            fixed = self._fused_fixed(iv, channels)
            if attempt:
                # just evaluated for x: held for this sample wherever its centre lies (its lookahead may place
                # it beyond its new radius from x), as the step-by-step path does
                fl = fixed[2].copy()
                fl[0] = math.inf
                fixed = (*fixed[:2], fl, *fixed[3:])
            status, nis, remapped, finite = cached_sample(x, P, u, u if u_next is None else u_next, y, Rd, floor,
                                                          x_out, r, S, *bufs, *fixed)
            if status != REFRESH:
                break
            iv = self._refresh(x, dt)
        if remapped:
            self.n_remap += 1
        if status != DONE:
            self.n_declined += 1
            return None
        return x_out, bufs[0], r, S, nis, finite

    def fused_run(self, k0: int, x: np.ndarray, P: np.ndarray, P_alt: np.ndarray, U: np.ndarray, Y: np.ndarray,
                  on_grid: np.ndarray, channels: tuple, Rd: np.ndarray, floor: np.ndarray, dt: float, bufs: tuple,
                  jumps: bool, outs: tuple) -> tuple | None:
        """:meth:`fused_sample` over the samples ``k0, k0 + 1, ...`` of a log in one compiled loop
        (:func:`.fused.cached_run`), while the held configuration serves and the kernel accepts them.

        ``x`` (updated in place) and ``P`` are the filter's state after sample ``k0 - 1``; ``P_alt`` is a
        spare of ``P``'s shape; ``U``, ``Y`` the log's inputs and measurements (C-ordered float arrays) and
        ``on_grid[k]`` whether ``t[k]`` lies one interval after ``t[k - 1]``; ``bufs = (r, S, P_pred, work, HP)``
        scratch; ``outs`` the filter's per-sample outputs (see :func:`.fused.cached_run`).

        Returns None where the fused path does not apply (nothing done), else ``(k, in_alt, finite)``: the
        first sample not done (the caller takes it step by step: a configuration to evaluate, a declined or
        partial sample), whether the latest covariance is in ``P_alt``, and whether it is finite.
        """
        if not self._fusable() or U.shape[1:] != self._u_shape:
            return None
        iv = self._last
        if iv is None or iv.kargs is None or iv.dt != dt:
            return None
        k, _status, in_alt, remaps, finite = cached_run(k0, U, Y, on_grid, jumps, x, P, P_alt, Rd, floor, *bufs,
                                                        *self._fused_fixed(iv, channels), *outs)
        self.n_remap += remaps
        return k, in_alt, finite

    def _fusable(self) -> bool:
        """The compiled whole-sample kernels apply: the cached method with its compiled kernels, fusing on."""
        return self.fused and self.method == "cached" and self.kernel_name == "numba"

    def _fused_fixed(self, iv: _Interval, channels: tuple) -> tuple:
        """The fixed arguments of the fused kernels for iv and these channels (:meth:`_fused_arguments`, kept on
        iv while they serve)."""
        args = iv.fused
        if args is None or args[0] is not channels:
            args = self._fused_arguments(iv, channels)
        return args[1]

    def _fused_arguments(self, iv: _Interval, channels: tuple) -> tuple:
        """The arguments of :func:`.fused.cached_sample` that stay fixed while iv is held (until a step-by-step
        sample rebuilds its step map into new arrays), packed into one buffer (:func:`.fused.pack_arguments`)
        and kept on iv with the channels they are for. iv's step map arrays become views of the buffer, so
        that the kernel's in-place rebuilds are what the step-by-step path reads."""
        nx, nu = self.nx, len(self.mech.motors)
        if iv.q_map is None:  # no step map yet: the kernel builds one (a NaN q_map forces it)
            maps = (np.full(self.nq, np.nan), np.empty((nx, nx)), np.empty((nx, self.r)), np.empty((nx, nu)),
                    np.empty((nx, nx)))
        else:
            maps = (iv.q_map, iv.Pn, iv.SQM, iv.L, iv.Q)
        c0, Hm, dH = self._secant_rows(iv, channels)
        k = iv.kargs  # (has_old, nq, beta, h, n, the 18 held arrays)
        pack, lay, views = pack_arguments(
            (iv.q0, iv.q0 if iv.old is None else iv.d, *k[5:], self.torque_var,
             self._noQ if self.q_extra is None else self.q_extra, *maps, *iv.forces.jacobian_tensors(), c0, Hm,
             self._noRows if dH is None else dH), views=range(22, 27))
        iv.q_map, iv.Pn, iv.SQM, iv.L, iv.Q = views
        thr, w = self._jump_test()
        fl = np.array([iv.rad, self._measurement_radius(iv), iv.dd, self.remap_rad, k[2], k[3], thr,
                       self.remap_ahead, self.remap_horizon, *w])
        iv.fused = (channels, (pack, lay, fl, k[0], k[1], k[4]))
        return iv.fused

    def _linear(self, iv: _Interval, channels: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_affine`, cached per interval (keeping the entries of the held configurations only, once the
        cache grows beyond 64)."""
        channels = tuple(channels)
        key = (iv.serial, channels)
        lin = self._channel_cache.get(key)
        if lin is None:
            if len(self._channel_cache) > 64:
                keep = {iv.serial, self._last.serial if self._last is not None else -1}
                if self._last is not None and self._last.old is not None:
                    keep.add(self._last.old.serial)
                self._channel_cache = {k: v for k, v in self._channel_cache.items() if k[0] in keep}
            lin = self._affine(iv, channels)
            self._channel_cache[key] = lin
        return lin

    def _affine(self, iv: _Interval, channels: tuple) -> tuple[np.ndarray, np.ndarray]:
        """``y = c0 + Hm x`` for the channels, about the interval's configuration (rigid parts to first
        order in q, elastic parts exact in p): the rows of :func:`.rows.sensor_rows`, for all channels at once
        (:class:`.rows.ChannelRows`)."""
        nq, r = self.nq, self.r
        plan = self._channel_rows.get(channels)
        if plan is None:
            plan = self._channel_rows[channels] = channel_rows(
                self.model, [sensor(self.mech, self.sensors, ch) for ch in channels], self.link_names)
        U, points = plan.at(self.model, iv.mats.rc.cfg)
        Hm = np.zeros((len(channels), self.nx))
        Hm[:, :r] = U @ iv.mats.rc.H[nq:]
        rows = plan.angle @ iv.Sz_theta  # the link-angle channels' rigid rows
        c0 = plan.angle @ iv.theta0 - rows @ iv.q0
        Hm[:, :nq] += rows
        for i, p0, Sp in points:
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

"""The reduced flexible-multibody model as the filter's discrete-time model (eqs. 8-9).

State ``z = [p; p']`` with ``p = [q; u_m; eta]`` (:class:`exuflex.reduction.ReducedModel`); input the measured
motor torques, held over each interval between two samples or linear between them as the log declares
(:attr:`ReducedObserverModel.input_hold`; docs/held_step.md, "The input over a sample interval"); output any of the mechanism's sensor channels
(encoders, curvature gauges, tip position) as the nonlinear functions of the state they are.

Over an interval of ``dt`` seconds the reduced equations ``M_r p'' + C_r p' + K_r p = G_r u + f_r(p, p')`` are
advanced by ``n`` RK4 sub-steps (the paper's scheme). Two ways (``method``):

- ``"cached"`` (the default): the configuration (pose, basis, reduced matrices, the velocity-dependent forces as
  quadratic forms and the q-gradients of ``M_r``, ``K_r``: :meth:`ReducedModel.held`) is evaluated only when q
  leaves a refresh radius around the held one, undeformed; in between the model follows the links to second order
  in q and the elastic coordinates exactly but for ``M_r``'s second order (:mod:`.expansion`; docs/held_elastic.md), and each interval's
  sub-steps use the matrices at the interval's midpoint elastic coordinates ``p_e + dt/2 p_e'`` and the forces at
  its start (:func:`.expansion._held_model`), the geometric stiffness of the motion's axial loads (a form in the
  torques and rates held with the configuration, :meth:`ReducedModel.motion_geometric`) as a force at its midpoint
  positions (:func:`.expansion._motion_forces`). The radius adapts like an ODE step size under two error targets, the
  smaller radius winning. (1) The held matrices' validity: the previous held model's relative error of ``M_r`` and
  ``K_r`` (mass metric, :func:`.expansion.prediction_error`) near ``refresh_tol``. (2) What the held model costs the filter: the
  replaced held model's state error over one interval against the exact configuration
  (:meth:`ReducedObserverModel._held_error`, every held quantity included: ``M_r``, ``K_r``, damping, input
  matrix, velocity forces; reported as ``held_model_error`` by ``observe``, with the error relative to the
  interval's process noise), near ``refresh_std_tol`` in the bias it leaves: the held model's error has one sign
  over the whole radius, so it repeats over the intervals the radius spans and the filter accumulates it for as
  many intervals as its gain takes to forget it (several hundred on a gauge-informed arm at 1 kHz); its figure is
  the filter's steady response to the error repeated at every interval, in the coordinates' readings and rates
  over the filter's standard deviation of them (:meth:`ReducedObserverModel._persistent_bias`), 0.1 of it
  adding 1 % to their mean square error. (Per interval against each state's standard deviation instead, errors of
  a hundredth of it left 0.2 to 0.4 of the bound on the relative readings of noiseless logs:
  docs/reading_floor.md.) The second alone is
  not enough: during the start-up the filter's standard deviations are large, the radius grows until the held
  mass matrix is no longer valid, and the filter fails (the six-bar's Exudyn log, seed 2). Without a filter's
  covariance (the model used alone) only the first applies. The step Jacobian and process noise (the *step
  map*) are rebuilt when q moved the map radius from where they were built, or when the interval's length
  changes. The map radius is controlled by the map's effect on the filter's own
  uncertainty: at each rebuild the replaced map's covariance prediction is compared with the new one's on the
  filter's present covariance (:func:`.expansion.map_error`, a relative error of the predicted
  standard deviations), and the next radius keeps that error near ``remap_tol`` (the error grows linearly with
  the distance; the maps' centres are two radii apart, so the largest error while a map is in use is about half
  of it). How strongly the maps depend on q differs by orders of magnitude between mechanisms (a single link
  turning: not at all; a slider-crank near its dead centres: strongly), which no fixed radius serves.
- ``"rk4"`` (the exact reference): the configuration evaluated at every interval and every RK4 stage at its own
  state; the Jacobian and process noise of the interval's start.

Sub-steps: ``n`` is the smallest count with sub-steps no longer than ``h`` for which RK4 is stable, with a
margin, on every eigenvalue of the held linear system (``|R(1.25 h lambda)| <= 1``, :func:`rk4_substep_limit`);
the spectrum is recomputed at every configuration evaluation. A model whose stiffest mode needs sub-steps shorter
than ``min_substep`` is refused with the mode's frequency (a master set with a stiff Guyan mode); a long interval
(a gap in the log) just takes more sub-steps.

Intervals of different length (a lab clock's jitter) are each integrated over their own length; the step map
(Jacobian and process noise) is rebuilt when the length differs from the one it was built for by more than
``dt_tol`` (relative): within it the map's error is of that relative size in its departure from the identity.

Jacobian: ``F = P^n + S dF/dz``: the held linear system's map ``P^n`` plus its response ``S`` to the change of the
held generalised forces with the start state (the velocity-dependent forces, exactly:
:func:`.expansion.step_jacobian`; under gravity the weight's gradient and the held matrices' change with q as the
forces it causes, :func:`.expansion.position_forces`).

Process noise: the measured torques carry white noise of std ``sigma`` (the motors' ``noise_std``), held over
the interval, so ``Q = L diag(sigma^2) L^T`` with ``L`` the interval's response to a unit torque held over it,
plus an optional diagonal for unmodelled dynamics. A torque jump between two samples (two successive samples
differing by more than their noise, :meth:`input_jump`) adds the mean and covariance of its effect at an
unknown instant of the interval (:meth:`input_jump_moments`).

Measurements: the rows about a held configuration with their exact first-order change with ``q`` in every
direction, and the rigid parts to second order (:meth:`ReducedObserverModel._expansion`): the gauges' rows change
with the configuration at rates of the elastic rows themselves per radian (the basis's static shapes change
with the joint angles, the rows turn with their links), which over the measurement radius is of the order of
the gauges' noise. The measurement Jacobian is the derivative of the channels returned except the elastic rows'
q-derivative in its q-columns (:meth:`ReducedObserverModel.measure` says why); the derivation is in
docs/measurement_rows.md.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from operator import sub

import numpy as np

from ..erls.kinematics import KinematicsError
from ..erls.sensing import SecondOrderPlan
from ..erls.simulate import rk4_amplification, rk4_step
from ..reduction import CraigBampton, ReducedModel
from ..reduction.model import ReducedMatrices
from .base import LoopModel, Measurement, Prediction
from .expansion import (
    CachedStep,
    held_ramp,
    HeldSystem,
    LoopMap,
    LoopState,
    held_interval,
    held_step,
    map_error,
    measurement_rows,
    motion_form_gradient,
    motion_forces,
    motion_gradient,
    motion_rates,
    motion_stiffness,
    next_map_radius,
    position_forces,
    prediction_error,
    rebuild_map,
    secant_factor,
    step_jacobian,
    step_maps,
    step_maps_noise,
    warm_up,
)
from .kalman import InputStepTest
from .rows import channel_rows, sensor

__all__ = ["INPUT_HOLDS", "METHODS", "ReducedObserverModel", "StepTolerances", "rk4_input_steps", "rk4_substep_limit"]

METHODS = ("cached", "rk4")
#: what a log's torques did between two samples (:data:`exuflex.runs.INPUT_HOLDS`): held at each sample ("zoh", a
#: digital controller's output) or a smooth signal sampled, taken linear between the samples ("linear")
INPUT_HOLDS = ("zoh", "linear")

_NO_ROWS = np.empty((0, 0))  # rows of a term that is absent
_NONE = np.empty(0)

#: margin on the eigenvalues in the sub-step choice: the held system changes between two evaluations
SUBSTEP_MARGIN = 1.25


def _max_abs(v: np.ndarray) -> float:
    """max |v_i| of a short vector (a few coordinates: cheaper in Python than two NumPy reductions)."""
    return max(map(abs, v.tolist()))


def _by_rows(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` one row at a time: each row the same numbers whichever other rows ``A`` has (a matrix product's
    blocking, and so its rounding, changes with the number of rows; the rows of a subset of the channels must be
    those of all of them, as the filter's compiled loop takes them)."""
    out = np.empty((A.shape[0], B.shape[1]))
    for i in range(A.shape[0]):
        out[i] = A[i] @ B
    return out


def rk4_substep_limit(lam: np.ndarray) -> float:
    """Longest RK4 sub-step stable, with :data:`SUBSTEP_MARGIN`, for every decaying eigenvalue ``lam``.

    RK4 multiplies a mode by ``R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24`` per sub-step, ``z = h lambda``; a decaying
    mode must not grow, ``|R(z)| <= 1`` (``|z| <= 2.83`` on the imaginary axis, 2.79 on the negative real axis).
    Found by bisection on ``h`` between the real-axis bound and the imaginary-axis one."""
    lam = SUBSTEP_MARGIN * lam[lam.real <= 0]
    w = float(np.abs(lam).max()) if lam.size else 0.0
    if w == 0.0:
        return math.inf
    lo, hi = 2.0 / w, 2.85 / w  # stable at lo for every direction in the left half-plane's stable region
    if np.all(np.abs(rk4_amplification(hi * lam)) <= 1.0 + 1e-12):
        return hi
    if not np.all(np.abs(rk4_amplification(lo * lam)) <= 1.0 + 1e-12):
        lo = 1e-3 / w
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if np.all(np.abs(rk4_amplification(mid * lam)) <= 1.0 + 1e-12):
            lo = mid
        else:
            hi = mid
    return lo


def rk4_input_steps(f, z: np.ndarray, u: np.ndarray, du: np.ndarray, dt: float, n: int) -> np.ndarray:
    """``n`` RK4 sub-steps of ``z' = f(t, z, u(t))`` over ``dt`` with the input linear over the interval,
    ``u(t) = u + (t / dt) du`` (``du`` zero: held), each stage at its own time and input (RK4's order holds for
    an input linear in time)."""
    h = dt / n
    x = np.array(z, float)
    for i in range(n):
        t = i * h
        u0, um, u1 = u + (t / dt) * du, u + ((t + 0.5 * h) / dt) * du, u + ((t + h) / dt) * du
        k1 = f(t, x, u0)
        k2 = f(t + h / 2, x + h / 2 * k1, um)
        k3 = f(t + h / 2, x + h / 2 * k2, um)
        k4 = f(t + h, x + h * k3, u1)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def _radius_limits(name: str, rad, lo, hi) -> None:
    """An adaptive radius's start and limits checked, ``0 < lo <= rad <= hi`` (the names ``{name}_rad``,
    ``{name}_min``, ``{name}_max`` in the message)."""
    if not 0 < lo <= rad <= hi:
        raise ValueError(f"need 0 < {name}_min <= {name}_rad <= {name}_max, got {lo}, {rad}, {hi}")


@dataclass(frozen=True)
class StepTolerances:
    """The cached step's error targets and the radii that keep them (module docstring;
    :class:`ReducedObserverModel` takes them as attributes of the same names).

    Attributes
    ----------
    refresh_std_tol : float
        Error target of the cached step's held model: the filter's steady bias from its state error over one
        interval repeated, relative to the filter's standard deviations of the coordinates' readings and rates
        (:meth:`ReducedObserverModel._held_error`), kept by the refresh radius.
    refresh_tol, refresh_min, refresh_max : float
        Error target of the held matrices (relative, mass metric), also kept by the refresh radius, and the
        radius's limits (rad).
    remap_tol : float
        Error target of the step map: the relative error of the predicted standard deviations it causes
        (:func:`.expansion.map_error`), measured at each rebuild and kept near this by the map radius.
    remap_rad, remap_min, remap_max : float
        The map radius (rad) q moves before the step map is rebuilt (cached step): its initial value and limits.
    dt_tol : float
        Relative change of the interval's length before the step map is rebuilt.
    rows_tol : float
        Error target of the measurement rows: the filter's steady bias from their error at the measurement radius
        repeated at every update, relative to its standard deviations of the coordinates' readings and rates
        (without the filter's covariance: the error relative to each channel's noise;
        :meth:`ReducedObserverModel._rows_error`), measured at each rebuild and kept near this by the measurement
        radius (:meth:`ReducedObserverModel._rows_radius`).
    rows_rad, rows_min, rows_max : float
        The measurement radius (rad): its initial value and limits.
    """

    refresh_std_tol: float = 0.1
    refresh_tol: float = 3e-2
    refresh_min: float = 2e-3
    refresh_max: float = 4e-2
    remap_tol: float = 5e-2
    remap_rad: float = 2e-3
    remap_min: float = 1e-4
    remap_max: float = 4e-2
    dt_tol: float = 1e-3
    rows_tol: float = 0.1
    rows_rad: float = 5e-3
    rows_min: float = 1e-3
    rows_max: float = 6e-2

    def __post_init__(self):
        for f in fields(self):  # floats, whatever number was given
            object.__setattr__(self, f.name, float(getattr(self, f.name)))
        _radius_limits("remap", self.remap_rad, self.remap_min, self.remap_max)
        _radius_limits("rows", self.rows_rad, self.rows_min, self.rows_max)
        if not self.rows_tol > 0:
            raise ValueError(f"rows_tol must be positive, got {self.rows_tol}")


def _secant_factor(iv: _Held, dl: np.ndarray) -> float:
    """``s = (dl . d) / (d . d)``: how far along the secant to the previous held configuration q has moved
    (:func:`.expansion.secant_factor`).

    Zero (first order only) without a partner or when q moves away from the secant's line (cosine below 0.7):
    the secant's differences then say nothing about the change, and extrapolating them along a different
    direction breaks the filter during the start-up transient, where the estimate jitters in every direction."""
    return secant_factor(dl, iv.d, iv.dd) if iv.old is not None else 0.0


@dataclass
class _StepMap:
    """The held linear system's maps over one interval, built at ``q`` for an interval of ``dt`` in ``n`` sub-steps."""

    q: np.ndarray
    dt: float
    n: int
    Pn: np.ndarray  # (nx, nx) state map
    S: np.ndarray  # (nx, r) response to a unit generalised force held over the interval
    L: np.ndarray  # (nx, n_motors) response to a unit torque held over the interval
    Q: np.ndarray  # (nx, nx) process noise
    q_list: list = None  # q as floats
    tail: tuple = ()  # the compiled interval's arguments fixed while this map and its configuration are held


@dataclass
class _Held:
    """A configuration the model holds: its reduced matrices and pose data (and, for the cached step, the force
    model with its q-gradients, the secant partner, the refresh radius and the step map)."""

    q0: np.ndarray
    mats: ReducedMatrices
    Sz_theta: np.ndarray  # (n_links, nq) link-angle sensitivity at q0
    theta0: np.ndarray  # link angles at q0
    serial: int  # identifies the configuration in the measurement-row cache
    forces: object = None  # QuadraticForces at q0
    h_stable: float | None = None  # longest stable RK4 sub-step at q0 (:func:`rk4_substep_limit`)
    Ca: np.ndarray | None = None  # C_r - beta K_r at q0
    old: _Held | None = None  # secant partner: the previous held configuration
    d: np.ndarray | None = None  # q0 - old.q0
    dd: float = 0.0  # d . d
    rad: float = 0.0  # refresh radius
    err: float = float("nan")  # prediction error of the previous held model at q0
    system: HeldSystem | None = None  # the held arrays of the compiled step
    map: _StepMap | None = None
    rows: dict = None  # measurement rows about q0 per channel tuple: (c0, Hm, D, G) (:meth:`_expansion`)

    def __post_init__(self):
        self.rows = {}

    @property
    def rc(self):
        """The basis at ``q0`` (:class:`~exuflex.reduction.basis.ReducedConfiguration`)."""
        return self.mats.rc

    @property
    def dHdq(self) -> np.ndarray | None:
        """``d(H e_k)/dq`` of every reduced coordinate at ``q0`` if the evaluation computed it (else None)."""
        return None if self.forces is None else self.forces.dHdq


@dataclass
class _RowsAt:
    """A configuration evaluated for the measurement rows only (no reduced matrices): ``q0``, the basis there
    ``rc``, the link-angle sensitivity ``Sz_theta`` and angles ``theta0``; ``dHdq`` None (computed with the rows)."""

    q0: np.ndarray
    rc: object
    Sz_theta: np.ndarray
    theta0: np.ndarray
    dHdq: None = None


@dataclass
class _RowsCentre:
    """The configuration ``at`` the measurement rows are taken about (a held one or one evaluated for them), its
    ``q0`` and the measurement radius ``rad`` (max norm, rad) within which its rows serve
    (:meth:`ReducedObserverModel._rows_radius`); the rows ``(c0, Hm, D, G)`` per channel tuple
    (:meth:`ReducedObserverModel._expansion`), made as measurements ask for them. One centre serves every channel
    tuple: a sample with some channels takes the rows of the same configuration as one with all."""

    at: object
    q0: np.ndarray
    q_list: list
    rad: float
    rows: dict


class _Pairs:
    """Float pairs appended one at a time and kept as doubles, 16 bytes a pair (a list of tuples of floats takes
    about 120): a record that grows with a long log's refreshes."""

    def __init__(self):
        self._a = array("d")

    def append(self, pair: tuple[float, float]) -> None:
        self._a.extend(pair)

    def __len__(self) -> int:
        return len(self._a) // 2

    def asarray(self) -> np.ndarray:
        """A copy, shape (n, 2)."""
        return np.array(self._a, dtype=float).reshape(-1, 2)


class ReducedObserverModel:
    """:class:`~exuflex.observer.base.DiscreteModel` of a reduced ERLS model.

    Parameters
    ----------
    reduced : ReducedModel or CraigBampton
    h : float
        Longest RK4 sub-step (s), default 1e-4 (the paper's); shorter where stability needs it.
    method : {"cached", "rk4"}
        The default cached step or the exact reference (see the module docstring).
    torque_std : sequence of float, optional
        Std of the measured torques (N m) per motor; default the motors' ``noise_std``.
    q_extra : array_like, optional
        (nx,) diagonal added to Q per interval (unmodelled dynamics).
    jump_p : float or None
        False-alarm probability per interval of the torque-jump test (:meth:`input_jump`); None: no test.
    min_substep : float
        Shortest RK4 sub-step (s) the model may need for stability before it is refused (see :meth:`substeps`).
    tolerances : StepTolerances
        The cached step's error targets and the radii that keep them (each also an attribute of the model).
    input_hold : {"zoh", "linear"}
        What the torques did between two samples (:attr:`input_hold`, the log's declaration).
    input_delay : float
        With a linear input, the time (s) by which the torques reach the mechanism after their samples
        (:attr:`input_delay`).

    Attributes
    ----------
    n_refresh, n_remap, n_rescue, n_evaluations : configuration evaluations of the cached step, step-map
        rebuilds, evaluations forced by a held mass matrix that lost positive definiteness, all evaluations.
    n_rows : measurement-row rebuilds (about a held configuration or a configuration evaluated for them).
    n_jumps : intervals with a torque jump since the last :meth:`reset`.
    last_step : ``(held configuration, step map)`` of the last :meth:`predict`: the reduced matrices the interval
        was held at (``.mats``) and its maps ``Pn, S, L, Q`` (what augmented models differentiate through).
    torque_var : variances of the measured torques (the process noise's), per motor.
    input_hold : the input over an interval (settable: a log declares it, :func:`exuflex.runs.read_run`): "zoh",
        each torque sample held to the next (a digital controller's zero-order hold; the paper's eq. 10); "linear",
        the torques linear between the interval's two samples at the actual sample times, each RK4 stage at its
        own time (a smooth signal sampled: every exuflex truth). Held, a smooth torque lags by half an interval
        (docs/held_step.md, "The input over a sample interval"). The torque-jump test (``jump_p``) applies to a
        held input only.
    input_delay : with a linear input, the time (s) by which the torques act after their samples, settable (a
        log declares it): an exuflex truth holds its torque table over the table's step ``h``, a staircase that
        follows the smooth torque by ``h / 2`` on average; the step then takes ``u(t - delay)``, linear, i.e. the
        interval's start torque ``u - (delay / dt) du``.
    """

    def __init__(self, reduced, h: float = 1e-4, method: str = "cached", torque_std=None, q_extra=None,
                 jump_p: float | None = None, min_substep: float = 2e-6, tolerances: StepTolerances = StepTolerances(),
                 input_hold: str = "zoh", input_delay: float = 0.0):
        if isinstance(reduced, CraigBampton):
            reduced = ReducedModel(reduced)
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if not (h > 0 and math.isfinite(h)):
            raise ValueError(f"h must be a positive number of seconds, got {h}")
        self.input_hold = input_hold
        self.input_delay = float(input_delay)
        self.rm = reduced
        self.model = reduced.model
        self.mech = self.model.mech
        self.nq = reduced.nq
        self.r = reduced.r
        self.nx = 2 * reduced.r
        self.h = float(h)
        self.method = method
        self.min_substep = float(min_substep)
        self.tolerances = tolerances
        vars(self).update(asdict(self.tolerances))  # (each an attribute: refresh_tol, rows_rad, ...)
        self.lookahead = 0.8  # radii ahead of q along its motion where a configuration is evaluated
        self.remap_ahead = 1.0  # remap radii ahead of q along its motion where a step map is built ...
        self.remap_horizon = 0.02  # ... but no further than q moves in this many seconds
        nu = len(self.mech.motors)
        sig = [m.noise_std for m in self.mech.motors] if torque_std is None else list(torque_std)
        if len(sig) != nu:
            raise ValueError(f"torque_std has {len(sig)} entries, expected one per motor ({nu})")
        self.torque_var = np.asarray(sig, float) ** 2
        self.q_extra = None if q_extra is None else np.asarray(q_extra, float)
        #: the diagonal added to the process noise per interval as the kernels take it (empty: none)
        self.q_extra_diag = _NONE if q_extra is None else np.ascontiguousarray(self.q_extra)
        self.jump_p = jump_p
        self.jump_test = InputStepTest(self.torque_var, jump_p)
        self._u_shape = (nu,)
        self.link_names = [lk.name for lk in self.mech.links]
        self.sensors = {s.name: s for s in self.mech.sensors}
        self._channel_rows: dict = {}  # configuration-independent parts of the sensor rows, per channel tuple
        self._second_order: dict = {}  # the tip points' SecondOrderPlan, per (link, station)
        G = self.model.coordinate_reading_rows()
        #: (nq, ne) the coordinates' encoder readings beyond q
        #: (:meth:`~exuflex.erls.model.ErlsModel.coordinate_reading_rows`); None where every row is zero (no
        #: relative angle coordinate): the physical q is the state's q
        self.reading_G = G if np.any(G) else None
        self._noC2 = np.zeros((0, self.r))
        self._weight = bool(np.any(self.model.g_N))  # gravity: the weight's gradient enters the step Jacobian
        self.n_refresh = self.n_remap = self.n_rescue = self.n_evaluations = self.n_rows = 0
        self.state_cov = None  # the filter's covariance, a callable (:meth:`watch_covariance`)
        self._serial = 0
        self._map_errs = np.empty(1024)  # the step maps the compiled loop replaces: their errors, per call
        self.reset()
        warm_up()
        if method == "cached":  # compile (or load) the evaluation's kernels now, not in a run's first interval
            z = self.rm.rest_state(np.asarray(self.rm.cb.q_star, float))
            self.rm.held(z[: self.r], z[self.r :])
            self.model.kin.reset_warm_start()

    @property
    def input_hold(self) -> str:
        """The input over an interval, "zoh" or "linear" (class docstring)."""
        return self._input_hold

    @input_hold.setter
    def input_hold(self, value: str) -> None:
        if value not in INPUT_HOLDS:
            raise ValueError(f"input_hold must be one of {INPUT_HOLDS}, got {value!r}")
        self._input_hold = value

    def interval_input(self, u: np.ndarray, u_next, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """``(u0, du)``: the torques at the interval's start and their change over it as the step takes them
        (:meth:`input_increment`; with a linear input the start torque delayed by :attr:`input_delay`)."""
        du = self.input_increment(u, u_next)
        if du.size and self.input_delay:
            u = u - (self.input_delay / dt) * du
        return u, du

    def input_increment(self, u: np.ndarray, u_next) -> np.ndarray:
        """``du``: the torques' change over the interval as the step takes it (:func:`.expansion.held_interval`):
        empty with a held input; with a linear one ``u_next - u`` (zeros without a next sample)."""
        if self._input_hold == "zoh":
            return _NONE
        return np.zeros(self._u_shape) if u_next is None else self._input(u_next) - u

    def watch_covariance(self, get_P) -> None:
        """Give the model the filter's covariance (``get_P()`` returns it): the held model's error is then
        measured against the filter's uncertainty at every evaluation (:meth:`_held_error`), and the step map's
        radius is controlled by its effect on it (:func:`.expansion.map_error`). Without it the map radius stays ``remap_rad``."""
        self.state_cov = get_P

    def reset(self) -> None:
        """Forget the held configuration, the cached measurement rows and the closure solver's warm start (a new
        run starts clean: its estimates do not depend on what the model evaluated before)."""
        self._last: _Held | None = None
        self._renewed = None  # (z, dt, what _hold returned): an interval the compiled loop renewed and handed back
        self.map_rad = self.remap_rad  # the present map radius (:func:`.expansion.next_map_radius`)
        self.map_errors = array("d")  # the replaced maps' errors (:func:`.expansion.map_error`), 8 bytes each
        self._interval_matrices = None
        self.n_jumps = 0
        self.held_errors = _Pairs()  # (vs std, vs process noise) per refresh
        self._centre: _RowsCentre | None = None  # the measurement rows' configuration
        self._measured: tuple = ()  # the channels of the last rows rebuilt (the filter's gain in _held_error)
        self.rows_errors = _Pairs()  # (error at the measurement radius, the radius) per rebuild (:meth:`_recentre`)
        self.model.kin.reset_warm_start()

    # ------------------------------------------------------------------ configurations
    def _configuration(self, z: np.ndarray, held: bool = False, frozen_forces: bool = False) -> _Held:
        """Evaluate the configuration at the state z (reduced matrices, pose data). With ``held`` also the force
        model with the q-derivatives of the cached step; with ``frozen_forces`` the forces at z and their force
        model without q-derivatives."""
        forces = None
        if held:  # undeformed: the cached step adds the elastic coordinates' terms (:func:`.expansion._elastic_terms`)
            p = z[: self.r].copy()
            p[self.nq :] = 0.0
            mats, forces = self.rm.held(p, z[self.r :])
        elif frozen_forces:  # with gravity the gradients too (the step Jacobian's position_forces)
            mats, forces = self.rm.held(z[: self.r], z[self.r :], fr=True, gradients=self._weight)
        else:
            mats = self.rm.matrices(z[: self.r], z[self.r :])
        self.n_evaluations += 1
        pose = mats.rc.cfg.pose
        self._serial += 1
        return _Held(z[: self.nq].copy(), mats, pose.Sz[2::3].copy(), pose.z[2::3].copy(), self._serial,
                     forces=forces)

    def _spectrum(self, mats: ReducedMatrices) -> np.ndarray:
        """Eigenvalues of the linear system ``[[0, I], [-M^-1 K, -M^-1 C]]`` at a configuration."""
        r = self.r
        A = np.zeros((2 * r, 2 * r))
        A[:r, r:] = np.eye(r)
        X = np.linalg.solve(mats.Mr, np.hstack([mats.Kr, mats.Cr]))
        A[r:, :r] = -X[:, :r]
        A[r:, r:] = -X[:, r:]
        return np.linalg.eigvals(A)

    def substeps(self, iv: _Held, dt: float) -> int:
        """RK4 sub-steps over an interval of ``dt`` at the configuration ``iv``: each at most ``h`` long and
        stable on the configuration's spectrum (:meth:`_stable_substep`)."""
        if iv.h_stable is None:
            iv.h_stable = self._stable_substep(iv.mats)
        return max(1, math.ceil(dt / min(self.h, iv.h_stable) - 1e-9))

    def substeps_at(self, z: np.ndarray, dt: float) -> int:
        """:meth:`substeps` over ``dt`` of the configuration evaluated at the state ``z`` (the reference step's
        count, :meth:`advance`)."""
        return self.substeps(self._configuration(np.asarray(z, float)), dt)

    def _stable_substep(self, mats: ReducedMatrices) -> float:
        """The longest RK4 sub-step stable on a configuration's spectrum (:func:`rk4_substep_limit`); an error
        naming the stiffest mode if stability needs sub-steps shorter than ``min_substep``."""
        lam = self._spectrum(mats)
        h_stable = rk4_substep_limit(lam)
        if h_stable < self.min_substep:
            w = float(np.abs(lam).max())
            raise ValueError(
                f"the reduced model's stiffest mode (|lambda| = {w:.4g} 1/s, {w / (2 * np.pi):.4g} Hz) needs RK4 "
                f"sub-steps of at most {h_stable:.3g} s, shorter than min_substep={self.min_substep:g} s. A "
                "master dof with a stiff Guyan mode (e.g. an axial one) causes this: choose other masters")
        return h_stable

    def frozen_interval(self, z: np.ndarray, u, dt: float, du=None) -> tuple[Prediction, _Held, _StepMap]:
        """The configuration evaluated at ``z`` and held over the interval: the linear system with the forces at
        ``z`` advanced by its sub-steps (``x = P^n z + L u + S f_r``, and the response to the torques' change
        ``du`` over the interval where they are linear, :meth:`input_increment`), its Jacobian and process noise.
        The linearisation of the steady-state bound and the observability test, and the reference step's Jacobian."""
        z = np.asarray(z, float)
        u = self._input(u)
        du = _NONE if du is None else np.asarray(du, float)
        um = u + 0.5 * du if du.size else u  # the torques at the interval's midpoint
        iv = self._configuration(z, frozen_forces=True)
        m = iv.mats
        n = self.substeps(iv, dt)
        Pn, S, L, Q = self._maps(m.Mr, m.Kr, m.Cr, m.Gr, dt, n)
        # the motion's geometric forces at the start's rates and the midpoint's torques, at the interval's midpoint
        # positions, as the cached step takes them (expansion.motion_forces)
        KGd = iv.forces.KGd
        Kd = motion_stiffness(um, z, self.nq, KGd)
        f = m.fr.copy()
        motion_forces(f, z, 0.5 * dt, Kd)
        x = Pn @ z + L @ u + S @ f
        if du.size and np.any(du):  # the response to the torques' ramp (the linear system's: zero start and force)
            zero = np.zeros(self.nx)
            x = x + held_ramp(zero, zero[: len(u)], du, m.Mr, m.Kr, m.Cr, m.Gr, zero[: self.r], dt / n, n)
        Fp = iv.forces.Wg
        if Fp.shape[0]:
            Fp = position_forces(z, x, dt, Fp, iv.forces.dMr2, iv.forces.dKr2, float(self.model.beta))
            Fp[:, : self.nq] += self.rm.velocity_force_gradient(z[: self.r], z[self.r :])  # the rates' forces too
        if KGd.shape[0]:
            Fp = motion_gradient(Fp, Kd)
            motion_form_gradient(Fp, um, z, 0.5 * dt, iv.forces.dKGd, self.nq)
        F = step_jacobian(z, *iv.forces.jacobian_tensors(), Pn, S, Fp)
        motion_rates(F, z, um, self.nq, S, KGd, Kd, dt)
        self._interval_matrices = (m.Mr, m.Kr, m.Cr, m.Gr, dt / n, n)
        return Prediction(x, F, Q), iv, _StepMap(z[: self.nq].copy(), dt, n, Pn, S, L, Q)

    def _maps(self, Mr, Kr, Cr, Gr, dt: float, n: int) -> tuple:
        """``(P^n, S, L, Q)`` of ``n`` RK4 sub-steps over ``dt`` of the linear system with these matrices."""
        Pn, S, L, Q = step_maps_noise(Mr, Kr, Cr, Gr, dt / n, n, self.torque_var)
        if self.q_extra is not None:
            Q = Q + np.diag(self.q_extra)
        return Pn, S, L, Q

    # ------------------------------------------------------------------ the cached step
    def _refresh(self, z: np.ndarray, u=None, dt: float | None = None) -> _Held:
        """Evaluate and hold the configuration at z (ahead of q along its motion). The previous held one becomes
        its secant partner if it lies far enough away to give a usable direction, and how well it predicted this
        configuration sets the next refresh radius (:meth:`_radius`). With the interval's ``u`` and ``dt``, the
        state error the previous held model causes there is recorded (:meth:`_held_error`)."""
        old = self._last
        iv = None
        if old is not None and old.forces is not None:
            # the held model is as good behind its centre as ahead of it: a centre placed ahead along the motion
            # covers (lookahead + 1) radii of the path instead of one
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
        iv.Ca = iv.mats.Cr - self.model.beta * iv.mats.Kr
        iv.rad = self.refresh_min
        s_old = 0.0  # where the old held model stood on its secant at iv (before its partner is dropped)
        if old is not None and old.forces is not None:
            s_old = _secant_factor(old, iv.q0 - old.q0)
            iv.err = self._prediction_error(old, iv)
            dist = _max_abs(iv.q0 - old.q0)
            order = 3.0 if old.old is not None else 2.0  # the old held model's order (before its partner goes)
            iv.rad = self._radius(old, dist, iv.err, self.refresh_tol, order)
            if dist >= 0.5 * iv.rad:  # extrapolate at most about twice the partner's distance
                d = iv.q0 - old.q0
                iv.old, iv.d, iv.dd = old, d, float(d @ d)
            old.old = None  # keep one partner only (no chain of held configurations)
        iv.system = self._held_system(iv)
        iv.h_stable = self._stable_substep(iv.mats)  # the sub-step rechecked at every evaluation
        if old is not None and old.forces is not None and u is not None and dt is not None \
                and self.state_cov is not None:
            err = self._held_error(old, s_old, iv, z, u, dt)
            self.held_errors.append(err)
            iv.rad = min(iv.rad, self._radius(old, dist, err[0], self.refresh_std_tol, order))
        self.n_refresh += 1
        self._last = iv
        self._renewed = None
        return iv

    def _held_error(self, old: _Held, s_old: float, iv: _Held, z: np.ndarray, u: np.ndarray,
                    dt: float) -> tuple[float, float]:
        """The state error over one interval that the held model ``old`` (at secant factor ``s_old``) causes where it
        is replaced by the
        configuration ``iv`` evaluated exactly, against the filter's uncertainty: ``(b, max_i |dz_i| / sqrt(Q_ii))``
        with ``dz`` the difference of the two interval steps from the filter's state (its configuration moved to
        ``iv``'s) and ``Q`` the interval's process noise; ``b`` the filter's steady bias from ``dz`` repeated at
        every interval (:meth:`_persistent_bias`, with the channels the measurement rows were last rebuilt for),
        or, before any rows or where the filter's error map does not contract, ``max_i |dz_i| / sigma_i`` with
        ``sigma`` the
        filter's standard deviations before the interval. Every held quantity enters (``M_r``, ``K_r``, damping,
        input matrix, velocity forces, all along the secant): the first figure well below 1 means the
        approximation is lost in the filter's uncertainty, the second below 1 that it is smaller than the noise
        the filter adds per interval (consistent with its own model)."""
        zq = z.copy()
        zq[: self.nq] = iv.q0
        n = self.substeps(old, dt)
        dl = iv.q0 - old.q0
        held = held_step(zq, u, dl, s_old, dt / n, n, old.system)[0]
        # iv's own held system at its centre (no offset, no secant step): the exact configuration
        exact = held_step(zq, u, np.zeros(self.nq), 0.0, dt / n, n, iv.system)[0]
        P = self.state_cov()
        q = old.map.Q.diagonal() if old.map is not None else None
        e_q = float(np.max(np.abs(held - exact) / np.sqrt(np.maximum(q, 1e-300)))) if q is not None else math.nan
        c, channels = self._centre, self._measured
        if c is not None and channels:  # the filter's gain: the channels it measured last
            bias = self._persistent_bias(P[: self.nx, : self.nx], self._centre_rows(c, channels)[1],
                                         self._noise(channels), iv.rc, dz=held - exact)
            if bias is not None:
                return bias, e_q
        sig = np.sqrt(np.maximum(np.diagonal(P)[: self.nx], 1e-300))
        return float(np.max(np.abs(held - exact) / sig)), e_q

    def _radius(self, old: _Held, dist: float, err: float, tol: float, p: float) -> float:
        """Next refresh radius from the error ``err`` of the last held model after ``dist`` rad: the error grows
        as ``dist^p`` (3: second order, with a secant partner; 2: first order), so the radius that keeps it at
        ``tol`` is ``dist (tol / err)^(1/p)`` (with a 0.9 margin, at most twice the last radius, within
        ``[refresh_min, refresh_max]``). The model's curvature in q varies along a path, and a fixed radius would
        be either wasteful or unsafe."""
        if not err > 0:
            return min(2.0 * old.rad, self.refresh_max)
        rad = 0.9 * dist * (tol / err) ** (1.0 / p)
        return float(min(max(rad, self.refresh_min), 2.0 * old.rad, self.refresh_max))

    def _prediction_error(self, old: _Held, iv: _Held) -> float:
        """How well the previously held model predicted the new configuration: the relative error of ``M_r`` and
        ``K_r`` predicted by ``old`` at ``iv.q0``, in the metric of the new ``M_r``
        (:func:`.expansion.prediction_error`)."""
        dl = iv.q0 - old.q0
        s = float(dl @ old.d) / old.dd if old.old is not None else 0.0
        return float(prediction_error(dl, s, iv.mats.Mr, iv.mats.Kr, tuple(old.system)))

    def _held_system(self, iv: _Held) -> HeldSystem:
        """The arrays of the compiled cached step while iv is held (:class:`.expansion.HeldSystem`)."""
        fm, m = iv.forces, iv.mats
        old = iv.old
        o, om, oCa = (fm, m, iv.Ca) if old is None else (old.forces, old.mats, old.Ca)
        hess, We, Me = None, _NO_ROWS, _NO_ROWS
        if self._weight and self.rm.consistent and fm.dHdq is not None and self.r > self.nq:
            # the weight's and the mass matrix's q-gradients at the sag (ReducedModel.weight_curvature,
            # ReducedModel.mass_curvature), with the basis's second derivatives the velocity forms take as well
            hess = self.rm.basis_hessian(m.rc.cfg.pose.q)
            We = self.rm.weight_curvature(m, fm.dHdq, hess)
            Me = self.rm.mass_curvature(m, fm.dHdq, hess)
        # under gravity every force's q-gradient enters the step Jacobian: the velocity forms' too
        # (ReducedModel.velocity_forms_gradient)
        dT2, dV2, dC2 = self.rm.velocity_forms_gradient(m.rc.cfg.pose.q) if self._weight else (_NO_ROWS,) * 3
        return HeldSystem(
            has_old=old is not None, beta=float(self.model.beta), Mr=m.Mr, Kr=m.Kr, Ca=iv.Ca, Gr=m.Gr,
            dM=fm.dMr2, dK=fm.dKr2, fg=fm.fg, T2=fm.T2, V2=fm.V2, C2=self._c2(fm),
            old_dM=o.dMr2, old_dK=o.dKr2, old_Ca=oCa, old_Gr=om.Gr, old_fg=o.fg, old_T2=o.T2, old_V2=o.V2,
            old_C2=self._c2(o), **self._elastic(fm), Wg=fm.Wg, old_Wg=o.Wg, **self._velocity_forms(iv, hess),
            KGd=fm.KGd, We=We, dKGd=fm.dKGd, dT2=dT2, dV2=dV2, dC2=dC2, Me=Me)

    def _velocity_forms(self, iv: _Held, hess: np.ndarray | None = None) -> dict:
        """``pT``, ``pC2`` (:class:`.expansion.HeldSystem`): the velocity forms ``T`` and ``C2`` of the held
        configuration differentiated in each elastic coordinate ``p_m`` (empty in the paper's form, ``J = H``).

        The held configuration is undeformed; a deformed one has the velocity map ``J = J_0 + sum_m p_m A_m``,
        ``A_m = [d(H e_m)/dq, 0]`` (its rigid columns). The velocity tensor ``T(J)`` (``J^T h(J w) = 1/2 sum_k w_k
        T_k w``, :meth:`~exuflex.erls.model.ErlsModel.velocity_force_tensor`) is quadratic in ``J`` (through ``W J``),
        so its derivative along ``A_m`` is the central difference ``(T(J_0 + c A_m) - T(J_0 - c A_m)) / 2c``
        exactly, for any ``c`` (``c |A_m| = |J_0|``: the differences' round-off at the forms' own scale); the bias
        form ``C2[k, j] = 2 (W J)^T M_N W d(H e_k)/dq_j`` is linear in ``J``: ``pC2_m`` takes ``W A_m`` for ``W J``.
        The bias acceleration's curvature term ``d^2(H p)/dq^2 [q', q']`` (:meth:`.ReducedModel.basis_curvature`)
        is linear in the elastic coordinates and zero at the held configuration: its force ``-(W J_0)^T M_N W
        d^2(H e_m)/dq_k dq_j q'_k q'_j p_m`` is a bilinear form in the joint rates per unit ``p_m``, added to
        ``pC2_m``'s entries ``k < nq`` (:meth:`.ReducedModel.basis_hessian`). The geometric q-row form ``V`` is
        exact in the elastic coordinates already."""
        nq, r = self.nq, self.r
        fm = iv.forces
        if fm.elastic is None or fm.dHdq is None or r == nq:
            return {"pT": _NO_ROWS, "pC2": _NO_ROWS}
        model = self.model
        cfg = iv.mats.rc.cfg
        J0 = iv.mats.J
        dHdq = fm.dHdq  # (r, n, nq): d(H e_k)/dq
        Sd = model.coordinate_derivatives(cfg)
        MW = cfg.M_N @ cfg.W
        n_el = r - nq
        pT = np.empty((n_el, r * r * r))
        pC2 = np.empty((n_el, r * nq * r))
        scale = float(np.abs(J0).max())
        for m in range(n_el):
            A = np.zeros_like(J0)
            A[:, :nq] = dHdq[nq + m]
            c = scale / max(float(np.abs(A).max()), 1e-300)
            dT = (model.velocity_force_tensor(cfg, J0 + c * A, Sd) - model.velocity_force_tensor(cfg, J0 - c * A, Sd))
            pT[m] = (dT / (2.0 * c)).ravel()
            dJtM = (cfg.W @ A).T @ MW  # (r, n): d((W J)^T M_N W) along A_m, rows j < nq only
            pC2[m] = (2.0 * np.swapaxes(dJtM @ dHdq, 1, 2)).ravel()
        # the curvature of the bias acceleration: (W J_0)^T M_N W Z_m[:, k, j] in pC2_m[k, j, :], k < nq
        Z = self.rm.basis_hessian(cfg.pose.q) if hess is None else hess  # (r - nq, n, nq, nq)
        JtMW = (cfg.W @ J0).T @ MW  # (r, n)
        pC = pC2.reshape(n_el, r, nq, r)
        pC[:, :nq] += np.einsum("cx,mxkj->mkjc", JtMW, Z)
        return {"pT": pT, "pC2": pC2}

    @staticmethod
    def _elastic(fm) -> dict:
        """The held system's elastic-coordinate terms (``pM, pK, pC, pG, p2C``; empty in the paper's form)."""
        names = ("pM", "pK", "pC", "pG", "p2C")
        return dict.fromkeys(names, _NO_ROWS) if fm.elastic is None else dict(zip(names, fm.elastic, strict=True))

    def _c2(self, fm) -> np.ndarray:
        return self._noC2 if fm.C2 is None else fm.C2

    def _held_at(self, z: np.ndarray, u: np.ndarray, dt: float) -> tuple[_Held, np.ndarray]:
        """The held configuration for an interval from ``z`` (evaluated anew when q left its radius) and
        ``dl = q - q0``."""
        iv = self._last
        dl = self._offset(iv, z, iv.rad) if iv is not None and iv.system is not None else None
        if dl is not None:
            return iv, dl
        iv = self._refresh(z, u, dt)
        return iv, z[: self.nq] - iv.q0

    def _offset(self, iv: _Held, x: np.ndarray, radius: float) -> np.ndarray | None:
        """``dl = q - q0`` of the state ``x`` from the held ``iv`` if within ``radius`` (max norm); else None."""
        dl = x[: self.nq] - iv.q0
        return dl if max(map(abs, dl.tolist())) <= radius else None

    def _hold(self, z: np.ndarray, u: np.ndarray, dt: float) -> tuple[_Held, np.ndarray, int, _StepMap]:
        """The held configuration and its step map for an interval of ``dt`` from ``z``, each renewed where q
        left its radius (:meth:`_held_at`, :meth:`_step_map`), with ``dl = q - q0`` and the sub-steps ``n``. An
        interval the compiled loop renewed and handed back (``_renewed``) keeps what was renewed for it."""
        done, self._renewed = self._renewed, None
        if done is not None and done[1] == dt and np.array_equal(done[0], z):
            return done[2]
        iv, dl = self._held_at(z, u, dt)
        n = self.substeps(iv, dt)
        return iv, dl, n, self._step_map(iv, z, dl, dt, n)

    def _cached(self, z: np.ndarray, u: np.ndarray, dt: float, du: np.ndarray) -> Prediction:
        """The cached step: the held configuration (evaluated anew when q left its radius), the model at z
        followed from it to second order and advanced by the interval's sub-steps (the torques ``u + (t/dt) du``),
        with the step map's Jacobian correction and process noise (:meth:`_step_map`)."""
        iv, dl, s, n, sm = self.prepare(z, u, dt)
        z_next, F, Mr, Kr, Cr, Gr = held_interval(z, u, du, dl, s, dt / n, n, *sm.tail)
        if not math.isfinite(z_next[0]) and (s or np.any(dl)):
            iv, dl, s, n, sm = self.rescue(z, u, dt)
            z_next, F, Mr, Kr, Cr, Gr = held_interval(z, u, du, dl, s, dt / n, n, *sm.tail)
        self._interval_matrices = (Mr, Kr, Cr, Gr, dt / n, n)
        return Prediction(z_next, F, sm.Q)

    def rescue(self, z: np.ndarray, u: np.ndarray, dt: float) -> tuple:
        """Where the held model broke down before its radius said so (``M_r`` not positive definite: a step that
        went non-finite): the configuration evaluated anew at ``z`` and its step map, ``(iv, dl, s, n, sm)`` as
        :meth:`prepare` returns them, the secant left out (``s = 0``)."""
        self.n_rescue += 1
        iv = self._refresh(z, u, dt)
        dl = z[: self.nq] - iv.q0
        n = self.substeps(iv, dt)
        sm = self._step_map(iv, z, dl, dt, n)
        self.last_step = (iv, sm)
        return iv, dl, 0.0, n, sm

    # ------------------------------------------------------------------ the filter's compiled sample loop
    @property
    def compiled(self) -> bool:
        """The filter's compiled sample loop (:func:`.loop.samples`) may take this model's intervals: the cached
        step (the exact reference step runs sample by sample)."""
        return self.method == "cached"

    def loop_model(self, z: np.ndarray, u: np.ndarray, dt: float, channels: tuple) -> LoopModel:
        """The cached step as the compiled loop takes it (:class:`.expansion.CachedStep`, its carried
        :class:`.expansion.LoopState`) for samples from the state ``z`` with the torques ``u`` over ``dt``: the held
        configuration and its step map renewed for that interval where q left their radii (as :meth:`predict`
        would), the present measurement rows of ``channels`` (:meth:`measure` rebuilds them where the loop hands a
        measurement back: the same rows as sample by sample)."""
        held = iv, _, _, sm = self._hold(z, self._input(u), dt)
        self._renewed = (z.copy(), dt, held)  # for predict(), if the loop hands this interval back
        c = self._centre
        # none yet: the loop hands the first measurement back (measure() makes them there)
        c0, Hm, D, G = self._rows_none(channels) if c is None else self._centre_rows(c, channels)
        q_rows, rad_rows = (np.zeros(self.nq), -1.0) if c is None else (c.q0, c.rad)
        d = iv.d if iv.old is not None else _NONE
        step = CachedStep(self.jump_test.weights, self._jump_threshold, self.ramp, self.input_delay, iv.q0, iv.rad, self._measurement_radius(iv),
                          min(self.h, iv.h_stable), self.dt_tol, self.remap_ahead, self.remap_horizon,
                          self.torque_var, self.q_extra_diag, *self._map_radius_limits, c0, Hm, D, G,
                          q_rows, rad_rows, d, iv.dd,
                          *sm.tail[:3], self._map_errs, iv.system)
        state = LoopState(LoopMap(sm.q, self.map_rad, sm.dt, sm.n, sm.Pn, sm.S, sm.L, sm.Q), 0, -1,
                          (False, 0.0, sm.Pn, sm.S, sm.L, sm.Q))
        self._loop_step = (iv, sm)
        return LoopModel(step, state, None)

    def _rows_none(self, channels: tuple) -> tuple:
        """``(c0, Hm, D, G)`` of the right shapes for a loop without rows yet."""
        m, nq = len(channels), self.nq
        return np.zeros(m), np.zeros((m, self.nx)), np.zeros((nq, m, self.r)), np.zeros((m, nq, nq))

    @property
    def ramp(self) -> float:
        """The compiled step's input over an interval (:class:`.expansion.CachedStep`): 1.0 linear, 0.0 held."""
        return 1.0 if self._input_hold == "linear" else 0.0

    @property
    def _jump_threshold(self) -> float:
        """The torque-jump test's threshold as the compiled step takes it: infinite (no test) with a linear input."""
        return self.jump_test.threshold if self._input_hold == "zoh" else math.inf

    @property
    def loop_step(self) -> tuple:
        """``(iv, sm)``: the held configuration and step map :meth:`loop_model` last handed the loop."""
        return self._loop_step

    def loop_done(self, mats: tuple, dt: float, state: LoopState, z: np.ndarray, k: int) -> None:
        """After samples of the compiled loop up to ``k`` (not done), the filter's state now ``z``: the step maps
        it rebuilt (``state``, :func:`.expansion.cached_interval`), and ``last_step`` and :attr:`interval_system`
        of its last interval (matrices ``mats`` over ``dt``), as :meth:`predict` leaves them. A map built for
        sample ``k`` stays the map of that interval when :meth:`predict` takes it."""
        iv, sm = self._loop_step
        lm, n_maps, k_map = state.map, state.n_maps, state.k_map
        self.map_rad = lm.rad
        if n_maps:
            sm = self._new_map(iv, lm.dt, sm.n, lm.q, lm.Pn, lm.SQM, lm.L, lm.Q)
            self.n_remap += n_maps
            self.map_errors.extend(self._map_errs[:n_maps].tolist())
            if k_map == k:
                self._renewed = (z.copy(), lm.dt, (iv, z[: self.nq] - iv.q0, sm.n, sm))
        self.last_step = (iv, sm)
        n = self.substeps(iv, dt)
        self._interval_matrices = (*(a.copy() for a in mats), dt / n, n)

    @property
    def n_inputs(self) -> int:
        """The number of inputs a step takes: one torque per motor."""
        return self._u_shape[0]

    # ------------------------------------------------------------------ for models built on this one (augmented)
    def torques(self, u) -> np.ndarray:
        """The motor torques ``u`` as an array of the model's motor count (zeros for None); a clear error else."""
        return self._input(u)

    @property
    def interval_system(self) -> tuple:
        """``(M_r, K_r, C_r, G_r, h, n)`` of the last interval: the held matrices of its sub-steps (cached: at its
        midpoint elastic coordinates) and its ``n`` sub-steps of ``h`` (:meth:`predict`; after :meth:`prepare`,
        those of the caller's own step)."""
        return self._interval_matrices

    @interval_system.setter
    def interval_system(self, value: tuple) -> None:
        self._interval_matrices = value

    @staticmethod
    def secant_factor(iv: _Held, dl: np.ndarray) -> float:
        """How far along the secant to its previous configuration q has moved from the held ``iv`` (0 without a
        usable secant): the factor the cached step uses."""
        return _secant_factor(iv, dl)

    def prepare(self, z: np.ndarray, u: np.ndarray, dt: float) -> tuple:
        """Everything of the cached step over ``dt`` from ``z`` with the torques ``u`` except the step itself: the
        held configuration (evaluated anew where q left its radius) and the step map, and ``last_step`` as
        :meth:`predict` leaves it. Returns ``(iv, dl, s, n, sm)``: the held configuration, ``dl = q - q0``, the
        secant factor, the sub-steps and the step map. For a model that steps a modified held system itself (a
        payload scale: :mod:`.augmented`) and would discard the nominal sub-steps; it sets :attr:`interval_system`
        to its own step's held matrices (for :meth:`input_jump_moments`)."""
        iv, dl, n, sm = self._hold(z, u, dt)
        self.last_step = (iv, sm)
        return iv, dl, _secant_factor(iv, dl), n, sm

    def _step_map(self, iv: _Held, z: np.ndarray, dl: np.ndarray, dt: float, n: int) -> _StepMap:
        """The held configuration's step map, rebuilt when q moved the map radius from where it was built or the
        interval's length changed by more than ``dt_tol``: built ahead of q along its motion
        (:func:`.expansion.map_lookahead`), from the held model there (not beyond the measurement radius). A
        rebuild at the same interval length measures the replaced map's error and sets the next radius
        (:func:`.expansion.next_map_radius`)."""
        sm = iv.map
        if sm is not None and abs(sm.dt - dt) <= self.dt_tol * dt and \
                max(map(abs, map(sub, z[: self.nq].tolist(), sm.q_list))) <= self.map_rad:
            return sm
        new = self._new_map(iv, dt, n, *rebuild_map(z, iv.q0, self._measurement_radius(iv), self.map_rad,
                                                    self.remap_ahead, self.remap_horizon, *self._secant(iv), dt, n,
                                                    self.torque_var, self.q_extra_diag, tuple(iv.system)))
        self.n_remap += 1
        if sm is not None and sm.n == n and abs(sm.dt - dt) <= self.dt_tol * dt and self.state_cov is not None:
            err = map_error(sm.Pn, new.Pn, sm.Q, new.Q, self.state_cov())
            self.map_errors.append(err)
            self.map_rad = next_map_radius(new.q, sm.q, err, self.map_rad, *self._map_radius_limits)
        return new

    def _new_map(self, iv: _Held, dt: float, n: int, q, Pn, S, L, Q) -> _StepMap:
        """``iv``'s step map, now ``(q, P^n, S, L, Q)`` (:func:`.expansion.rebuild_map`)."""
        new = iv.map = _StepMap(q, dt, n, Pn, S, L, Q)
        new.q_list = q.tolist()
        new.tail = (*iv.forces.jacobian_tensors(), Pn, S, tuple(iv.system))
        return new

    @property
    def _map_radius_limits(self) -> tuple:
        """``(remap_tol, remap_min, remap_max)``: the last arguments of :func:`.expansion.next_map_radius`."""
        return self.remap_tol, self.remap_min, self.remap_max

    @staticmethod
    def _secant(iv: _Held) -> tuple:
        """``(d, d . d)`` of iv's secant (``d`` empty without a partner)."""
        return (iv.d, iv.dd) if iv.old is not None else (_NONE, 0.0)

    # ------------------------------------------------------------------ the reference step
    def _rk4(self, z: np.ndarray, u: np.ndarray, dt: float, du: np.ndarray) -> Prediction:
        """Every RK4 stage of the nonlinear reduced equations at its own state and input; ``F`` and ``Q`` those of
        the configuration at the interval's start (:meth:`frozen_interval`)."""
        pred, iv, sm = self.frozen_interval(z, u, dt, du)
        self._last = iv
        self.last_step = (iv, sm)
        return Prediction(self.advance(z, u, dt, iv, du), pred.F, pred.Q)

    def advance(self, z: np.ndarray, u, dt: float, iv: _Held | None = None, du=None) -> np.ndarray:
        """The reduced equations ``M_r(p) p'' + C_r(p) p' + K_r(p) p = G_r(p) u + f_r(p, p')`` integrated over
        ``dt`` from ``z`` with the torques ``u`` held (``du`` None) or ``u + (t / dt) du``: RK4 sub-steps
        (:meth:`substeps`, of the configuration ``iv`` at ``z``, evaluated if not given), every stage at its own
        state and input (:func:`rk4_input_steps`). The reference step's state."""
        u = self._input(u)
        z = np.asarray(z, float)
        if iv is None:
            iv = self._configuration(z)
        n = self.substeps(iv, dt)
        if du is None or not np.any(du):
            x = z.copy()
            for _ in range(n):
                x = rk4_step(self.rm.rhs, 0.0, x, dt / n, u)
            return x
        return rk4_input_steps(self.rm.rhs, z, u, np.asarray(du, float), dt, n)

    # ------------------------------------------------------------------ the model's interface
    def _input(self, u) -> np.ndarray:
        """The motor torques as an array of the model's motor count (zeros for None); a clear error else."""
        if u is None:
            return np.zeros(self._u_shape)
        u = np.ascontiguousarray(u, float)  # (a log's row may be strided: one compiled version of each kernel)
        if u.shape != self._u_shape:
            raise ValueError(f"input has shape {u.shape}, expected {self._u_shape}: one torque per motor "
                             f"{list(self.mech.motor_names)}")
        return u

    def predict(self, x: np.ndarray, u, dt: float, u_next=None) -> Prediction:
        """Advance ``x`` over ``dt`` from the torques ``u`` (:class:`~exuflex.observer.base.Prediction`): held, or
        linear to ``u_next`` (the sample that ends the interval) with a linear :attr:`input_hold`; held, a torque
        jump within the interval (``u_next`` far from ``u``, :meth:`input_jump`) adds its effect."""
        u = self._input(u)
        x = np.asarray(x, float)
        u0, du = self.interval_input(u, u_next, dt)
        pred = self.interval(x, u0, dt, du)
        if u_next is not None and self._input_hold == "zoh":
            jump = self.input_jump(u, u_next)
            if jump is not None:
                dx, dQ = self.input_jump_moments(jump)
                pred = Prediction(pred.x + dx, pred.F, pred.Q + dQ)
        return pred

    def interval(self, x: np.ndarray, u, dt: float, du: np.ndarray) -> Prediction:
        """The step over ``dt`` from ``x`` with the torques ``u + (t / dt) du`` (:meth:`predict` without the
        torque-jump test): the cached step or the reference."""
        u = self._input(u)
        x = np.asarray(x, float)
        return self._cached(x, u, dt, du) if self.method == "cached" else self._rk4(x, u, dt, du)

    def input_jump(self, u0, u1):
        """The increment ``u1 - u0`` of two successive torque samples if it is a jump: beyond what the sample
        noise explains (chi-square test against twice the noise variance, false-alarm probability ``jump_p`` per
        interval); else (and with ``jump_p`` None) None. A jump is counted in ``n_jumps`` (the interval that holds it
        is predicted with it: :meth:`input_jump_moments`)."""
        if self.jump_p is None or not self.jump_test(u0, u1):
            return None
        self.n_jumps += 1
        return np.subtract(u1, u0)

    def input_jump_moments(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and covariance of the effect of a torque jump ``d`` at an unknown instant of the last interval.

        The torques a controller applies change at its own steps, not at the sensor samples: a jump between two
        samples is held at its old value for part of the interval, a deterministic error the held-input step
        cannot see. The jump is taken at one of the interval's sub-step boundaries ``j = 1..n`` with equal
        probability (``j = n``: at the next sample, no effect), and ``R_j``, the response at the interval's end
        to ``d`` applied from sub-step ``j`` on (RK4 of the linear system of the last :meth:`predict`), is
        moment-matched: the prediction is shifted by the mean of the ``R_j`` and their covariance is added to
        the process noise.
        """
        Mr, Kr, Cr, Gr, h, n = self._interval_matrices
        P1, _, L1 = step_maps(np.linalg.inv(Mr), Kr, Cr, Gr, h, 1)
        R = np.zeros((n, self.nx))  # row j - 1: the jump at sub-step boundary j (row n - 1: none)
        v = L1 @ d  # one sub-step's response, carried to the interval's end by the later sub-steps
        for j in range(n - 1, 0, -1):
            R[j - 1] = R[j] + v
            v = P1 @ v
        mean = R.mean(axis=0)
        D = R - mean
        return mean, (D.T @ D) / n

    # ------------------------------------------------------------------ measurements
    def _measurement_radius(self, iv: _Held) -> float:
        """The held model's reach: 1.5 refresh radii (at least ``refresh_min``), how far from the held configuration
        a step map may be built (:meth:`_step_map`). The measurement rows have their own radius
        (:meth:`_rows_radius`)."""
        return 1.5 * max(iv.rad, self.refresh_min)

    def _rows(self, iv, channels: tuple) -> tuple:
        """``(c0, Hm, D, G)`` of the channels about the configuration ``iv`` (:meth:`_expansion`); kept with a held
        configuration."""
        cache = iv.rows if isinstance(iv, _Held) else None
        rows = None if cache is None else cache.get(channels)
        if rows is None:
            rows = self._expansion(iv, channels)
            if cache is not None:
                cache[channels] = rows
        return rows

    def _measurement_rows(self, x: np.ndarray, channels: tuple) -> tuple:
        """``(c0, Hm, D, G, q0)``: the measurement rows of ``channels`` that serve at ``x`` and their centre: the
        present centre's while q lies within its radius, else a new centre's (:meth:`_recentre`)."""
        c = self._centre
        if c is None or max(map(abs, map(sub, x[: self.nq].tolist(), c.q_list))) > c.rad:
            c = self._recentre(x, channels, c)
        return (*self._centre_rows(c, channels), c.q0)

    def _centre_rows(self, c: _RowsCentre, channels: tuple) -> tuple:
        """``(c0, Hm, D, G)`` of ``channels`` about the centre ``c``, made once."""
        rows = c.rows.get(channels)
        if rows is None:
            rows = c.rows[channels] = self._rows(c.at, channels)
        return rows

    def _recentre(self, x: np.ndarray, channels: tuple, old: _RowsCentre | None) -> _RowsCentre:
        """A new centre of the measurement rows for the state ``x``: the held configuration if it lies within the
        radius of q and ahead of it along its motion (no evaluation), else a configuration evaluated for them ahead
        of q along its motion (``lookahead`` radii: the rows are as good behind their centre as ahead of it). With
        the centre it replaces, the replaced rows' error (of ``channels``) sets the new radius
        (:meth:`_rows_error`, :meth:`_rows_radius`)."""
        nq = self.nq
        self._measured = channels  # (the same samples whether the compiled loop or step by step makes the rows)
        rad = self.rows_rad if old is None else old.rad
        q, qd = x[:nq], x[self.r : self.r + nq]
        iv = self._last
        if iv is None or _max_abs(q - iv.q0) > rad or float((iv.q0 - q) @ qd) < 0.0:
            iv = None
            vmax = _max_abs(qd)
            if vmax > 0.0:
                try:
                    iv = self._rows_at(q + (self.lookahead * rad / vmax) * qd)
                except KinematicsError:  # ahead lies beyond the workspace: evaluate here
                    iv = None
            if iv is None:
                iv = self._rows_at(q)
        new = self.rows_about(iv, rad)
        if old is not None:
            err = self._rows_error(old, new, x, channels)
            new.rad = self._rows_radius(old.rad, _max_abs(new.q0 - old.q0), err)
            self.rows_errors.append((err, new.rad))
        return new

    def rows_about(self, iv: _Held | _RowsAt, rad: float) -> _RowsCentre:
        """Make the configuration ``iv`` the centre of the measurement rows :meth:`measure` takes, within ``rad`` of
        it (until q leaves that radius)."""
        q0 = iv.q0.copy()
        new = self._centre = _RowsCentre(iv, q0, q0.tolist(), float(rad), {})
        self.n_rows += 1
        return new

    def _rows_at(self, q: np.ndarray) -> _RowsAt:
        """The configuration at ``q`` as the measurement rows need it (the basis and the link angles)."""
        rc = self.rm.cb.at(q)
        pose = rc.cfg.pose
        self.n_evaluations += 1
        return _RowsAt(np.array(q, float), rc, pose.Sz[2::3].copy(), pose.z[2::3].copy())

    def _rows_error(self, old: _RowsCentre, new: _RowsCentre, x: np.ndarray, channels: tuple) -> float:
        """The replaced rows' error where the new ones are exact, at the filter's state ``x`` moved to the new
        centre: ``dy = y_old - y_new``. The rows' error is of second order in the distance from their centre and
        proportional to the elastic state (the elastic rows' change, ``O(dl^2 |p_e|)``), of third order in the rigid
        parts, and of one sign over the radius: a bias of the channels that persists over every update the rows
        serve.

        Without the filter's covariance: ``max_i |dy_i| / noise_i``, what the filter can tell from its
        measurements. With it (:meth:`watch_covariance`): what that bias does to the estimate
        (:meth:`_persistent_bias`): the filter's steady response to the channels biased by ``dy`` at every update,
        in the coordinates' estimates (the encoders' readings and their rates) over the filter's standard deviation
        of them. Against a channel's own noise or standard deviation instead, a gauge's bias of a tenth of its
        standard deviation biased the reading of a relative joint by 0.5 to 3.8 of the filter's standard deviation
        of it (the filter averages several hundred samples of the gauge, and the reading's combination of q and
        the elastic rotation is what the gauges inform most): docs/reading_floor.md."""
        xq = np.array(x[: self.nx], float)
        xq[: self.nq] = new.q0
        c0, Hm, D, G = self._centre_rows(old, channels)
        y_old, H = np.empty(len(c0)), np.empty_like(Hm)
        measurement_rows(c0, Hm, D, G, xq, new.q0 - old.q0, y_old, H)
        c0, Hm = self._centre_rows(new, channels)[:2]
        dy = y_old - c0 - Hm @ xq
        s = self._noise(channels)
        if self.state_cov is not None:
            bias = self._persistent_bias(self.state_cov()[: self.nx, : self.nx], Hm, s, new.at.rc, dy=dy)
            if bias is not None:
                return bias
        return float(np.max(np.abs(dy) / s))

    def _persistent_bias(self, P: np.ndarray, Hm: np.ndarray, noise: np.ndarray, rc, *, dy=None, dz=None
                         ) -> float | None:
        """The filter's steady bias from an error that repeats at every interval, over its standard deviation, in the
        coordinates' estimates: ``max_j |T_j b| / sqrt(T_j P+ T_j^T)`` with ``T`` the rows of the coordinates'
        readings and their rates (``q + R p``, ``q' + R p'``, :meth:`reading_maps` at the configuration ``rc``).

        A channel bias ``dy`` at every update or a state error ``dz`` at every prediction moves the posterior
        error by ``e+ = A e + c`` per interval, ``A = (I - K H) F`` (the filter's error map, ``K = P H^T (H P H^T +
        R)^-1`` its gain from the covariance ``P`` and the channels' rows ``H`` and noise ``R``, ``F`` the held step
        map's state map) and ``c = -K dy`` or ``(I - K H) dz``; repeated, the error tends to ``b = (I - A)^-1 c``.
        The error a held approximation makes grows over its radius from zero at its centre, so its steady response
        over-states what a radius' worth of intervals leaves when the filter's memory (the intervals over which
        ``A^k`` decays) exceeds them, and is what it leaves where the memory is shorter. None (the caller's own
        figure serves) without a held step map or where the error map is not contracting (the filter not
        converged: ``|eig(A)| >= 1``)."""
        iv = self._last
        if iv is None or iv.map is None or iv.map.Pn.shape[0] != self.nx:
            return None
        F = iv.map.Pn
        S = Hm @ P @ Hm.T
        S[np.diag_indices_from(S)] += noise**2
        S = 0.5 * (S + S.T)
        try:
            K = np.linalg.solve(S, Hm @ P).T  # P H^T S^-1 (S, P symmetric)
        except np.linalg.LinAlgError:
            return None
        IKH = np.eye(self.nx) - K @ Hm
        A = IKH @ F
        if np.max(np.abs(np.linalg.eigvals(A))) >= 1.0:
            return None
        c = np.zeros(self.nx)
        if dy is not None:
            c -= K @ dy
        if dz is not None:
            c += IKH @ dz
        b = np.linalg.solve(np.eye(self.nx) - A, c)
        nq, r = self.nq, self.r
        T = np.zeros((2 * nq, self.nx))
        T[:nq, :nq] = T[nq:, r : r + nq] = np.eye(nq)
        R = self._reading_rows(rc)
        T[:nq, :r] += R
        T[nq:, r:] += R
        Pp = IKH @ P
        sd = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", T, Pp, T), 1e-300))
        return float(np.max(np.abs(T @ b) / sd))

    def _noise(self, channels: tuple) -> np.ndarray:
        """The channels' noise standard deviations (the sensors' ``noise_std``; infinite for a channel without
        noise, which no filter takes: its error is not measured)."""
        return np.array([self.sensors[c].noise_std or math.inf for c in channels], float)

    def _rows_radius(self, rad: float, dist: float, err: float) -> float:
        """The next measurement radius from the replaced rows' error ``err`` at ``dist`` rad from their centre
        (:meth:`_rows_error`): the error grows as ``dist^2`` (the elastic rows' second-order term; the rigid parts'
        third-order one grows faster, so this shrinks the radius more than they need), so the radius that keeps it
        at ``rows_tol`` is ``dist (rows_tol / err)^(1/2)`` (with a 0.9 margin, at most twice the last radius
        ``rad``, within ``[rows_min, rows_max]``)."""
        if not err > 0:
            return min(2.0 * rad, self.rows_max)
        new = 0.9 * dist * math.sqrt(self.rows_tol / err)
        return float(min(max(new, self.rows_min), 2.0 * rad, self.rows_max))

    def measure(self, x: np.ndarray, channels: Sequence[str]) -> Measurement:
        """The channels at ``x`` from the measurement rows about a configuration ``q0`` and their exact first-order
        change with q (:meth:`_expansion`): ``y_i = c0_i + (Hm + sum_k dl_k D_k)_i x + 1/2 dl^T G_i dl``,
        ``dl = q - q0``, and ``H`` its derivative in x (:func:`.expansion.measurement_rows`) except the elastic rows'
        change with q, ``D_j x``, in the q-columns. The rows are rebuilt where q leaves their radius, which their
        own error controls (:meth:`_recentre`). ``D_j x`` makes the gauges a source of information on q, through
        the elastic rows' q-sensitivity times the elastic state: a detail of the reduced model less accurate than
        the filter would then take it to be. With a channel's bias as a state (the six-bar's q1, read once:
        ``tests/test_bias.py``) the filter estimated the bias from it with a standard deviation of 1.6 mrad and
        an error of 22 mrad on the full-order ERLS log. Left out, q is informed by the encoders and the rigid
        rows as before; the value ``y`` follows q, which is what the filter's consistency needs."""
        x = np.asarray(x, float)
        c0, Hm, D, G, q0 = self._measurement_rows(x, tuple(channels))
        H = np.empty_like(Hm)
        y = np.empty(len(c0))
        measurement_rows(c0, Hm, D, G, x, x[: self.nq] - q0, y, H)
        return Measurement(y, H)

    def _affine(self, iv: _Held | _RowsAt, channels: tuple) -> tuple[np.ndarray, np.ndarray]:
        """``y = c0 + Hm x`` for the channels, about the configuration ``iv`` (rigid parts to first order in q,
        elastic parts exact in p): the rows of :func:`.rows.sensor_rows`, for all channels at once
        (:class:`.rows.ChannelRows`)."""
        return self._affine_rows(iv, channels)[:2]

    def _affine_rows(self, iv: _Held | _RowsAt, channels: tuple) -> tuple:
        """``(c0, Hm, U, plan)``: :meth:`_affine`'s rows, the channels' u rows and their :class:`.rows.ChannelRows`."""
        nq, r = self.nq, self.r
        plan = self._channel_rows.get(channels)
        if plan is None:
            plan = self._channel_rows[channels] = channel_rows(
                self.model, [sensor(self.mech, self.sensors, ch) for ch in channels], self.link_names)
        U, points = plan.at(self.model, iv.rc.cfg)
        Hm = np.zeros((len(channels), self.nx))
        Hm[:, :r] = _by_rows(U, iv.rc.H[nq:])
        rows = _by_rows(plan.angle, iv.Sz_theta)  # the link-angle channels' rigid rows
        c0 = plan.angle @ iv.theta0 - rows @ iv.q0
        Hm[:, :nq] += rows
        for i, p0, Sp in points:
            c0[i] = p0 - Sp @ iv.q0
            Hm[i, :nq] += Sp
        return c0, Hm, U, plan

    def _expansion(self, iv: _Held | _RowsAt, channels: tuple) -> tuple:
        """``(c0, Hm, D, G)``: the channels about the configuration ``iv`` to first order in ``dl = q - q0``.

        Every channel is ``y(q, p) = rigid(q) + U(q) H_u(q) p`` (:mod:`.rows`; ``H_u`` the basis's
        elastic-displacement rows, whose q-columns are zero). :meth:`_affine` gives ``y ~ c0 + Hm x`` with the
        rigid part to first order and the rows at ``q0``. To first order in ``dl`` the rows ``E = U H_u`` change
        by ``sum_k dl_k D_k``, ``D_k = dU/dq_k H_u + U dH_u/dq_k`` (the u rows turn with their link's angle,
        :meth:`.rows.ChannelRows.rates`; the basis changes with the configuration, ``dH/dq`` of
        :meth:`~exuflex.reduction.CraigBampton.basis_derivative`), and the rigid part gains its second-order
        term ``1/2 dl^T G dl``, ``G = d^2 rigid/dq^2``. The error of ``y`` is then ``O(dl^2 |p_e|) + O(dl^3)``
        (against ``O(dl |p_e|) + O(dl^2)`` of the rows at ``q0`` alone); ``H``'s elastic columns err by
        ``O(dl^2)``, its q-columns by ``O(|p_e|) + O(dl^2)`` (the elastic rows' q-derivative is left out of them,
        :meth:`measure`)."""
        nq, r = self.nq, self.r
        c0, Hm, U, plan = self._affine_rows(iv, channels)
        rc = iv.rc
        Ut, G = plan.rates(self.model, rc.cfg)
        # dU/dq_k = U_theta dtheta_l/dq_k, l each channel's link (none: the encoders)
        turn = np.where((plan.link >= 0)[:, None], iv.Sz_theta[plan.link], 0.0)  # (m, nq)
        m, ne = U.shape
        # d(H_u e_c)/dq_k of the elastic coordinates c (the basis's q-columns do not change)
        dH = iv.dHdq  # the held evaluation's, else computed here
        if dH is None:
            dH = self.rm.cb.basis_derivative(rc, np.eye(r)[:, nq:])
        else:
            dH = dH[nq:]
        dHu = dH[:, nq:, :]  # (r - nq, ne, nq)
        UdH = _by_rows(U, dHu.transpose(1, 0, 2).reshape(ne, -1)).reshape(m, r - nq, nq)
        D = np.zeros((nq, m, r))
        D[:, :, nq:] = UdH.transpose(2, 0, 1) + turn.T[:, :, None] * _by_rows(Ut, rc.H[nq:, nq:])[None]
        return c0, Hm, D, np.ascontiguousarray(G)

    # ------------------------------------------------------------------ physical states
    def initial_state(self, q, qd=None) -> np.ndarray:
        z = self.rm.rest_state(q)
        if qd is not None:
            z[self.r : self.r + self.nq] = qd
        return z

    def tip_maps(self, q, link: str, station: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(A, C, Gr)`` at configuration q: the tip's elastic displacement (global frame) to second order in p,
        ``e = A p + C (Gr p)^2`` (squares entry by entry): ``A`` (2, r) the linear rows (the point's displacement
        rows, :meth:`~exuflex.erls.model.ErlsModel.point_displacement_rows`, in the basis; with a relative angle
        coordinate less the rigid tip's move from q to the coordinates' readings to second order,
        :meth:`_tip_from_reading`), ``C``
        (2, n_g) and ``Gr = G H_u`` (n_g, r) the links' foreshortening in the basis's elastic displacements
        ``u = H_u p`` (:class:`~exuflex.erls.sensing.SecondOrderPlan`)."""
        rc = self.rm.cb.at(q)
        Hu = rc.H[self.nq :]
        key = (link, float(station))
        plan = self._second_order.get(key)
        if plan is None:
            plan = self._second_order[key] = SecondOrderPlan(self.model, [key])
        so = plan.at(rc.cfg.pose)
        A = self.model.point_displacement_rows(rc.cfg, link, station) @ Hu
        C, Gr = so.C[0, :2], so.G @ Hu
        if self.reading_G is not None:
            A, C, Gr = self._tip_from_reading(rc, link, station, Hu, A, C, Gr)
        return A, C, Gr

    def _tip_from_reading(self, rc, link: str, station: float, Hu, A, C, Gr):
        """The tip maps ``(A, C, Gr)`` of the elastic displacement from the rigid tip at the coordinates' readings
        ``q + d``, ``d = R p`` (:meth:`reading_maps`: what a truth's q is), instead of at the ERLS frames' q:
        ``p_rigid(q) - p_rigid(q + d) = -J d - 1/2 d' H_c d`` to second order (``J`` the rigid tip's q-Jacobian,
        ``H_c`` its Hessian per component ``c``). The first order joins ``A``; the second, written as squares like
        the foreshortening's, joins ``C`` and ``Gr``: ``d' H d = sum_i (H_ii - sum_(j != i) H_ij) d_i^2 + sum_(i < j)
        H_ij (d_i + d_j)^2``, rows ``R_i`` and ``R_i + R_j`` that do not depend on H (so that their q-derivatives are
        smooth, unlike an eigenbasis')."""
        kin = self.model.kin
        R = self.reading_G @ Hu  # (nq, r)
        J = kin.point(rc.cfg.pose, link, station)[1]
        li = np.array([kin.link_names.index(link)], dtype=np.int64)
        Hs = kin.coordinate_rates(rc.cfg.pose, li, np.array([float(station)]))  # (nq, 3, nq): d2 x_c / dq_j dq
        nq = self.nq
        pairs = [(i, j) for i in range(nq) for j in range(i + 1, nq)]
        rows = np.vstack([R] + [R[i] + R[j] for i, j in pairs]) if pairs else R
        weights = np.zeros((2, len(rows)))
        for c in range(2):
            H = 0.5 * (Hs[:, c, :] + Hs[:, c, :].T)
            weights[c, :nq] = -0.5 * (2.0 * np.diag(H) - H.sum(axis=1))  # H_ii - sum_(j != i) H_ij
            for k, (i, j) in enumerate(pairs):
                weights[c, nq + k] = -0.5 * H[i, j]
        return A - J @ R, np.hstack([C, weights]), np.vstack([Gr, rows])

    def reading_maps(self, q) -> np.ndarray:
        """(nq, r) rows ``R`` of the coordinates' encoder readings beyond q in the reduced coordinates p at
        configuration q: the physical q (what a relative encoder reads, what a truth reports) is ``q + R p``,
        ``R = G H_u`` (:attr:`reading_G`, ``u = H_u p``); zero rows without a relative angle coordinate."""
        return self._reading_rows(self.rm.cb.at(q))

    def _reading_rows(self, rc) -> np.ndarray:
        """:meth:`reading_maps` at an evaluated configuration ``rc`` of the basis."""
        if self.reading_G is None:
            return np.zeros((self.nq, self.r))
        return self.reading_G @ rc.H[self.nq :]

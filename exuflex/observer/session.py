"""The observer as users run it: a mechanism, a sensor log, and the estimated physical states.

:func:`make_observer` builds the reduced model and the multirate EKF for a mechanism and a channel set;
:func:`estimate` filters a log (offline) and reconstructs the physical states the truth files use
(q, dq/dt, tip elastic displacement and velocity, see :mod:`exuflex.sensors`). Scoring them against a truth and
the bound they are compared with: :mod:`exuflex.scoring`.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import numpy as np

from .. import _compile
from ..erls.kinematics import KinematicsError
from ..erls.model import ErlsModel
from ..manoeuvre import start_configuration
from ..mechanism import Mechanism
from ..reduction import CraigBampton
from ..sensors import Signals, default_channels, tip_point, truth_names
from .augmented import AugmentedModel, nominal_mixture
from .ekf import EstimationResult, Monitoring, MultirateEKF
from .imm import IMMFilter
from .kalman import InputStepTest
from .reduced import ReducedObserverModel
from .smoother import SmoothedResult, rts_smooth
from .ukf import UnscentedKF

#: the estimators :func:`make_observer` builds (``ObserverConfig.estimator``)
ESTIMATORS = ("ekf", "ukf", "ekf-payload", "ekf-input", "imm")
#: the IMM's default expected dwell time in a mode, in manoeuvre durations (``ObserverConfig.imm_dwell_s``): the
#: payload changes within one manoeuvre with the probability ``1 - exp(-1 / IMM_DWELL_MANOEUVRES)``, about 1 %
IMM_DWELL_MANOEUVRES = 100.0
#: the estimators on an augmented state (:mod:`.augmented`)
AUGMENTED_ESTIMATORS = ("ekf-payload", "ekf-input", "imm")

__all__ = [
    "CHUNK_ROWS",
    "ESTIMATORS",
    "EstimateChunk",
    "Observer",
    "ObserverConfig",
    "default_channels",
    "estimate",
    "estimate_chunks",
    "make_observer",
    "physical_names",
    "physical_units",
]


@dataclass(frozen=True)
class ObserverConfig:
    """Observer settings (all recorded in result files).

    Parameters
    ----------
    channels
        measured sensor channels used (default :func:`default_channels`).
    masters, n_interior, q_star, ranking
        the reduction (default: the model file's).
    h
        longest RK4 sub-step (s); shorter where the reduced model's stiffest mode needs it (:mod:`.reduced`).
    dt
        nominal sample interval (s, default 1 / the model's sample rate); the filter steps by each sample's own
        time stamp.
    method
        ``"cached"`` (default) or ``"rk4"`` (the exact reference), see :mod:`.reduced`.
    q0_std, qd0_std, elastic0_std, elastic_rate0_std
        prior standard deviations (rad, rad/s, m or modal units,
        their rates).
    q_scale
        multiplies the torque-noise process covariance; 1.0 (default) is the stated noise. The
        bound always uses the stated noise.
    jump_p
        the false-alarm probability per interval of the test that flags two successive torque samples
        differing by more than their noise (chi-square); a flagged interval gets the effect of a jump at an
        unknown instant within it, moment-matched (:meth:`.reduced.ReducedObserverModel.input_jump_moments`).
        ``None`` (default): no test. The test helps where a log's torque steps fall between two samples, and
        biases the prediction where they fall on a sample (a time law aligned with the samples, as
        ``exuflex simulate`` makes them): there the held-input step is exact.
    q_extra_std
        extra white noise per interval on the elastic rates (unmodelled dynamics), as a standard
        deviation in the state's unit.
    max_gap
        longest interval (s) between two samples the filter predicts over.
    start_up
        seconds left out of the error metrics (the filter's transient).
    gate_p, fault_window, fault_p
        per-channel innovation gate and sensor-fault tests (see
        :mod:`.ekf`, :class:`.ekf.ChannelMonitor`); ``gate_p=None`` and ``fault_window=0`` turn them off.
    fault_isolation
        leave a channel with an open offset or stuck fault out of the updates (off by default: a
        model error, such as a wrong payload, looks like a sensor offset to the tests; they report it).
    fault_holdoff_s
        seconds after a detected torque step during which nothing is gated and the NIS and
        sensor-fault tests pause (the allowance for planned input steps).
    estimator
        one of :data:`ESTIMATORS`: ``"ekf"`` (the paper's), ``"ekf-payload"`` (the payload scale as a
        state), ``"ekf-input"`` (a torque disturbance per motor as states), see :mod:`.augmented`; ``"imm"``
        (an interacting multiple-model filter of the plain EKF and ``ekf-payload``'s filter, :mod:`.imm`).
    payload_std, payload0_std
        random-walk std of the payload scale per sqrt(s) (the payload is constant within a
        run: a small walk keeps the filter from locking on it), and its prior std (about 1).
    payload_nominal_p
        the prior probability that the payload is the model file's. The payload estimator reports
        its posterior mixed with its conditional on the nominal payload, by that hypothesis' posterior probability
        (:func:`.augmented.nominal_mixture`); 0: the filter's posterior as it is. The IMM: the nominal mode's
        prior probability.
    imm_dwell_s
        the IMM's expected dwell time in each mode (s): its transition matrix (:func:`.imm.transition_matrix`).
        None (default): :data:`IMM_DWELL_MANOEUVRES` times the manoeuvre's duration (1 s without a manoeuvre): a
        payload is picked or placed at rest, between motions, and changes within a motion in about one of that
        many.
    payload_linearity
        the payload scale is held at its prior from the start until the first interval whose
        second-order term in the scale over its standard deviation is within this many process-noise standard
        deviations (:class:`.augmented.AugmentedModel`, ``linearity_tol``).
    input_scale, input_tau, input0_scale
        torque-disturbance std per motor as a multiple of the motor's torque-noise
        std (per sqrt(s) for a random walk, stationary for a Gauss-Markov process with correlation time
        ``input_tau`` s), and its prior std (about 0) as such a multiple.
    """

    channels: tuple[str, ...] | None = None
    masters: tuple[str, ...] | None = None
    n_interior: int | str | None = None
    q_star: tuple[float, ...] | None = None
    ranking: str = "imr"
    h: float = 1e-4
    dt: float | None = None
    method: str = "cached"
    q0_std: float = 0.05
    qd0_std: float = 0.1
    elastic0_std: float = 1e-3
    elastic_rate0_std: float = 0.01
    q_scale: float = 1.0
    jump_p: float | None = None
    q_extra_std: float = 0.0
    max_gap: float = 1.0
    start_up: float = 0.3
    gate_p: float | None = 1e-6
    fault_window: int = 100
    fault_p: float = 1e-6
    fault_holdoff_s: float = 0.4
    fault_isolation: bool = False
    estimator: str = "ekf"
    payload_std: float = 0.01
    payload0_std: float = 0.5
    payload_linearity: float = 1.0
    payload_nominal_p: float = 0.5
    imm_dwell_s: float | None = None
    input_scale: float = 1.0
    input_tau: float | None = None
    input0_scale: float = 1.0

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}

    @classmethod
    def for_model(cls, mech: Mechanism, **overrides) -> ObserverConfig:
        """The settings for ``mech``: the defaults, then its model file's ``[observer]`` table
        (:class:`exuflex.mechanism.ObserverSpec`), then ``overrides`` (e.g. command-line options)."""
        return cls(**{**mech.observer.settings(), **overrides})


def physical_names(mech: Mechanism) -> tuple[str, ...]:
    """Names of the physical estimates: exactly the truth columns (:func:`exuflex.sensors.truth_names`)."""
    return truth_names(mech)


def physical_units(mech: Mechanism) -> tuple[str, ...]:
    """Units of the :func:`physical_names` columns."""
    nq = len(mech.coordinate_names)
    return ("rad",) * nq + ("rad/s",) * nq + (("m", "m", "m/s", "m/s") if tip_point(mech) is not None else ())


@dataclass
class Observer:
    """A ready-to-run observer: reduced model, EKF, and the map to physical states."""

    mech: Mechanism
    config: ObserverConfig
    model: ReducedObserverModel
    ekf: MultirateEKF
    channels: tuple[str, ...]
    basis_s: float
    info: dict = field(default_factory=dict)

    def use_input_hold(self, hold: str, delay: float = 0.0) -> None:
        """Step every reduced model the filter uses with the input a log declares between two samples, ``"zoh"``
        or ``"linear"`` delayed by ``delay`` s (:attr:`.reduced.ReducedObserverModel.input_hold`,
        :func:`exuflex.runs.input_hold_of`)."""
        for m in (self.model, *getattr(self.ekf, "models", (self.ekf.model,))):
            m = getattr(m, "inner", m)
            m.input_hold, m.input_delay = hold, float(delay)

    def physical(self, t: np.ndarray, Z: np.ndarray, refresh_rad: float = 1e-2, *, carry: dict | None = None
                 ) -> Signals:
        """Physical estimates (q, dq/dt, tip elastic displacement and rate) from reduced states (n, nx).

        ``q`` is what each coordinate's encoder reads, as in the truths (:func:`exuflex.sensors.true_states`): the
        state's q plus ``R(q) p`` (:meth:`~exuflex.observer.reduced.ReducedObserverModel.reading_maps`, zero but for
        a relative angle coordinate, whose ERLS frame is its link's own tangent: the reading adds the difference of
        the two links' elastic rotations at the joint), its rate ``q' + R p' + sum_i (dR/dq_i p) q'_i``.
        The tip's elastic displacement is ``e = A(q) p + w`` with ``A`` the tip rows (global
        frame) and ``w = C(q) (Gr(q) p)^2`` its second order, the links' foreshortening
        (:meth:`~exuflex.observer.reduced.ReducedObserverModel.tip_maps`, what the truth's tip position holds and
        linear elastic displacements do not), and its rate, what the truth's ``p_tip' - J q'`` is,
        ``e' = A(q) p' + sum_i (dA/dq_i p) q'_i + w'``: the rows turn with the links, so a deflection across a
        turning link has a global rate even when it is constant in the link's frame. ``R``, ``A``, ``C``, ``Gr`` and
        their q-derivatives are evaluated where q moved by more than ``refresh_rad`` from the last evaluation; in
        between they follow q to first order (error of order ``refresh_rad^2 / 2`` of the deflection) and the
        derivatives are held (error of order ``refresh_rad`` of the rate's turning term, itself the deflection times
        q').

        The rows are solved by the filter's model with its closure solver, from this computation's own warm start
        (the first from the initial guess), and the filter's is set back after: the estimates depend on neither
        what the filter evaluated before nor what comes after. ``carry``: a dict passed to the calls on successive
        blocks of rows of one record (empty at the first); it carries the evaluation and the warm start from one
        block to the next, so that the blocks give the numbers of one call on the whole record.
        """
        nq, r = self.model.nq, self.model.r
        Z = np.asarray(Z)[:, : self.model.nx]  # a filter's extra states (augmented estimators) are not physical
        names = physical_names(self.mech)
        out = np.full((len(t), len(names)), np.nan)
        out[:, :nq] = Z[:, :nq]
        out[:, nq : 2 * nq] = Z[:, r : r + nq]
        value, rate = self.row_columns()
        carry = {} if carry is None else carry
        if len(value):
            base = out.copy()
            base[:, 2 * nq :] = 0.0  # rows in no run of the rows: the state's q, no tip value
            with self.own_warm_start(carry):
                self._row_values(Z, base, out, value, rate, refresh_rad, carry)
        return Signals(np.asarray(t, float), names, out, physical_units(self.mech))

    def row_columns(self) -> tuple[np.ndarray, np.ndarray]:
        """The :meth:`physical` columns that the rows of :meth:`physical_rows_and_rates` add to: the values' (the
        q columns where a coordinate reads beyond q, then the tip's two) and the rates' (dq, then the tip's)."""
        nq = self.model.nq
        value, rate = [], []
        if getattr(self.model, "reading_G", None) is not None:
            value += list(range(nq))
            rate += list(range(nq, 2 * nq))
        if tip_point(self.mech) is not None:
            value += [2 * nq, 2 * nq + 1]
            rate += [2 * nq + 2, 2 * nq + 3]
        return np.array(value, dtype=np.int64), np.array(rate, dtype=np.int64)

    @contextmanager
    def own_warm_start(self, carry: dict):
        """The closure solver (shared with the filter's model) with ``carry["warm"]`` as its warm start (None: the
        initial guess) inside the block; on exit the warm start reached goes back into ``carry`` and the
        solver's previous one is restored."""
        kin = self.model.model.kin
        saved = kin.warm_start
        kin.warm_start = carry.get("warm")
        try:
            yield
        finally:
            carry["warm"] = kin.warm_start
            kin.warm_start = saved

    def _row_values(self, Z: np.ndarray, base: np.ndarray, out: np.ndarray, value: np.ndarray, rate: np.ndarray,
                    refresh_rad: float, carry: dict) -> None:
        """The ``value`` and ``rate`` columns of ``out``: ``base``'s plus the rows' values and rates
        (:meth:`physical`)."""
        nq, r = self.model.nq, self.model.r
        for a, b, (A0, dA, q0, second) in self.row_segments(Z, refresh_rad, carry):
            p, v, qd = Z[a:b, :r], Z[a:b, r : 2 * r], Z[a:b, r : r + nq]
            A = rows_along(A0, dA, Z[a:b, :nq] - q0)  # (n, k, r)
            Cw, Gw, Cwd, Gwd = second_order_along(second, Z[a:b, :nq] - q0, qd)
            g = apply_rows(Gw, p)  # (n, n_g): the slopes at the Gauss points
            out[a:b, value] = base[a:b, value] + apply_rows(A, p) + apply_rows(Cw, g * g)
            out[a:b, rate] = base[a:b, rate] + (apply_rows(A, v) + apply_rows(rows_along(0.0, dA, qd), p)
                               + apply_rows(Cwd, g * g)
                               + apply_rows(Cw, 2.0 * g * (apply_rows(Gw, v) + apply_rows(Gwd, p))))

    def row_segments(self, Z: np.ndarray, refresh_rad: float, carry: dict, lookahead: int = 64):
        """The runs of rows of ``Z`` that share one evaluation of the rows (:meth:`physical_rows_and_rates`):
        ``(a, b, (A, dA/dq, q0, second))`` for rows ``a:b``, all finite and with ``max |q - q0| <= refresh_rad``. A
        row beyond that radius starts a new evaluation at its own ``q``; rows with a non-finite entry, and rows where
        the loops do not close (no evaluation), are in no run. ``carry["rows"]`` holds the evaluation from one block
        of rows to the next. The rows' end is searched ``lookahead`` rows at a time, doubling (a run's cost is its
        length, not the record's)."""
        nq = self.model.nq
        rows = carry.get("rows")
        finite = np.all(np.isfinite(Z), axis=1)
        n, k = len(Z), 0
        while k < n:
            if not finite[k]:
                k += 1
                continue
            if rows is None or np.max(np.abs(Z[k, :nq] - rows[2])) > refresh_rad:
                rows = self.physical_rows_and_rates(Z[k, :nq])
                if rows is None:  # a runaway estimate where the loops cannot close: no tip value
                    k += 1
                    continue
            b, w = k + 1, lookahead
            while b < n:
                e = min(n, b + w)
                stop = ~finite[b:e] | (np.max(np.abs(Z[b:e, :nq] - rows[2]), axis=1) > refresh_rad)
                if stop.any():
                    b += int(np.argmax(stop))
                    break
                b, w = e, 2 * w
            yield k, b, rows
            k = b
        carry["rows"] = rows

    def physical_maps(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(A, C, Gr)`` at ``q``: the rows the physical quantities add to the state's (:meth:`row_columns`),
        ``A p + C (Gr p)^2``: the coordinates' readings beyond q where a coordinate reads beyond q, no second order
        (:meth:`~exuflex.observer.reduced.ReducedObserverModel.reading_maps`), then the tip's
        (:meth:`~exuflex.observer.reduced.ReducedObserverModel.tip_maps`)."""
        som = self.model
        tp = tip_point(self.mech)
        A, C, Gr = [], [], np.zeros((0, som.r))
        if tp is not None:
            At, Ct, Gr = som.tip_maps(q, *tp)
        if getattr(som, "reading_G", None) is not None:
            A.append(som.reading_maps(q))
            C.append(np.zeros((som.nq, Gr.shape[0])))
        if tp is not None:
            A.append(At)
            C.append(Ct)
        return np.vstack(A), np.vstack(C), Gr

    def physical_rows_and_rates(self, q: np.ndarray, eps: float = 1e-6):
        """``(A, dA/dq, q, (C, dC/dq, Gr, dGr/dq))``: the rows of :meth:`physical_maps` at ``q`` (``A`` (k, r)) and
        their derivatives (nq, ...) by forward differences of step ``eps`` rad (the maps are smooth in q, rotations
        and Guyan shapes: the truncation error is of order ``eps`` relative, far below the first-order
        interpolation's ``refresh_rad^2``); None where the loops do not close."""
        som = self.model
        q = np.array(q, float)
        try:
            maps = self.physical_maps(q)
            d = [np.empty((som.nq, *m.shape)) for m in maps]
            for i in range(som.nq):
                e = np.zeros(som.nq)
                e[i] = eps
                for m, dm, m1 in zip(maps, d, self.physical_maps(q + e), strict=True):
                    dm[i] = (m1 - m) / eps
        except KinematicsError:
            return None
        return maps[0], d[0], q, (maps[1], d[1], maps[2], d[2])


def second_order_along(second: tuple, dQ: np.ndarray, qd: np.ndarray) -> tuple:
    """``(C, Gr, dC/dt, dGr/dt)`` per row (n, ...) of the tip's second order ``C (Gr p)^2`` moved to first order in
    ``dQ = q - q0`` (:func:`rows_along`), their rates along ``qd`` (the derivatives held)."""
    C0, dC, G0, dG = second
    return rows_along(C0, dC, dQ), rows_along(G0, dG, dQ), rows_along(0.0, dC, qd), rows_along(0.0, dG, qd)


def rows_along(A0, dA: np.ndarray, dQ: np.ndarray) -> np.ndarray:
    """``A0 + sum_i dQ[:, i] dA[i]`` for each row of ``dQ`` (n, nq): rows (n, *A0.shape) moved to first order.
    Element by element, so that a row's numbers do not depend on the rows computed with it."""
    A = np.zeros((len(dQ), *dA.shape[1:])) + A0
    for i in range(dA.shape[0]):
        A += dQ[:, i, None, None] * dA[i]
    return A


def apply_rows(A: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``A[k] @ p[k]`` for each k (A (n, a, r), p (n, r)), row by row as :func:`rows_along`."""
    return (A * p[:, None, :]).sum(axis=-1)


def _noise_std(mech: Mechanism, channels: Sequence[str]) -> dict[str, float]:
    sensors = {s.name: s for s in mech.sensors}
    out = {}
    for c in channels:
        if c not in sensors:
            raise KeyError(f"{mech.source or mech.name}: no sensor channel {c!r}; the model has {sorted(sensors)}")
        if not sensors[c].noise_std > 0:
            raise ValueError(
                f"{mech.source or mech.name}: sensor {c!r} has no noise_std; the observer needs a positive "
                "standard deviation for every channel it uses"
            )
        out[c] = sensors[c].noise_std
    return out


def check_arguments(config=None, observer=None) -> None:
    """``config`` an :class:`ObserverConfig` or None, ``observer`` an :class:`Observer` or None: else a
    :class:`~exuflex.errors.UsageError` naming the parameter and the type expected."""
    from ..errors import UsageError

    if config is not None and not isinstance(config, ObserverConfig):
        raise UsageError(f"config: expected an exuflex.ObserverConfig or None, got {type(config).__name__}"
                         + (" (settings are its fields, e.g. ObserverConfig(q_scale=1.0))" if isinstance(config, str)
                            else ""))
    if observer is not None and not isinstance(observer, Observer):
        raise UsageError("observer: expected an exuflex.Observer (exuflex.make_observer(mech, config)) or None, got "
                         f"{type(observer).__name__}")


def make_observer(mech: Mechanism, config: ObserverConfig | None = None, x0=None, model: ErlsModel | None = None,
                  cb: CraigBampton | None = None) -> Observer:
    """Build the reduced model and the EKF for ``mech``.

    ``x0`` is the prior mean (reduced state); default: at rest at the manoeuvre's start, else q_ref.
    The full model is built on ``mech``'s mesh; :func:`exuflex.reduction.gauge_rule.observer_mesh` gives the mesh
    refined next to the curvature gauges until their rows converge for the filter's sake (``docs/gauge_mesh.md``;
    not the default). A prebuilt ``model`` or basis ``cb`` may be passed to share them between observers. Without
    ``config``: :meth:`ObserverConfig.for_model` (the model file's ``[observer]`` table over the defaults).
    """
    from ..validate import check_mechanism_argument, check_observer_settings

    check_mechanism_argument(mech)
    check_arguments(config=config)
    config = config or ObserverConfig.for_model(mech)
    check_observer_settings(mech, config)
    # the first run with an empty kernel cache: compiled in parallel processes (._compile)
    _compile.prepare(augmented=config.estimator in AUGMENTED_ESTIMATORS)
    t0 = time.perf_counter()
    model = model or (cb.model if cb is not None else ErlsModel(mech))
    if cb is None:
        cb = CraigBampton(model, masters=config.masters, q_star=config.q_star, n_interior=config.n_interior,
                          ranking=config.ranking, channels=config.channels)
    basis_s = time.perf_counter() - t0
    channels = tuple(config.channels) if config.channels else default_channels(mech)
    dt = config.dt or 1.0 / mech.sample_rate_hz
    stated = np.array([m.noise_std for m in mech.motors], float)
    q_extra = None
    if config.q_extra_std > 0:
        q_extra = np.zeros(2 * cb.r)
        q_extra[cb.r + len(mech.coordinate_names) :] = config.q_extra_std**2
    def reduced_model() -> ReducedObserverModel:
        m = ReducedObserverModel(cb, h=config.h, method=config.method, jump_p=config.jump_p,
                                 torque_std=stated * np.sqrt(config.q_scale), q_extra=q_extra)
        m.torque_var_nominal = stated**2
        return m

    som = reduced_model()
    r, nq = som.r, som.nq
    if x0 is None:
        x0 = som.initial_state(start_configuration(mech))
    P0 = np.empty(som.nx)
    P0[:nq] = config.q0_std**2
    P0[nq:r] = config.elastic0_std**2
    P0[r : r + nq] = config.qd0_std**2
    P0[r + nq :] = config.elastic_rate0_std**2
    fmodel, x0, P0 = _filter_model(som, config, x0, P0)
    monitoring = Monitoring(gate_p=config.gate_p, fault_window=config.fault_window, fault_p=config.fault_p,
                            fault_holdoff=max(0, round(config.fault_holdoff_s / dt)),
                            input_step=InputStepTest(som.torque_var, config.fault_p), isolate=config.fault_isolation)
    if config.estimator == "ukf":
        ekf = UnscentedKF(fmodel, channels, _noise_std(mech, channels), x0, P0, dt=dt, max_gap=config.max_gap,
                          monitoring=monitoring)
    elif config.estimator == "imm":  # the nominal mode: the plain EKF's model (its own held configuration)
        dwell = config.imm_dwell_s or IMM_DWELL_MANOEUVRES * (mech.manoeuvre.duration if mech.manoeuvre else 1.0)
        ekf = IMMFilter([reduced_model(), fmodel], [[1.0], []], channels, _noise_std(mech, channels), x0, P0, dt,
                        dwell_s=[dwell, dwell], mode_p0=[config.payload_nominal_p, 1.0 - config.payload_nominal_p],
                        max_gap=config.max_gap, monitoring=monitoring)
    else:
        ekf = MultirateEKF(fmodel, channels, _noise_std(mech, channels), x0, P0, dt=dt, max_gap=config.max_gap,
                           monitoring=monitoring)
    info = {"reduced_ndof": int(cb.r), "masters": list(mech.coordinate_names) + list(cb.masters),
            "interior_modes": int(cb.n_interior), "channels": list(channels)}
    return Observer(mech, config, som, ekf, channels, basis_s, info)


def _filter_model(som: ReducedObserverModel, config: ObserverConfig, x0, P0):
    """The filter's model for ``config.estimator`` (the reduced model, or it augmented), with the prior extended
    to its extra states."""
    if config.estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {', '.join(ESTIMATORS)}; got {config.estimator!r}")
    if config.estimator in ("ekf", "ukf"):
        return som, x0, P0
    if config.estimator in ("ekf-payload", "imm"):
        if not 0.0 <= config.payload_nominal_p <= 1.0:
            raise ValueError(f"payload_nominal_p must be a probability in [0, 1], got {config.payload_nominal_p}")
        fm = AugmentedModel(som, payload_std=config.payload_std, linearity_tol=config.payload_linearity)
    else:
        fm = AugmentedModel(som, input_std=config.input_scale * np.sqrt(som.torque_var_nominal),
                            input_tau=config.input_tau)
    P0x = np.empty(fm.nx)
    P0x[: som.nx] = P0
    if fm.i_theta is not None:
        P0x[fm.i_theta] = config.payload0_std**2
    if fm.i_inputs is not None:
        P0x[fm.i_inputs] = config.input0_scale**2 * som.torque_var_nominal
    return fm, _augmented_mean(fm, x0), P0x


def _augmented_mean(ekf_model, x0) -> np.ndarray:
    """A reduced-state prior mean extended for the extra states of the filter's model (if any): the payload scale
    at 1 (nominal), disturbances at 0."""
    x0 = np.asarray(x0, float).reshape(-1)
    if len(x0) == ekf_model.nx:
        return x0
    out = np.concatenate([x0, np.zeros(ekf_model.nx - len(x0))])
    i = getattr(ekf_model, "i_theta", None)
    if i is not None:
        out[i] = 1.0
    return out


@dataclass
class Estimate:
    """A filtered (and optionally smoothed) record: ``physical`` holds the smoothed estimates where
    ``smoothed`` is set, the filter's otherwise; ``wall_s`` and ``real_time_factor`` are the filter's.

    A record filtered for its summary only (:func:`observe_run` with ``keep`` other than ``"all"``) has a
    ``result`` without per-sample estimates, covariances and innovations (None; its NIS sequence and the run's
    counters, flags and faults are there) and ``physical`` None unless kept."""

    result: EstimationResult
    physical: Signals | None
    wall_s: float
    real_time_factor: float
    smoothed: SmoothedResult | None = None
    filtered_physical: Signals | None = None


#: rows of a record filtered and post-processed at a time by :func:`estimate_chunks` where the caller keeps only
#: what it needs of each chunk: the chunk's record with the full covariance (8 nx**2 bytes a row, 2.8 MB for the
#: six-bar's 26 states) and its derived tables stay a few megabytes
CHUNK_ROWS = 512


@dataclass
class EstimateChunk:
    """Rows ``start`` to ``start + len(result.t)`` of a record filtered by :func:`estimate_chunks`.

    ``result``: the filter's record of these rows (:meth:`MultirateEKF.run`), its run-level counters, flags and
    faults those of the record so far; ``physical``: the physical estimates of these rows; ``wall_s``: the
    filter's wall-clock time for them."""

    start: int
    result: EstimationResult
    physical: Signals
    wall_s: float


def estimate_chunks(obs: Observer, t, U, Y, x0=None, P0=None, *, rows: int | None = None,
                    innovations: bool = True) -> Iterator[EstimateChunk]:
    """Filter a record ``rows`` (default :data:`CHUNK_ROWS`) samples at a time (:meth:`MultirateEKF.run` on each block, continuing from the
    previous one) and yield each block's record and physical estimates as it is done.

    The numbers are those of :func:`estimate` on the whole record (the filter's steps do not depend on where the
    record is cut, and :meth:`Observer.physical` carries its evaluation across blocks); what the caller keeps of
    each block is all the memory the record takes beyond the log. ``t`` (n,); ``U``, ``Y``: arrays (n, k) or
    anything that gives the rows ``a:b`` as an array (:class:`exuflex.runs.LogColumns`); ``innovations``: record the
    innovations and their covariance in each block."""
    t = np.asarray(t, float)
    x0 = None if x0 is None else _augmented_mean(obs.ekf.model, x0)
    n = len(t)
    rows = max(int(rows or CHUNK_ROWS), 1)
    carry: dict = {}
    for a in range(0, max(n, 1), rows):
        b = min(a + rows, n)
        first = a == 0
        w0 = time.perf_counter()
        res = obs.ekf.run(t[a:b], None if U is None else U[a:b], Y[a:b], reset=first, x0=x0 if first else None,
                          P0=P0 if first else None, innovations=innovations)
        wall = time.perf_counter() - w0
        res = reported(obs, res, float(t[0]))
        yield EstimateChunk(a, res, obs.physical(res.t, res.x_hat, carry=carry), wall)
        del res  # one chunk's record alive at a time


def estimate(obs: Observer, t, U, Y, x0=None, P0=None, smooth: bool = False) -> Estimate:
    """Filter a record: times (n,), measured torques (n, n_motors), channels (n, m) in ``obs.channels`` order.
    ``x0``, ``P0``: a prior for this record (reduced state and its covariance or variances; default the
    observer's). ``smooth``: also the smoother (:func:`.smoother.rts_smooth`; the IMM's :meth:`.imm.IMMFilter.smooth`),
    which runs the filter's forward pass again, recording its predictions."""
    t = np.asarray(t, float)
    (chunk,) = estimate_chunks(obs, t, U, Y, x0, P0, rows=max(len(t), 1))
    res, phys, wall = chunk.result, chunk.physical, chunk.wall_s
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    if not smooth:
        return Estimate(res, phys, wall, span / wall if wall > 0 else float("inf"))
    x0 = None if x0 is None else _augmented_mean(obs.ekf.model, x0)
    sm = (obs.ekf.smooth(t, U, Y, x0=x0, P0=P0) if isinstance(obs.ekf, IMMFilter)
          else reported(obs, rts_smooth(obs.ekf, t, U, Y, x0=x0, P0=P0), float(t[0])))
    return Estimate(res, obs.physical(sm.t, sm.x_hat), wall, span / wall if wall > 0 else float("inf"), sm, phys)


def reported(obs: Observer, res, t0: float):
    """What the observer reports of a filtered (:class:`EstimationResult`) or smoothed (:class:`SmoothedResult`)
    record starting at ``t0``: for the payload estimator with ``payload_nominal_p`` > 0 the estimates and
    covariances mixed with their conditional on the nominal payload (:func:`.augmented.nominal_mixture`; the
    scale's prior variance at each sample is the filter's prior plus its random walk since ``t0``) and the nominal
    payload's probability per sample in ``nominal_p``; else ``res`` itself. The scale's prior is the filter's
    (its mean 1 unless the filter was started elsewhere)."""
    fm = obs.ekf.model
    it = getattr(fm, "i_theta", None)
    p = obs.config.payload_nominal_p
    if it is None or p <= 0.0 or res.x_hat is None or res.nominal_p is not None:  # (the IMM reports its own)
        return res
    cross = res.P[:, :, it] if isinstance(res, SmoothedResult) else res.P_theta
    prior_var = obs.ekf.P0[it, it] + fm.payload_std**2 * (np.asarray(res.t, float) - t0)
    x, P, w = nominal_mixture(res.x_hat, res.P, cross, it, prior_var, p, float(obs.ekf.x0[it]))
    if isinstance(res, SmoothedResult):
        return replace(res, x_hat=x, P=P, nominal_p=w)
    return replace(res, x_hat=x, P=P, P_theta=None, nominal_p=w)

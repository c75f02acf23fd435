"""The observer as users run it: a mechanism, a sensor log, and the estimated physical states.

:func:`make_observer` builds the reduced model and the multirate EKF for a mechanism and a channel set;
:func:`estimate` filters a log (offline) and reconstructs the physical states the truth files use
(q, dq/dt, tip elastic displacement and velocity, see :mod:`exuflex.sensors`); :func:`metrics` compares
them with a truth; :func:`estimation_bound` gives the yardstick of an RMS error: the posterior Cramer-Rao bound of
the reduced model linearised along the true trajectory (or the planned one), on the log's sampling schedule
(:func:`bound_track`, :mod:`.bound`); :func:`steady_bound` a quick estimate of it, the steady-state Kalman
covariance at frozen poses.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .. import _compile
from ..erls.kinematics import KinematicsError
from ..erls.model import ErlsModel
from ..manoeuvre import plan
from ..mechanism import Mechanism
from ..reduction import CraigBampton
from ..sensors import Signals, default_channels, tip_point, truth_names
from .augmented import AugmentedModel, nominal_mixture
from .bound import BoundTrack, periodic_posterior, riccati_track, steady_posterior, unobservable_states
from .ekf import EstimationResult, Monitoring, MultirateEKF
from .expansion import step_jacobian
from .imm import NO_SMOOTHER, IMMFilter
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
    "LogColumns",
    "Observer",
    "ObserverConfig",
    "UnobservableError",
    "augmented_estimates",
    "bound_track",
    "default_channels",
    "estimate",
    "estimate_chunks",
    "estimation_bound",
    "make_observer",
    "metrics",
    "physical_names",
    "physical_units",
    "start_configuration",
    "steady_bound",
]

log = logging.getLogger(__name__)


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

    def physical(self, t: np.ndarray, Z: np.ndarray, refresh_rad: float = 1e-2, *, carry: dict | None = None
                 ) -> Signals:
        """Physical estimates (q, dq/dt, tip elastic displacement and rate) from reduced states (n, nx).

        The tip's elastic displacement is ``e = A(q) p`` with ``A`` the tip rows (:meth:`tip_rows`, global frame)
        and its rate, what the truth's ``p_tip' - J q'`` is, ``e' = A(q) p' + sum_i (dA/dq_i p) q'_i``: the rows
        turn with the links, so a deflection across a turning link has a global rate even when it is constant in
        the link's frame. ``A`` and ``dA/dq`` are evaluated where q moved by more than ``refresh_rad`` from the
        last evaluation; in between ``A`` follows q to first order (error of order ``refresh_rad^2 / 2`` of the
        deflection) and ``dA/dq`` is held (error of order ``refresh_rad`` of the rate's turning term, itself the
        deflection times q').

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
        tp = tip_point(self.mech)
        carry = {} if carry is None else carry
        if tp is not None:
            with self._own_warm_start(carry):
                self._tip_columns(Z, out, tp, refresh_rad, carry)
        return Signals(np.asarray(t, float), names, out, physical_units(self.mech))

    @contextmanager
    def _own_warm_start(self, carry: dict):
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

    def _tip_columns(self, Z: np.ndarray, out: np.ndarray, tp, refresh_rad: float, carry: dict) -> None:
        """The tip elastic displacement and rate columns of :meth:`physical` into ``out``."""
        nq, r = self.model.nq, self.model.r
        for a, b, (A0, dA, q0) in self._tip_segments(Z, tp, refresh_rad, carry):
            p, v, qd = Z[a:b, :r], Z[a:b, r : 2 * r], Z[a:b, r : r + nq]
            A = _rows_along(A0, dA, Z[a:b, :nq] - q0)  # (n, 2, r)
            out[a:b, 2 * nq : 2 * nq + 2] = _apply_rows(A, p)
            out[a:b, 2 * nq + 2 : 2 * nq + 4] = _apply_rows(A, v) + _apply_rows(_rows_along(0.0, dA, qd), p)

    def _tip_segments(self, Z: np.ndarray, tp, refresh_rad: float, carry: dict, lookahead: int = 64):
        """The runs of rows of ``Z`` that share one evaluation of the tip rows: ``(a, b, (A, dA/dq, q0))`` for rows
        ``a:b``, all finite and with ``max |q - q0| <= refresh_rad``. A row beyond that radius starts a new
        evaluation at its own ``q``; rows with a non-finite entry, and rows where the loops do not close (no
        evaluation), are in no run. ``carry["rows"]`` holds the evaluation from one block of rows to the next. The
        rows' end is searched ``lookahead`` rows at a time, doubling (a run's cost is its length, not the
        record's)."""
        nq = self.model.nq
        rows = carry.get("rows")
        finite = np.all(np.isfinite(Z), axis=1)
        n, k = len(Z), 0
        while k < n:
            if not finite[k]:
                k += 1
                continue
            if rows is None or np.max(np.abs(Z[k, :nq] - rows[2])) > refresh_rad:
                rows = self._tip_rows_and_rates(Z[k, :nq], tp)
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

    def _tip_rows_and_rates(self, q: np.ndarray, tp, eps: float = 1e-6):
        """``(A, dA/dq, q)``: the tip rows (2, r) at ``q`` and their derivatives (nq, 2, r) by forward differences
        of step ``eps`` rad (the rows are smooth in q, rotations and Guyan shapes: the truncation error is of order
        ``eps`` relative, far below the first-order interpolation's ``refresh_rad^2``); None where the loops do not
        close."""
        som = self.model
        q = np.array(q, float)
        try:
            A = som.tip_rows(q, *tp)
            dA = np.empty((som.nq, *A.shape))
            for i in range(som.nq):
                e = np.zeros(som.nq)
                e[i] = eps
                dA[i] = (som.tip_rows(q + e, *tp) - A) / eps
        except KinematicsError:
            return None
        return A, dA, q

    def physical_covariance(self, Z: np.ndarray, P: np.ndarray, refresh_rad: float = 1e-3, *,
                            carry: dict | None = None) -> np.ndarray:
        """Covariance (n, k, k) of the :meth:`physical` quantities (q, dq/dt, tip elastic displacement and rate)
        from reduced states (n, nx) and the filter's full covariances (n, nx, nx; ``store_P="full"``), through
        their maps linearised at each state (the filter's extra states, if any, are left out; the rate's turning
        term is linearised in p and q', not in q). For NEES against a truth of the physical quantities. The tip
        rows are evaluated as in :meth:`physical` (its own warm start; ``carry`` as there)."""
        carry = {} if carry is None else carry
        with self._own_warm_start(carry):
            return self._physical_covariance(Z, P, refresh_rad, carry)

    def _physical_covariance(self, Z: np.ndarray, P: np.ndarray, refresh_rad: float, carry: dict) -> np.ndarray:
        som = self.model
        nq, r, nx = som.nq, som.r, som.nx
        tp = tip_point(self.mech)
        k = 2 * nq + (4 if tp is not None else 0)
        C = np.zeros((k, nx))
        C[:nq, :nq] = np.eye(nq)
        C[nq : 2 * nq, r : r + nq] = np.eye(nq)
        if tp is None:
            return C @ P[:, :nx, :nx] @ C.T
        out = np.full((len(Z), k, k), np.nan)  # (rows in no run of tip rows: no tip value)
        for a, b, (A0, dA, q0) in self._tip_segments(Z[:, :nx], tp, refresh_rad, carry):
            z = Z[a:b, :nx]
            A = _rows_along(A0, dA, z[:, :nq] - q0)  # (m, 2, r)
            dAp = np.einsum("iaj,kj->kai", dA, z[:, :r])  # d(A p)/dq (m, 2, nq)
            Cb = np.zeros((b - a, k, nx))
            Cb[:] = C
            Cb[:, 2 * nq : 2 * nq + 2, :r] = A
            Cb[:, 2 * nq : 2 * nq + 2, :nq] += dAp
            Cb[:, 2 * nq + 2 :, r:] = A
            Cb[:, 2 * nq + 2 :, :r] = _rows_along(0.0, dA, z[:, r : r + nq])
            Cb[:, 2 * nq + 2 :, r : r + nq] += dAp
            # d(A p')/dq; the rate's turning term q' dA/dq p also varies with q (second derivatives of A),
            # left out: of the order of q' times the deflection per radian, times q's small uncertainty
            Cb[:, 2 * nq + 2 :, :nq] += np.einsum("iaj,kj->kai", dA, z[:, r:])
            out[a:b] = Cb @ P[a:b, :nx, :nx] @ Cb.transpose(0, 2, 1)
        return out


def _rows_along(A0, dA: np.ndarray, dQ: np.ndarray) -> np.ndarray:
    """``A0 + sum_i dQ[:, i] dA[i]`` for each row of ``dQ`` (n, nq): rows (n, *A0.shape) moved to first order.
    Element by element, so that a row's numbers do not depend on the rows computed with it."""
    A = np.zeros((len(dQ), *dA.shape[1:])) + A0
    for i in range(dA.shape[0]):
        A += dQ[:, i, None, None] * dA[i]
    return A


def _apply_rows(A: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``A[k] @ p[k]`` for each k (A (n, a, r), p (n, r)), row by row as :func:`_rows_along`."""
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


NIS_WHOLE_LOG_P = 1e-6
"""False-alarm probability of the whole-log NIS test (:func:`nis_whole_log_flag`)."""

NIS_GROSS_FACTOR = 3.0
"""How far above a consistent filter's bound the whole log's mean NIS must lie to be flagged whatever the window:
the windowed test judges mild mismatch; this one a gross inconsistency (several times the innovations' stated
covariance: a log that cannot support the model, wrong units or noise)."""


def nis_whole_log_flag(nis_mean: float, nis_expected: float, n_updates: int, p: float = NIS_WHOLE_LOG_P,
                       factor: float = NIS_GROSS_FACTOR) -> bool:
    """The NIS test over the whole log, beside the filter's windowed one. With a consistent filter the sum of the
    ``n`` updates' NIS is chi-square with ``k = n d`` degrees of freedom (``d`` the mean channels per update); the
    log is flagged where the mean NIS exceeds ``factor`` times that sum's ``1 - p`` quantile over ``n``, so that a
    mean NIS far above its expectation is flagged even where no window of the windowed test fills (a short log, a
    slow one). The quantile ``chi2_{1-p}(k) = 2 Q^{-1}(k / 2, p)``, the inverse of the regularised upper incomplete
    gamma function."""
    if not (n_updates > 0 and math.isfinite(nis_mean) and math.isfinite(nis_expected) and nis_expected > 0):
        return False
    from scipy.special import gammainccinv

    q = 2.0 * float(gammainccinv(n_updates * nis_expected / 2.0, p))
    return bool(nis_mean * n_updates > factor * q)


def _check_arguments(config=None, observer=None) -> None:
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
    A prebuilt ``model`` or basis ``cb`` may be passed to share them between observers. Without ``config``:
    :meth:`ObserverConfig.for_model` (the model file's ``[observer]`` table over the defaults).
    """
    from ..validate import check_mechanism_argument, check_observer_settings

    check_mechanism_argument(mech)
    _check_arguments(config=config)
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
                            input_step=_torque_step_test(som.torque_var, config.fault_p), isolate=config.fault_isolation)
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
                           **monitoring._asdict())
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


def _torque_step_test(torque_var, p: float) -> InputStepTest:
    """Two successive torque samples differ by more than their noise explains (:class:`.kalman.InputStepTest`,
    false-alarm probability ``p``)."""
    return InputStepTest(torque_var, p)


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


def start_configuration(mech: Mechanism) -> np.ndarray:
    """The configuration the observer starts from: the planned manoeuvre's first (the model's ``q_ref`` without a
    manoeuvre, or where the plan fails, with a warning)."""
    if mech.manoeuvre is not None:
        try:
            p = plan(mech, dt=mech.manoeuvre.duration, t_end=0.0)
            return np.asarray(p.q[0], float)
        except Exception as exc:  # noqa: BLE001 - fall back to q_ref, with a note
            log.warning("could not plan the manoeuvre's start (%s); starting the observer at q_ref", exc)
    return np.asarray(mech.q_ref, float)


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


class LogColumns:
    """Columns of a log's table, a block of rows at a time: ``cols[a:b]`` is the ``(b - a, k)`` array of the
    columns ``cols`` of ``data`` (n, c) in rows ``a`` to ``b``, a copy of those rows only (the whole selection is
    never copied). :meth:`of` selects a :class:`Signals`' columns by name.

    ``hold``: a non-finite value is replaced by the column's last finite value before it, and by its first one
    before that (a torque not sampled at a time is held, ``docs/run_format.md``); a column without a finite value
    is an error naming it."""

    def __init__(self, data: np.ndarray, cols: Sequence[int], names: Sequence[str] | None = None,
                 hold: bool = False):
        self._data = data
        self.cols = [int(c) for c in cols]
        self.names = tuple(names) if names is not None else tuple(str(c) for c in self.cols)
        self.hold = bool(hold)
        self._prev: tuple[int, np.ndarray] | None = None
        if self.hold:
            first = np.empty(len(self.cols))
            for j, c in enumerate(self.cols):
                ok = np.flatnonzero(np.isfinite(data[:, c]))
                if not len(ok):
                    raise ValueError(f"torque column {self.names[j]} has no finite sample")
                first[j] = data[ok[0], c]
            self._first = first

    @classmethod
    def of(cls, signals: Signals, names: Sequence[str], hold: bool = False) -> LogColumns:
        """The columns ``names`` of ``signals`` (KeyError naming the missing ones, as :meth:`Signals.select`)."""
        names = tuple(names)
        cols = [signals.names.index(n) if n in signals.names else None for n in names]
        missing = [n for n, c in zip(names, cols, strict=True) if c is None]
        if missing:
            raise KeyError(f"no channel(s) {missing}; channels are {list(signals.names)}")
        return cls(signals.data, cols, names, hold)

    def __len__(self) -> int:
        return len(self._data)

    @property
    def shape(self) -> tuple[int, int]:
        return (len(self._data), len(self.cols))

    def __getitem__(self, rows: slice) -> np.ndarray:
        a, b, step = rows.indices(len(self._data))
        if step != 1:
            raise IndexError("LogColumns: contiguous rows only")
        block = self._data[a:b, self.cols]
        if not self.hold:
            return block
        prev = self._prev[1] if self._prev is not None and self._prev[0] == a else self._before(a)
        bad = ~np.isfinite(block)
        if bad.any():
            for j in np.flatnonzero(bad.any(axis=0)):
                col = block[:, j]
                ok = np.isfinite(col)
                idx = np.where(ok, np.arange(len(col)), -1)
                np.maximum.accumulate(idx, out=idx)
                col[:] = np.where(idx >= 0, col[np.maximum(idx, 0)], prev[j])
        if b > a:
            self._prev = (b, block[-1].copy())
        return block

    def _before(self, a: int) -> np.ndarray:
        """Per column, the held value entering row ``a``: the last finite value before it, else the first."""
        out = self._first.copy()
        for j, c in enumerate(self.cols):
            ok = np.flatnonzero(np.isfinite(self._data[:a, c]))
            if len(ok):
                out[j] = self._data[ok[-1], c]
        return out


def estimate_chunks(obs: Observer, t, U, Y, x0=None, P0=None, *, rows: int | None = None,
                    innovations: bool = True) -> Iterator[EstimateChunk]:
    """Filter a record ``rows`` (default :data:`CHUNK_ROWS`) samples at a time (:meth:`MultirateEKF.run` on each block, continuing from the
    previous one) and yield each block's record and physical estimates as it is done.

    The numbers are those of :func:`estimate` on the whole record (the filter's steps do not depend on where the
    record is cut, and :meth:`Observer.physical` carries its evaluation across blocks); what the caller keeps of
    each block is all the memory the record takes beyond the log. ``t`` (n,); ``U``, ``Y``: arrays (n, k) or
    anything that gives the rows ``a:b`` as an array (:class:`LogColumns`); ``innovations``: record the
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
    observer's). ``smooth``: also the RTS smoother (:func:`.smoother.rts_smooth`, which runs the filter's forward
    pass again, recording its predictions)."""
    t = np.asarray(t, float)
    (chunk,) = estimate_chunks(obs, t, U, Y, x0, P0, rows=max(len(t), 1))
    res, phys, wall = chunk.result, chunk.physical, chunk.wall_s
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    if not smooth:
        return Estimate(res, phys, wall, span / wall if wall > 0 else float("inf"))
    if isinstance(obs.ekf, IMMFilter):
        from ..errors import UsageError

        raise UsageError(NO_SMOOTHER)
    x0 = None if x0 is None else _augmented_mean(obs.ekf.model, x0)
    sm = reported(obs, rts_smooth(obs.ekf, t, U, Y, x0=x0, P0=P0), float(t[0]))
    return Estimate(res, obs.physical(sm.t, sm.x_hat), wall, span / wall if wall > 0 else float("inf"), sm, phys)


def _scored(t: np.ndarray, start_up: float, truth_t: np.ndarray | None = None) -> np.ndarray:
    """The samples of a record of times ``t`` that :func:`metrics` scores: from ``t[0] + start_up`` on, within the
    truth's span (half a median interval's tolerance) where a truth's times are given."""
    t = np.asarray(t, float)
    sel = t >= t[0] + start_up
    if truth_t is not None and len(truth_t):
        tol = 0.5 * float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        sel &= (t >= float(truth_t[0]) - tol) & (t <= float(truth_t[-1]) + tol)
    return sel


def _bound_kind(along: str, smooth: bool) -> str:
    """What the bound of a summary is, in words (``bound_kind``)."""
    return (("smoothed " if smooth else "") + "posterior Cramer-Rao bound along the "
            + {"truth": "truth", "plan": "plan (no truth)", "q_ref": "reference pose at rest (no manoeuvre)"}[along])


def metrics(est: Signals, truth: Signals, start_up: float = 0.3, names: Sequence[str] | None = None, *,
            min_coverage: float = 0.9) -> dict:
    """RMS and max absolute error per quantity after ``start_up`` s (truth interpolated onto the estimate's times).

    The truth must cover the scored interval ``[t_0 + start_up, t_end]`` of the estimate: interpolation holds a
    truth's end values, so a truth cut short or on another clock would be scored silently against constants.
    Only the estimate's samples within the truth's span (half a sample's tolerance) are scored; if they are less
    than ``min_coverage`` of the scored interval it is an error (``ValueError`` naming both spans), else a
    partial cover is a warning. ``truth_coverage`` in the result is the covered fraction.
    """
    names = [n for n in (names or est.names) if n in truth]
    sel = est.t >= est.t[0] + start_up
    if not np.any(sel):
        raise ValueError(
            f"the log is {est.t[-1] - est.t[0]:.3g} s long, not longer than the start-up period left out of the "
            f"error metrics ({start_up:g} s); use a longer log or a shorter start_up"
        )
    ts = est.t[sel]
    tol = 0.5 * float(np.median(np.diff(est.t))) if len(est.t) > 1 else 0.0
    t0, t1 = (float(truth.t[0]), float(truth.t[-1])) if len(truth.t) else (math.nan, math.nan)
    inside = (ts >= t0 - tol) & (ts <= t1 + tol)
    coverage = float(inside.mean())
    span = f"the truth spans {t0:.6g} to {t1:.6g} s, the scored estimate {ts[0]:.6g} to {ts[-1]:.6g} s"
    if coverage < min_coverage:
        raise ValueError(f"the truth covers {coverage:.0%} of the scored interval ({span}): not the same run or "
                         f"clock? (at least {min_coverage:.0%} needed)")
    if coverage < 1.0:
        log.warning("the truth covers %.1f%% of the scored interval (%s); scoring the covered part only",
                    100 * coverage, span)
    ts = ts[inside]
    rms, mx = {}, {}
    for n in names:
        tr = np.interp(ts, truth.t, truth[n])
        e = est[n][sel][inside] - tr
        e = e[np.isfinite(e)]
        rms[n] = float(np.sqrt(np.mean(e**2))) if e.size else float("nan")
        mx[n] = float(np.max(np.abs(e))) if e.size else float("nan")
    return {"rms_error": rms, "max_error": mx, "truth_coverage": coverage}


def estimation_bound(obs: Observer, run=None, *, span: tuple[float, float] | None = None, smooth: bool = False,
                     log_check=None) -> dict[str, float]:
    """The bound an RMS error is compared with: the RMS over ``span`` of the posterior Cramer-Rao bound's standard
    deviation of each physical quantity (:func:`bound_track`).

    ``run`` (:class:`exuflex.runs.Run`): along its truth if it has one, else along the plan, on its log's times,
    torques and sampled channels; without: along the plan at the observer's interval, every channel at every
    sample, the plan's computed torques. ``span = (t0, t1)`` in seconds from the first sample (default: from the
    observer's ``start_up`` to the end). ``smooth``: the smoothed bound. ``log_check`` (the log's
    :class:`exuflex.validate.LogCheck`) is only used for the observability test's channel set.

    Raises
    ------
    UnobservableError
        As :func:`steady_bound`: the channels leave states that neither decay nor are measured.
    """
    mech = obs.mech
    if run is None:
        d = mech.manoeuvre.duration if mech.manoeuvre is not None else 1.0
        t = np.arange(0.0, d + 0.5 * obs.ekf.dt, obs.ekf.dt)
        U, sampled, truth = None, None, None
    else:
        S = run.sensors
        t = np.asarray(S.t, float)
        U = LogColumns.of(S, run.motors or mech.motor_names, hold=True)
        sampled = _Sampled(S, obs.channels)
        truth = run.truth
    check_observable(obs, log_check)
    track, _ = bound_track(obs, t, U, sampled, truth=truth, smooth=smooth)
    t0, t1 = (obs.config.start_up, float(t[-1] - t[0])) if span is None else (float(span[0]), float(span[1]))
    sel = (t - t[0] >= t0 - 1e-9) & (t - t[0] <= t1 + 1e-9)
    if not sel.any():
        raise ValueError(f"span {span} holds no sample of the record ({t[0]:.6g} to {t[-1]:.6g} s)")
    return dict(zip(physical_names(mech), map(float, track.rms(sel, smoothed=smooth)), strict=True))


class _Sampled:
    """Which of ``channels`` are sampled (finite) in each row of a log's table, a block of rows at a time."""

    def __init__(self, signals: Signals, channels: Sequence[str]):
        self._cols = LogColumns.of(signals, channels)

    def __getitem__(self, rows: slice) -> np.ndarray:
        return np.isfinite(self._cols[rows])


class _Trajectory:
    """Reduced states along a trajectory of the rigid coordinates, a block of rows at a time: ``q`` and ``q'`` at
    the times ``t`` from a truth (linear interpolation of its samples) or from the plan (cubic Hermite from the
    plan's grid at the log's interval); the elastic coordinates and their rates at zero (the truth files hold the
    tip's elastic displacement, not the reduced model's coordinates)."""

    def __init__(self, obs: Observer, t: np.ndarray, truth: Signals | None):
        self.obs, self.t = obs, np.asarray(t, float)
        mech = obs.mech
        qn = list(mech.coordinate_names)
        self.plan_torque = None
        if truth is not None:
            self._q = lambda ts: np.column_stack([np.interp(ts, truth.t, truth[n]) for n in qn])
            self._qd = lambda ts: np.column_stack([np.interp(ts, truth.t, truth["d" + n]) for n in qn])
            self.along = "truth"
            return
        t0 = float(self.t[0])
        span = float(self.t[-1] - t0) if len(self.t) > 1 else 0.0
        if mech.manoeuvre is None:
            q = np.asarray(mech.q_ref, float)
            self._q = lambda ts: np.tile(q, (len(ts), 1))
            self._qd = lambda ts: np.zeros((len(ts), len(q)))
            self.along = "q_ref"
            return
        step = float(np.median(np.diff(self.t))) if len(self.t) > 1 else obs.ekf.dt
        p = plan(mech, dt=step, t_end=span + step)
        from scipy.interpolate import CubicHermiteSpline  # (here: scipy.interpolate is a large import)

        sq = CubicHermiteSpline(p.t, p.q, p.qd, axis=0)
        sqd = CubicHermiteSpline(p.t, p.qd, p.qdd, axis=0)
        self._q = lambda ts: sq(ts - t0)
        self._qd = lambda ts: sqd(ts - t0)
        self._plan = p
        self.along = "plan"

    def torques(self) -> np.ndarray:
        """The plan's computed torques (:func:`exuflex.manoeuvre.computed_torque`) at the times ``t``; zeros
        without a plan."""
        from ..manoeuvre import computed_torque

        nu = len(self.obs.mech.motors)
        if self.along != "plan":
            return np.zeros((len(self.t), nu))
        p = self._plan
        tau = computed_torque(self.obs.mech, p)
        return np.column_stack([np.interp(self.t - self.t[0], p.t, tau[:, i]) for i in range(nu)])

    def __getitem__(self, rows: slice) -> np.ndarray:
        som = self.obs.model
        ts = self.t[rows]
        X = np.zeros((len(ts), som.nx))
        X[:, : som.nq] = self._q(ts)
        X[:, som.r : som.r + som.nq] = self._qd(ts)
        return X


def bound_track(obs: Observer, t, U=None, sampled=None, *, truth: Signals | None = None,
                smooth: bool = False) -> tuple[BoundTrack, str]:
    """The posterior Cramer-Rao bound of the observer's reduced model along a record (:func:`.bound.riccati_track`):
    the Kalman covariance recursion with the model's step and measurement Jacobians evaluated at the true states
    (``truth``: :class:`~exuflex.sensors.Signals` with the truth columns) or, without a truth, at the planned ones,
    mapped into the reduced coordinates (:class:`_Trajectory`: the rigid coordinates and their rates; the elastic
    ones at zero). The filter's noise model and prior: the motors' stated torque noise as process noise through
    the model's interval maps (not ``q_scale`` or ``q_extra``, the filter's tuning), the channels' stated noise, the
    filter's prior covariance ``P0`` at the first sample, and the model's own step (``method``, held matrices and
    step maps under the same error control as the filter's, measured against this recursion's covariance).

    ``t`` (n,): the sample times; ``U``: the torques (n, n_motors) held over each interval (None: the plan's
    computed torques); ``sampled``: which channels of ``obs.channels`` each sample holds ((n, m) bool, default
    all). ``smooth``: also the smoothed bound. Returns the track (variances of the :func:`physical_names`
    quantities, through the maps of :meth:`Observer.physical_covariance`) and what it runs along (``"truth"``,
    ``"plan"``, or ``"q_ref"`` at rest without a manoeuvre).
    """
    t = np.asarray(t, float)
    traj = _Trajectory(obs, t, truth)
    if U is None:
        U = traj.torques()
    model = _bound_model(obs)
    P0 = obs.ekf.P0
    nx = model.nx
    P0 = np.diag(P0[:nx]) if P0.ndim == 1 else P0[:nx, :nx]
    R = np.asarray(obs.ekf.R_std, float) ** 2
    carry: dict = {}

    def outputs(a, b, Xb, Pb):
        if a == 0:  # a pass over the record starts (the smoothed one after the filtered one)
            carry.clear()
        return np.diagonal(obs.physical_covariance(Xb, Pb, refresh_rad=BOUND_TIP_RADIUS, carry=carry),
                           axis1=1, axis2=2)

    track = riccati_track(model, t, traj, U, obs.channels, R, P0, sampled, outputs=outputs, smooth=smooth,
                          linearise=_step_linearisation(model))
    return track, traj.along


#: the radius (rad) within which the bound's tip rows follow q to first order (:meth:`Observer.physical_covariance`):
#: their error, about half its square relative, stays below 5e-4 of the tip's standard deviations
BOUND_TIP_RADIUS = 3e-2


def _step_linearisation(model: ReducedObserverModel):
    """``(x, u, dt) -> (F, Q)``: the cached step's Jacobian and process noise at ``x`` without its sub-steps (the
    held configuration and step map as :meth:`.reduced.ReducedObserverModel.predict` renews them, and the step
    Jacobian kernel :func:`.expansion.step_jacobian` it calls with them); None for the reference step (``rk4``:
    through ``predict``). ``tests/test_bound.py`` checks that it returns ``predict``'s ``F`` and ``Q``."""
    if model.method != "cached":
        return None

    def linearise(x, u, dt):
        sm = model.prepare(x, model.torques(u), dt)[4]
        return step_jacobian(x, *sm.tail[:5]), sm.Q

    return linearise


def _bound_model(obs: Observer) -> ReducedObserverModel:
    """The observer's reduced model (its step ``method`` and sub-step ``h``) with the stated torque noise: a model of
    its own, so that the filter's caches are left alone."""
    var = getattr(obs.model, "torque_var_nominal", obs.model.torque_var)
    return ReducedObserverModel(obs.model.rm, h=obs.model.h, method=obs.model.method, torque_std=np.sqrt(var))


def check_observable(obs: Observer, log_check=None) -> None:
    """Raise :class:`UnobservableError` if the channels (those the log samples, with ``log_check``) leave states
    that neither decay nor are measured at the start of the manoeuvre (PBH test, :func:`.bound.unobservable_states`)."""
    _linearised(obs, start_configuration(obs.mech), None, log_check)


def steady_bound(obs: Observer, q=None, qd=None, points: int = 9, *, log_check=None,
                 span: tuple[float, float] | None = None) -> dict[str, float]:
    """A quick estimate of the bound: the steady-state Kalman covariance of the reduced model linearised and frozen
    at a configuration, the stated torque noise as process noise (no trajectory is followed: at a pose the
    trajectory stays at, :func:`estimation_bound` approaches it).

    The covariance depends on the configuration (a tip's global x and y swap roles as its link turns; the
    sensitivities of the encoders and gauges change with the pose), so by default it is evaluated at ``points``
    configurations of the manoeuvre (its plan, positions and rates, evenly spread over 5-95 % of its duration)
    and the per-quantity standard deviations are combined as an RMS. ``span = (t0, t1)`` (s from the manoeuvre's
    start): the configurations at the midpoints of ``points`` equal parts of that interval instead (past the
    manoeuvre's end: its final pose at rest). With ``q`` (and ``qd``) given, or without a manoeuvre (``q_ref``,
    at rest): that one configuration.

    ``log_check`` (:class:`exuflex.validate.LogCheck` of the log at hand) makes it the estimate for that log: the
    interval is the log's, channels never sampled are left out, and channels sampled every k-th row update
    every k-th interval (:func:`.bound.periodic_posterior`, averaged over the period). Without it: every channel
    of the observer at every interval of the model's rate.

    Raises
    ------
    UnobservableError
        The channels leave states that neither decay nor are measured (e.g. gauges only: the rigid motion); the
        message names them.
    """
    mech = obs.mech
    if q is not None or mech.manoeuvre is None or points < 1:
        return _bound_at(obs, _mid_q(mech) if q is None else q, qd, log_check)
    d = mech.manoeuvre.duration
    t_end = d if span is None else max(float(span[1]), float(span[0]))
    try:
        p = plan(mech, dt=t_end / 400 if t_end > 0 else d / 200, t_end=t_end if t_end > 0 else d)
    except Exception as exc:  # noqa: BLE001 - the bound at q_ref instead, with a note
        log.warning("could not plan the manoeuvre for the bound (%s); using the bound at q_ref", exc)
        return _bound_at(obs, np.asarray(mech.q_ref, float), None, log_check)
    if span is None:
        idx = np.unique(np.round(np.linspace(0.05, 0.95, points) * (len(p.t) - 1)).astype(int))
    else:
        t0, t1 = float(span[0]), t_end
        ts = t0 + (np.arange(points) + 0.5) * (t1 - t0) / points
        idx = np.unique(np.clip(np.searchsorted(p.t, ts), 0, len(p.t) - 1))
    per = [_bound_at(obs, p.q[k], p.qd[k], log_check) for k in idx]
    return {name: float(np.sqrt(np.mean([b[name] ** 2 for b in per]))) for name in per[0]}


def _linearised(obs: Observer, q, qd=None, log_check=None) -> tuple:
    """The reduced model frozen at ``q`` with rates ``qd`` (None: at rest) over the log's interval: ``(som, z, A, Q,
    H, R, channels, every)`` with the channels the log samples and their spacing in intervals; the PBH test of
    their observability first (:class:`UnobservableError`)."""
    mech = obs.mech
    som = ReducedObserverModel(obs.model.rm, h=obs.model.h, method="rk4")
    q = np.asarray(q, float)
    z = som.initial_state(q, qd)
    u = np.zeros(len(mech.motors))
    channels = list(obs.channels)
    R_all = {c: s**2 for c, s in zip(obs.channels, obs.ekf.R_std, strict=True)}
    dt = obs.ekf.dt
    every = {c: 1 for c in channels}
    if log_check is not None:
        dt = log_check.interval_s or dt
        mult = max(1, round(dt / obs.ekf.dt))
        channels = [c for c in channels if log_check.channel_rate_hz.get(c, 1.0) > 0]
        every = {c: max(1, round(log_check.channel_every.get(c, mult) / mult)) for c in channels}
    if not channels:
        raise UnobservableError(f"{mech.source or mech.name}: no channel of {list(obs.channels)} is sampled in the "
                                "log: nothing to estimate with")
    pred, _, maps = som.frozen_interval(z, u, dt)
    A = pred.F
    # the bound is a property of the sensors and the *stated* noise, not of the filter's tuning
    var = getattr(obs.model, "torque_var_nominal", som.torque_var)
    Q = (maps.L * var) @ maps.L.T
    _, H = som.measure(z, channels)
    R = np.array([R_all[c] for c in channels])
    nq, r = som.nq, som.r
    state_names = (list(mech.coordinate_names) + [f"p{i + 1}" for i in range(r - nq)]
                   + [f"d{c}" for c in mech.coordinate_names] + [f"dp{i + 1}" for i in range(r - nq)])
    d = np.sqrt(np.clip(np.diag(Q), 0, None))
    d = np.where(d > 0, d, d[d > 0].min() if np.any(d > 0) else 1.0)
    bad = unobservable_states(A, H, state_names, scale=d)
    if bad:
        rigid = [b for b in bad if not b.lstrip("d").startswith("p")]
        raise UnobservableError(
            f"the channels {channels} cannot observe {', '.join(bad)}"
            + (" (the rigid motion: add an encoder)" if rigid else " (add a strain gauge or a tip sensor)")
            + "; no filter has a bounded error there")
    return som, z, A, Q, H, R, channels, every


def _bound_at(obs: Observer, q, qd=None, log_check=None) -> dict[str, float]:
    """:func:`steady_bound` at one configuration ``q`` with rates ``qd`` (None: at rest)."""
    mech = obs.mech
    som, z, A, Q, H, R, channels, every = _linearised(obs, q, qd, log_check)
    period = int(np.lcm.reduce([every[c] for c in channels]))
    if period == 1:
        P = steady_posterior(A, Q, H, R)
    else:
        if period > 1000:
            raise UnobservableError(f"channel spacings {every} give a period of {period} intervals; resample the log")
        pattern = np.array([[k % every[c] == 0 for c in channels] for k in range(period)])
        P = periodic_posterior(A, Q, H, R, pattern)
    nq, r = som.nq, som.r
    q = np.asarray(q, float)
    names = physical_names(mech)
    out = {}
    sd = np.sqrt(np.diag(P))
    for i in range(nq):
        out[names[i]] = float(sd[i])
        out[names[nq + i]] = float(sd[r + i])
    tp = tip_point(mech)
    if tp is not None:
        # the maps of Observer.physical linearised at z: e = A(q) p, e' = A(q) p' + sum_i (dA/dq_i p) q'_i
        A, dA, _ = obs._tip_rows_and_rates(q, tp)
        dAp = np.einsum("iaj,j->ai", dA, z[:r])
        for k in range(2):
            C = np.zeros(som.nx)
            C[:r] = A[k]
            C[:nq] += dAp[k]
            out[names[2 * nq + k]] = float(np.sqrt(C @ P @ C))
            Cd = np.zeros(som.nx)
            Cd[r:] = A[k]
            Cd[:r] += np.tensordot(z[r : r + nq], dA, axes=1)[k]
            Cd[r : r + nq] += dAp[k]
            out[names[2 * nq + 2 + k]] = float(np.sqrt(Cd @ P @ Cd))
    return out


class UnobservableError(ValueError):
    """A channel set that leaves states unobservable (the bound does not exist); the message names them."""


def _mid_q(mech: Mechanism) -> np.ndarray:
    if mech.manoeuvre is not None:
        try:
            d = mech.manoeuvre.duration
            p = plan(mech, dt=d / 2, t_end=d)
            return np.asarray(p.q[len(p.q) // 2], float)
        except Exception as exc:  # noqa: BLE001
            log.warning("could not plan the manoeuvre's middle (%s); using q_ref", exc)
    return np.asarray(mech.q_ref, float)



# ------------------------------------------------------------------------------------------ runs
@dataclass
class Outcome:
    """The observer run on one log, with everything a result file records."""

    estimate: Estimate
    metrics: dict | None
    bound: dict | None
    summary: dict


#: what :func:`observe_run` keeps of the filtered record (``keep``)
KEEP = ("all", "physical", "summary")


def observe_run(mech: Mechanism, run, config: ObserverConfig | None = None, *, with_bound: bool = True,
                observer: Observer | None = None, report=None, smooth: bool = False, keep: str = "all",
                sink=None, log_check=None) -> Outcome:
    """Run the observer on a run folder's log (:class:`exuflex.runs.Run`) and score it against its truth
    (``smooth``: the RTS-smoothed estimates; the filter's errors are then in ``filtered_rms_error``).

    The log is checked first (:func:`exuflex.validate.check_run`): its clock, per-channel availability and rates.
    The filter steps by each sample's own time stamp (jitter and drift within the documented tolerance need no
    grid). The bound is the one for this log (:func:`bound_track`: the posterior Cramer-Rao bound along its truth,
    else along the plan, on its times, torques and sampled channels; with ``smooth`` the smoothed bound), its RMS
    over the samples :func:`metrics` scores (``bound_rms``, ``ratio_to_bound``; with ``smooth`` also
    ``filtered_bound_rms`` and ``filtered_ratio_to_bound`` for the filter's errors); it is computed before
    filtering, and an unobservable channel set is reported at once.
    ``report``: a callable taking one-line stage messages (the CLI prints them on stderr). ``log_check``: the
    log's check if the caller made it already (:func:`exuflex.validate.check_run` with the observer's channels and
    sample interval; the command line checks a log before it builds the model).

    Memory: besides the log, ``keep`` says what the outcome holds of the filtered record, per sample:

    - ``"all"`` (default): the filter's whole record (:class:`~.ekf.EstimationResult`: estimates, covariances as
      the filter's ``store_P`` says, innovations, NIS) and the physical estimates;
    - ``"physical"``: the physical estimates (8 bytes a column) and the NIS sequence (10 bytes);
    - ``"summary"``: the NIS sequence, and the physical estimates only where a truth is scored.

    Except with ``"all"`` or ``smooth`` (the smoother needs the whole record) the log is filtered
    :data:`CHUNK_ROWS` rows at a time (:func:`estimate_chunks`, the same numbers) and nothing else grows with it.
    ``sink``: called with each :class:`EstimateChunk` as it is filtered (the smoothed run: once, with the smoothed
    physical estimates), e.g. :class:`.output.EstimatesWriter` streaming ``estimates.csv``.
    """
    from ..validate import check_mechanism_argument, check_run

    if keep not in KEEP:
        raise ValueError(f"keep must be one of {', '.join(KEEP)}, got {keep!r}")
    check_mechanism_argument(mech)
    _check_arguments(config=config, observer=observer)
    if not hasattr(run, "sensors") or not hasattr(run, "meta"):
        from ..errors import UsageError

        hint = " (a path: read it with exuflex.runs.read_run(path) first)" if isinstance(run, (str, bytes)) or \
            hasattr(run, "__fspath__") else ""
        raise UsageError(f"run: expected an exuflex.runs.Run, got {type(run).__name__}{hint}")
    say = report or (lambda msg: log.info("%s", msg))
    config = config or ObserverConfig.for_model(mech)
    obs = observer or make_observer(mech, config)
    if log_check is None:
        log_check = check_run(mech, run, obs.channels, dt=obs.ekf.dt)
    elif set(log_check.channel_rate_hz) != set(obs.channels) or log_check.dt != obs.ekf.dt:
        raise ValueError(f"log_check: made for channels {sorted(log_check.channel_rate_hz)} at {log_check.dt} s, "
                         f"the observer has {sorted(obs.channels)} at {obs.ekf.dt} s")
    say(f"channels: {log_check.availability()}; log interval {log_check.interval_s * 1e3:.4g} ms"
        + (f", clock {log_check.clock_drift_ppm:+.1f} ppm, jitter up to {log_check.jitter_max_s * 1e6:.3g} us"
           if log_check.jitter_max_s > 1e-6 * log_check.dt else ""))
    for w in log_check.warnings:
        say(f"note: {w}")
    S = run.sensors
    motors = run.motors or mech.motor_names
    # a torque not sampled at a time: hold the last value (documented in docs/run_format.md)
    U = LogColumns.of(S, motors, hold=True)
    Y = LogColumns.of(S, obs.channels)
    bnd, unobservable, track = None, None, None
    if with_bound:  # before filtering: an unobservable channel set is reported at once
        try:
            check_observable(obs, log_check)
        except UnobservableError as exc:
            unobservable = str(exc)
            say(f"warning: no bound: {exc}")
    span = float(S.t[-1] - S.t[0]) if len(S.t) > 1 else 0.0
    start_up = config.start_up if span > config.start_up else 0.5 * span
    if start_up != config.start_up:
        log.warning("log is %.3g s long: error metrics from %.3g s instead of the %.3g s start-up", span, start_up,
                    config.start_up)
    if run.truth is not None:  # before filtering: a truth of another run or clock is refused at once
        try:
            metrics(Signals(S.t, (), np.empty((len(S.t), 0))), run.truth, start_up)
        except ValueError as exc:
            from ..errors import LogFormatError

            raise LogFormatError(f"{Path(run.path) / 'truth.csv'}: {exc}") from None
    if with_bound and unobservable is None:
        track, along = bound_track(obs, S.t, U, _Sampled(S, obs.channels), truth=run.truth, smooth=smooth)
        scored = _scored(S.t, start_up, None if run.truth is None else run.truth.t)
        names = physical_names(mech)
        bnd = dict(zip(names, map(float, track.rms(scored, smoothed=smooth)), strict=True))
        say(f"bound for this log ({_bound_kind(along, smooth)}): " + ", ".join(f"{k} {v:.3g}" for k, v in bnd.items()))
    say(f"filtering {len(S.t)} samples" + (" (and smoothing)" if smooth else ""))
    if keep == "all" or smooth:
        est = estimate(obs, S.t, U[:], Y[:], smooth=smooth)
        last = _last_state(est)
        if sink is not None:
            sink(EstimateChunk(0, est.result, est.physical, est.wall_s))
    else:
        est, last = _estimate_kept(obs, S.t, U, Y, keep == "physical" or run.truth is not None, sink)
    met = metrics(est.physical, run.truth, start_up) if run.truth is not None else None
    res = est.result
    summary = {
        "model": mech.name,
        "model_file": mech.source,
        "run": str(run.path),
        "channels": list(obs.channels),
        "channels_used": [c for c in obs.channels if log_check.channel_rate_hz.get(c, 0) > 0],
        "reduced_ndof": obs.info["reduced_ndof"],
        "config": config.as_dict(),
        "nis_mean": res.mean_nis()[0],
        "nis_expected": res.mean_nis()[1],
        "n_updates": res.n_updates,
        "n_missing": res.n_missing,
        # diverged: the estimates became non-finite (the filter's covariance test can only flag inconsistency)
        "diverged": bool(res.nonfinite),
        "diverged_at": res.diverged_at if res.nonfinite else None,
        # (an estimator that reports its NIS test through ``diverged`` without non-finite values: the UKF)
        "nis_inconsistent": bool(res.nis_flagged or (res.diverged and not res.nonfinite)
                                 or nis_whole_log_flag(*res.mean_nis(), res.n_updates)),
        "nis_whole_log_flag": nis_whole_log_flag(*res.mean_nis(), res.n_updates),
        "nis_flagged_at": res.nis_flagged_at if res.nis_flagged else (
            res.diverged_at if res.diverged and not res.nonfinite else None),
        "flagged_intervals": [list(iv) for iv in res.flagged_intervals],
        "channel_faults": [dict(f) for f in res.channel_faults],
        "n_rejected": dict(res.n_rejected),
        "wall_s": est.wall_s,
        "real_time_factor": est.real_time_factor,
        "basis_s": obs.basis_s,
        "log_check": log_check.as_dict(),
        "metrics_from_s": start_up,
    }
    summary["estimator"] = config.estimator
    summary["smoothed"] = bool(smooth)
    if obs.ekf.model is obs.model and obs.model.method == "cached":
        summary["held_model_error"] = obs.model.held_error_summary()
    summary.update(_extra_states(obs.ekf.model, *last))
    if met is not None:
        summary.update(met)
        if est.filtered_physical is not None:
            summary["filtered_rms_error"] = metrics(est.filtered_physical, run.truth, start_up)["rms_error"]
    if unobservable:
        summary["unobservable"] = unobservable
    # the ERLS model's validity along the motion (links turning fast against their clamped frequency; logged)
    from ..erls.validity import signal_warnings

    motion = run.truth if run.truth is not None else est.physical
    summary["validity"] = [w.as_dict() for w in signal_warnings(mech, motion)] if motion is not None else []
    if bnd is not None:
        summary["bound_rms"] = bnd
        summary["bound_kind"] = _bound_kind(along, smooth)
        summary["bound_for"] = {"interval_s": log_check.interval_s, "channel_rate_hz": log_check.channel_rate_hz,
                                "along": along, "smoothed": bool(smooth), "scored_from_s": start_up}
        summary["bound_wall_s"] = track.wall_s
        if smooth:
            summary["filtered_bound_rms"] = dict(zip(bnd, map(float, track.rms(scored)), strict=True))
        if met is not None:
            summary["ratio_to_bound"] = {k: met["rms_error"][k] / bnd[k] for k in met["rms_error"] if bnd.get(k)}
            if smooth and "filtered_rms_error" in summary:
                fb = summary["filtered_bound_rms"]
                summary["filtered_ratio_to_bound"] = {k: v / fb[k] for k, v in summary["filtered_rms_error"].items()
                                                      if fb.get(k)}
    return Outcome(est, met, bnd, summary)


def _estimate_kept(obs: Observer, t: np.ndarray, U, Y, keep_physical: bool, sink) -> tuple[Estimate, tuple]:
    """The record filtered in chunks (:func:`estimate_chunks`), of which only the NIS sequence (and with
    ``keep_physical`` the physical estimates) is kept; each chunk goes to ``sink``. Returns the estimate and the
    last sample's state and variances (None if the filter stores no covariance)."""
    n = len(t)
    nis = np.empty(n)
    dof = np.empty(n, dtype=np.int16)  # a count of channels
    names = physical_names(obs.mech)
    phys = np.empty((n, len(names))) if keep_physical else None
    nominal = None  # the nominal payload's probability per sample, where reported
    wall = 0.0
    final = (np.full(obs.ekf.nx, np.nan), None, None)
    for ch in estimate_chunks(obs, t, U, Y, innovations=False):
        r = ch.result
        a, b = ch.start, ch.start + len(r.t)
        nis[a:b] = r.nis
        dof[a:b] = r.nis_dof
        if phys is not None:
            phys[a:b] = ch.physical.data
        if r.nominal_p is not None:
            nominal = np.empty(n) if nominal is None else nominal
            nominal[a:b] = r.nominal_p
        wall += ch.wall_s
        if sink is not None:
            sink(ch)
        if b > a:
            final = (r.x_hat[-1].copy(), None if r.P is None else r.P_diag[-1].copy(),
                     None if r.nominal_p is None else float(r.nominal_p[-1]))
        # the run-level counters, flags and faults so far, without the chunk's arrays (one chunk alive at a time)
        last = replace(r, x_hat=None, P=None, innovations=None, S=None, P_theta=None, nominal_p=None)
        del ch, r
    res = replace(last, t=t, nis=nis, nis_dof=dof, wall_s=wall, nominal_p=nominal)
    span = float(t[-1] - t[0]) if n > 1 else 0.0
    est = Estimate(res, None if phys is None else Signals(t, names, phys, physical_units(obs.mech)), wall,
                   span / wall if wall > 0 else float("inf"))
    return est, final


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


def _last_state(est: Estimate) -> tuple[np.ndarray, np.ndarray | None, float | None]:
    """The last sample's state, variances (None without a stored covariance) and nominal payload probability
    (None where not reported) of a whole record, smoothed where smoothing ran."""
    src = est.smoothed if est.smoothed is not None else est.result
    return (src.x_hat[-1], src.P_diag[-1] if src.P_diag is not None else None,
            None if src.nominal_p is None else float(src.nominal_p[-1]))


def augmented_estimates(fmodel, est: Estimate) -> dict:
    """The augmented states' estimates at the end of the record ``est`` of the filter model ``fmodel``
    (:func:`_extra_states`): the payload scale or the torque disturbances; empty for a plain model."""
    return _extra_states(fmodel, *_last_state(est))


def _extra_states(fmodel, x: np.ndarray, var: np.ndarray | None, nominal_p: float | None = None) -> dict:
    """The augmented states' estimates ``x`` and variances ``var`` at the end of the record (smoothed where
    smoothing ran; NaN standard deviations without ``var``): ``{"parameters": {"payload_scale": ...,
    "payload_scale_std": ..., "payload_nominal_p": ...}}`` (the last where reported, :func:`reported`) and
    ``{"inputs": {motor: {"value", "std"}}}``; empty for a plain model."""
    out: dict = {}
    it, ii = getattr(fmodel, "i_theta", None), getattr(fmodel, "i_inputs", None)
    if it is None and ii is None:
        return out
    var = np.full(len(x), np.nan) if var is None else var
    if it is not None:
        out["parameters"] = {"payload_scale": float(x[it]), "payload_scale_std": float(np.sqrt(var[it]))}
        if nominal_p is not None:
            out["parameters"]["payload_nominal_p"] = nominal_p
    if ii is not None:
        names = fmodel.inner.mech.motor_names
        out["inputs"] = {m: {"value": float(v), "std": float(np.sqrt(s))}
                         for m, v, s in zip(names, x[ii], var[ii], strict=True)}
    return out


def _hold(U: np.ndarray) -> np.ndarray:
    """A torque table (n, k) with its non-finite values held (:class:`LogColumns` with ``hold``), a copy."""
    U = np.asarray(U, float)
    return LogColumns(U, range(U.shape[1]), hold=True)[0 : len(U)]

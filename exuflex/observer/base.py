"""The contract between a discrete-time model and the filter.

A model plugs into :class:`~exuflex.observer.ekf.MultirateEKF` through :class:`DiscreteModel`: for one interval
between two samples it supplies a :class:`Prediction` (the state at the interval's end, the step Jacobian and
the process noise: the paper's ``f_d``, ``A_k`` and ``Q`` of eqs. 10-13), and for a set of channels a
:class:`Measurement` (``g`` and ``D_k``). The filter owns all the Kalman algebra and never looks inside a
model: the reduced flexible-multibody model (eqs. 7-9), the full-order ERLS model and the toy models of the
tests are interchangeable.

Conventions
-----------
- An *interval* runs from one sample to the next; its length ``dt`` is whatever the two time stamps say (a lab
  clock's jitter and drift included). The model integrates over it with its own sub-steps.
- The input ``u`` (measured torques) is the sample that starts the interval, ``u_next`` the sample that ends it:
  a model holds ``u`` over the interval (zero-order hold, eq. 10) or takes the input linear between the two (a
  smooth signal sampled: :attr:`.reduced.ReducedObserverModel.input_hold`), or uses ``u_next`` to detect a step
  within the interval. Either may be ``None`` for an autonomous model.
- Every channel is a *scalar* signal; a multi-component sensor is several channels (``"tip_x"``, ``"tip_y"``).
- States are 1-D ``(nx,)``, matrices ``(nx, nx)`` and ``(m, nx)``, float64.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np

__all__ = ["GENERAL", "INPUT_STEP", "LOOP_DONE", "MONITOR", "NONFINITE", "REFRESH", "REMAP", "ROWS", "SINGULAR", "Belief", "CompiledModel", "DiscreteModel",
           "FilterDivergedError", "LinearDiscreteModel", "LoopModel", "Measurement", "ModelHooks", "Prediction", "hooks", "takes_compiled_loop"]

#: Why the filter's compiled sample loop (:func:`.loop.samples`) stopped: the samples asked for are done; the held
#: configuration's or the step map's radius was left (the model renews its arrays, :meth:`CompiledModel.loop_model`,
#: and the loop resumes at that sample); a sample whose interval the model's own :meth:`~DiscreteModel.predict` must
#: take (a torque jump, the model's own reasons); the sensor-fault monitor's report of its findings is full (the
#: filter reads it); an input step at the last sample done (the filter records it): after the last two the loop
#: resumes; the prediction left the measurement
#: rows' radius (the model's :meth:`~DiscreteModel.measure` at the prediction renews them, the loop resumes there);
#: the sample went non-finite, or its innovation covariance was singular (the filter flags or raises: the monitors
#: saw the sample, its state is not kept).
LOOP_DONE, REFRESH, REMAP, GENERAL, MONITOR, INPUT_STEP, ROWS, NONFINITE, SINGULAR = 0, 1, 2, 3, 4, 5, 6, 7, 8


class FilterDivergedError(RuntimeError):
    """The filter produced a non-finite state or covariance, or failed its divergence test in ``raise`` mode."""


class Belief(NamedTuple):
    """A Gaussian belief about the state: mean and covariance (what a filter carries from sample to sample)."""

    x: np.ndarray
    """(nx,) mean."""
    P: np.ndarray
    """(nx, nx) covariance."""


class Prediction(NamedTuple):
    """What a model predicts over one interval."""

    x: np.ndarray
    """(nx,) state at the end of the interval."""
    F: np.ndarray
    """(nx, nx) Jacobian ``d x / d x_start`` along the step."""
    Q: np.ndarray
    """(nx, nx) process-noise covariance of the interval."""


class Measurement(NamedTuple):
    """Predicted channels and their Jacobian at a state."""

    y: np.ndarray
    """(m,) predicted value of each requested channel, in the requested order."""
    H: np.ndarray
    """(m, nx) Jacobian ``d y / d x``."""


@runtime_checkable
class DiscreteModel(Protocol):
    """A discrete-time nonlinear state-space model: ``nx``, :meth:`predict`, :meth:`measure` (and optionally
    ``reset()``, called when a filter restarts, for models that cache configuration-dependent data)."""

    nx: int

    def predict(self, x: np.ndarray, u, dt: float, u_next=None) -> Prediction:
        """Advance the state ``x`` over an interval of ``dt`` seconds with the input ``u`` held."""
        ...

    def measure(self, x: np.ndarray, channels: Sequence[str]) -> Measurement:
        """Predicted measurement of the requested channels at ``x`` and its Jacobian."""
        ...


@dataclass
class LinearDiscreteModel:
    """A linear time-invariant :class:`DiscreteModel`: ``x+ = A x + B u``, ``y = C x``.

    Useful as a reference model (the EKF on it is an ordinary Kalman filter) and for linearised models.

    Parameters
    ----------
    A : ndarray, shape (nx, nx)
        Discrete transition matrix over one interval.
    B : ndarray, shape (nx, nu) or None
        Discrete input matrix over one interval (zero-order hold).
    C : dict[str, ndarray]
        Output row (shape (nx,)) per channel name.
    Q : ndarray, shape (nx, nx)
        Process-noise covariance per interval.
    dt : float or None
        The interval the matrices were built for; if set, ``predict`` checks it.
    """

    A: np.ndarray
    B: np.ndarray | None
    C: dict[str, np.ndarray]
    Q: np.ndarray
    dt: float | None = None
    _rows: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        self.A = np.asarray(self.A, float)
        self.B = None if self.B is None else np.atleast_2d(np.asarray(self.B, float))
        self.C = {k: np.asarray(v, float).reshape(-1) for k, v in self.C.items()}
        self.Q = np.asarray(self.Q, float)
        self.nx = self.A.shape[0]
        for k, v in self.C.items():
            if v.shape != (self.nx,):
                raise ValueError(f"output row of channel {k!r} has shape {v.shape}, expected ({self.nx},)")

    @property
    def n_inputs(self) -> int:
        """The number of inputs (columns of ``B``; 0 without)."""
        return 0 if self.B is None else int(self.B.shape[1])

    def _C(self, channels) -> np.ndarray:
        key = tuple(channels)
        H = self._rows.get(key)
        if H is None:
            H = np.array([self.C[c] for c in key]).reshape(len(key), self.nx)
            self._rows[key] = H
        return H

    def predict(self, x, u, dt, u_next=None) -> Prediction:
        if self.dt is not None and abs(dt - self.dt) > 1e-9 * self.dt:
            raise ValueError(f"model discretised for dt={self.dt}, asked for dt={dt}")
        xn = self.A @ x
        if self.B is not None and u is not None:
            xn = xn + self.B @ np.atleast_1d(u)
        return Prediction(xn, self.A, self.Q)

    def measure(self, x, channels) -> Measurement:
        H = self._C(channels)
        return Measurement(H @ x, H)


class LoopModel(NamedTuple):
    """What a :class:`CompiledModel` hands the filter's compiled sample loop for a stretch of samples: ``step``,
    the arrays its compiled interval and measurement read (:class:`.expansion.CachedStep`); ``state``, what the
    interval carries from one sample to the next (:class:`.expansion.LoopState`); ``extras``, an augmented state's
    arrays (:class:`.expansion.LoopExtras`) or None."""

    step: tuple
    state: tuple
    extras: tuple | None


@runtime_checkable
class CompiledModel(DiscreteModel, Protocol):
    """A :class:`DiscreteModel` whose intervals and measurements (every channel) the filter's compiled sample loop
    (:func:`.loop.samples`) can take: the same numbers as :meth:`predict` and :meth:`measure`, from the arrays
    :meth:`loop_model` hands it.

    The optional members of any :class:`DiscreteModel` are :class:`ModelHooks`' (looked up in one place,
    :func:`hooks`)."""

    compiled: bool
    """The compiled loop may take this model's intervals (False: :meth:`predict` alone)."""

    def loop_model(self, x: np.ndarray, u: np.ndarray, dt: float, channels: tuple) -> LoopModel:
        """The compiled step's arrays for samples from the state ``x`` with the input ``u`` held over ``dt``."""
        ...

    def loop_done(self, mats: tuple, dt: float, state: tuple, x: np.ndarray, k: int) -> None:
        """After the loop's samples up to ``k`` (not done), the filter's state now ``x``: what the model keeps of
        them (the carried ``state``, the last interval's held matrices ``mats`` over ``dt``)."""
        ...


def takes_compiled_loop(model) -> bool:
    """Whether the filter's compiled sample loop may take ``model``'s intervals: its class implements
    :class:`CompiledModel` (a wrapping model that forwards attribute reads to the model it wraps does not) and the
    model's step is the compiled one (``compiled``)."""
    return all(hasattr(type(model), name) for name in ("compiled", "loop_model", "loop_done")) and bool(model.compiled)


class ModelHooks(NamedTuple):
    """The optional members of the model contract, as a filter uses them (:func:`hooks` looks them up once; a model
    without one gets its default)."""

    reset: Callable[[], None] | None
    """Forget what the model cached (a filter's restart); None: nothing to forget."""
    watch_covariance: Callable[[Callable[[], np.ndarray]], None] | None
    """Take the filter's covariance (a callable returning it): the model measures its approximations against it."""
    n_jumps: Callable[[], int]
    """Intervals with a torque step so far (the filter's hold-off after one); 0 without the count."""
    i_theta: int | None
    """Index of a payload-scale state (None: none)."""
    i_inputs: np.ndarray | None
    """Indices of torque-disturbance states (None: none)."""
    n_inputs: int | None
    """The number of inputs (torques) a step takes (None: the model does not say)."""


def _no_jumps() -> int:
    return 0


def hooks(model) -> ModelHooks:
    """The optional members of ``model`` (:class:`ModelHooks`): the one place a filter looks for them."""
    jumps = (lambda: model.n_jumps) if hasattr(model, "n_jumps") else _no_jumps
    return ModelHooks(getattr(model, "reset", None), getattr(model, "watch_covariance", None), jumps,
                      getattr(model, "i_theta", None), getattr(model, "i_inputs", None),
                      getattr(model, "n_inputs", None))

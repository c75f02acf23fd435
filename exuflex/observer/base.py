"""The contract between a discrete-time model and the observer machinery.

Any model the observers estimate plugs in through :class:`DiscreteModel`: a one-interval step map with its
state Jacobian (the paper's ``f_d`` and ``A_k`` of eqs. 10-13), a measurement map with its Jacobian for a
requested set of channels (``g`` and ``D_k``), and the process-noise covariance for one interval (``Q``).
The observers never look inside the model; the reduced flexible-multibody model (eqs. 7-9) and the toy models
of the tests are interchangeable.

Conventions
-----------
- One *interval* is one measurement period ``dt`` (2 ms at 500 Hz in the paper). The model integrates over it
  with its own sub-steps (RK4 at 0.1 ms in the paper) and returns the state at the end of the interval and
  ``F = d x_next / d x``.
- The input ``u`` is held constant over the interval (zero-order hold). It may be ``None`` for an autonomous
  model.
- Every channel is a *scalar* sensor signal; a multi-component sensor is listed as several channels (e.g.
  ``"tip_x"``, ``"tip_y"``). ``measure`` returns the channels in the order requested.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["DiscreteModel", "FilterDivergedError", "LinearDiscreteModel"]


class FilterDivergedError(RuntimeError):
    """The filter produced a non-finite state or covariance, or failed its divergence test in ``raise`` mode."""


@runtime_checkable
class DiscreteModel(Protocol):
    """A discrete-time nonlinear state-space model over one measurement interval.

    Attributes
    ----------
    nx : int
        State size.
    """

    nx: int

    def step(self, x: np.ndarray, u, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Advance one interval.

        Parameters
        ----------
        x : ndarray, shape (nx,)
            State at the start of the interval.
        u : ndarray or None
            Input held over the interval.
        dt : float
            Interval length (s); the model sub-steps internally.

        Returns
        -------
        x_next : ndarray, shape (nx,)
            State at the end of the interval.
        F : ndarray, shape (nx, nx)
            Jacobian ``d x_next / d x`` evaluated along the step.
        """
        ...

    def measure(self, x: np.ndarray, channels: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """Predicted measurements and their Jacobian.

        Parameters
        ----------
        x : ndarray, shape (nx,)
            State.
        channels : sequence of str
            Names of the requested (scalar) channels.

        Returns
        -------
        y : ndarray, shape (m,)
            Predicted measurement, one entry per requested channel, in the requested order.
        H : ndarray, shape (m, nx)
            Jacobian ``d y / d x``.
        """
        ...

    def process_noise(self, x: np.ndarray, u, dt: float) -> np.ndarray:
        """Process-noise covariance ``Q`` of one interval, shape (nx, nx); may be constant."""
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
        The interval the matrices were built for; if set, ``step`` checks it.
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

    def _C(self, channels) -> np.ndarray:
        key = tuple(channels)
        H = self._rows.get(key)
        if H is None:
            H = np.array([self.C[c] for c in key]).reshape(len(key), self.nx)
            self._rows[key] = H
        return H

    def step(self, x, u, dt):
        if self.dt is not None and abs(dt - self.dt) > 1e-9 * self.dt:
            raise ValueError(f"model discretised for dt={self.dt}, asked for dt={dt}")
        xn = self.A @ x
        if self.B is not None and u is not None:
            xn = xn + self.B @ np.atleast_1d(u)
        return xn, self.A

    def input_jacobian(self):
        """``d x_next / d u``: ``B`` (for :class:`~exuflex.observer.hold.LinearHoldModel`)."""
        return self.B

    def measure(self, x, channels):
        H = self._C(channels)
        return H @ x, H

    def process_noise(self, x, u, dt):
        return self.Q

"""Sensor-bias states: an offset per chosen channel estimated together with the mechanism's states.

:class:`SensorBiasModel` wraps a filter model (a :class:`~exuflex.observer.reduced.ReducedObserverModel`,
state ``z``) into one with the state ``x = [z; b]``, ``b_c`` the offset of channel ``c`` in the channel's unit:

- measurement: ``y_c = g_c(z) + b_c`` for a channel with a bias state, ``y_c = g_c(z)`` otherwise, so
  ``dy_c / db_c = 1``;
- process: ``b`` a random walk, ``b_next = b`` with variance ``bias_std^2 dt`` per interval (``bias_std`` per
  square root of a second; a constant offset has ``bias_std`` near zero), independent of ``z``.

An offset present from the first sample moves every reading of its channel by the same amount, so an
innovation test cannot see it unless another channel measures the same quantity: with a channel's only absolute
information being the biased sensor, ``b_c`` and the state it reads are not separable (the pair is
unobservable) and the bias state's variance stays at its prior, which then appears in the estimate's own
variance instead of in an unreported error. With a second reading of the same quantity (the six-bar's relative
encoder ``q3rel = q3 - q1 - pi`` reads ``q1`` through the loop) the offset of the channel that has a bias
state becomes observable.

:func:`with_bias_states` gives an :class:`~exuflex.observer.session.Observer` this model (the EKF rebuilt with
the same settings, the prior extended by ``b = 0`` and ``bias0_std``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from .base import Measurement, Prediction

__all__ = ["SensorBiasModel", "with_bias_states"]


class SensorBiasModel:
    """A filter model with an offset state for each channel of ``channels`` (module docstring).

    Parameters
    ----------
    inner : filter model
        ``predict(x, u, dt, u_next)`` and ``measure(x, channels)`` on the state ``z`` (``inner.nx`` entries).
    channels : sequence of str
        The channels that get a bias state, in the order of the states.
    bias_std : float
        Random-walk standard deviation of every bias per square root of a second (channel units / sqrt(s)).

    Attributes
    ----------
    nx : int
        ``inner.nx + len(channels)``.
    i_bias : dict str -> int
        Index of each channel's bias in the state.
    """

    def __init__(self, inner, channels: Sequence[str], bias_std: float = 0.0):
        channels = tuple(channels)
        if not channels or len(set(channels)) != len(channels) or not all(isinstance(c, str) for c in channels):
            raise ValueError(f"bias channels: expected distinct channel names, got {list(channels)}")
        if not (np.isfinite(bias_std) and bias_std >= 0):
            raise ValueError(f"bias_std must be a non-negative number, got {bias_std!r}")
        self.inner = inner
        self.n0 = inner.nx
        self.bias_channels = channels
        self.bias_std = float(bias_std)
        self.i_bias = {c: self.n0 + k for k, c in enumerate(channels)}
        self.nx = self.n0 + len(channels)
        self.state_labels = tuple(getattr(inner, "state_labels", tuple(f"z{i}" for i in range(self.n0)))) + \
            tuple(f"b_{c}" for c in channels)

    def reset(self) -> None:
        if hasattr(self.inner, "reset"):
            self.inner.reset()

    def predict(self, x: np.ndarray, u, dt: float, u_next=None) -> Prediction:
        """``[f(z, u); b]`` with ``F = diag(F_z, I)`` and ``Q = diag(Q_z, bias_std^2 dt I)``."""
        x = np.asarray(x, float)
        n0, N = self.n0, self.nx
        pred = self.inner.predict(x[:n0], u, dt, u_next)
        xn = np.empty(N)
        xn[:n0] = pred.x
        xn[n0:] = x[n0:]
        F = np.zeros((N, N))
        F[:n0, :n0] = pred.F
        F[n0:, n0:] = np.eye(N - n0)
        Q = np.zeros((N, N))
        Q[:n0, :n0] = pred.Q
        Q[n0:, n0:] = self.bias_std**2 * dt * np.eye(N - n0)
        return Prediction(xn, F, Q)

    def measure(self, x: np.ndarray, channels: Sequence[str]) -> Measurement:
        """``g(z) + b`` on the channels with a bias state; ``dy_c / db_c = 1``."""
        x = np.asarray(x, float)
        y, H0 = self.inner.measure(x[: self.n0], channels)
        y = np.array(y, float)
        H = np.zeros((len(y), self.nx))
        H[:, : self.n0] = H0
        for i, c in enumerate(channels):
            j = self.i_bias.get(c)
            if j is not None:
                y[i] += x[j]
                H[i, j] = 1.0
        return Measurement(y, H)

    def __getattr__(self, name):
        # physical maps (tip_maps, initial_state, rm, nq, ...) are the inner model's
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)


def with_bias_states(obs, channels: Sequence[str], bias0_std: float | Sequence[float], bias_std: float = 0.0):
    """``obs`` (an :class:`~exuflex.observer.session.Observer` of the plain EKF) with a bias state on each of
    ``channels``: prior mean 0 and standard deviation ``bias0_std`` (channel units; one value or one per
    channel), random walk ``bias_std`` per sqrt(s). The EKF is rebuilt with the observer's settings."""
    from .ekf import MultirateEKF
    from .session import _noise_std

    ekf = obs.ekf
    if not isinstance(ekf, MultirateEKF) or ekf.model is not obs.model:
        raise ValueError("with_bias_states: expected an observer of the plain EKF (estimator 'ekf')")
    unknown = [c for c in channels if c not in obs.channels]
    if unknown:
        raise ValueError(f"with_bias_states: {unknown} not among the observer's channels {list(obs.channels)}")
    s0 = np.broadcast_to(np.asarray(bias0_std, float), (len(channels),))
    if not np.all(np.isfinite(s0) & (s0 > 0)):
        raise ValueError(f"bias0_std must be positive, got {bias0_std!r}")
    model = SensorBiasModel(obs.model, channels, bias_std)
    x0 = np.concatenate([np.asarray(ekf.x0, float), np.zeros(len(channels))])
    P0 = np.zeros((model.nx, model.nx))
    n0 = model.n0
    P0_z = ekf.P0
    P0[:n0, :n0] = np.diag(P0_z) if P0_z.ndim == 1 else P0_z
    P0[n0:, n0:] = np.diag(s0**2)
    new = MultirateEKF(model, obs.channels, _noise_std(obs.mech, obs.channels), x0, P0, dt=ekf.dt,
                       max_gap=obs.config.max_gap, monitoring=ekf.monitoring)
    return dataclasses.replace(obs, ekf=new)

"""Sampled noisy inputs interpolated linearly between samples: their noise as states (``input_hold="linear"``).

The measured torques are samples ``u~_k = u_k + w_k`` with white noise ``w_k ~ N(0, S)``. With the linear
hold (:class:`~.ekf.MultirateEKF`, ``input_hold="linear"``) the interval from ``t_k`` to ``t_k+1`` is predicted
with the mean ``(u~_k + u~_k+1) / 2`` of its two bounding samples, so its input error ``(w_k + w_k+1) / 2``
shares ``w_k+1`` with the next interval: moving-average (MA(1)) process noise, which a filter with white
process noise cannot represent (measured on the six-bar with the full-order ERLS truth: per-quantity NEES
contributions 0.62-1.71 instead of 1). Here the noise of the latest sample is part of the state, so the
filter models it exactly. With ``G = d x_next / d u`` of the model's step (its response to a unit input held
over the interval) the truth, to first order in the noise, is

    x_k+1 = f(x_k, u_bar) - G w_k / 2 - G w_k+1 / 2,

and the augmented state ``xi = [x; w]`` (``w`` the noise of the newest sample) evolves as

    xi_k+1 = [f(x_k, u_bar) - G w_k / 2; 0] + [-G / 2; I] w_k+1,
    F_aug = [[F, -G/2], [0, 0]],   Q_aug = [[G S G'/4 + Q_extra, -G S / 2], [-S G' / 2, S]].

An interval predicted with a held sample instead (the filter holds across missing samples) has ``a = 1``,
``b = 0`` in the general form ``x_k+1 = f - a G w_old - b G w_new``; the noise state is renewed with the new
sample at the end of the last interval before it (``F_ww = 0``, ``Q_ww = S``) and kept otherwise
(``F_ww = I``). The filter tells the model which case each interval is through :meth:`hold_interval`.

The physical state is the leading ``base.nx`` block of the estimate and of its covariance.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["LinearHoldModel"]


class LinearHoldModel:
    """:class:`~.base.DiscreteModel` of ``base`` with the noise of the newest input sample as extra states.

    Parameters
    ----------
    base : DiscreteModel
        Must also offer ``input_jacobian()``: ``d x_next / d u`` (nx, nu) of its last :meth:`step`.
    input_var : array_like, shape (nu,)
        Variance of the white noise on each input sample.
    extra : array_like, shape (nx,), optional
        Diagonal of the base model's own white process noise per interval (unmodelled dynamics), if any.
    """

    def __init__(self, base, input_var, extra=None):
        self.base = base
        self.input_var = np.asarray(input_var, float).reshape(-1)
        self.n = int(base.nx)
        self.nu = len(self.input_var)
        self.nx = self.n + self.nu
        self.extra = None if extra is None else np.asarray(extra, float).reshape(self.n)
        self._a, self._b, self._renew = 0.5, 0.5, True
        self._G = None

    def reset(self) -> None:
        if hasattr(self.base, "reset"):
            self.base.reset()
        self._a, self._b, self._renew = 0.5, 0.5, True

    def hold_interval(self, mean: bool, renew: bool) -> None:
        """How the filter drives the next interval: with the mean of its two samples (``mean``) or the older one
        held; ``renew``: a new sample arrives at its end (the noise state becomes that sample's)."""
        self._a, self._b = (0.5, 0.5) if mean else (1.0, 0.0)
        self._renew = bool(renew)

    def initial_covariance(self, P0) -> np.ndarray:
        """The augmented prior: ``P0`` of the base state, the input variance for the first sample's noise."""
        P0 = np.asarray(P0, float)
        out = np.zeros((self.nx, self.nx))
        out[: self.n, : self.n] = np.diag(P0) if P0.ndim == 1 else P0
        out[self.n :, self.n :] = np.diag(self.input_var)
        return out

    def step(self, x, u, dt):
        n = self.n
        x = np.asarray(x, float)
        xn, F = self.base.step(x[:n], u, dt)
        G = np.asarray(self.base.input_jacobian(), float)
        self._G = G
        out = np.empty(self.nx)
        w = x[n:]
        out[:n] = xn - self._a * (G @ w)
        Fa = np.zeros((self.nx, self.nx))
        Fa[:n, :n] = F
        Fa[:n, n:] = -self._a * G
        if self._renew:
            out[n:] = 0.0
        else:
            out[n:] = w
            Fa[n:, n:] = np.eye(self.nu)
        return out, Fa

    def process_noise(self, x, u, dt):
        n, S, b = self.n, self.input_var, self._b
        G = self._G
        if G is None:  # process_noise before any step: the map at x
            self.step(x, u, dt)
            G = self._G
        Q = np.zeros((self.nx, self.nx))
        if b:
            Q[:n, :n] = (b * b) * ((G * S) @ G.T)
        if self.extra is not None:
            Q[:n, :n] += np.diag(self.extra)
        if self._renew:
            if b:
                Q[:n, n:] = -b * (G * S)
                Q[n:, :n] = Q[:n, n:].T
            Q[n:, n:] = np.diag(S)
        return Q

    def measure(self, x, channels: Sequence[str]):
        y, H = self.base.measure(np.asarray(x, float)[: self.n], channels)
        Ha = np.zeros((len(y), self.nx))
        Ha[:, : self.n] = H
        return y, Ha

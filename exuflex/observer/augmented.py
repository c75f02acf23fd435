"""Augmented-state models: unknown parameters and unknown inputs estimated together with the states.

:class:`AugmentedModel` wraps a :class:`~exuflex.observer.reduced.ReducedObserverModel` (state ``z = [p; p']``)
into a :class:`~exuflex.observer.base.DiscreteModel` with the state ``x = [z; theta; d]``:

- ``theta`` (optional): the scale of the model file's tip payload (1 = nominal), a random walk with the stated
  standard deviation per square root of a second;
- ``d`` (optional): a torque disturbance per motor added to the measured torques, a random walk or a first-order
  Gauss-Markov process (time constant ``input_tau``).

Payload. The payload is a lumped mass ``m_p`` (and inertia ``I_p``) at one node, so the reduced mass matrix is
linear in its scale: ``M_r(theta) = M_r0 + (theta - 1) M_p`` with ``M_p = A_p^T diag(m_p, m_p, I_p) A_p``, where
``A_p = (W J)`` restricted to the node's three absolute coordinates (the rows through the basis at the held
configuration; :mod:`exuflex.reduction.model` has ``M_r = (W J)^T M_N (W J)``). With ``theta`` the equations
``M_r(theta) p'' + ... = f`` are the nominal ones with the extra generalised force
``g = (theta - 1) (G_p - M_p a_theta)`` (``G_p`` the extra payload's weight, ``a_theta`` the acceleration of the
scaled system). Over one interval ``a_theta`` is taken as the interval's mean: the nominal step's mean
acceleration ``a0 = (p'_end - p'_start) / dt`` satisfies ``M_r0 a0 = f`` (mean forces), hence
``M_r(theta) a_theta = M_r0 a0 + (theta - 1) G_p``. ``g`` is held over the interval, so the step is

``x_next = f_nom(z, u + d) + S g(theta, a0)``

with ``S`` the nominal step map's response to a unit generalised force held over the interval (the held linear
system's, :class:`~exuflex.observer.reduced.ReducedObserverModel`). Its derivatives are analytic:
``dg/dtheta = w - (theta - 1) M_p M_r(theta)^-1 w`` with ``w = G_p - M_p a_theta``, and
``dg/da0 = -(theta - 1) M_p M_r(theta)^-1 M_r0`` with ``da0/dz = (F_nom[p' rows] - [0 I]) / dt``. The
approximations (mean acceleration, force held over the interval, ``M_p`` and ``S`` at the held configuration)
are of the order of the within-interval change of the payload's inertia force; the process noise covers them.

Inputs. ``d`` enters the step as the measured torques do: ``d x_next / d d = L`` (the step map's response to a
unit torque held over the interval). Random walk: ``d_next = d``, variance ``input_std^2 dt`` per interval;
Gauss-Markov: ``d_next = exp(-dt / tau) d``, variance ``input_std^2 (1 - exp(-2 dt / tau))`` (``input_std`` is
then the stationary standard deviation).

The measurements do not depend on ``theta`` or ``d``: their Jacobian columns are zero.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .base import Measurement, Prediction

__all__ = ["AugmentedModel", "payload_rows"]


def payload_rows(inner, mats) -> tuple[np.ndarray, np.ndarray]:
    """``(A_p, m)``: the (3, r) map from ``p'`` to the payload node's absolute velocity ``(x', y', theta')``,
    ``(W J)`` at the node's coordinates, at the configuration of ``mats``, and its nominal masses
    ``(m_p, m_p, I_p)``."""
    mech = inner.mech
    if mech.payload is None:
        raise ValueError(f"{mech.source or mech.name}: model has no [payload]; the payload estimator needs one")
    i = list(mech.node_ids).index(mech.payload.node)
    W = mats.rc.cfg.W
    A = W[3 * i : 3 * i + 3] @ mats.J
    m = np.array([mech.payload.mass, mech.payload.mass, mech.payload.inertia], float)
    return A, m


class AugmentedModel:
    """A reduced model with the payload scale and/or motor torque disturbances as extra states.

    Parameters
    ----------
    inner : ReducedObserverModel
        The nominal reduced model (its step and measurements).
    payload_std : float or None
        Random-walk standard deviation of the payload scale per sqrt(s); None: the payload is not estimated.
    input_std : float, array_like (n_motors,) or None
        Torque disturbance per motor (N m): random-walk std per sqrt(s) (``input_tau`` None), or the stationary
        std of a Gauss-Markov process; None: no disturbance states.
    input_tau : float or None
        Correlation time (s) of the Gauss-Markov disturbance; None: random walk.

    Attributes
    ----------
    nx : int
        ``inner.nx + (1 if payload) + (n_motors if inputs)``.
    i_theta : int or None
        Index of ``theta`` in the state.
    i_inputs : slice or None
        Indices of the disturbances in the state.
    """

    def __init__(self, inner, payload_std: float | None = None, input_std: float | None = None,
                 input_tau: float | None = None):
        if payload_std is None and input_std is None:
            raise ValueError("an augmented model needs payload_std or input_std (or both)")
        for name, v in (("payload_std", payload_std), ("input_std", input_std), ("input_tau", input_tau)):
            if v is not None and not np.all((np.asarray(v, float) > 0) & np.isfinite(v)):
                raise ValueError(f"{name} must be positive, got {v}")
        self.inner = inner
        self.n0 = inner.nx
        self.r = inner.r
        self.nu = len(inner.mech.motors)
        self.payload_std = payload_std
        self.input_std = None if input_std is None else np.broadcast_to(np.asarray(input_std, float), (self.nu,))
        self.input_tau = input_tau
        n = self.n0
        self.i_theta = None
        if payload_std is not None:
            if inner.mech.payload is None:
                raise ValueError(f"{inner.mech.source or inner.mech.name}: model has no [payload]; the payload "
                                 "estimator needs one")
            self.i_theta = n
            n += 1
        self.i_inputs = None
        if input_std is not None:
            self.i_inputs = slice(n, n + self.nu)
            n += self.nu
        self.nx = n
        g = np.zeros(3)
        g[:2] = inner.mech.gravity
        self._g = g
        self._payload_cache: dict = {}
        self.state_labels = tuple(f"z{i}" for i in range(self.n0)) + (
            ("payload_scale",) if self.i_theta is not None else ()) + (
            tuple(f"d_{m}" for m in inner.mech.motor_names) if self.i_inputs is not None else ())

    def reset(self) -> None:
        self.inner.reset()
        self._payload_cache = {}

    # ------------------------------------------------------------------ payload terms
    def payload_terms(self, mats) -> tuple[np.ndarray, np.ndarray]:
        """``(M_p, G_p)`` at the held configuration ``mats``: the nominal payload's reduced mass matrix and
        the generalised force of its weight (cached per configuration)."""
        key = id(mats)
        hit = self._payload_cache.get(key)
        if hit is not None and hit[0] is mats:
            return hit[1], hit[2]
        A, m = payload_rows(self.inner, mats)
        Mp = (A.T * m) @ A
        Gp = A.T @ (m * self._g)
        if len(self._payload_cache) > 8:
            self._payload_cache = {}
        self._payload_cache[key] = (mats, Mp, Gp)
        return Mp, Gp

    # ------------------------------------------------------------------ the model's interface
    def predict(self, x: np.ndarray, u, dt: float, u_next=None) -> Prediction:
        """``x_next = [f_nom(z, u + d) + S g(theta); theta; phi d]`` and its Jacobian (module docstring)."""
        x = np.asarray(x, float)
        n0, r, N = self.n0, self.r, self.nx
        z = x[:n0]
        if self.i_inputs is not None:
            d = x[self.i_inputs]
            u = (np.zeros(self.nu) if u is None else np.asarray(u, float)) + d
            if u_next is not None:
                u_next = np.asarray(u_next, float) + d
        pred = self.inner.predict(z, u, dt, u_next)
        iv, sm = self.inner.last_step
        xn = np.empty(N)
        xn[:n0] = pred.x
        F = np.zeros((N, N))
        F[:n0, :n0] = pred.F
        Q = np.zeros((N, N))
        Q[:n0, :n0] = pred.Q
        if self.i_inputs is not None:
            s = self.i_inputs
            F[:n0, s] = sm.L
            if self.input_tau is None:
                phi, q = 1.0, self.input_std**2 * dt
            else:
                phi = math.exp(-dt / self.input_tau)
                q = self.input_std**2 * (1.0 - phi * phi)
            xn[s] = phi * d
            F[s, s] = phi * np.eye(self.nu)
            Q[s, s] = np.diag(q)
        if self.i_theta is not None:
            it = self.i_theta
            th = float(x[it])
            M0 = iv.mats.Mr
            Mp, Gp = self.payload_terms(iv.mats)
            Mth = M0 + (th - 1.0) * Mp
            a0 = (pred.x[r:] - z[r:]) / dt
            a_th = np.linalg.solve(Mth, M0 @ a0 + (th - 1.0) * Gp)
            w = Gp - Mp @ a_th
            g = (th - 1.0) * w
            xn[:n0] += sm.S @ g
            # dg/dtheta and dg/da0 (module docstring)
            dg_dth = w - (th - 1.0) * (Mp @ np.linalg.solve(Mth, w))
            F[:n0, it] = sm.S @ dg_dth
            if th != 1.0:
                G_a = -(th - 1.0) * (Mp @ np.linalg.solve(Mth, M0)) / dt  # dg/da0 / dt
                SG = sm.S @ G_a  # (n0, r)
                da = pred.F[r:].copy()  # d(p'_end - p'_start)/dz
                da[:, r:] -= np.eye(r)
                F[:n0, :n0] += SG @ da
                if self.i_inputs is not None:
                    F[:n0, self.i_inputs] += SG @ sm.L[r:]
            xn[it] = th
            F[it, it] = 1.0
            Q[it, it] = self.payload_std**2 * dt
        return Prediction(xn, F, Q)

    def measure(self, x: np.ndarray, channels: Sequence[str]) -> Measurement:
        """The inner model's channels; zero Jacobian columns for the extra states."""
        x = np.asarray(x, float)
        y, H0 = self.inner.measure(x[: self.n0], channels)
        H = np.zeros((len(y), self.nx))
        H[:, : self.n0] = H0
        return Measurement(y, H)

    # ------------------------------------------------------------------ delegated
    def __getattr__(self, name):
        # physical maps (tip_rows, initial_state, rm, nq, ...) are the inner model's
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

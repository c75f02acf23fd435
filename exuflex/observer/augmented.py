"""Augmented-state models: unknown parameters and unknown inputs estimated together with the states.

:class:`AugmentedModel` wraps a :class:`~exuflex.observer.reduced.ReducedObserverModel` (state ``z = [p; p']``)
into a :class:`~exuflex.observer.base.DiscreteModel` with the state ``x = [z; theta; d]``:

- ``theta`` (optional): the scale of the model file's tip payload (1 = nominal), a random walk with the stated
  standard deviation per square root of a second;
- ``d`` (optional): a torque disturbance per motor added to the measured torques, a random walk or a first-order
  Gauss-Markov process (time constant ``input_tau``).

Payload. The payload is a lumped mass and inertia carried by one node. The full-order model's nodal mass matrix
is linear in them, and so is everything of the reduced model that comes from it on a fixed basis: ``M_r``, its
q-gradients, the mass-proportional damping and the velocity-dependent forces (the payload's Coriolis and
centripetal terms, ``A^T m (dA/dt) p'`` with ``A`` the node's rows of ``W J``), and the weight. With the basis
held (the nominal model's Craig-Bampton basis), the reduced model with the payload scaled by ``theta`` is
therefore exactly

``S(theta) = S(1) + (theta - 1) dS``,   ``dS = S_twin - S(1)``

for each array ``S`` of the held system (:class:`~exuflex.observer.expansion.HeldSystem`), where ``S_twin`` is
the same evaluation of a twin model whose payload is doubled (:func:`payload_twin`: the nominal basis on the
doubled payload's full-order model). ``dS`` is the analytic derivative ``dS/dtheta``: the payload enters
linearly (``dM_r/dtheta = A^T diag(m_p, m_p, I_p) A``, :func:`payload_rows`; the tests compare the two).
Per interval the step is the cached step's RK4 sub-steps of that held system (:func:`scaled_steps`), the
stiffness, input matrix and geometric terms unchanged. Its derivative in ``theta`` is the forward difference
of the same compiled step at ``theta + dtheta`` (``dtheta = 1e-4``: the step is smooth in ``theta``, its
truncation error ``dtheta / 2 d^2x/dtheta^2`` is far below the filter's uncertainty). Its derivative in the
state and the process noise are the nominal step map's where the payload's change of the modal masses,
``|theta - 1| rho`` with ``rho = max eig(dM_r, M_r)``, is within the tolerance the cached step holds its
matrices to (``refresh_tol``); beyond it, the held linear system's maps with ``M_r + (theta - 1) dM_r`` (and the
damping's increment), rebuilt with the nominal step map or when ``theta`` moved by that tolerance, and the
force Jacobian with the payload's velocity forms (:meth:`AugmentedModel._scaled_map`). ``theta`` below 0 is taken
as 0 in the step (a negative mass has no meaning and can make ``M_r`` indefinite); the derivative there is kept,
so that the measurements pull the estimate back. For ``hold_s`` seconds from the start the scale is held (its
Jacobian column zero: see :class:`AugmentedModel`).

With ``method="rk4"`` (the exact reference) the step is RK4 of the nonlinear reduced equations at every stage
with the matrices and forces of the two models combined the same way.

Inputs. ``d`` enters the step as the measured torques do: ``d x_next / d d = L`` (the step map's response to a
unit torque held over the interval). Random walk: ``d_next = d``, variance ``input_std^2 dt`` per interval;
Gauss-Markov: ``d_next = exp(-dt / tau) d``, variance ``input_std^2 (1 - exp(-2 dt / tau))`` (``input_std`` is
then the stationary standard deviation).

The measurements do not depend on ``theta`` or ``d``: their Jacobian columns are zero.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import scipy.linalg

from ..erls.model import ErlsModel
from ..reduction import ReducedModel
from .base import Measurement, Prediction
from .expansion import HeldSystem, _held_step, _jit, step_jacobian
from .reduced import _secant_factor

__all__ = ["AugmentedModel", "PayloadIncrement", "payload_rows", "payload_twin", "scaled_steps"]

#: the step of the scale used for the step's derivative in theta (forward difference)
DTHETA = 1e-4


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


def payload_twin(reduced: ReducedModel, scale: float = 2.0) -> ReducedModel:
    """The reduced model on the same Craig-Bampton basis (interior modes, masters, q*) with the payload scaled
    (default doubled): the difference of its evaluations and the nominal ones is the payload's share of every
    mass-dependent array. The basis at a configuration depends on the stiffness only (the interior modes are held
    from q*), so the twin's basis is the nominal one. Its own full-order model: its closure solver's warm starts
    are its own."""
    mech = reduced.model.mech
    if mech.payload is None:
        raise ValueError(f"{mech.source or mech.name}: model has no [payload]; the payload estimator needs one")
    cb = copy.copy(reduced.cb)
    cb.model = ErlsModel(mech.with_payload_scale(scale) if scale != 1.0 else mech, form=reduced.model.form)
    return ReducedModel(cb, consistent=reduced.consistent, compiled=reduced.compiled)


class PayloadIncrement(NamedTuple):
    """``dS = dS/dtheta`` of the held system's mass-dependent arrays (:class:`HeldSystem` names), at the held
    configuration and at its secant partner (``old_*``)."""

    Mr: np.ndarray
    Ca: np.ndarray
    dM: np.ndarray
    fg: np.ndarray
    T2: np.ndarray
    old_dM: np.ndarray
    old_Ca: np.ndarray
    old_fg: np.ndarray
    old_T2: np.ndarray


def _scaled_steps(z, u, dl, s, h, n, c, dc, has_old, beta, Mr, Kr, Ca, Gr, dM, dK, fg, T2, V2, C2, old_dM, old_dK,
                  old_Ca, old_Gr, old_fg, old_T2, old_V2, old_C2, iMr, iCa, idM, ifg, iT2, iold_dM, iold_Ca,
                  iold_fg, iold_T2):  # pragma: no cover - compiled
    """The held step (:func:`.expansion.held_step`) of the system ``S + c dS`` and of ``S + (c + dc) dS``: the
    states at the interval's end for the payload scale ``1 + c`` and ``1 + c + dc`` (``dc = 0``: the first only,
    the second row zero). The held arrays come one by one (``*system, *increment``), as the expansion's kernels
    take them."""
    out = np.zeros((2, z.shape[0]))
    for k in range(2 if dc != 0.0 else 1):  # dc = 0: the step alone (no derivative asked for)
        a = c if k == 0 else c + dc
        out[k] = _held_step(z, u, dl, s, h, n, has_old, beta, Mr + a * iMr, Kr, Ca + a * iCa, Gr, dM + a * idM, dK,
                            fg + a * ifg, T2 + a * iT2, V2, C2, old_dM + a * iold_dM, old_dK, old_Ca + a * iold_Ca,
                            old_Gr, old_fg + a * iold_fg, old_T2 + a * iold_T2, old_V2, old_C2)[0]
    return out


scaled_steps = _jit(_scaled_steps)


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
    hold_s : float
        Seconds of intervals from the start (or :meth:`reset`) during which the payload scale is held: its column
        of the step Jacobian is zero, so the states and the scale stay uncorrelated and no measurement moves the
        scale (the step still uses its current value). An EKF's joint state-parameter update during the
        filter's start-up transient, where the states' errors far exceed their covariance, attributes part of
        those errors to the parameter with a confidence it does not have; the scale is learned from the
        consistent part of the record instead.

    Attributes
    ----------
    nx : int
        ``inner.nx + (1 if payload) + (n_motors if inputs)``.
    i_theta : int or None
        Index of ``theta`` in the state.
    i_inputs : slice or None
        Indices of the disturbances in the state.
    twin : ReducedModel or None
        The doubled-payload model on the nominal basis (:func:`payload_twin`).
    """

    def __init__(self, inner, payload_std: float | None = None, input_std: float | None = None,
                 input_tau: float | None = None, hold_s: float = 0.0):
        if payload_std is None and input_std is None:
            raise ValueError("an augmented model needs payload_std or input_std (or both)")
        for name, v in (("payload_std", payload_std), ("input_std", input_std), ("input_tau", input_tau)):
            if v is not None and not np.all((np.asarray(v, float) > 0) & np.isfinite(v)):
                raise ValueError(f"{name} must be positive, got {v}")
        if not (hold_s >= 0 and math.isfinite(hold_s)):
            raise ValueError(f"hold_s must be a non-negative number of seconds, got {hold_s}")
        self.inner = inner
        self.n0 = inner.nx
        self.r = inner.r
        self.nu = len(inner.mech.motors)
        self.payload_std = payload_std
        self.input_std = None if input_std is None else np.broadcast_to(np.asarray(input_std, float), (self.nu,))
        self.input_tau = input_tau
        n = self.n0
        self.i_theta = None
        self.twin = None
        if payload_std is not None:
            if inner.mech.payload is None:
                raise ValueError(f"{inner.mech.source or inner.mech.name}: model has no [payload]; the payload "
                                 "estimator needs one")
            self.i_theta = n
            n += 1
            self.twin = payload_twin(inner.rm)
        self.i_inputs = None
        if input_std is not None:
            self.i_inputs = slice(n, n + self.nu)
            n += self.nu
        self.nx = n
        self.hold_s = float(hold_s)
        self._elapsed = self._start = 0.0  # time at the end and at the start of the current interval
        self._last_interval = None
        self._increments: dict = {}
        self._shares: dict = {}
        self._map = None
        self._plain = None  # the nominal model's own evaluation, where an increment is asked for later
        self.state_labels = tuple(f"z{i}" for i in range(self.n0)) + (
            ("payload_scale",) if self.i_theta is not None else ()) + (
            tuple(f"d_{m}" for m in inner.mech.motor_names) if self.i_inputs is not None else ())

    def reset(self) -> None:
        self.inner.reset()
        self._elapsed = self._start = 0.0
        self._last_interval = None
        self._increments = {}
        self._shares = {}
        self._map = None
        for m in (self.twin, self._plain):
            if m is not None:
                m.model.kin.reset_warm_start()

    # ------------------------------------------------------------------ payload terms
    def payload_terms(self, mats) -> tuple[np.ndarray, np.ndarray]:
        """``(M_p, G_p)`` at the configuration of ``mats``: ``dM_r/dtheta = A^T diag(m) A`` (:func:`payload_rows`)
        and the generalised force of the nominal payload's weight ``A^T m g``."""
        A, m = payload_rows(self.inner, mats)
        g = np.zeros(3)
        g[:2] = self.inner.mech.gravity
        return (A.T * m) @ A, A.T @ (m * g)

    def increment(self, iv, z: np.ndarray, fresh: bool = False) -> PayloadIncrement:
        """``dS/dtheta`` of the held configuration ``iv``, cached per configuration: the twin's evaluation at
        ``iv``'s q with the coordinates of ``z`` less the nominal one there. ``fresh``: ``iv`` was evaluated at
        ``z`` in this interval (its q ahead along the motion, the other coordinates ``z``'s), so the nominal
        arrays are ``iv``'s own; else the nominal model is evaluated too. The secant partner's increment comes
        from the cache (its own if that is gone: the payload's share is then held, not followed)."""
        hit = self._increments.get(iv.serial)
        if hit is not None:
            return hit
        r, nq = self.r, self.inner.nq
        p = z[:r].copy()
        p[:nq] = iv.q0
        mats, fm = self.twin.held(p, z[r:])
        beta = self.twin.model.beta
        if fresh:
            hs = iv.system
            nom = (hs.Mr, hs.Ca, hs.dM, hs.fg, hs.T2)
        else:
            if self._plain is None:
                self._plain = payload_twin(self.inner.rm, scale=1.0)
            m0, f0 = self._plain.held(p, z[r:])
            nom = (m0.Mr, m0.Cr - beta * m0.Kr, f0.dMr2, f0.fg, f0.T2)
        own = (mats.Mr - nom[0], (mats.Cr - beta * mats.Kr) - nom[1], fm.dMr2 - nom[2], fm.fg - nom[3],
               fm.T2 - nom[4])
        old = self._increments.get(iv.old.serial) if iv.old is not None else None
        o = own[1:] if old is None else (old.Ca, old.dM, old.fg, old.T2)
        inc = PayloadIncrement(own[0], own[1], own[2], own[3], own[4], o[1], o[0], o[2], o[3])
        # the payload's largest share of a mode's mass, max eig(dM_r, M_r), and the symmetrised velocity forms
        # of the payload's Coriolis and centripetal terms (for the scaled step's Jacobian)
        rho = float(scipy.linalg.eigh(inc.Mr, nom[0], eigvals_only=True)[-1])
        T3 = inc.T2.reshape(r, r, r)
        share = (rho, np.ascontiguousarray(T3 + np.transpose(T3, (2, 1, 0))))
        if len(self._increments) > 4:  # the held configuration and its partner are all a step needs
            keep = {iv.old.serial} if iv.old is not None else set()
            self._increments = {k: v for k, v in self._increments.items() if k in keep}
            self._shares = {k: v for k, v in self._shares.items() if k in keep}
        self._increments[iv.serial] = inc
        self._shares[iv.serial] = share
        return inc

    def _scaled_cached(self, z, u, dt, c, fresh, derivative=True):
        """The cached step at the payload scale ``1 + c`` and its forward difference to ``1 + c + DTHETA`` (module
        docstring); without ``derivative`` the step alone (the derivative returned as zeros)."""
        inner = self.inner
        iv, _ = inner.last_step
        inc = self.increment(iv, z, fresh)
        n = inner.substeps(iv, dt)
        dl = z[: inner.nq] - iv.q0
        dc = DTHETA if derivative else 0.0
        out = scaled_steps(z, u, dl, _secant_factor(iv, dl), dt / n, n, c, dc, *iv.system, *inc)
        if not np.all(np.isfinite(out)):  # as the nominal step's rescue: first order only
            out = scaled_steps(z, u, dl, 0.0, dt / n, n, c, dc, *iv.system, *inc)
        return out[0], ((out[1] - out[0]) / DTHETA if derivative else out[1])

    def _scaled_map(self, z, c, pred):
        """``(F, Q, L)`` of the interval at the payload scale ``1 + c``: the nominal step's where the payload's
        change of the modal masses, ``|c| rho`` (``rho = max eig(dM_r, M_r)``), is within the error the cached step
        holds its matrices to (``inner.refresh_tol``, relative in the mass metric); else the held linear system's
        maps with ``M_r + c dM_r`` and ``C_r + c dC_r`` (rebuilt when the step map is, or when ``c`` moved by
        more than that tolerance), and the force Jacobian with the payload's velocity forms."""
        inner = self.inner
        iv, sm = inner.last_step
        if inner.method != "cached":
            return pred.F, pred.Q, sm.L
        rho, dTs = self._shares[iv.serial]
        tol = inner.refresh_tol
        if abs(c) * rho <= tol:
            return pred.F, pred.Q, sm.L
        mp = self._map
        if mp is None or mp[0] is not sm or abs(c - mp[1]) * rho > tol:
            inc = self._increments[iv.serial]
            Mr, Kr, Cr, Gr, h, n = inner._interval_matrices
            Pn, S, L, Q = inner._maps(Mr + c * inc.Mr, Kr, Cr + c * inc.Ca, Gr, h * n, n)
            mp = self._map = (sm, c, Pn, S, L, Q)
        Ts, Vs, C3 = iv.forces.jacobian_tensors()
        F = step_jacobian(z, Ts + c * dTs, Vs, C3, mp[2], mp[3])
        return F, mp[5], mp[4]

    def _scaled_rk4(self, z, u, dt, c):
        """The reference step: RK4 of the nonlinear reduced equations of ``S(1) + c dS`` at every stage."""
        inner = self.inner
        iv, _ = inner.last_step
        n = inner.substeps(iv, dt)
        h = dt / n
        r = self.r
        out = np.empty((2, self.n0))
        for k, a in enumerate((c, c + DTHETA)):
            def f(x):
                m1 = inner.rm.matrices(x[:r], x[r:])
                m2 = self.twin.matrices(x[:r], x[r:])
                M = m1.Mr + a * (m2.Mr - m1.Mr)
                C = m1.Cr + a * (m2.Cr - m1.Cr)
                rhs = m1.Gr @ u + m1.fr + a * (m2.fr - m1.fr) - C @ x[r:] - m1.Kr @ x[:r]
                return np.concatenate([x[r:], np.linalg.solve(M, rhs)])

            x = np.array(z, float)
            for _ in range(n):
                k1 = f(x)
                k2 = f(x + h / 2 * k1)
                k3 = f(x + h / 2 * k2)
                k4 = f(x + h * k3)
                x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            out[k] = x
        return out[0], (out[1] - out[0]) / DTHETA

    # ------------------------------------------------------------------ the model's interface
    def predict(self, x: np.ndarray, u, dt: float, u_next=None) -> Prediction:
        """``x_next = [f(z, u + d; theta); theta; phi d]`` and its Jacobian (module docstring)."""
        x = np.asarray(x, float)
        n0, N = self.n0, self.nx
        inner = self.inner
        z = x[:n0]
        u = inner._input(u)
        # the hold's clock advances once per interval: the sigma points of an unscented filter step the model
        # several times over the same interval (the same inputs and length)
        key = (dt, u.tobytes())
        if key != self._last_interval:
            self._start, self._elapsed = self._elapsed, self._elapsed + dt
            self._last_interval = key
        if self.i_inputs is not None:
            d = x[self.i_inputs]
            u = u + d
        # the nominal step: the held configuration, its step map (Jacobian, process noise); a torque jump within
        # the interval is added below, to whichever step is taken
        n_refresh = inner.n_refresh
        pred = inner.predict(z, u, dt)
        L_in = inner.last_step[1].L
        xn = np.empty(N)
        xn[:n0] = pred.x
        F = np.zeros((N, N))
        F[:n0, :n0] = pred.F
        Q = np.zeros((N, N))
        Q[:n0, :n0] = pred.Q
        if self.i_theta is not None:
            it = self.i_theta
            th = float(x[it])
            c = max(th, 0.0) - 1.0
            held = self._start < self.hold_s  # the scale held: its Jacobian column stays zero
            if held and c == 0.0:  # the nominal step is the scaled one
                xs, dxs = pred.x, None
            elif inner.method == "cached":
                xs, dxs = self._scaled_cached(z, u, dt, c, inner.n_refresh != n_refresh, derivative=not held)
            else:
                xs, dxs = self._scaled_rk4(z, u, dt, c)
            if c != 0.0:
                xn[:n0] = xs
                Fz, Qz, L_in = self._scaled_map(z, c, pred)
                F[:n0, :n0] = Fz
                Q[:n0, :n0] = Qz
            if not held:
                F[:n0, it] = dxs
            xn[it] = th
            F[it, it] = 1.0
            Q[it, it] = self.payload_std**2 * dt
        if u_next is not None:
            jump = inner.input_jump(u, np.asarray(u_next, float) + (0.0 if self.i_inputs is None else d))
            if jump is not None:
                inner.n_jumps += 1
                dx, dQ = inner.input_jump_moments(jump)
                xn[:n0] += dx
                Q[:n0, :n0] += dQ
        if self.i_inputs is not None:
            s = self.i_inputs
            F[:n0, s] = L_in
            if self.input_tau is None:
                phi, q = 1.0, self.input_std**2 * dt
            else:
                phi = math.exp(-dt / self.input_tau)
                q = self.input_std**2 * (1.0 - phi * phi)
            xn[s] = phi * d
            F[s, s] = phi * np.eye(self.nu)
            Q[s, s] = np.diag(q)
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

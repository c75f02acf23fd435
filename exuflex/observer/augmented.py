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
stiffness, input matrix and geometric terms unchanged: the payload's share of the links' axial loads (its weight
and inertia in the geometric stiffness, static and of the motion) is left out (on the serial arm at a turning
state some 0.2-4 % of the payload's effect on the accelerations; ``tests/test_estimators.py`` bounds it). Its
derivative in the state and the process noise are the nominal step map's where the payload's change of the modal
masses, ``|theta - 1| rho`` with ``rho = max eig(dM_r, M_r)``, is within the tolerance the cached step holds its
matrices to (``refresh_tol``); beyond it, the maps of the scaled held linear system (the step's own matrices at
the interval's start: ``M_r + (theta - 1) dM_r`` and the damping's increment), rebuilt with the nominal step map
or when ``theta`` moved by that tolerance, and the force Jacobian with the payload's velocity forms (one compiled
call per interval, :func:`payload_interval`). ``theta`` below 0 is taken as 0 in the step (a negative mass has no
meaning and can make ``M_r`` indefinite).

The step's derivative in ``theta`` is the forward difference of the same compiled step at ``theta + DTHETA``
(``DTHETA = 1e-4``: the step is smooth in ``theta``, the truncation error ``DTHETA / 2 d^2x/dtheta^2`` is far
below the filter's uncertainty).

When the scale starts being learned. The EKF's joint update is consistent while the step's response to the scale
is close to linear over the scale's uncertainty. With ``x(a)`` the step at the scale ``1 + a``, ``c = theta - 1``
and ``s`` the scale's standard deviation (the filter's, :meth:`AugmentedModel.watch_covariance`; at most the
distance to a zero payload),

``e2 = (x(c + s) + x(c - s)) / 2 - x(c)``   (``= s^2 / 2 d^2x/dtheta^2`` to leading order)

is the second-order term the first-order model leaves out. A start that accelerates the links hard while the
scale is at its prior makes it a hundred to a thousand times the interval's process noise (the six-bar's torque
pulse), and an EKF learning there attributes the step's curvature to the scale with a confidence it does not
have: with the payload doubled its estimate stays near the prior at several standard deviations from the truth,
and keeps part of that bias to the end. So the scale is held (its column of the step Jacobian zero: no
measurement moves it, no correlation with the states is built; the step uses its current value) from the start
until the first interval with ``max_i |e2_i| / sqrt(Q_ii) <= linearity_tol`` (default 1: the left-out term within
one process-noise standard deviation in every state component); from then on it is learned in every interval
(that interval's column is ``(x(c + s) - x(c - s)) / 2 s``). The test is not applied to every interval: where a
payload dominates a link's inertia the second-order term grows with the first-order one, so the intervals that
fail it are the informative ones, and a per-interval hold keeps the scale from being learned at all (the single
link). A model outside a filter (no covariance watched) is never held.

While held, the scale's uncertainty still enters the states' prediction: the first-order spread of the step over
``+-s``, ``e1 = (x(c + s) - x(c - s)) / 2``, adds ``e1 e1^T`` to the interval's process noise. This is the
covariance a parameter of variance ``s^2`` that is considered but not estimated adds to the prediction (the
Schmidt-Kalman filter's consider parameter, its effect taken as independent between intervals). Without it a
wrong scale held through a hard start drives the states far outside their covariance, and the scale's first
updates after the hold overshoot (the single link and the four-bar with their payloads doubled).

With ``method="rk4"`` (the exact reference) the step is RK4 of the nonlinear reduced equations at every stage
with the matrices and forces of the two models combined the same way.

Inputs. ``d`` enters the step as the measured torques do: ``d x_next / d d = L`` (the step map's response to a
unit torque held over the interval). Random walk: ``d_next = d``, variance ``input_std^2 dt`` per interval;
Gauss-Markov: ``d_next = exp(-dt / tau) d``, variance ``input_std^2 (1 - exp(-2 dt / tau))`` (``input_std`` is
then the stationary standard deviation).

The measurements do not depend on ``theta`` or ``d``: their Jacobian columns are zero.

The nominal payload as a hypothesis. A filter that learns the scale pays for it while the scale is uncertain:
at the nominal payload its states are less accurate than the plain EKF's, which knows the scale, until the data
have pinned the scale down (on the six-bar most of the first second). The payload is most often the model file's,
so the estimator reports a Bayesian model average of two hypotheses (:func:`nominal_mixture`): ``H0``, the
payload is nominal (``theta = 1``), with prior probability ``p`` (``ObserverConfig.payload_nominal_p``), and
``H1``, it is unknown (the filter's prior and walk). Under ``H0`` the posterior is the filter's conditioned on
``theta = 1``: ``x0 = x + P_x,theta (1 - theta) / s^2``, ``P0 = P - P_x,theta P_theta,x / s^2`` (``s^2`` the
scale's variance); for a linear-Gaussian model that is exactly the posterior of a filter that knows the scale.
The Bayes factor of ``H0`` against ``H1`` needs no second filter: with ``H0`` nested in ``H1`` at ``theta = 1``,
it is the scale's posterior density at 1 over its prior density there (the Savage-Dickey ratio),
``B = sqrt(s0^2 / s^2) exp(-(theta - 1)^2 / (2 s^2))`` with ``s0^2`` the prior variance (plus the walk's since
the start). ``H0``'s posterior probability is ``w = p B / (p B + 1 - p)``, and the report is the two Gaussians'
mixture: mean ``x + w (x0 - x)``, covariance ``w P0 + (1 - w) P + w (1 - w) (x0 - x)(x0 - x)^T``. At the nominal
payload ``B`` grows as the scale's deviation narrows around 1 (the evidence for the simpler hypothesis), and the
report approaches the plain EKF's; with the payload changed ``(theta - 1)^2 / s^2`` grows and ``w`` goes to 0
within a fraction of a second, leaving the filter's own estimate. The filter itself runs unchanged (its posterior
is what the next sample needs); the report is computed from its record (``EstimationResult.P_theta``, the
covariance's scale column) by :func:`.session.reported`.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import scipy.linalg

from ..erls.model import ErlsModel
from ..erls.simulate import rk4_step
from ..reduction import ReducedModel
from .base import LoopModel, Measurement, Prediction
from .expansion import (
    NO_DISTURBANCES,
    NO_PAYLOAD,
    NO_SCALED_MAP,
    LoopExtras,
    extra_interval,
    payload_interval,
    scaled_steps,
)
from .reduced import rk4_input_steps

__all__ = ["AugmentedModel", "PayloadIncrement", "nominal_mixture", "payload_interval", "payload_rows",
           "payload_twin", "scaled_steps", "warm_up"]

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
    configuration and at its secant partner (``old_*``): the mass matrix, its q-gradient, the mass-proportional
    damping, and the forces' forms (weight ``fg``, velocity forms ``T2``, bias force ``C2``, the payload's share of
    ``J^T M a_b``; ``(0, r)`` where the model has none)."""

    Mr: np.ndarray
    Ca: np.ndarray
    dM: np.ndarray
    fg: np.ndarray
    T2: np.ndarray
    C2: np.ndarray
    old_dM: np.ndarray
    old_Ca: np.ndarray
    old_fg: np.ndarray
    old_T2: np.ndarray
    old_C2: np.ndarray


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
    linearity_tol : float
        The scale is held from the start (or :meth:`reset`) until the first interval whose second-order term in
        the scale over its standard deviation is within this many process-noise standard deviations in every
        state component (module docstring); 1 by default: the term the first-order model leaves out is no
        larger than the noise the filter adds per interval. While held, the scale's uncertainty enters the
        interval's process noise (a consider parameter).

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
    released : bool
        The scale is learned (the linearity test has passed since the last :meth:`reset`).
    n_held : int
        Intervals the scale was held since the last :meth:`reset`.
    last_linearity : float
        The last held interval's second-order term over the process noise (the test's left-hand side).
    """

    def __init__(self, inner, payload_std: float | None = None, input_std: float | None = None,
                 input_tau: float | None = None, linearity_tol: float = 1.0):
        if payload_std is None and input_std is None:
            raise ValueError("an augmented model needs payload_std or input_std (or both)")
        for name, v in (("payload_std", payload_std), ("input_std", input_std), ("input_tau", input_tau)):
            if v is not None and not np.all((np.asarray(v, float) > 0) & np.isfinite(v)):
                raise ValueError(f"{name} must be positive, got {v}")
        if not linearity_tol > 0:
            raise ValueError(f"linearity_tol must be positive, got {linearity_tol}")
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
        self.linearity_tol = float(linearity_tol)
        self._cov = None  # the filter's covariance, a callable (:meth:`watch_covariance`)
        self._plain = None  # the nominal model's own evaluation, where an increment is asked for later
        self._forget()
        self.state_labels = tuple(f"z{i}" for i in range(self.n0)) + (
            ("payload_scale",) if self.i_theta is not None else ()) + (
            tuple(f"d_{m}" for m in inner.mech.motor_names) if self.i_inputs is not None else ())

    def _forget(self) -> None:
        """The per-run state: the scale's hold, the cached increments and shares, the last map."""
        self.released = False
        self.n_held = 0
        self.last_linearity = math.nan
        self._increments: dict = {}
        self._shares: dict = {}
        self._map = None

    def reset(self) -> None:
        self.inner.reset()
        self._forget()
        for m in (self.twin, self._plain):
            if m is not None:
                m.model.kin.reset_warm_start()

    def watch_covariance(self, get_P) -> None:
        """Give the model the filter's covariance (``get_P()`` returns it, the augmented state's): the payload
        scale's standard deviation sets the divided differences of the step in the scale, and the inner model
        measures its held approximations against it (:meth:`.reduced.ReducedObserverModel.watch_covariance`)."""
        self._cov = get_P
        self.inner.watch_covariance(get_P)

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
        ``z`` in this interval (its q ahead along the motion), so the nominal arrays are ``iv``'s own where ``z``
        is undeformed as ``iv`` is held; else the nominal model is evaluated too (the increment is taken at
        ``z``'s elastic coordinates: the payload's share of the matrices' change with them is held). The bias form
        ``C2`` carries the bias acceleration's curvature term at those coordinates (zero where they are), as the
        reduced model's forces ``fr`` do (:meth:`.ReducedModel.basis_curvature`). The secant partner's increment
        comes from the cache (its own if that is gone: the payload's share is then held, not followed)."""
        hit = self._increments.get(iv.serial)
        if hit is not None:
            return hit
        r, nq = self.r, self.inner.nq
        p = z[:r].copy()
        p[:nq] = iv.q0
        mats, fm = self.twin.held(p, z[r:])
        beta = self.twin.model.beta
        c2 = self.inner._c2  # the bias form, (0, r) where the model has none
        if fresh and not np.any(p[nq:]):  # (the nominal held configuration is undeformed)
            hs = iv.system
            nom = (hs.Mr, hs.Ca, hs.dM, hs.fg, hs.T2, hs.C2)
        else:
            if self._plain is None:
                self._plain = payload_twin(self.inner.rm, scale=1.0)
            m0, f0 = self._plain.held(p, z[r:])
            nom = (m0.Mr, m0.Cr - beta * m0.Kr, f0.dMr2, f0.fg, f0.T2, c2(f0))
        C2 = c2(fm)
        if C2.shape[0] and np.any(p[nq:]):
            # the bias acceleration's curvature term d2(H p)/dq2 [q', q'] at z's elastic coordinates: its force
            # -(W J)^T M_N W d2(H p)/dq_k dq_j q'_k q'_j is linear in M_N on the shared basis, so the payload's
            # share is the twin's form less the nominal one's, on the basis's second derivatives at the held
            # configuration (the nominal model's, which its velocity forms computed there)
            Zp = np.tensordot(p[nq:], self.inner.rm.basis_hessian(p[:nq]), axes=(0, 0))
            C2 = self.twin._curved_bias_form(mats, C2, p, Zp)
            nom = (*nom[:5], self._plain._curved_bias_form(m0, nom[5], p, Zp))
        own = (mats.Mr - nom[0], (mats.Cr - beta * mats.Kr) - nom[1], fm.dMr2 - nom[2], fm.fg - nom[3],
               fm.T2 - nom[4], C2 - nom[5])
        old = self._increments.get(iv.old.serial) if iv.old is not None else None
        o = own[1:] if old is None else (old.Ca, old.dM, old.fg, old.T2, old.C2)
        inc = PayloadIncrement(own[0], own[1], own[2], own[3], own[4], own[5], o[1], o[0], o[2], o[3], o[4])
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

    def _scaled_rk4(self, z, u, dt, a, du=None):
        """The reference step at the payload scales ``1 + a_k``: RK4 of the nonlinear reduced equations of
        ``S(1) + a_k dS`` at every stage (the torques ``u + (t / dt) du``, :func:`.reduced.rk4_input_steps`), with
        the nominal model's geometric stiffness of the motion
        (:meth:`.ReducedModel.accelerations`; the payload's share of the axial loads is left out, as the cached
        step leaves it out)."""
        inner = self.inner
        iv, _ = inner.last_step
        n = inner.substeps(iv, dt)
        r = self.r
        out = np.empty((len(a), self.n0))
        for k, c in enumerate(a):
            def f(_t, x, u, c=c):
                m1 = inner.rm.matrices(x[:r], x[r:])
                m2 = self.twin.matrices(x[:r], x[r:])
                M = m1.Mr + c * (m2.Mr - m1.Mr)
                C = m1.Cr + c * (m2.Cr - m1.Cr)
                K = m1.Kr + inner.rm.motion_stiffness(m1.rc, m1.J, x[r : r + inner.nq], u)
                rhs = m1.Gr @ u + m1.fr + c * (m2.fr - m1.fr) - C @ x[r:] - K @ x[:r]
                return np.concatenate([x[r:], np.linalg.solve(M, rhs)])

            if du is None or not np.any(du):
                x = np.array(z, float)
                for _ in range(n):
                    x = rk4_step(f, 0.0, x, dt / n, u)
            else:
                x = rk4_input_steps(f, z, u, du, dt, n)
            out[k] = x
        return out

    def _reference(self, x: np.ndarray, u: np.ndarray, dt: float, du: np.ndarray) -> tuple:
        """The reference step (``method="rk4"``) of the augmented state: the inner model's, its state at the scale
        ``c`` (:meth:`_scaled_rk4`) and the scale's column its forward difference over :data:`DTHETA` (the scale
        learned at every interval: the linearity hold is the cached step's, :func:`.expansion.extra_interval`);
        ``(x, F, Q)``, the disturbances entering through the nominal map's torque response."""
        inner, n0, N = self.inner, self.n0, self.nx
        xn, F, Q = np.zeros(N), np.zeros((N, N)), np.zeros((N, N))
        xn[:n0], F[:n0, :n0], Q[:n0, :n0] = inner.interval(x[:n0], u, dt, du)
        if self.i_theta is not None:
            it = self.i_theta
            c = max(float(x[it]), 0.0) - 1.0
            rows = self._scaled_rk4(x[:n0], u, dt, [c + DTHETA] + ([c] if c != 0.0 else []), du)
            xn[:n0] = rows[-1] if c != 0.0 else xn[:n0]
            F[:n0, it] = (rows[0] - xn[:n0]) / DTHETA
            xn[it], F[it, it], Q[it, it] = x[it], 1.0, self.payload_std**2 * dt
        if self.i_inputs is not None:  # the disturbances' decay and noise (as extra_interval's)
            s, tau = self.i_inputs, self.input_tau
            phi = 1.0 if tau is None else math.exp(-dt / tau)
            xn[s], F[s, s] = phi * x[s], phi * np.eye(self.nu)
            Q[s, s] = np.diag(self.input_std**2 * (dt if tau is None else 1.0 - phi * phi))
            F[:n0, s] = inner.last_step[1].L
        return xn, F, Q

    # ------------------------------------------------------------------ the model's interface
    def predict(self, x: np.ndarray, u, dt: float, u_next=None) -> Prediction:
        """``x_next = [f(z, u + d; theta); theta; phi d]`` and its Jacobian (module docstring): the cached step's
        interval in the compiled loop's own kernel (:func:`.expansion.extra_interval`: the held scale's linearity
        test, the scaled maps, the disturbances), or the reference step (:meth:`_reference`); ``u_next`` (the
        sample that ends the interval): a torque jump within it adds its effect."""
        x = np.asarray(x, float)
        inner, n0 = self.inner, self.n0
        d = 0.0 if self.i_inputs is None else x[self.i_inputs]
        u0 = inner.torques(u)
        du = inner.input_increment(u0, u_next)  # (of the measured torques: the disturbances do not change over it)
        u = u0 + d
        if du.size and inner.input_delay:  # the compiled step's order of operations (expansion.cached_interval)
            u = (u0 - (inner.input_delay / dt) * du) + d
        if inner.method != "cached":
            xn, F, Q = self._reference(x, u, dt, du)
        else:
            z = x[:n0]
            n_refresh = inner.n_refresh
            iv, dl, s, n, sm = inner.prepare(z, u, dt)
            extras, scaled = self._extras(iv, sm, z, inner.n_refresh != n_refresh)
            for rescue in (False, True):
                var = self._cov()[n0, n0] if extras.pay_held else 0.0
                xn, F, Q, Mo, Ko, Co, Go, scaled_out, release = extra_interval(
                    x, u, du, dl, s, dt, n, extras, var, scaled, (sm.Pn, sm.S, sm.L, sm.Q, inner.torque_var,
                                                              inner.q_extra_diag), sm.tail[:3], sm.tail[5])
                if rescue or math.isfinite(xn[0]) or not (s or np.any(dl)):
                    break
                iv, dl, s, n, sm = inner.rescue(z, u, dt)  # (the held model broke down: evaluated anew)
                extras, scaled = self._extras(iv, sm, z, True)
            if scaled_out[0]:
                self._map = (sm, *scaled_out[1:])
            if extras.pay_held:
                self.last_linearity = float(extras.pay_stats[1])
                self.released = bool(release)
                self.n_held += not release
            inner.interval_system = (Mo, Ko, Co, Go, dt / n, n)
        if u_next is not None and inner.input_hold == "zoh":
            jump = inner.input_jump(u, np.asarray(u_next, float) + d)
            if jump is not None:
                dx, dQ = inner.input_jump_moments(jump)
                xn[:n0] += dx
                Q[:n0, :n0] += dQ
        return Prediction(xn, F, Q)

    # ------------------------------------------------------------------ the filter's compiled sample loop
    @property
    def compiled(self) -> bool:
        """The filter's compiled sample loop (:func:`.loop.samples`) may take the intervals :meth:`predict` takes
        with the cached step (the interval whose linearity test releases a held scale it hands back); not the
        reference step."""
        return self.inner.method == "cached"

    def loop_model(self, x: np.ndarray, u: np.ndarray, dt: float, channels: tuple) -> LoopModel:
        """The inner model's cached step (:meth:`.reduced.ReducedObserverModel.loop_model`, at the torques with the
        disturbances) with the extra states' arrays (:class:`.expansion.LoopExtras`): the payload's (the increment
        of the held configuration, its payload share and velocity forms, the scaled step map where it is the
        current nominal map's: :meth:`_extras`) and the disturbances' noise."""
        inner, n0 = self.inner, self.n0
        z = x[:n0]
        if self.i_inputs is not None:
            u = inner.torques(u) + x[self.i_inputs]
        n_refresh = inner.n_refresh
        step, state, _ = inner.loop_model(z, u, dt, channels)
        iv, sm = inner.loop_step
        extras, scaled = self._extras(iv, sm, z, inner.n_refresh != n_refresh)
        return LoopModel(step, state._replace(scaled=scaled), extras)

    def _extras(self, iv, sm, z: np.ndarray, fresh: bool) -> tuple:
        """The extra states' arrays for intervals of the held configuration ``iv`` with the step map ``sm``
        (:class:`.expansion.LoopExtras`: the payload's, with the increment of ``iv``, :meth:`increment`, ``fresh``
        where ``iv`` was evaluated at ``z`` for this interval, its payload share and velocity forms and whether the
        scale is held; the disturbances' noise) and the scaled step map where it is ``sm``'s
        (:func:`.expansion.payload_interval`)."""
        extra, scaled = NO_PAYLOAD, (False, *NO_SCALED_MAP)
        if self.i_theta is not None:
            inc = self.increment(iv, z, fresh)
            rho, dTs = self._shares[iv.serial]
            held = not self.released and self._cov is not None
            self._stats = np.zeros(2)  # (the held intervals the loop does, the last one's linearity measure)
            extra = (True, held, self.payload_std**2, DTHETA, rho, self.inner.refresh_tol, dTs, self.linearity_tol,
                     self._stats, *inc)
            if self._map is not None and self._map[0] is sm:
                scaled = (True, *self._map[1:])
        inp = (NO_DISTURBANCES if self.i_inputs is None
               else (np.ascontiguousarray(self.input_std**2), float(self.input_tau or 0.0)))
        return LoopExtras(*extra, *inp), scaled

    def loop_done(self, mats: tuple, dt: float, state, x: np.ndarray, k: int) -> None:
        """After the compiled loop's samples up to ``k``: the inner model's (:meth:`.reduced.ReducedObserverModel.
        loop_done`) and the scaled step map the loop leaves (for the current nominal map, or none)."""
        inner = self.inner
        inner.loop_done(mats, dt, state, x[: self.n0], k)
        if self.i_theta is not None and self._stats[0]:  # the held scale's intervals the loop did
            self.n_held += int(self._stats[0])
            self.last_linearity = float(self._stats[1])
            self._stats[0] = 0.0
        ok, c, Pn, S, L, Q = state.scaled
        self._map = (inner.last_step[1], c, Pn, S, L, Q) if ok else None

    def measure(self, x: np.ndarray, channels: Sequence[str]) -> Measurement:
        """The inner model's channels; zero Jacobian columns for the extra states."""
        x = np.asarray(x, float)
        y, H0 = self.inner.measure(x[: self.n0], channels)
        H = np.zeros((len(y), self.nx))
        H[:, : self.n0] = H0
        return Measurement(y, H)

    # ------------------------------------------------------------------ delegated
    def __getattr__(self, name):
        # physical maps (tip_maps, initial_state, rm, nq, ...) are the inner model's
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)


def warm_up() -> None:
    """Compile (or load from numba's on-disk cache) the augmented step's kernels, for the argument types the model
    and the compiled sample loop pass: :func:`scaled_steps`, :func:`payload_interval` (which calls it, with the
    step map's and the step Jacobian's kernels) and :func:`.expansion.extra_interval` (the loop's interval of an
    augmented state), and the filter's sample loop's specialisation for augmented states (:func:`.loop.warm_up`)."""
    from .expansion import _example_system
    from .loop import warm_up as warm_up_loop

    r, nq = 2, 1
    z, u, dl, a = np.zeros(2 * r), np.zeros(nq), np.zeros(nq), np.zeros(1)
    M, T3, V3, C3 = np.eye(r), np.zeros((r, r, r)), np.zeros((nq, r, r)), np.zeros((r, nq, r))
    maps = (np.eye(2 * r), np.zeros((2 * r, r)), np.zeros((2 * r, nq)), np.eye(2 * r))
    for has_old in (False, True):
        hs = _example_system(r, nq, has_old)
        inc = PayloadIncrement(M, M, hs.dM, hs.fg, hs.T2, hs.C2, hs.old_dM, M, hs.old_fg, hs.old_T2, hs.old_C2)
        hs, inc = tuple(hs), tuple(inc)
        nominal = (*maps, np.ones(nq), np.zeros(0))
        scaled_steps(z, u, u, dl, 0.0, 1e-4, 1, a, hs, inc)
        for ok in (False, True):
            payload_interval(z, (u, u), dl, 0.0, 1e-4, 1, a, 1.0, 2 * r + 1, (1e-4, 1.0, 1.0, 0.0), (ok, 0.0, *maps),
                             nominal, (T3, T3, V3, C3), hs, inc)
        extras = LoopExtras(True, has_old, 1.0, 1e-4, 1.0, 0.03, T3, 1.0, np.zeros(2), *inc, np.ones(nq), 0.0)
        extra_interval(np.zeros(2 * r + 1 + nq), u, u, dl, 0.0, 1e-3, 1, extras, 1.0, (False, 0.0, *maps), nominal,
                       (T3, V3, C3), hs)
    warm_up_loop("augmented")


# ---------------------------------------------------------------------------------------------------- the report
def nominal_mixture(x: np.ndarray, P: np.ndarray | None, P_theta: np.ndarray, i_theta: int, prior_var,
                    p_nominal: float, prior_mean: float = 1.0) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """The payload estimator's report: the filter's posterior mixed with its conditional on the nominal payload,
    weighted by the nominal payload's posterior probability (module docstring, "The nominal payload as a
    hypothesis").

    Parameters
    ----------
    x : ndarray (n, nx) or (nx,)
        The filter's posterior means (the payload scale at ``i_theta``).
    P : ndarray (n, nx) (variances), (n, nx, nx) (covariances) or None; one sample's without the leading axis.
    P_theta : ndarray (n, nx) or (nx,)
        The covariance of every state with the payload scale (the covariance's ``i_theta`` column).
    prior_var : float or ndarray (n,)
        The scale's prior variance at each sample: the filter's prior plus its random walk since.
    p_nominal : float
        The prior probability of the nominal payload, in [0, 1].
    prior_mean : float
        The scale's prior mean (1 unless the filter was started elsewhere).

    Returns
    -------
    (x_report, P_report, w)
        The mixture's mean and covariance (the kind of ``P``; None with ``P`` None) and ``w`` (n,), the nominal
        payload's posterior probability. Samples without a positive finite scale variance are left as they are
        (``w`` 0)."""
    one = x.ndim == 1
    x, Pt = np.atleast_2d(x), np.atleast_2d(P_theta)
    if P is not None and one:
        P = P[None]
    s2 = Pt[:, i_theta]
    ok = np.isfinite(s2) & (s2 > 0.0)
    s2 = np.where(ok, s2, 1.0)
    dev = x[:, i_theta] - 1.0
    if p_nominal <= 0.0:
        w = np.zeros(len(x))
    else:
        # Savage-Dickey: p(data | nominal) / p(data | scale free) is the scale's posterior density at 1 over its
        # prior density there
        prior_var = np.asarray(prior_var, float)
        log_bf = 0.5 * np.log(prior_var / s2) - 0.5 * dev**2 / s2 + 0.5 * (1.0 - prior_mean) ** 2 / prior_var
        with np.errstate(over="ignore", divide="ignore"):
            w = 1.0 if p_nominal >= 1.0 else 1.0 / (1.0 + (1.0 - p_nominal) / p_nominal * np.exp(-log_bf))
        w = np.where(ok, w, 0.0)
    # the conditional on theta = 1: the mean moved along the scale's regression, the scale's share of P removed
    g = np.where(ok[:, None], Pt / s2[:, None], 0.0)
    d = -g * dev[:, None]
    xr = x + w[:, None] * d
    Pr = None
    if P is not None:
        ww = w * (1.0 - w)
        if P.ndim == 2:
            Pr = P - w[:, None] * g * Pt + ww[:, None] * d * d
        else:
            Pr = (P - w[:, None, None] * g[:, :, None] * Pt[:, None, :]
                  + ww[:, None, None] * d[:, :, None] * d[:, None, :])
    if one:
        return xr[0], None if Pr is None else Pr[0], w
    return xr, Pr, w

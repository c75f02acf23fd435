"""Implicit generalized-alpha integration of second-order models ``M(x) x'' = Q(t, x, x')`` (stiff-stable truth).

The explicit RK4 of :mod:`exuflex.erls.simulate` is stable only for ``h |lambda| <= 2.8``: a fine mesh's axial
modes (tens of kHz) and the overdamped modes that stiffness damping makes of them dictate its step. The
generalized-alpha method (Chung & Hulbert 1993, in the form of Arnold & Bruels 2007, the one Exudyn uses) is
unconditionally stable on linear problems, second-order accurate, and its numerical damping grows as
``(omega h)^3`` (negligible in the band, an amplification ``rho_inf`` per step at infinite frequency): the step
is then chosen for accuracy in the band of interest.

Method (``rho_inf``: spectral radius at infinite frequency, 1 = trapezoidal rule, no numerical damping)::

    alpha_m = (2 rho - 1) / (rho + 1),  alpha_f = rho / (rho + 1),
    gamma = 1/2 + alpha_f - alpha_m,    beta = (gamma + 1/2)^2 / 4
    M(x1) x1'' = Q(t1, x1, v1)                                  (balance at the step's end t1)
    (1 - alpha_m) a1 + alpha_m a0 = (1 - alpha_f) x1'' + alpha_f x0''
    v1 = v0 + h (1 - gamma) a0 + h gamma a1
    x1 = x0 + h v0 + h^2 (1/2 - beta) a0 + h^2 beta a1

Newton on the residual ``r = M(x1) x1'' - Q``, in the position increment ``dx`` (``dv = gamma' dx``,
``dx'' = beta' dx`` with ``beta' = (1 - alpha_m) / (h^2 beta (1 - alpha_f))``, ``gamma' = gamma / (h beta)``):
``S dx = -r`` with the iteration matrix ``S = beta' M + gamma' C_t + K_t`` (``C_t = -dQ/dv``,
``K_t = d(M x'' - Q)/dx``). ``S`` is inverted once and reused over steps (simplified Newton) until the
contraction rate of the iteration exceeds :data:`REFRESH_RATE`; the iteration stops when the estimated distance
to the solution, ``eta / (1 - eta) |dx|`` (Hairer & Wanner, IV.8, with ``eta`` the contraction rate last
measured), is below the tolerance. One iteration per step suffices while the rate is small; every
:data:`PROBE_EVERY` steps a second one re-measures it as the matrix ages. The residual is always exact, so a stale
``S`` costs iterations, not accuracy.

The step: :func:`band_step` picks the largest step whose frequency error at the top of the band of interest is
within :data:`FREQ_TOL`; the error falls as ``(omega h)^2 / 12`` below it. That bounds the error per cycle, not
its accumulation over the cycles a lightly damped mode rings for: :func:`phase_step` bounds the accumulated error
(derivation in ``docs/theory/truth_step.md``). On ``x'' + omega^2 x = 0`` with ``Omega = omega h`` and
``g = gamma - 1/2 = (1 - rho_inf) / (1 + rho_inf)`` (:func:`period_error`, the leading terms of the principal
root ``lambda = exp(h s)`` of the amplification matrix)::

    relative frequency error  e = -(1/12 + 3 g^2 / 8) Omega^2        (trapezoidal rule, g = 0: -Omega^2 / 12)
    numerical damping ratio   z = g^3 Omega^3 / 2

A mode of frequency ``omega`` and damping ratio ``zeta`` responds to the forcing of the last ``1 / (zeta omega)``
seconds (its impulse response's decay time), so over a run of ``T`` seconds its phase error accumulates over
``L = min(1 / zeta, omega T)`` radians of its motion; its response is then in error by ``|e + i z| L`` of its
amplitude (for a steady response near resonance exactly ``|e| / zeta``: the resonance moves by ``e omega``, and the
response's sensitivity to the frequency is ``1 / zeta``; for a free decay the peak of ``omega t exp(-zeta omega t)``
is ``1 / (zeta e_Euler)``, smaller). :func:`phase_step` picks the largest step that divides the output interval and
keeps ``|e + i z| L`` within :data:`PHASE_TOL` for every mode below the band (:func:`band_modes`).

:func:`algorithmic_damping` gives the method's damping ratio and frequency error on an undamped mode of
frequency ``omega`` for a step ``h`` (from the eigenvalues of its amplification matrix); :func:`erls_implicit`
integrates the ERLS model under a zero-order-hold torque table.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .model import ErlsModel
from .simulate import Trajectory

__all__ = [
    "FREQ_TOL",
    "PHASE_TOL",
    "REFRESH_RATE",
    "GeneralizedAlpha",
    "HeldTable",
    "accumulated_error",
    "algorithmic_damping",
    "band_modes",
    "band_step",
    "erls_implicit",
    "generalized_alpha",
    "period_error",
    "phase_step",
]

log = logging.getLogger(__name__)

FREQ_TOL = 0.005  # band_step: the largest relative frequency error at the band's upper edge
# phase_step: the largest accumulated relative error of a mode's response. The truth's error in a quantity is this
# times the mode's amplitude there; its ringing amplitude reaches about 50 times the observer's bound (measured,
# docs/truth_step.md), and the truth's error must stay within 0.2 of the bound: 0.2 / 50 = 0.004.
PHASE_TOL = 0.004
REFRESH_RATE = 0.02  # refactor the iteration matrix when Newton contracts slower than this per iteration
PROBE_EVERY = 8  # steps accepted after one iteration before one is iterated twice to re-measure the rate
MAX_ITERATIONS = 8


@dataclass(frozen=True)
class GeneralizedAlpha:
    """Coefficients of the generalized-alpha method for a spectral radius ``rho_inf`` in [0, 1]."""

    rho_inf: float = 0.9

    def __post_init__(self):
        if not 0.0 <= self.rho_inf <= 1.0:
            raise ValueError(f"rho_inf must be in [0, 1], got {self.rho_inf}")

    @property
    def alpha_m(self) -> float:
        return (2 * self.rho_inf - 1) / (self.rho_inf + 1)

    @property
    def alpha_f(self) -> float:
        return self.rho_inf / (self.rho_inf + 1)

    @property
    def gamma(self) -> float:
        return 0.5 + self.alpha_f - self.alpha_m

    @property
    def beta(self) -> float:
        return 0.25 * (self.gamma + 0.5) ** 2

    def primes(self, h: float) -> tuple[float, float]:
        """``(beta', gamma')``: d x''/dx and d v/dx of one step's update (see module docstring)."""
        beta_p = (1 - self.alpha_m) / (h * h * self.beta * (1 - self.alpha_f))
        return beta_p, self.gamma / (h * self.beta)


def algorithmic_damping(omega_h, rho_inf: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """Numerical damping ratio and relative frequency error of generalized-alpha on ``x'' + omega^2 x = 0``.

    One step maps ``(x, v, a)`` linearly (with ``x'' = -omega^2 x`` at every step end); its principal
    eigenvalues ``lambda = exp(h s)`` define the discrete mode ``s = -zeta w +- i w sqrt(1 - zeta^2)``:
    ``w h = |ln lambda|`` and ``zeta = -Re(ln lambda) / |ln lambda|``.

    Returns
    -------
    zeta : numerical damping ratio (0 for ``rho_inf = 1``).
    freq_error : ``w / omega - 1`` (negative: the discrete mode is slower; trapezoidal rule
        ``2 atan(omega h / 2) / (omega h) - 1``).
    """
    ga = GeneralizedAlpha(rho_inf)
    am, af, g, b = ga.alpha_m, ga.alpha_f, ga.gamma, ga.beta
    wh = np.atleast_1d(np.asarray(omega_h, float))
    zeta, err = np.empty_like(wh), np.empty_like(wh)
    for i, z in enumerate(wh):
        # unit omega, step z: x1'' = -x1; x1 = x + z v + z^2 ((1/2 - b) a + b a1), a1 = c0 x'' + c1 a + c x1''
        c = (1 - af) / (1 - am)
        A = np.zeros((3, 3))
        for j in range(3):
            x, v, a = np.eye(3)[j]
            c_x, c_a = -af / (1 - am), -am / (1 - am)  # a1 = c_x x + c_a a + c x1'' with x'' = -x
            # x1 = x + z v + z^2 (1/2 - b) a + z^2 b (c_x x + c_a a - c x1)  ->  solve for x1
            x1 = (x + z * v + z * z * ((0.5 - b) * a + b * (c_x * x + c_a * a))) / (1 + z * z * b * c)
            a1 = c_x * x + c_a * a - c * x1
            v1 = v + z * ((1 - g) * a + g * a1)
            A[:, j] = (x1, v1, a1)
        lam = np.linalg.eigvals(A).astype(complex)
        osc = lam[lam.imag > 1e-14]  # the principal (oscillating) pair; the third root is real (spurious)
        lam = osc[0] if len(osc) else lam[np.argmax(np.abs(lam))]
        s = np.log(lam)
        zeta[i] = -s.real / abs(s)
        err[i] = abs(s) / z - 1
    return zeta, err


def band_step(band_hz: float, h: float, output_dt: float, rho_inf: float = 0.9, freq_tol: float = FREQ_TOL) -> float:
    """The largest step ``k h`` that divides ``output_dt`` and keeps generalized-alpha's frequency error at
    ``band_hz`` (the top of the band of interest) within ``freq_tol`` (:func:`algorithmic_damping`); at least ``h``.

    The error falls as ``(omega h)^2 / 12`` below the edge (a quarter of it at half the frequency), and the
    numerical damping there is far smaller (``zeta ~ (omega h)^3``).
    """
    n_out = round(output_dt / h)
    best = 1
    for k in range(1, n_out + 1):
        if n_out % k == 0 and abs(algorithmic_damping(2 * math.pi * band_hz * k * h, rho_inf)[1][0]) <= freq_tol:
            best = k
    return best * h


def period_error(omega_h, rho_inf: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """The leading terms of generalized-alpha's relative frequency error and numerical damping ratio on
    ``x'' + omega^2 x = 0`` at ``Omega = omega h`` (closed form; :func:`algorithmic_damping` is exact)::

        e = -(1/12 + 3 g^2 / 8) Omega^2,   zeta = g^3 Omega^3 / 2,   g = gamma - 1/2 = (1 - rho_inf) / (1 + rho_inf)

    From the series in ``Omega`` of the principal root of the amplification matrix's characteristic polynomial
    (``lambda = exp(i Omega (1 + e) - zeta Omega)``), with ``beta = (gamma + 1/2)^2 / 4`` (second order, the
    engine's choice); ``rho_inf = 1`` gives the trapezoidal rule's ``-Omega^2 / 12`` and no damping. The next terms
    are of relative order ``Omega^2``.

    Returns
    -------
    freq_error : ``w / omega - 1`` (negative: the discrete mode is slower).
    zeta : numerical damping ratio.
    """
    W = np.asarray(omega_h, float)
    g = (1.0 - rho_inf) / (1.0 + rho_inf)
    return -(1.0 / 12.0 + 0.375 * g * g) * W**2, 0.5 * g**3 * W**3


def band_modes(model: ErlsModel, qs, band_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The model's oscillating modes below ``band_hz`` at the configurations ``qs`` (joint coordinates, one per
    row): their angular frequencies ``omega = |s|`` and damping ratios ``zeta = -Re(s) / |s|`` from the eigenvalues
    ``s`` of the state matrix linearised at rest (:meth:`ErlsModel.state_matrix`; the model's own damping, whatever
    its form). Rigid modes (``|s|`` zero) and overdamped ones (real ``s``) do not ring and are left out."""
    omegas, zetas = [], []
    for q in np.atleast_2d(np.asarray(qs, float)):
        s = np.linalg.eigvals(model.state_matrix(model.configuration(q))[0])
        s = s[s.imag > 1e-9 * np.maximum(1.0, np.abs(s))]
        w = np.abs(s)
        keep = (w > 0) & (w <= 2 * math.pi * band_hz)
        omegas.append(w[keep])
        zetas.append(-s.real[keep] / w[keep])
    return np.concatenate(omegas), np.concatenate(zetas)


def accumulated_error(omega, zeta, step: float, duration: float, rho_inf: float = 0.9) -> np.ndarray:
    """The relative error of each mode's response after its accumulation (module docstring):
    ``|e + i z| min(1 / zeta, omega T)``, with ``e`` and ``z`` generalized-alpha's frequency error and numerical
    damping at ``omega h`` (:func:`algorithmic_damping`, exact) and ``zeta`` the mode's own damping ratio."""
    omega, zeta = np.atleast_1d(np.asarray(omega, float)), np.atleast_1d(np.asarray(zeta, float))
    if omega.size == 0:
        return np.zeros(0)
    z, e = algorithmic_damping(omega * step, rho_inf)
    return np.hypot(e, z) * _memory(omega, zeta, duration)


def _memory(omega: np.ndarray, zeta: np.ndarray, duration: float) -> np.ndarray:
    """The radians of each mode's motion its phase error accumulates over: ``min(1 / zeta, omega T)``."""
    return np.minimum(1.0 / np.maximum(zeta, 1e-12), omega * duration)


def phase_step(omega, zeta, duration: float, output_dt: float, rho_inf: float = 0.9,
               tol: float = PHASE_TOL) -> float:
    """The largest step ``output_dt / n`` (``n = 1, 2, ...``) whose accumulated error
    (:func:`accumulated_error`) is within ``tol`` for every mode (``omega`` rad/s, damping ratios ``zeta``) over a
    run of ``duration`` s.

    With ``|e| ~ c Omega^2`` (:func:`period_error`) the condition is ``h <= sqrt(tol / (c L)) / omega``: the
    largest ``omega^2 L`` decides, for Rayleigh damping the highest mode (``omega^2 / zeta = 2 omega^3 / (alpha +
    beta omega^2)`` grows with ``omega``). Assumptions: the modes are those of the model linearised at rest
    (:func:`band_modes`); a mode rings with its linear damping and frequency along the motion.
    """
    omega = np.atleast_1d(np.asarray(omega, float))
    zeta = np.atleast_1d(np.asarray(zeta, float))
    if omega.size == 0:
        return output_dt
    c = -float(period_error(1.0, rho_inf)[0])  # |e| = c Omega^2
    # the closed form's step, then the exact error decides (checked one n after another from just below it)
    h0 = float(np.min(np.sqrt(tol / (c * _memory(omega, zeta, duration))) / omega))
    n = max(1, math.floor(output_dt / h0 * 0.9))
    while np.max(accumulated_error(omega, zeta, output_dt / n, duration, rho_inf)) > tol:
        n += 1
    while n > 1 and np.max(accumulated_error(omega, zeta, output_dt / (n - 1), duration, rho_inf)) <= tol:
        n -= 1
    return output_dt / n


class HeldTable:
    """A zero-order-hold table on an increasing grid ``t_tab``: value ``values[k]`` on ``[t_k, t_k+1)``, the first
    value before ``t_0`` and the last after the table (as the RK4 engine reads its inputs)."""

    def __init__(self, t_tab, values):
        self.t = np.asarray(t_tab, float)
        self.values = np.asarray(values, float).reshape(len(self.t), -1)
        if self.t.ndim != 1 or len(self.t) < 2 or np.any(np.diff(self.t) <= 0):
            raise ValueError("torque table: t must be strictly increasing, with at least two points")
        # int_{t_0}^{t_k} of the hold, k = 0 .. n-1
        self._cum = np.vstack([np.zeros((1, self.values.shape[1])),
                               np.cumsum(self.values[:-1] * np.diff(self.t)[:, None], axis=0)])

    def integral(self, t) -> np.ndarray:
        """``int_{t_0}^{t}`` of the hold, for a time or an array of times (then time-first)."""
        t = np.asarray(t, float)
        k = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 1)
        inside = self._cum[k] + (t - self.t[k])[..., None] * self.values[k]
        before = (t - self.t[0])[..., None] * self.values[0]
        return np.where((t <= self.t[0])[..., None], before, inside)

    def mean(self, a, b) -> np.ndarray:
        """Mean of the hold over ``[a, b]`` (times or arrays of times)."""
        return (self.integral(b) - self.integral(a)) / (np.asarray(b, float) - np.asarray(a, float))[..., None]

    def step_ends(self, h: float, n_steps: int, every: int = 0) -> np.ndarray:
        """``(n_steps + 1, k)``: the forces generalized-alpha balances at the step ends ``t_j = j h`` under this
        hold, with a record every ``every`` steps (0: none).

        Generalized-alpha balances forces at step ends and integrates them as if linear in between: the impulse
        it gives the step ``[t_j, t_j+1]`` is ``h (f_j + f_j+1) / 2``, so each ``f_j`` carries a weight ``h``. The
        hold's mean over ``[t_j - h/2, t_j + h/2]``: these windows tile the time axis, so ``h (f_0 + ... + f_j)`` is
        the hold's integral up to ``t_j + h/2``, the impulse without lag.

        A record is the state at its instant ``t_j``, which under a bounded force depends on the hold before
        ``t_j`` alone (positions and rates are continuous; a torque switched at ``t_j`` acts after it, as the
        observer's sampled model has it: the torque sampled at ``t_j`` is held over the interval that follows). The
        symmetric mean at a recorded ``t_j`` takes half a step of the hold after ``t_j`` into the record: a torque
        step there ramps over ``[t_j - h, t_j + h]`` and the record carries a step's worth of the response of the
        mesh's stiffest modes, whose instantaneous acceleration under a torque step is large (``docs/ringing.md``).
        So at a recorded ``t_j`` (``0 < j < n_steps``, ``every >= 2``) the force is the mean over the half
        ``[t_j - h/2, t_j]`` before it: the impulse up to ``t_j``, ``h (f_0 / 2 + f_1 + ... + f_j-1) + h f_j / 2``
        plus the first half-window's, is then the hold's integral up to ``t_j`` exactly. The next step end takes
        the impulse left out,

        ``f_j+1 = int_{t_j}^{t_j + 3h/2} F / h - f_j / 2``,

        so that ``h (f_j + f_j+1)`` is the integral over ``[t_j - h/2, t_j + 3h/2]`` and the windows tile on (a
        torque step ``F_0 -> F_1`` at ``t_j``: ``f_j = F_0``, ``f_j+1 = (3 F_1 - F_0) / 2``; the impulse is short by
        ``h (F_1 - F_0) / 4`` at ``t_j+1`` and exact from ``t_j+2`` on). With a record at every step (``every == 1``) no step end is free to
        take the impulse left out: the symmetric means are kept (a causal force there would lag the hold by half a
        step)."""
        t = np.arange(n_steps + 1) * h
        f = self.mean(t - h / 2, t + h / 2)
        if every >= 2:
            j = np.arange(every, n_steps, every)
            f[j] = self.mean(t[j] - h / 2, t[j])
            f[j + 1] = (self.integral(t[j] + 1.5 * h) - self.integral(t[j])) / h - 0.5 * f[j]
        return f


def generalized_alpha(
    residual: Callable[[float, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    iteration_matrix: Callable[[float, np.ndarray, np.ndarray, np.ndarray, float, float], np.ndarray],
    x0: np.ndarray,
    v0: np.ndarray,
    a0: np.ndarray,
    t_end: float,
    h: float,
    *,
    rho_inf: float = 0.9,
    tol: float = 1e-9,
    output_every: int = 1,
    progress: Callable[[float], None] | None = None,
    stats: dict | None = None,
    refresh_rate: float = REFRESH_RATE,
    probe_every: int = PROBE_EVERY,
) -> Trajectory:
    """Integrate ``r(t, x, v, x'') = 0`` (e.g. ``M(x) x'' - Q(t, x, v)``) by generalized-alpha with step ``h``.

    Parameters
    ----------
    residual : ``r(t, x, v, x'')`` (n,).
    iteration_matrix : ``S(t, x, v, x'', beta', gamma')`` (n, n), an approximation of
        ``beta' dr/dx'' + gamma' dr/dv + dr/dx`` (exact: quadratic convergence; approximate: more iterations).
    x0, v0, a0 : initial positions, rates and accelerations (``r(0, x0, v0, a0) = 0``).
    tol : Newton stops when the estimated error of the positions (max norm, units of x) is below ``tol``.
    output_every : store every k-th step. progress : called with the fraction done.
    stats : if a dict, filled with the residual evaluations per step and the number of iteration matrices built.
    refresh_rate : rebuild the iteration matrix when the measured contraction rate exceeds this.
    probe_every : steps accepted after one iteration before a second iteration re-measures the rate.

    Returns
    -------
    Trajectory
        ``y = [x, v]`` (time-first) at ``t = 0, k h, 2 k h, ...``.
    """
    ga = GeneralizedAlpha(rho_inf)
    am, af, g, b = ga.alpha_m, ga.alpha_f, ga.gamma, ga.beta
    beta_p, gamma_p = ga.primes(h)
    ca = (1 - af) / (1 - am)  # d a1 / d x1''
    n_steps = round(t_end / h)
    x, v, dd = (np.array(z, float) for z in (x0, v0, a0))
    a = dd.copy()
    ts, ys = [0.0], [np.concatenate([x, v])]
    S_inv = None
    eta_est = 1.0  # estimated contraction rate of the current matrix (unknown after a factorisation)
    since_probe = 0
    n_res = n_lu = 0
    report = max(1, n_steps // 100)
    for k in range(n_steps):
        t1 = (k + 1) * h
        for attempt in range(2):
            if S_inv is None:
                # the iteration matrix's inverse: one matrix-vector product per iteration (a factorisation's
                # triangular solves cost more at this size); its round-off only affects the contraction rate
                S_inv = np.linalg.inv(iteration_matrix(t1, x, v, dd, beta_p, gamma_p))
                n_lu += 1
                eta_est = 1.0
            # predictor: x1'' = a0, the algorithmic acceleration (on the four-bar with 8 elements per link it needed
            # fewer iterations and matrix refreshes than x1'' = x0'' or a linear extrapolation of x'')
            dd1 = a.copy()
            a1 = (af * dd - am * a) / (1 - am) + ca * dd1
            v1 = v + h * ((1 - g) * a + g * a1)
            x1 = x + h * v + h * h * ((0.5 - b) * a + b * a1)
            # at least two iterations every probe_every steps: the rate estimate follows the matrix's ageing
            probe = since_probe >= probe_every
            eta, prev, converged, observed = eta_est, None, False, 0.0
            for it in range(MAX_ITERATIONS):
                r = residual(t1, x1, v1, dd1)
                n_res += 1
                dx = S_inv @ r
                dx *= -1.0
                x1 += dx
                v1 += gamma_p * dx
                dd1 += beta_p * dx
                a1 += ca * beta_p * dx
                norm = float(np.max(np.abs(dx)))
                if prev is not None:
                    eta = norm / prev if prev > 0 else 0.0
                    observed = max(observed, eta)
                    if eta >= 1.0:
                        break  # diverging: refresh the matrix and redo the step
                if norm == 0.0 or (eta < 1.0 and eta / (1 - eta) * norm <= tol and (prev is not None or not probe)):
                    converged = True
                    break
                prev = norm
            if converged:
                break
            if attempt == 0:
                S_inv = None  # the matrix is too stale: rebuild it at the step's start and retry
                continue
            raise FloatingPointError(f"generalized-alpha: Newton did not converge at t = {t1:.6g} s (step {h:g} s)")
        if prev is not None:
            eta_est = observed
            since_probe = 0
        else:
            since_probe += 1
        if eta_est > refresh_rate:
            S_inv = None
        x, v, dd, a = x1, v1, dd1, a1
        if not np.all(np.isfinite(x)):
            raise FloatingPointError(f"generalized-alpha diverged at t = {t1:.6g} s")
        if (k + 1) % output_every == 0:
            ts.append(t1)
            ys.append(np.concatenate([x, v]))
        if progress is not None and (k + 1) % report == 0:
            progress((k + 1) / n_steps)
    if stats is not None:
        stats.update(n_steps=n_steps, residuals_per_step=n_res / max(n_steps, 1), factorisations=n_lu)
    return Trajectory(np.array(ts), np.array(ys))


class _ErlsSystem:
    """Residual and iteration matrix of the ERLS model's eq. 2 under a torque schedule ``tau(t)``."""

    def __init__(self, model: ErlsModel, tau: Callable[[float], np.ndarray]):
        self.model, self.tau = model, tau
        self._z = None

    def _cfg(self, x):
        cfg = self.model.configuration(x[: self.model.nq], self._z)
        self._z = cfg.pose.z
        return cfg

    def _r(self, cfg, t, x, v, dd):
        W = cfg.W
        return W.T @ (cfg.M_N @ (W @ dd)) - self.model.net_forces(cfg, x, v, self.tau(t))  # M dd - Q

    def residual(self, t, x, v, dd):
        return self._r(self._cfg(x), t, x, v, dd)

    def iteration_matrix(self, t, x, v, dd, beta_p, gamma_p):
        """``beta' M + gamma' (C + dh/dv) + K + dCv/du`` at ``x``: the model's analytic mass, damping (at ``x``),
        velocity-force Jacobian, stiffness and the damping forces' change with the elastic coordinates
        (:meth:`~exuflex.erls.model.ErlsModel.damping_position_jacobian`, u columns). Left out: the q columns'
        ``d(M x'' - Q)/dq`` (the change of the mass and forces with the configuration), which is of order ``h^2``
        relative to ``beta' M``; a simplified Newton (on the four-bar with 8 elements per link the iteration
        counts with and without them by central differences were equal)."""
        m = self.model
        cfg = self._cfg(x)
        S = beta_p * m.mass(cfg) + gamma_p * (m.damping(cfg, x) + m.velocity_force_jacobian(cfg, x, v)) + m.stiffness(cfg)
        S[:, m.nq :] += m.damping_position_jacobian(cfg, x, v)
        return S


def erls_implicit(
    model: ErlsModel,
    t_tab: np.ndarray,
    tau_tab: np.ndarray,
    y0: np.ndarray,
    t_end: float,
    h: float,
    *,
    rho_inf: float = 0.9,
    tol: float = 1e-9,
    output_every: int = 1,
    progress: Callable[[float], None] | None = None,
    stats: dict | None = None,
    refresh_rate: float = REFRESH_RATE,
    probe_every: int = PROBE_EVERY,
) -> Trajectory:
    """Integrate the ERLS model's eq. 2 under a zero-order-hold torque table by :func:`generalized_alpha`.

    The table (increasing grid ``t_tab``, value ``tau_tab[k]`` held over ``[t_k, t_k+1)``, as the RK4 engine
    reads it) enters generalized-alpha, which balances forces at step ends and acts as if they were linear
    in between, as its mean over ``[t1 - h/2, t1 + h/2]`` at each step end ``t1``: the hold's impulse over every
    step, without lag (for ``h`` equal to the table step, the mean of the values either side of ``t1``, as the
    Exudyn truth does); at a recorded step end (every ``output_every`` steps) the mean over the half before it,
    the next step end taking the rest, so that a record depends on the torques before its instant alone
    (:meth:`HeldTable.step_ends`).

    Returns
    -------
    Trajectory
        ``y = [x; v]`` in :meth:`ErlsModel.rhs`'s layout.
    """
    table = HeldTable(t_tab, tau_tab)
    n = model.n
    y0 = np.asarray(y0, float)
    tau_steps = table.step_ends(h, round(t_end / h), output_every)  # the force at every step end
    inv_h = 1.0 / h
    system = _ErlsSystem(model, lambda t: tau_steps[int(t * inv_h + 0.5)])
    x0, v0 = y0[:n], y0[n:]
    a0 = model.accelerations(x0, v0, system.tau(0.0))
    return generalized_alpha(
        system.residual,
        system.iteration_matrix,
        x0,
        v0,
        a0,
        t_end,
        h,
        rho_inf=rho_inf,
        tol=tol,
        output_every=output_every,
        progress=progress,
        stats=stats,
        refresh_rate=refresh_rate,
        probe_every=probe_every,
    )

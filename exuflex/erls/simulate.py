"""Time integration of first-order models ``y' = f(t, y, u(t))``: fixed-step RK4 or scipy's solve_ivp."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["Trajectory", "rk4_amplification", "rk4_step", "rk4_substeps", "simulate"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Trajectory:
    t: np.ndarray  # (n_steps,)
    y: np.ndarray  # (n_steps, n_states), time-first
    names: tuple[str, ...] = ()


def rk4_step(f, t, y, h, u):
    k1 = f(t, y, u)
    k2 = f(t + h / 2, y + h / 2 * k1, u)
    k3 = f(t + h / 2, y + h / 2 * k2, u)
    k4 = f(t + h, y + h * k3, u)
    return y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def rk4_amplification(z):
    """RK4's amplification of a linear mode per step, ``R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24``, ``z = h lambda``."""
    return 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24


def rk4_substeps(A: np.ndarray, h: float, max_substeps: int = 10000) -> int:
    """The fewest RK4 sub-steps per step ``h`` for which the linear system ``y' = A y`` is stable.

    RK4 multiplies a mode ``lambda`` by :func:`rk4_amplification` ``R(z)`` per sub-step, ``z = h lambda``; a
    mode that decays physically (``Re lambda <= 0``) must not grow, ``|R(z)| <= 1``. Stiffness-proportional
    damping makes the highest elastic modes of a fine mesh overdamped, with large negative real eigenvalues,
    where RK4 is stable only up to ``|z| = 2.79`` (on the imaginary axis up to 2.83).
    """
    lam = np.linalg.eigvals(np.asarray(A, float))
    lam = lam[lam.real <= 0]
    for n in range(1, max_substeps + 1):
        z = (h / n) * lam
        if np.all(np.abs(rk4_amplification(z)) <= 1.0 + 1e-12):
            return n
    raise ValueError(f"RK4 needs more than {max_substeps} sub-steps of h = {h:g} s for max |lambda| = "
                     f"{np.abs(lam).max():.3g} 1/s")


def simulate(
    f: Callable[[float, np.ndarray, np.ndarray], np.ndarray],
    y0: np.ndarray,
    t_end: float,
    inputs: Callable[[float], np.ndarray],
    *,
    h: float = 1e-4,
    method: str = "rk4",
    output_every: int = 1,
    progress: Callable[[float], None] | None = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    jac: Callable[[float, np.ndarray], np.ndarray] | None = None,
) -> Trajectory:
    """Integrate ``y' = f(t, y, inputs(t))`` from 0 to ``t_end``.

    Parameters
    ----------
    method : "rk4" (fixed step ``h``, inputs held over each step at their start value, as a
        zero-order hold), "trapezoid" (fixed step ``h``, the implicit trapezoidal rule
        ``y1 = y0 + h/2 (f(t0, y0) + f(t1, y1))`` solved by Newton's method with ``jac``: A-stable and free of
        numerical damping, second order; the Jacobian once per step, one iteration exact for a system linear in
        ``y``, the residual checked against ``rtol`` times ``max|y1| + h max|f1|`` plus ``atol``; inputs at each step's
        end) or any ``solve_ivp`` method name ("RK45", "Radau", "LSODA", ...), which
        samples the output every ``h * output_every``.
    output_every : store every k-th step.
    progress : called with the fraction done (0..1) from time to time.
    jac : ``dy'/dy (t, y)``: needed by "trapezoid"; for the implicit ``solve_ivp`` methods ("Radau", "BDF",
        "LSODA") optional (without it they estimate it by finite differences).
    """
    y0 = np.asarray(y0, float)
    n_steps = int(round(t_end / h))
    if method == "rk4":
        ts = [0.0]
        ys = [y0.copy()]
        y = y0.copy()
        report = max(1, n_steps // 100)
        for k in range(n_steps):
            t = k * h
            y = rk4_step(f, t, y, h, inputs(t))
            if not np.all(np.isfinite(y)):
                raise FloatingPointError(f"simulation diverged at t = {t + h:.6g} s (step h = {h:g} s too large?)")
            if (k + 1) % output_every == 0:
                ts.append((k + 1) * h)
                ys.append(y.copy())
            if progress is not None and (k + 1) % report == 0:
                progress((k + 1) / n_steps)
        return Trajectory(np.array(ts), np.array(ys))
    if method == "trapezoid":
        if jac is None:
            raise ValueError("simulate: method 'trapezoid' needs jac (dy'/dy)")
        ts, ys = [0.0], [y0.copy()]
        y = y0.copy()
        f0 = f(0.0, y, inputs(0.0))
        eye = np.eye(len(y))
        for k in range(n_steps):
            t1 = (k + 1) * h
            u1 = inputs(t1)
            y1 = y + h * f0  # Euler predictor
            A = eye - 0.5 * h * jac(t1, y1)  # modified Newton: the Jacobian once per step
            for _ in range(8):
                f1 = f(t1, y1, u1)
                G = y1 - y - 0.5 * h * (f0 + f1)
                if np.abs(G).max() <= rtol * (np.abs(y1).max() + h * np.abs(f1).max()) + atol:
                    break
                y1 = y1 - np.linalg.solve(A, G)
            else:
                raise FloatingPointError(f"trapezoidal Newton did not converge at t = {t1:.6g} s")
            y, f0 = y1, f1
            if not np.all(np.isfinite(y)):
                raise FloatingPointError(f"simulation diverged at t = {t1:.6g} s")
            if (k + 1) % output_every == 0:
                ts.append(t1)
                ys.append(y.copy())
            if progress is not None and (k + 1) % max(1, n_steps // 100) == 0:
                progress((k + 1) / n_steps)
        return Trajectory(np.array(ts), np.array(ys))
    t_eval = np.arange(0, n_steps + 1, output_every) * h
    from scipy.integrate import solve_ivp  # here, not at import: scipy.integrate is a large import

    sol = solve_ivp(
        lambda t, y: f(t, y, inputs(t)), (0.0, t_end), y0, method=method, t_eval=t_eval, rtol=rtol, atol=atol,
        **({} if jac is None else {"jac": jac}),
    )
    if not sol.success:
        raise FloatingPointError(f"solve_ivp ({method}) failed: {sol.message}")
    return Trajectory(sol.t, sol.y.T)

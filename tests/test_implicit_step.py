"""The truth engines' step rule (:func:`exuflex.erls.implicit.phase_step`): generalized-alpha's period error and
numerical damping in closed form against the method's amplification matrix and against the engine's own output
on an oscillator, the accumulated error of a damped mode's response, and the rule's step on a model."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.implicit import (
    PHASE_TOL,
    accumulated_error,
    algorithmic_damping,
    band_modes,
    generalized_alpha,
    period_error,
    phase_step,
)

ROOT = Path(__file__).resolve().parents[1]


def oscillator(omega: float, zeta: float, h: float, t_end: float, rho: float):
    """``x'' + 2 zeta omega x' + omega^2 x = 0`` from ``x = 1`` at rest by the engine's generalized-alpha."""
    c, k = 2 * zeta * omega, omega**2
    return generalized_alpha(lambda t, x, v, a: a + c * v + k * x,
                             lambda t, x, v, a, bp, gp: np.array([[bp + gp * c + k]]),
                             np.array([1.0]), np.array([0.0]), np.array([-k]), t_end, h, rho_inf=rho, tol=1e-13)


@pytest.mark.parametrize("rho", [1.0, 0.9, 0.5, 0.0])
def test_closed_form_is_the_amplification_matrix_series(rho):
    """period_error's leading terms against the exact eigenvalues of the one-step map: the relative difference
    falls as Omega^2 (the next term's order)."""
    W = np.array([0.02, 0.05, 0.1])
    zeta, err = algorithmic_damping(W, rho)
    e, z = period_error(W, rho)
    rel = np.abs(err / e - 1)
    assert np.all(rel < 2.5 * W**2)
    if rho < 1:
        assert np.all(np.abs(zeta / z - 1) < 4 * W**2)
    else:
        np.testing.assert_allclose(zeta, 0.0, atol=1e-12)


@pytest.mark.parametrize("rho, omega_h", [(0.9, 0.2), (0.5, 0.2), (0.0, 0.1)])
def test_engine_period_and_damping_on_an_oscillator_equal_the_closed_form(rho, omega_h):
    """The engine's trajectory of an undamped oscillator over 300 cycles: its frequency (from the zero crossings)
    and its numerical damping (from the decay of the peaks) equal period_error's within a few %."""
    omega = 2 * math.pi * 50.0
    h = omega_h / omega
    tr = oscillator(omega, 0.0, h, 300 * 2 * math.pi / omega, rho)
    x, t = tr.y[:, 0], tr.t
    s = np.nonzero(np.sign(x[:-1]) != np.sign(x[1:]))[0][2:]  # after the spurious root has decayed
    t0 = t[s] - x[s] * (t[s + 1] - t[s]) / (x[s + 1] - x[s])  # the crossings, interpolated
    half = np.polyfit(np.arange(len(t0)), t0, 1)[0]
    e, z = period_error(omega_h, rho)
    measured_e = math.pi / half / omega - 1
    assert measured_e == pytest.approx(float(e), rel=0.03)
    if rho < 1:
        peaks = [i for i in range(1, len(x) - 1) if abs(x[i]) >= abs(x[i - 1]) and abs(x[i]) > abs(x[i + 1])][2:]
        decay = -np.polyfit(t[peaks], np.log(np.abs(x[peaks])), 1)[0]  # zeta w
        assert decay / (omega * (1 + measured_e)) == pytest.approx(float(z), rel=0.05)


@pytest.mark.parametrize("zeta", [0.01, 0.03])
def test_free_decay_error_accumulates_to_the_phase_error_over_the_modes_life(zeta):
    """A damped mode's free decay by the engine against the exact solution: the largest error is |e| times the
    peak of omega t exp(-zeta omega t), 1 / (zeta e_Euler), not |e| per cycle; and accumulated_error's bound
    |e| / zeta holds above it."""
    omega, rho = 2 * math.pi * 60.0, 0.9
    h = 2e-4
    tr = oscillator(omega, zeta, h, 10.0 / (zeta * omega), rho)
    wd = omega * math.sqrt(1 - zeta**2)
    exact = np.exp(-zeta * omega * tr.t) * (np.cos(wd * tr.t) + zeta * omega / wd * np.sin(wd * tr.t))
    largest = float(np.max(np.abs(tr.y[:, 0] - exact)))
    e = abs(float(period_error(omega * h, rho)[0]))
    assert largest == pytest.approx(e / (zeta * math.e), rel=0.05)
    assert largest <= float(accumulated_error(omega, zeta, h, 1e9, rho)[0]) * 1.001


def test_phase_step_is_the_largest_within_the_tolerance():
    omega = 2 * np.pi * np.array([12.9, 44.4, 61.6, 121.7, 156.9, 173.8])
    zeta = np.array([0.0103, 0.0053, 0.0056, 0.0081, 0.0099, 0.0108])
    for duration, out in ((3.0, 1e-3), (0.2, 1e-3), (3.0, 2e-3)):
        step = phase_step(omega, zeta, duration, out)
        n = round(out / step)
        assert n * step == pytest.approx(out)
        assert np.max(accumulated_error(omega, zeta, step, duration)) <= PHASE_TOL
        assert n == 1 or np.max(accumulated_error(omega, zeta, out / (n - 1), duration)) > PHASE_TOL
    # the highest mode decides (omega^2 / zeta grows with omega for Rayleigh damping), and its closed form step
    life = 1 / zeta[-1]
    e2 = -float(period_error(1.0)[0])
    assert phase_step(omega, zeta, 3.0, 1e-3) == pytest.approx(math.sqrt(PHASE_TOL / (e2 * life)) / omega[-1], rel=0.03)
    assert phase_step(np.zeros(0), np.zeros(0), 1.0, 1e-3) == 1e-3


def test_band_modes_have_the_model_files_rayleigh_damping():
    """The vertical link's modes below its band: the file's Rayleigh damping alpha/(2w) + beta w/2 (1 % at both)."""
    from exuflex.erls.model import ErlsModel
    from exuflex.mechanism import load_mechanism

    mech = load_mechanism(ROOT / "benchmarks" / "models" / "vertical_link.toml")
    w, z = band_modes(ErlsModel(mech), mech.q_ref, mech.reduction.band_hz)
    assert len(w) == 2
    np.testing.assert_allclose(z, mech.damping.alpha / (2 * w) + mech.damping.beta * w / 2, rtol=0.02)


@pytest.mark.slow
def test_vertical_link_truth_at_the_rules_step_is_within_the_tolerance_of_rk4():
    """The vertical link (1 % damping at 62.8 and 161.6 Hz, 1.2 s): the ERLS truth at the automatic step against the
    same model by RK4 (exact to the model). The error of the elastic tip rate, whose motion is the modes' ringing,
    over its RMS is within the accumulated error the rule allows; at the old per-cycle rule's 0.2 ms it is five times
    that and more. (Their ratio is below the step ratio squared: the engines' torque holds differ by O(h^2) too.)"""
    from exuflex.erls.implicit import band_step
    from exuflex.mechanism import load_mechanism
    from exuflex.sensors import true_states
    from exuflex.truth.engines import erls_truth, plan_drive

    mech = load_mechanism(ROOT / "benchmarks" / "models" / "vertical_link.toml")
    h, out, duration = 1e-4, 1e-3, mech.manoeuvre.duration
    drive = plan_drive(mech, duration, h)

    def truth(integrator, step):
        st: dict = {}
        rec = erls_truth(mech, drive.t, drive.tau, duration, h, out, drive.q0, drive.qd0, integrator=integrator,
                         stats=st, step=step)
        return true_states(mech, rec), st.get("step_s")

    ref, _ = truth("rk4", None)
    scored = ref.t >= 0.1

    def error(tr, k):
        return float(np.sqrt(np.mean((tr[k][scored] - ref[k][scored]) ** 2) / np.mean(ref[k][scored] ** 2)))

    new, step = truth("gen-alpha", "auto")
    old, old_step = truth("gen-alpha", band_step(180.0, h, out))
    assert old_step == pytest.approx(2e-4) and step < old_step / 5
    for k in ("dx10", "dy11"):
        assert error(new, k) <= PHASE_TOL
        assert error(old, k) > 5 * PHASE_TOL

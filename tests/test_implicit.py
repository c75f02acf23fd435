"""Implicit generalized-alpha integration (the stiff-stable ERLS truth): the method's spectral properties, its
driver on linear oscillators, and the ERLS engine against the explicit RK4 reference."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.implicit import (
    GeneralizedAlpha,
    HeldTable,
    algorithmic_damping,
    erls_implicit,
    generalized_alpha,
)
from exuflex.erls.model import ErlsModel
from exuflex.erls.simulate import rk4_substeps, simulate
from exuflex.manoeuvre import computed_torque, plan
from exuflex.mechanism import load_mechanism

MODELS = Path(__file__).resolve().parents[1] / "models"


def test_coefficients_and_trapezoidal_limit():
    ga = GeneralizedAlpha(1.0)
    assert (ga.alpha_m, ga.alpha_f, ga.gamma, ga.beta) == (0.5, 0.5, 0.5, 0.25)  # trapezoidal rule
    for rho in (0.0, 0.6, 0.9, 1.0):
        ga = GeneralizedAlpha(rho)
        assert ga.gamma == pytest.approx(0.5 + ga.alpha_f - ga.alpha_m)  # second order
    wh = np.array([0.01, 0.1, 0.5, 1.0, 3.0])
    zeta, err = algorithmic_damping(wh, 1.0)
    np.testing.assert_allclose(zeta, 0.0, atol=1e-12)
    np.testing.assert_allclose(err, 2 * np.arctan(wh / 2) / wh - 1, rtol=1e-9, atol=1e-13)  # exact for trapezoid
    with pytest.raises(ValueError, match=r"rho_inf must be in \[0, 1\]"):
        GeneralizedAlpha(1.2)


def test_damping_is_third_order_and_bounded_by_rho_inf():
    """Numerical damping grows as (omega h)^3 at low frequency (Chung & Hulbert: zeta ~ c (omega h)^3) and the
    amplification at infinite frequency is rho_inf."""
    z, _ = algorithmic_damping(np.array([0.01, 0.02]), 0.9)
    assert np.log(z[1] / z[0]) / np.log(2) == pytest.approx(3.0, abs=0.01)
    wh = 1e6
    for rho in (0.5, 0.9):
        zeta, err = algorithmic_damping(wh, rho)
        lam_abs = np.exp(-zeta[0] * (1 + err[0]) * wh)  # |lambda| = exp(-zeta w h)
        assert lam_abs == pytest.approx(rho, rel=1e-3)


def test_driver_reproduces_the_spectral_analysis_on_an_oscillator():
    """x'' + omega^2 x = 0 by the driver: the positions obey the 3-term recurrence of the one-step map (state x, v,
    a); its roots, fitted to the sequence (Prony), give the damping and frequency that algorithmic_damping says."""
    omega, h, rho = 2 * np.pi * 50.0, 2e-3, 0.6  # omega h = 0.63
    zeta, err = algorithmic_damping(omega * h, rho)
    tr = generalized_alpha(lambda t, x, v, a: a + omega**2 * x, lambda t, x, v, a, bp, gp: np.array([[bp + omega**2]]),
                           np.array([1.0]), np.array([0.0]), np.array([-(omega**2)]), 60 * h, h, rho_inf=rho, tol=1e-14)
    x = tr.y[:, 0]
    A = np.column_stack([x[2:-1], x[1:-2], x[:-3]])
    c = np.linalg.lstsq(A, x[3:], rcond=None)[0]
    roots = np.roots([1.0, -c[0], -c[1], -c[2]])
    lam = roots[np.argmax(roots.imag)]
    s = np.log(lam) / h
    assert -s.real / abs(s) == pytest.approx(zeta[0], rel=1e-4)
    assert abs(s) / omega - 1 == pytest.approx(err[0], rel=1e-4)
    assert zeta[0] > 1e-3 and err[0] < -0.02  # a case where both are visible


def test_stiff_oscillator_is_stable_where_rk4_is_not():
    """A 1 MHz mode with a 0.1 ms step (omega h = 628): RK4 blows up, generalized-alpha damps it to rho_inf^n."""
    omega, h = 2 * np.pi * 1e6, 1e-4
    tr = generalized_alpha(lambda t, x, v, a: a + omega**2 * x, lambda t, x, v, a, bp, gp: np.array([[bp + omega**2]]),
                           np.array([1e-6]), np.array([0.0]), np.array([-(omega**2) * 1e-6]), 50 * h, h, rho_inf=0.9)
    assert np.all(np.isfinite(tr.y)) and abs(tr.y[-1, 0]) < 1e-6 * 0.9**20


def test_held_table_mean_is_the_exact_integral():
    t = np.arange(5) * 0.1
    vals = np.array([[1.0], [2.0], [4.0], [8.0], [16.0]])
    tab = HeldTable(t, vals)
    assert tab.mean(0.05, 0.15)[0] == pytest.approx(1.5)  # half of each of the first two holds
    assert tab.mean(-0.1, 0.0)[0] == pytest.approx(1.0)  # the first value before the table
    assert tab.mean(0.4, 0.6)[0] == pytest.approx(16.0)  # the last after it
    assert tab.mean(0.0, 0.4)[0] == pytest.approx((1 + 2 + 4 + 8) / 4)


@pytest.mark.parametrize("name,duration", [("fourbar", 0.05), ("sixbar", 0.15)])
def test_erls_truth_matches_the_explicit_reference(name, duration):
    """The manoeuvre's start on the model file's (coarse) mesh: q within 1e-3 rad of RK4 (which needs 6 sub-steps
    of its 0.1 ms step on the four-bar), the largest elastic coordinate within 2 % RMS of its RMS (seen: 1.4e-7 rad
    and 0.33 % on the four-bar, 2e-6 rad and 0.04 % on the six-bar)."""
    mech = load_mechanism(MODELS / f"{name}.toml")
    h = 1e-4
    p = plan(mech, dt=h, t_end=duration)
    tau = computed_torque(mech, p)
    model = ErlsModel(mech)
    n, nq = model.n, model.nq
    y0 = np.zeros(2 * n)
    y0[:nq], y0[n : n + nq] = p.q[0], p.qd[0]
    imp = erls_implicit(model, p.t, tau, y0, duration, h, output_every=10)
    sub = rk4_substeps(model.state_matrix(model.configuration(p.q[0]))[0], h)
    ref = simulate(model.rhs, y0, duration, lambda t: tau[min(int(np.floor(t / h + 1e-6)), len(tau) - 1)],
                   h=h / sub, output_every=10 * sub)
    np.testing.assert_allclose(imp.t, ref.t, atol=1e-12)
    assert np.max(np.abs(imp.y[:, :nq] - ref.y[:, :nq])) < 1e-3
    assert np.max(np.abs(ref.y[:, :nq] - p.q[0])) > 1e-3  # the mechanism did move
    u = np.abs(ref.y[:, nq:n]).max(axis=0).argmax() + nq  # the largest elastic coordinate
    rms = np.sqrt(np.mean(ref.y[:, u] ** 2))
    assert np.sqrt(np.mean((imp.y[:, u] - ref.y[:, u]) ** 2)) < 0.02 * rms

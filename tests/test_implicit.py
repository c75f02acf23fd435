"""Implicit generalized-alpha integration (the stiff-stable ERLS truth): the method's spectral properties, its
driver on linear oscillators, and the ERLS engine against the explicit RK4 reference."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.implicit import (
    FREQ_TOL,
    GeneralizedAlpha,
    HeldTable,
    algorithmic_damping,
    band_step,
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


def test_band_step_is_the_largest_within_the_frequency_tolerance():
    for band, h, out in ((180.0, 1e-4, 1e-3), (180.0, 1e-4, 2e-3), (50.0, 1e-4, 1e-3), (2000.0, 1e-4, 1e-3)):
        step = band_step(band, h, out)
        k = round(step / h)
        assert round(out / h) % k == 0
        err = abs(algorithmic_damping(2 * np.pi * band * step)[1][0])
        assert err <= FREQ_TOL or k == 1  # never below the table step
        larger = [j for j in range(k + 1, round(out / h) + 1) if round(out / h) % j == 0]
        assert all(abs(algorithmic_damping(2 * np.pi * band * j * h)[1][0]) > FREQ_TOL for j in larger)
    assert band_step(180.0, 1e-4, 1e-3) == pytest.approx(2e-4) and band_step(2000.0, 1e-4, 1e-3) == pytest.approx(1e-4)


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


def test_cli_erls_engine_integrators(tmp_path, capsys):
    """exuflex simulate --engine erls: generalized-alpha (default) and the RK4 reference agree on the four-bar's
    start; the step and integrator are recorded; a step off the sample grid is refused by name."""
    import json

    from exuflex.cli import main
    from exuflex.runs import read_run

    model = str(MODELS / "fourbar.toml")
    runs = {}
    for name, extra in (("ga", ["--erls-step", "1e-4"]), ("ga2", []), ("rk4", ["--integrator", "rk4"])):
        out = tmp_path / name
        assert main(["simulate", model, "--out", str(out), "--engine", "erls", "--duration", "0.03", "--seed", "1",
                     *extra]) == 0
        runs[name] = read_run(out)
    truth = {k: json.loads((tmp_path / k / "meta.json").read_text())["settings"]["truth"] for k in runs}
    assert truth["ga"]["integrator"] == "gen-alpha" and truth["ga"]["step_s"] == 1e-4
    # auto: the largest step dividing the 1 ms sample interval whose phase error accumulated over 0.03 s is within
    # PHASE_TOL for the modes below 180 Hz (tests/test_implicit_step.py), below the band rule's 0.2 ms
    from exuflex.erls.implicit import PHASE_TOL, band_modes, phase_step

    mech = load_mechanism(model)
    modes = band_modes(ErlsModel(mech), np.vstack([mech.q_ref, runs["rk4"].truth.data[0, :1]]), 180.0)
    assert truth["ga2"]["band_hz"] == 180.0 and truth["ga2"]["phase_error"] <= PHASE_TOL
    assert truth["ga2"]["step_s"] == pytest.approx(min(2e-4, phase_step(*modes, 0.03, 1e-3)))
    assert truth["ga2"]["freq_error_at_band"] > -0.005
    assert truth["rk4"]["integrator"] == "rk4" and truth["rk4"]["rk4_substeps"] > 1
    ref = runs["rk4"].truth.data
    for k in ("ga", "ga2"):
        np.testing.assert_allclose(runs[k].truth.t, runs["rk4"].truth.t, atol=1e-12)
        np.testing.assert_allclose(runs[k].truth.data[:, 0], ref[:, 0], atol=1e-5)  # q1 (rad)
        np.testing.assert_allclose(runs[k].truth.data[:, 1], ref[:, 1], atol=0.02 * np.abs(ref[:, 1]).max())  # dq1
    capsys.readouterr()
    assert main(["simulate", model, "--out", str(tmp_path / "bad"), "--engine", "erls", "--duration", "0.01",
                 "--erls-step", "3e-4"]) == 2
    assert "--erls-step: expected a multiple of --h = 0.0001 s that divides the sample interval" in capsys.readouterr().err

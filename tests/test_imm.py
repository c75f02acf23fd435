"""The interacting multiple-model filter (:mod:`exuflex.observer.imm`): its algebra, not only that it runs.

- one mode: the IMM is that mode's EKF (:class:`MultirateEKF`), estimates and covariances bit for bit, with gaps,
  partial samples and the gate;
- two identical modes: the mode probabilities stay at their prior and the estimate is the single filter's;
- filterpy's ``IMMEstimator`` on a linear two-mode system: the mode probabilities, the mixed and combined
  estimates to rounding;
- mixing over nested state spaces (unbiased mixing) entry by entry against its definition, and the transition
  matrix against the two-state Markov chain's closed form.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from exuflex.observer import LinearDiscreteModel, MultirateEKF
from exuflex.observer.base import Belief
from exuflex.observer.ekf import Monitoring
from exuflex.observer.imm import IMMFilter, combine, mix, transition_matrix

DT = 1 / 100


def linear_model(seed: int, nx: int = 4, m: int = 3, q: float = 1e-3) -> LinearDiscreteModel:
    rng = np.random.default_rng(seed)
    Qo, _ = np.linalg.qr(rng.standard_normal((nx, nx)))
    C = {f"c{i}": rng.standard_normal(nx) for i in range(m)}
    return LinearDiscreteModel(0.99 * Qo, 0.1 * rng.standard_normal((nx, 1)), C, q * np.eye(nx), dt=DT)


def record(model, n: int, seed: int, R: float = 0.1):
    rng = np.random.default_rng(seed)
    H = np.array(list(model.C.values()))
    t = np.arange(n) * DT
    U = np.sin(2 * np.pi * t)[:, None]
    x = rng.standard_normal(model.nx)
    Y = np.empty((n, len(model.C)))
    for k in range(n):
        Y[k] = H @ x + R * rng.standard_normal(len(model.C))
        x = model.A @ x + model.B @ U[k] + np.sqrt(np.diag(model.Q)) * rng.standard_normal(model.nx)
    Y[rng.random(Y.shape) < 0.1] = np.nan  # partial samples
    Y[rng.random(n) < 0.05] = np.nan  # whole samples lost
    Y[17, 1] += 40 * R  # a spike for the gate
    Y[150:, 0] += 5 * R  # an offset for the fault windows
    return t, U, Y


def test_one_mode_is_the_ekf():
    model = linear_model(0)
    t, U, Y = record(model, 300, 1)
    R = {c: 0.1 for c in model.C}
    x0, P0 = np.zeros(model.nx), np.eye(model.nx)
    ekf = MultirateEKF(model, tuple(model.C), R, x0, P0, dt=DT, monitoring=Monitoring(gate_p=1e-4, fault_window=20))
    imm = IMMFilter([model], [[]], tuple(model.C), R, x0, P0, DT, dwell_s=[1.0], mode_p0=[1.0],
                    monitoring=ekf_monitoring(ekf))
    a = ekf.run(t, U, Y)
    b = imm.run(t, U, Y)
    np.testing.assert_array_equal(b.x_hat, a.x_hat)
    np.testing.assert_array_equal(b.P, a.P)
    np.testing.assert_array_equal(b.nominal_p, 1.0)
    assert b.n_rejected == a.n_rejected and sum(a.n_rejected.values()) >= 1
    np.testing.assert_allclose(b.nis, a.nis, rtol=1e-10)
    assert (b.n_updates, b.n_missing) == (a.n_updates, a.n_missing)
    assert b.channel_faults == a.channel_faults and any(f["kind"] == "offset" for f in a.channel_faults)
    assert b.flagged_intervals == a.flagged_intervals


def ekf_monitoring(ekf):
    return Monitoring(gate_p=ekf.gate_p, fault_window=ekf.faults.window, fault_p=ekf.faults.p)


def test_identical_modes_keep_their_prior():
    model = linear_model(2)
    t, U, Y = record(model, 200, 3)
    R = {c: 0.1 for c in model.C}
    x0, P0 = np.zeros(model.nx), np.eye(model.nx)
    single = IMMFilter([model], [[]], tuple(model.C), R, x0, P0, DT, dwell_s=[1.0], mode_p0=[1.0]).run(t, U, Y)
    # dwell times in the prior's ratio: the prior is the chain's stationary distribution (pi_i ~ tau_i)
    twin = IMMFilter([model, model], [[], []], tuple(model.C), R, x0, P0, DT, dwell_s=[0.6, 1.4],
                     mode_p0=[0.3, 0.7]).run(t, U, Y)
    np.testing.assert_allclose(twin.nominal_p, 0.3, rtol=1e-12)
    # any other prior follows the chain alone: mu_k = mu_0 T^k (the likelihoods are equal)
    drift = IMMFilter([model, model], [[], []], tuple(model.C), R, x0, P0, DT, dwell_s=[0.5, 2.0],
                      mode_p0=[0.3, 0.7]).run(t, U, Y)
    T = transition_matrix([0.5, 2.0], DT)
    mu = np.array([0.3, 0.7]) @ np.array([np.linalg.matrix_power(T, k) for k in range(len(t))])
    np.testing.assert_allclose(drift.nominal_p, mu[:, 0], rtol=1e-12)
    np.testing.assert_allclose(drift.x_hat, single.x_hat, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(twin.x_hat, single.x_hat, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(twin.P, single.P, rtol=1e-11, atol=1e-15)


def test_filterpy_imm_oracle():
    from filterpy.kalman import IMMEstimator, KalmanFilter

    nx, R = 4, 0.1
    base = linear_model(4, q=1e-4)
    # one sensor set, two dynamics: the second mode more damped and noisier
    models = [base, LinearDiscreteModel(0.97 / 0.99 * base.A, base.B, base.C, 4e-3 * np.eye(nx), dt=DT)]
    t, U, Y = record(models[1], 150, 6, R)
    Y = np.where(np.isfinite(Y), Y, 0.0)  # filterpy: every channel at every sample
    x0, P0 = 0.1 * np.ones(nx), np.eye(nx)
    dwell, p0 = [0.3, 0.5], np.array([0.6, 0.4])
    imm = IMMFilter(models, [[], []], tuple(models[0].C), {c: R for c in models[0].C}, x0, P0, DT, dwell_s=dwell,
                    mode_p0=p0, p_floor=0.0)
    fps = []
    for m in models:
        kf = KalmanFilter(dim_x=nx, dim_z=len(m.C), dim_u=1)
        kf.F, kf.B, kf.Q, kf.H, kf.R = m.A, m.B, m.Q, np.array(list(m.C.values())), R**2 * np.eye(len(m.C))
        kf.x, kf.P = x0.copy(), P0.copy()
        fps.append(kf)
    oracle = IMMEstimator(fps, p0.copy(), transition_matrix(dwell, DT))
    seen = []
    imm.step(t[0], U[0], None)  # the prior at the first sample (filterpy's sequence starts with a prediction)
    for k in range(1, len(t)):
        x = imm.step(t[k], U[k], Y[k])
        oracle.predict(u=U[k - 1])
        oracle.update(Y[k])
        np.testing.assert_allclose(imm.mode_p, oracle.mu, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(x, oracle.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(imm.P, oracle.P, rtol=1e-9, atol=1e-14)
        seen.append(imm.mode_p[0])
    assert np.ptp(seen) > 0.3  # the likelihoods moved the probabilities


def test_nested_mixing_entry_by_entry():
    rng = np.random.default_rng(7)
    a = rng.standard_normal((3, 3))
    b = rng.standard_normal((4, 4))
    small = Belief(rng.standard_normal(3), a @ a.T)
    big = Belief(rng.standard_normal(4), b @ b.T)
    mu, T = np.array([0.25, 0.75]), np.array([[0.9, 0.1], [0.2, 0.8]])
    c, (m0, m1) = mix(mu, T, [small, big])
    np.testing.assert_allclose(c, [0.25 * 0.9 + 0.75 * 0.2, 0.25 * 0.1 + 0.75 * 0.8])
    # into the small mode: the big mode's marginal
    w = np.array([0.25 * 0.9, 0.75 * 0.2]) / c[0]
    xm = w[0] * small.x + w[1] * big.x[:3]
    Pm = sum(wi * (P + np.outer(x - xm, x - xm)) for wi, x, P in zip(w, (small.x, big.x[:3]),
                                                                        (small.P, big.P[:3, :3])))
    np.testing.assert_allclose(m0.x, xm, rtol=1e-14)
    np.testing.assert_allclose(m0.P, Pm, rtol=1e-13)
    # into the big mode: the small mode filled with the big mode's own last component, uncorrelated
    w = np.array([0.25 * 0.1, 0.75 * 0.8]) / c[1]
    xs = np.append(small.x, big.x[3])
    Ps = np.zeros((4, 4))
    Ps[:3, :3], Ps[3, 3] = small.P, big.P[3, 3]
    xm = w[0] * xs + w[1] * big.x
    Pm = w[0] * (Ps + np.outer(xs - xm, xs - xm)) + w[1] * (big.P + np.outer(big.x - xm, big.x - xm))
    np.testing.assert_allclose(m1.x, xm, rtol=1e-14)
    np.testing.assert_allclose(m1.P, Pm, rtol=1e-13)
    # the estimate: the small mode's tail fixed at variance 0
    est = combine(mu, [small, big], [np.array([1.0]), np.empty(0)])
    xt = np.append(small.x, 1.0)
    assert est.x[3] == pytest.approx(0.25 * 1.0 + 0.75 * big.x[3])
    Pt = np.zeros((4, 4))
    Pt[:3, :3] = small.P
    Pe = 0.25 * (Pt + np.outer(xt - est.x, xt - est.x)) + 0.75 * (big.P + np.outer(big.x - est.x, big.x - est.x))
    np.testing.assert_allclose(est.P, Pe, rtol=1e-13)


def test_transition_matrix_two_state_chain():
    tau0, tau1, dt = 3.0, 0.5, 0.002
    T = transition_matrix([tau0, tau1], dt)
    a, b = 1 / tau0, 1 / tau1
    e = math.exp(-(a + b) * dt)  # the two-state chain: p01 = a / (a + b) (1 - exp(-(a + b) dt))
    np.testing.assert_allclose(T, [[1 - a / (a + b) * (1 - e), a / (a + b) * (1 - e)],
                                   [b / (a + b) * (1 - e), 1 - b / (a + b) * (1 - e)]], rtol=1e-12)
    assert transition_matrix([1.0], dt).tolist() == [[1.0]]


def test_bad_settings_name_the_argument():
    model = linear_model(0)
    R = {c: 0.1 for c in model.C}
    with pytest.raises(ValueError, match="mode_p0"):
        IMMFilter([model, model], [[], []], tuple(model.C), R, np.zeros(4), np.eye(4), DT, dwell_s=[1, 1],
                  mode_p0=[0.5, 0.6])
    with pytest.raises(ValueError, match="tails"):
        IMMFilter([model, model], [[1.0], []], tuple(model.C), R, np.zeros(4), np.eye(4), DT, dwell_s=[1, 1],
                  mode_p0=[0.5, 0.5])
    with pytest.raises(ValueError, match="dwell_s"):
        IMMFilter([model], [[]], tuple(model.C), R, np.zeros(4), np.eye(4), DT, dwell_s=[0.0], mode_p0=[1.0])


# ------------------------------------------------------------------------------------------ the payload estimator
def test_payload_imm_on_the_sixbar_reports_its_combination():
    """``estimator="imm"``: the nominal mode is the plain EKF's model (its own instance), the payload mode the payload
    EKF's; the reported payload scale is ``mu_0 * 1 + mu_1 * theta_1`` and the nominal mode's probability is the
    result's ``nominal_p``; the smoother is refused with a one-line error."""
    from pathlib import Path

    from exuflex.errors import UsageError
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.session import IMM_DWELL_MANOEUVRES, ObserverConfig, estimate, make_observer
    from exuflex.runs import read_run

    root = Path(__file__).resolve().parents[1]
    mech = load_mechanism(root / "models" / "sixbar.toml")
    run = read_run(root / "tests" / "data" / "sixbar_erls_3s")
    obs = make_observer(mech, ObserverConfig(estimator="imm", payload_nominal_p=0.3))
    imm = obs.ekf
    assert isinstance(imm, IMMFilter) and imm.models[1] is obs.ekf.model and imm.models[0] is not obs.model
    np.testing.assert_array_equal(imm.mode_p0, [0.3, 0.7])
    np.testing.assert_allclose(imm.dwell_s, IMM_DWELL_MANOEUVRES * mech.manoeuvre.duration)
    S = run.sensors
    k = np.searchsorted(S.t, 0.4)
    U, Y = S.select(mech.motor_names).data[:k], S.select(obs.channels).data[:k]
    res = estimate(obs, S.t[:k], U, Y).result
    it = obs.ekf.model.i_theta
    assert np.all((0 <= res.nominal_p) & (res.nominal_p <= 1)) and np.ptp(res.nominal_p) > 0.1
    mu, theta1 = imm.mode_p, imm._beliefs[1].x[it]
    assert res.nominal_p[-1] == mu[0]
    assert res.x_hat[-1, it] == pytest.approx(mu[0] * 1.0 + mu[1] * theta1, rel=1e-14)
    assert res.P[-1, it] == pytest.approx(mu[1] * imm._beliefs[1].P[it, it] + mu[0] * mu[1] * (theta1 - 1) ** 2,
                                          rel=1e-12)
    with pytest.raises(UsageError, match="no smoother"):
        estimate(obs, S.t[:k], U, Y, smooth=True)


def test_cli_refuses_smoothing_the_imm(capsys):
    """``exuflex observe --estimator imm --smooth``: a one-line usage error before anything is built."""
    from pathlib import Path

    from exuflex.cli import main

    root = Path(__file__).resolve().parents[1]
    rc = main(["observe", str(root / "models" / "sixbar.toml"), str(root / "tests" / "data" / "sixbar_erls_3s"),
               "--estimator", "imm", "--smooth"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--smooth" in err[0] and "not imm" in err[0]

"""The interacting multiple-model filter (:mod:`exuflex.observer.imm`): its algebra, not only that it runs.

- one mode: the IMM is that mode's EKF (:class:`MultirateEKF`), estimates and covariances bit for bit, with gaps,
  partial samples and the gate;
- two identical modes: the mode probabilities stay at their prior and the estimate is the single filter's;
- filterpy's ``IMMEstimator`` on a linear two-mode system: the mode probabilities, the mixed and combined
  estimates to rounding;
- mixing over nested state spaces (unbiased mixing) entry by entry against its definition, and the transition
  matrix against the two-state Markov chain's closed form;
- the smoother (:meth:`IMMFilter.smooth`): one mode (also one of two nested modes, held with probability 1) and
  identical modes are the RTS smoother to rounding; written out independently (a textbook IMM pass, each mode's
  chain by the RTS recursion, Kim's probabilities) on a linear system; held against the exact posterior over every
  mode sequence of a record (Gaussian sums, one Kalman smoother per sequence).
"""

from __future__ import annotations

import itertools
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
    result's ``nominal_p``; the smoother's mode probabilities sum to 1 and it narrows the start's uncertainty."""
    from pathlib import Path

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
    sm = estimate(obs, S.t[:k], U, Y, smooth=True).smoothed
    np.testing.assert_allclose(sm.mode_p.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(sm.nominal_p, sm.mode_p[:, 0])
    np.testing.assert_array_equal(sm.x_hat[-1], res.x_hat[-1])  # smoothed = filtered at the last sample
    # the later samples narrow every coordinate's uncertainty at the start
    assert np.all(sm.P_diag[0, :3] < 0.5 * res.P[0, :3])


@pytest.mark.slow
def test_cli_smooths_the_imm(tmp_path, capsys):
    """``exuflex observe --estimator imm --smooth``: smoothed estimates scored against the smoothed bound (its
    computation along the truth takes about a minute)."""
    import json
    from pathlib import Path

    from exuflex.cli import main

    root = Path(__file__).resolve().parents[1]
    rc = main(["observe", str(root / "models" / "sixbar.toml"), str(root / "tests" / "data" / "sixbar_erls_3s"),
               "--estimator", "imm", "--smooth", "--out", str(tmp_path), "--no-plots"])
    assert rc == 0, capsys.readouterr().err
    s = json.loads((tmp_path / "result.json").read_text())
    assert s["smoothed"] and s["bound_for"]["smoothed"] and "smoothed posterior" in s["bound_kind"]
    # the smoother's errors below the filter's on every joint coordinate
    assert all(s["rms_error"][k] < s["filtered_rms_error"][k] for k in ("q1", "q2", "q3"))


# ------------------------------------------------------------------------------------------ the smoother
def test_one_mode_smoother_is_the_rts_smoother():
    """The modified Bryson-Frazier recursion and the RTS recursion agree to rounding on one chain."""
    from exuflex.observer.smoother import rts_smooth

    model = linear_model(0)
    t, U, Y = record(model, 300, 1)
    R = {c: 0.1 for c in model.C}
    x0, P0 = np.zeros(model.nx), np.eye(model.nx)
    rts = rts_smooth(MultirateEKF(model, tuple(model.C), R, x0, P0, dt=DT), t, U, Y)
    one = IMMFilter([model], [[]], tuple(model.C), R, x0, P0, DT, dwell_s=[1.0], mode_p0=[1.0]).smooth(t, U, Y)
    np.testing.assert_allclose(one.x_hat, rts.x_hat, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(one.P, rts.P, rtol=1e-9, atol=1e-14)
    np.testing.assert_array_equal(one.mode_p, 1.0)
    # identical modes: the same smoother, to rounding, and the chain's own probabilities
    twin = IMMFilter([model, model], [[], []], tuple(model.C), R, x0, P0, DT, dwell_s=[0.6, 1.4],
                     mode_p0=[0.3, 0.7]).smooth(t, U, Y)
    np.testing.assert_allclose(twin.x_hat, rts.x_hat, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(twin.P, rts.P, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(twin.mode_p, [[0.3, 0.7]] * len(t), rtol=1e-12)
    # nested modes, the larger one held with probability 1 (no switching within the record): its RTS smoother
    big = LinearDiscreteModel(np.pad(model.A, ((0, 1), (0, 1))) + np.diag([0.0] * model.nx + [1.0]),
                              np.vstack([model.B, [[0.0]]]), {c: np.append(r, 0.5) for c, r in model.C.items()},
                              np.pad(model.Q, ((0, 1), (0, 1))) + np.diag([0.0] * model.nx + [1e-4]), dt=DT)
    xb, Pb = np.zeros(big.nx), np.eye(big.nx)
    rts = rts_smooth(MultirateEKF(big, tuple(big.C), R, xb, Pb, dt=DT), t, U, Y)
    held = IMMFilter([model, big], [[1.0], []], tuple(model.C), R, xb, Pb, DT, dwell_s=[1e300, 1e300],
                     mode_p0=[0.0, 1.0]).smooth(t, U, Y)
    np.testing.assert_array_equal(held.mode_p[:, 1], 1.0)
    np.testing.assert_allclose(held.x_hat, rts.x_hat, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(held.P, rts.P, rtol=1e-9, atol=1e-14)


def exact_posterior(models, T, mu0, x0, P0, U, Y, Rv):
    """The smoothed posterior of a linear switching system, exactly: a Kalman filter and RTS smoother per mode
    sequence (all ``K**n`` of them, batched), each weighted by its prior probability times its likelihood; the
    posterior mean, covariance (the Gaussian sum's moments) and mode probabilities per sample."""
    n, K = len(Y), len(models)
    seqs = np.array(list(itertools.product(range(K), repeat=n)))
    H = np.array(list(models[0].C.values()))
    A, B, Q = (np.array([getattr(m, a) for m in models]) for a in "ABQ")
    lw = np.log(mu0[seqs[:, 0]]) + np.log(T[seqs[:, :-1], seqs[:, 1:]]).sum(axis=1)
    x, P = np.tile(x0, (len(seqs), 1)), np.tile(P0, (len(seqs), 1, 1))
    xf, Pf, xp, Pp, F = [], [], [None], [None], [None]
    for k in range(n):
        if k:
            a = A[seqs[:, k]]
            x, P = np.einsum("sij,sj->si", a, x) + B[seqs[:, k]] @ U[k - 1], a @ P @ a.transpose(0, 2, 1) + Q[seqs[:, k]]
            xp.append(x), Pp.append(P), F.append(a)
        S = H @ P @ H.T + Rv * np.eye(len(H))
        r, Si = Y[k] - x @ H.T, np.linalg.inv(S)
        lw -= 0.5 * (np.einsum("si,sij,sj->s", r, Si, r) + np.linalg.slogdet(2 * np.pi * S)[1])
        G = P @ H.T @ Si
        x, P = x + np.einsum("sij,sj->si", G, r), P - G @ S @ G.transpose(0, 2, 1)
        xf.append(x), Pf.append(P)
    xs, Ps = [*xf[:-1], xf[-1]], [*Pf[:-1], Pf[-1]]
    for k in range(n - 2, -1, -1):
        C = Pf[k] @ F[k + 1].transpose(0, 2, 1) @ np.linalg.inv(Pp[k + 1])
        xs[k] = xf[k] + np.einsum("sij,sj->si", C, xs[k + 1] - xp[k + 1])
        Ps[k] = Pf[k] + C @ (Ps[k + 1] - Pp[k + 1]) @ C.transpose(0, 2, 1)
    w = np.exp(lw - lw.max())
    w /= w.sum()
    X, PS = np.stack(xs, 1), np.stack(Ps, 1)
    m = np.einsum("s,skn->kn", w, X)
    d = X - m
    Pm = np.einsum("s,sknm->knm", w, PS) + np.einsum("s,skn,skm->knm", w, d, d)
    return m, Pm, np.stack([np.bincount(seqs[:, k], weights=w, minlength=K) for k in range(n)])


def smoother_case(dwell: float, seed: int, n: int = 12) -> list[float]:
    """One record of a two-mode linear switching system (a nearly deterministic and a noisy, damped mode, each
    dwelling ``dwell`` s on average) smoothed by the IMM and exactly: the largest error of the smoothed means in the
    exact posterior's standard deviations, of the standard deviations relative, of the mode probabilities, and the
    filter's mean error in the same units (``benchmarks/imm.py --smoother`` tabulates them)."""
    Rv, B, C = 0.05, np.array([[0.0], [0.1]]), {"c0": np.array([1.0, 0.0])}
    models = [LinearDiscreteModel(np.array([[1, 0.1], [0, 1]]), B, C, np.diag([1e-4, 1e-4])),
              LinearDiscreteModel(np.array([[1, 0.1], [-0.5, 0.8]]), B, C, np.diag([1e-3, 0.3]))]
    mu0, T = np.array([0.5, 0.5]), transition_matrix([dwell, dwell], DT)
    x0, P0 = np.zeros(2), np.eye(2)
    rng = np.random.default_rng(seed)
    U = rng.standard_normal((n, 1))
    x, s, Y = rng.standard_normal(2), rng.choice(2, p=mu0), np.empty((n, 1))
    for k in range(n):
        if k:
            s = rng.choice(2, p=T[s])
            x = models[s].A @ x + B @ U[k - 1] + np.sqrt(np.diag(models[s].Q)) * rng.standard_normal(2)
        Y[k] = x[0] + math.sqrt(Rv) * rng.standard_normal()
    imm = IMMFilter(models, [[], []], ("c0",), {"c0": math.sqrt(Rv)}, x0, P0, DT, dwell_s=[dwell, dwell],
                    mode_p0=mu0, p_floor=0.0)
    sm = imm.smooth(np.arange(n) * DT, U, Y)
    np.testing.assert_allclose(sm.mode_p.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    m, P, mu = exact_posterior(models, T, mu0, x0, P0, U, Y, Rv)
    sd = np.sqrt(np.diagonal(P, axis1=1, axis2=2))
    return [float(np.abs((sm.x_hat - m) / sd).max()), float(np.abs(np.sqrt(sm.P_diag) / sd - 1).max()),
            float(np.abs(sm.mode_p - mu).max()), float(np.abs((sm.x_filt - m) / sd).max())]


def test_smoother_against_the_exact_posterior():
    """Dwell times of 5 s, ten records of 12 samples (:func:`smoother_case`): the smoothed means within 0.2 of the
    exact posterior's standard deviation (the filter's are off by more than one: it has not seen the later samples),
    the standard deviations within 25 %, the mode probabilities within 0.05 of the exact ones and summing to 1.
    (Kim's approximation grows as the dwell time shrinks towards the sample interval: docs/imm.md.)"""
    worst = np.max([smoother_case(5.0, seed) for seed in range(10)], axis=0)
    assert worst[0] < 0.2 and worst[1] < 0.25 and worst[2] < 0.05 and worst[3] > 1.0, worst


def test_smoother_written_out():
    """The smoother written out on a linear two-mode system from a textbook IMM pass: Kim's mode probabilities, each
    mode's chain by the RTS recursion (gain ``P_k A' Pp^-1`` with ``Pp`` the prediction from the mixed start), the
    estimate their combination; the same to rounding."""
    n, Rv = 12, 0.05
    models = [linear_model(8, nx=3, m=2, q=1e-4), linear_model(9, nx=3, m=2, q=3e-2)]
    models[1].C = models[0].C
    mu0, dwell = np.array([0.4, 0.6]), [0.2, 0.1]
    T = transition_matrix(dwell, DT)
    rng = np.random.default_rng(10)
    U, Y = rng.standard_normal((n, 1)), rng.standard_normal((n, 2))
    H, K = np.array(list(models[0].C.values())), len(models)
    X, P, XP, PP, MU = [], [], [None], [None], []
    x, Pm, mu = [np.zeros(3)] * K, [np.eye(3)] * K, mu0
    for k in range(n):
        c = mu @ T if k else mu
        if k:
            W = T * mu[:, None] / c
            mixed = [(sum(W[i, j] * X[-1][i] for i in range(K)), j) for j in range(K)]
            Pm = [models[j].A @ sum(W[i, j] * (P[-1][i] + np.outer(X[-1][i] - xm, X[-1][i] - xm)) for i in range(K))
                  @ models[j].A.T + models[j].Q for xm, j in mixed]
            x = [models[j].A @ xm + models[j].B @ U[k - 1] for xm, j in mixed]
            XP.append(list(x)), PP.append(list(Pm))
        L = np.empty(K)
        for j in range(K):
            S = H @ Pm[j] @ H.T + Rv * np.eye(2)
            r = Y[k] - H @ x[j]
            G = Pm[j] @ H.T @ np.linalg.inv(S)
            L[j] = np.exp(-0.5 * r @ np.linalg.solve(S, r)) / np.sqrt(np.linalg.det(2 * np.pi * S))
            x[j], Pm[j] = x[j] + G @ r, Pm[j] - G @ S @ G.T
        mu = c * L / (c @ L)
        X.append(list(x)), P.append(list(Pm)), MU.append(mu)
    xs, Ps, ms = X[-1], P[-1], MU[-1]
    est = [sum(ms[i] * xs[i] for i in range(K))]
    for k in range(n - 2, -1, -1):
        ms = (T * MU[k][:, None] / (MU[k] @ T)) @ ms
        G = [P[k][i] @ models[i].A.T @ np.linalg.inv(PP[k + 1][i]) for i in range(K)]
        xs = [X[k][i] + G[i] @ (xs[i] - XP[k + 1][i]) for i in range(K)]
        Ps = [P[k][i] + G[i] @ (Ps[i] - PP[k + 1][i]) @ G[i].T for i in range(K)]
        est.insert(0, sum(ms[i] * xs[i] for i in range(K)))
        MU[k] = ms
    imm = IMMFilter(models, [[], []], tuple(models[0].C), {c: math.sqrt(Rv) for c in models[0].C}, np.zeros(3),
                    np.eye(3), DT, dwell_s=dwell, mode_p0=mu0, p_floor=0.0)
    sm = imm.smooth(np.arange(n) * DT, U, Y)
    np.testing.assert_allclose(sm.mode_p, MU, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(sm.x_hat, est, rtol=1e-9, atol=1e-12)
    assert np.ptp(sm.mode_p[:, 0]) > 0.1  # the measurements moved the probabilities

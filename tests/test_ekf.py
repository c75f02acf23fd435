"""Tests of the model-agnostic multirate EKF (exuflex.observer) on toy models, against independent oracles.

Toy models (defined here, independent of the flexible-multibody model):
- a linear 2-mass spring-damper, discretised exactly (expm), on which the EKF is an ordinary Kalman filter
  (oracles: a textbook Kalman filter written here and filterpy's ``KalmanFilter``);
- the same in continuous time, discretised per interval, for irregular sampling;
- a 13-mass chain (26 states) against filterpy;
- a nonlinear damped pendulum integrated with RK4 sub-steps and an exact (forward-sensitivity) Jacobian.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy.linalg import expm

from exuflex.observer import (
    DiscreteModel,
    FilterDivergedError,
    LinearDiscreteModel,
    Measurement,
    MultirateEKF,
    NISMonitor,
    Prediction,
)
from exuflex.observer.ekf import Monitoring
from exuflex.scoring import bound_rms, linearise, steady_state_covariance
from exuflex.scoring.bound import van_loan
from exuflex.scoring.stats import chi2_band, eq21_stats, fft_peaks, match_peaks, max_error, mc_consistency, nees, nis, rms_error

DT = 1 / 500


def zoh_torque_noise(Gamma, sigma_tau, extra_diag=None) -> np.ndarray:
    """``Q = Gamma diag(sigma_tau^2) Gamma' (+ diag(extra_diag))``: zero-order-held torque noise of the toy models
    through their discrete input matrix ``Gamma`` (a vector for one input)."""
    Gamma = np.asarray(Gamma, float)
    Gamma = Gamma[:, None] if Gamma.ndim == 1 else Gamma
    Q = (Gamma * np.broadcast_to(np.asarray(sigma_tau, float) ** 2, (Gamma.shape[1],))) @ Gamma.T
    if extra_diag is not None:
        Q = Q + np.diag(np.broadcast_to(np.asarray(extra_diag, float), (Q.shape[0],)))
    return 0.5 * (Q + Q.T)


# ----------------------------------------------------------------------------------------------- toy models
def chain_continuous(masses, springs, dampers):
    """Continuous (A_c, B_c) of a chain of masses tied to the ground by the first spring; force on mass 1."""
    n = len(masses)
    K = np.zeros((n, n))
    C = np.zeros((n, n))
    for i, (k, c) in enumerate(zip(springs, dampers)):
        # spring i links mass i-1 (ground for i = 0) and mass i
        K[i, i] += k
        C[i, i] += c
        if i > 0:
            K[i - 1, i - 1] += k
            K[i - 1, i] -= k
            K[i, i - 1] -= k
            C[i - 1, i - 1] += c
            C[i - 1, i] -= c
            C[i, i - 1] -= c
    Minv = np.diag(1 / np.asarray(masses, float))
    A_c = np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ K, -Minv @ C]])
    B_c = np.zeros((2 * n, 1))
    B_c[n, 0] = 1 / masses[0]
    return A_c, B_c


def zoh(A_c, B_c, dt):
    n, nu = B_c.shape
    M = np.zeros((n + nu, n + nu))
    M[:n, :n] = A_c
    M[:n, n:] = B_c
    E = expm(M * dt)
    return E[:n, :n], E[:n, n:]


SIGMA_F = 0.5  # N, held force noise


def two_mass(k_scale=1.0, q_scale=1.0):
    A_c, B_c = chain_continuous([1.0, 0.5], [400.0 * k_scale, 200.0 * k_scale], [0.6, 0.3])
    A, Gam = zoh(A_c, B_c, DT)
    Q = q_scale * zoh_torque_noise(Gam, SIGMA_F, extra_diag=[1e-12, 1e-12, 1e-9, 1e-9])
    C = {"x1": [1, 0, 0, 0], "x2": [0, 1, 0, 0], "v2": [0, 0, 0, 1]}
    return LinearDiscreteModel(A, Gam, C, Q, dt=DT)


CH2 = ("x1", "x2", "v2")
R2 = {"x1": 2e-4, "x2": 5e-4, "v2": 2e-2}
X0_2 = np.array([0.01, 0.0, 0.0, 0.05])
P0_2 = np.diag([1e-4, 1e-4, 1e-2, 1e-2])


def chain26():
    n = 13
    A_c, B_c = chain_continuous(np.full(n, 0.2), np.full(n, 3e3), np.full(n, 0.5))
    A, Gam = zoh(A_c, B_c, DT)
    Q = zoh_torque_noise(Gam, 0.3, extra_diag=1e-12)
    C = {}
    for j, i in enumerate((0, 6, 12)):
        r = np.zeros(2 * n)
        r[i] = 1
        C[f"x{i}"] = r
    r = np.zeros(2 * n)
    r[n + 12] = 1
    C["v12"] = r
    return LinearDiscreteModel(A, Gam, C, Q, dt=DT)


def simulate_linear(model: LinearDiscreteModel, channels, R_std, x0, P0, n, rng, rates=None, p_drop=0.0):
    """Truth and noisy multirate measurements of a linear model.

    ``rates[c] = r`` keeps channel c only every r-th sample; ``p_drop`` drops whole samples at random.
    """
    nx = model.nx
    Lq = np.linalg.cholesky(model.Q + 1e-30 * np.eye(nx))
    H = np.array([model.C[c] for c in channels])
    r_std = np.array([R_std[c] for c in channels])
    t = np.arange(n) * DT
    U = 2.0 * np.sin(2 * np.pi * 1.5 * t)[:, None]
    X = np.empty((n, nx))
    x = x0 + np.linalg.cholesky(P0) @ rng.standard_normal(nx)
    for k in range(n):
        X[k] = x
        x = model.A @ x + model.B @ U[k] + Lq @ rng.standard_normal(nx)
    Y = X @ H.T + r_std * rng.standard_normal((n, len(channels)))
    for j, c in enumerate(channels):
        r = (rates or {}).get(c, 1)
        if r > 1:
            Y[np.arange(n) % r != 0, j] = np.nan
    if p_drop:
        Y[rng.random(n) < p_drop] = np.nan
    return t, U, X, Y


class Pendulum:
    """Damped pendulum driven by a torque, RK4 sub-steps with exact forward-sensitivity Jacobians.

    State ``[theta, omega]``; ``theta'' = -(g/l) sin(theta) - c omega + u / (m l^2)``. Channels: ``bob_x``
    (``l sin theta``), ``bob_y`` (``-l cos theta``), ``omega`` (gyro).
    """

    nx = 2

    def __init__(self, g=9.81, l=0.5, m=1.0, c=0.2, n_sub=5, sigma_tau=0.05):
        self.g, self.l, self.m, self.c, self.n_sub, self.sigma_tau = g, l, m, c, n_sub, sigma_tau

    def _f(self, x, u):
        th, om = x
        return np.array([om, -(self.g / self.l) * np.sin(th) - self.c * om + u / (self.m * self.l**2)])

    def _jx(self, x):
        return np.array([[0.0, 1.0], [-(self.g / self.l) * np.cos(x[0]), -self.c]])

    def step_full(self, x, u, dt):
        """x_next, F = dx_next/dx, Gamma = dx_next/du (RK4 differentiated stage by stage)."""
        u = float(np.atleast_1d(u)[0]) if u is not None else 0.0
        h = dt / self.n_sub
        ju = np.array([0.0, 1 / (self.m * self.l**2)])
        F = np.eye(2)
        G = np.zeros(2)
        x = np.array(x, float)
        for _ in range(self.n_sub):
            k1 = self._f(x, u)
            J1 = self._jx(x)
            d1x, d1u = J1 @ F, J1 @ G + ju
            x2 = x + 0.5 * h * k1
            k2 = self._f(x2, u)
            J2 = self._jx(x2)
            d2x, d2u = J2 @ (F + 0.5 * h * d1x), J2 @ (G + 0.5 * h * d1u) + ju
            x3 = x + 0.5 * h * k2
            k3 = self._f(x3, u)
            J3 = self._jx(x3)
            d3x, d3u = J3 @ (F + 0.5 * h * d2x), J3 @ (G + 0.5 * h * d2u) + ju
            x4 = x + h * k3
            k4 = self._f(x4, u)
            J4 = self._jx(x4)
            d4x, d4u = J4 @ (F + h * d3x), J4 @ (G + h * d3u) + ju
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            F = F + h / 6 * (d1x + 2 * d2x + 2 * d3x + d4x)
            G = G + h / 6 * (d1u + 2 * d2u + 2 * d3u + d4u)
        return x, F, G

    def predict(self, x, u, dt, u_next=None):
        xn, F, G = self.step_full(x, u, dt)
        return Prediction(xn, F, zoh_torque_noise(G, self.sigma_tau, extra_diag=1e-14))

    def measure(self, x, channels):
        th, om = x
        rows = {
            "bob_x": (self.l * np.sin(th), [self.l * np.cos(th), 0.0]),
            "bob_y": (-self.l * np.cos(th), [self.l * np.sin(th), 0.0]),
            "omega": (om, [0.0, 1.0]),
        }
        y = np.array([rows[c][0] for c in channels])
        H = np.array([rows[c][1] for c in channels]).reshape(len(channels), 2)
        return Measurement(y, H)


class ContinuousLinear:
    """``x' = A_c x + B_c u`` with white force noise held over each interval, discretised exactly for whatever
    interval the filter asks (irregular sampling)."""

    def __init__(self, A_c, B_c, C, sigma):
        self.A_c, self.B_c, self.C, self.sigma = A_c, B_c, C, sigma
        self.nx = A_c.shape[0]

    def maps(self, dt):
        A, Gam = zoh(self.A_c, self.B_c, dt)
        return A, Gam, zoh_torque_noise(Gam, self.sigma, extra_diag=1e-14)

    def predict(self, x, u, dt, u_next=None):
        A, Gam, Q = self.maps(dt)
        return Prediction(A @ x + Gam @ np.atleast_1d(0.0 if u is None else u), A, Q)

    def measure(self, x, channels):
        H = np.array([self.C[c] for c in channels], float)
        return Measurement(H @ x, H)


# ----------------------------------------------------------------------------------------------- helpers
def hand_kf(model, channels, R_std, x0, P0, U, Y):
    """Textbook linear Kalman filter (prior at the first sample, predict with the previous input)."""
    x, P = x0.copy(), P0.copy()
    H_all = np.array([model.C[c] for c in channels])
    r2 = np.array([R_std[c] for c in channels]) ** 2
    out = np.empty((len(Y), model.nx))
    for k in range(len(Y)):
        if k:
            x = model.A @ x + model.B @ U[k - 1]
            P = model.A @ P @ model.A.T + model.Q
        idx = np.flatnonzero(np.isfinite(Y[k]))
        if len(idx):
            H, R = H_all[idx], np.diag(r2[idx])
            S = H @ P @ H.T + R
            K = np.linalg.solve(S, H @ P).T
            x = x + K @ (Y[k, idx] - H @ x)
            P = (np.eye(model.nx) - K @ H) @ P
            P = 0.5 * (P + P.T)
        out[k] = x
    return out, P


def filterpy_kf(model, channels, R_std, x0, P0, U, Y):
    kf = KalmanFilter(dim_x=model.nx, dim_z=len(channels), dim_u=1)
    kf.x, kf.P, kf.F, kf.B, kf.Q = x0.copy(), P0.copy(), model.A, model.B, model.Q
    H_all = np.array([model.C[c] for c in channels])
    r2 = np.array([R_std[c] for c in channels]) ** 2
    out = np.empty((len(Y), model.nx))
    for k in range(len(Y)):
        if k:
            kf.predict(u=U[k - 1])
        idx = np.flatnonzero(np.isfinite(Y[k]))
        if len(idx):
            kf.update(Y[k, idx], R=np.diag(r2[idx]), H=H_all[idx])
        out[k] = kf.x
    return out


@pytest.fixture(scope="module")
def multirate_data():
    model = two_mass()
    rng = np.random.default_rng(1)
    t, U, X, Y = simulate_linear(
        model, CH2, R2, X0_2, P0_2, 1500, rng, rates={"x2": 5, "v2": 10}, p_drop=0.05
    )
    return model, t, U, X, Y


# ----------------------------------------------------------------------------------------------- (a)
def test_linear_ekf_equals_kalman_filter(multirate_data):
    """On a linear model the compiled filter core is an ordinary Kalman filter: the same estimates as two
    independent implementations (a textbook filter, filterpy's) to rounding."""
    model, t, U, X, Y = multirate_data
    assert isinstance(model, DiscreteModel)
    ekf = MultirateEKF(model, CH2, R2, X0_2, P0_2, DT, store_P="full")
    res = ekf.run(t, U, Y)
    ref, P_ref = hand_kf(model, CH2, R2, X0_2, P0_2, U, Y)
    ref_fp = filterpy_kf(model, CH2, R2, X0_2, P0_2, U, Y)
    scale = np.abs(ref).max(axis=0)
    assert np.all(np.abs(res.x_hat - ref) <= 1e-12 * scale)
    assert np.all(np.abs(res.x_hat - ref_fp) <= 1e-12 * scale)
    np.testing.assert_allclose(res.P[-1], P_ref, rtol=1e-10, atol=1e-14 * np.abs(P_ref).max())


# ----------------------------------------------------------------------------------------------- (b)
def test_run_equals_online_step_exactly(multirate_data):
    model, t, U, X, Y = multirate_data
    res = MultirateEKF(model, CH2, R2, X0_2, P0_2, DT).run(t, U, Y)
    online = MultirateEKF(model, CH2, R2, X0_2, P0_2, DT)
    xs = np.array([online.step(t[k], U[k], Y[k]) for k in range(len(t))])
    assert np.array_equal(xs, res.x_hat)
    assert online.n_missing == res.n_missing and online.n_updates == res.n_updates
    # run() resets: a second run gives the same result
    again = MultirateEKF(model, CH2, R2, X0_2, P0_2, DT)
    again.run(t, U, Y)
    assert np.array_equal(again.run(t, U, Y).x_hat, res.x_hat)


def test_compiled_core_equals_filterpy_on_26_states():
    """The compiled core against filterpy's Kalman filter (Joseph-form update) on a 26-state chain with
    multirate and dropped samples: estimates, covariances and NIS to rounding."""
    model = chain26()
    ch = tuple(model.C)
    R = dict(zip(ch, [1e-5, 1e-5, 1e-5, 1e-3]))
    x0 = np.zeros(26)
    P0 = np.eye(26) * 1e-4
    rng = np.random.default_rng(7)
    t, U, X, Y = simulate_linear(model, ch, R, x0, P0, 300, rng, rates={"v12": 3}, p_drop=0.05)
    a = MultirateEKF(model, ch, R, x0, P0, DT, store_P="full").run(t, U, Y)
    kf = KalmanFilter(dim_x=26, dim_z=len(ch), dim_u=1)
    kf.x, kf.P, kf.F, kf.B, kf.Q = x0.copy(), P0.copy(), model.A, model.B, model.Q
    H_all = np.array([model.C[c] for c in ch])
    r2 = np.array([R[c] for c in ch]) ** 2
    for k in range(len(t)):
        if k:
            kf.predict(u=U[k - 1])
        idx = np.flatnonzero(np.isfinite(Y[k]))
        if len(idx):
            kf.update(Y[k, idx], R=np.diag(r2[idx]), H=H_all[idx])
            assert a.nis[k] == pytest.approx(float(kf.y @ kf.SI @ kf.y), rel=1e-8)
        scale = np.abs(kf.x).max() + 1e-12
        assert np.all(np.abs(a.x_hat[k] - kf.x) <= 1e-9 * scale), k
        np.testing.assert_allclose(a.P[k], 0.5 * (kf.P + kf.P.T), rtol=1e-8, atol=1e-10 * np.abs(kf.P).max())


def test_irregular_sampling_is_the_kalman_filter_of_each_interval():
    """Time stamps with jitter and a gap: every interval is predicted over its own length (a textbook filter with
    the exact discretisation per interval is the oracle), and the skipped samples are counted."""
    A_c, B_c = chain_continuous([1.0, 0.5], [400.0, 200.0], [0.6, 0.3])
    C = {"x1": [1, 0, 0, 0], "x2": [0, 1, 0, 0], "v2": [0, 0, 0, 1]}
    model = ContinuousLinear(A_c, B_c, C, SIGMA_F)
    rng = np.random.default_rng(4)
    n = 400
    t = np.arange(n) * DT + rng.uniform(-0.2e-3, 0.2e-3, n)
    t[200:] += 5 * DT  # a gap of five samples
    U = np.sin(2 * np.pi * t)[:, None]
    Y = 1e-3 * rng.standard_normal((n, 3))
    res = MultirateEKF(model, CH2, R2, X0_2, P0_2, DT, store_P="full").run(t, U, Y)
    x, P = X0_2.copy(), P0_2.copy()
    H = np.array([C[c] for c in CH2], float)
    Rm = np.diag([R2[c] ** 2 for c in CH2])
    for k in range(n):
        if k:
            A, Gam, Q = model.maps(t[k] - t[k - 1])
            x, P = A @ x + Gam @ U[k - 1], A @ P @ A.T + Q
        S = H @ P @ H.T + Rm
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ (Y[k] - H @ x)
        I_KH = np.eye(4) - K @ H
        P = I_KH @ P @ I_KH.T + K @ Rm @ K.T
        np.testing.assert_allclose(res.x_hat[k], x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.P[-1], P, rtol=1e-8)
    assert res.n_missing == 5


# ----------------------------------------------------------------------------------------------- (c)
def test_nan_samples_are_predictions_only_and_counted():
    model = two_mass()
    rng = np.random.default_rng(3)
    t, U, X, Y = simulate_linear(model, CH2, R2, X0_2, P0_2, 200, rng, rates={"v2": 4})
    Y[50:60] = np.nan
    Y[100] = np.nan
    ekf = MultirateEKF(model, CH2, R2, X0_2, P0_2, DT, store_P="full")
    res = ekf.run(t, U, Y)
    assert res.n_missing == 11 and res.n_updates == 189
    assert np.all(np.isnan(res.nis[50:60])) and np.all(res.nis_dof[50:60] == 0)
    assert np.all(np.isnan(res.innovations[50:60]))
    # a missing sample is exactly the prediction from the previous posterior
    for k in (50, 55, 100):
        assert np.allclose(res.x_hat[k], model.A @ res.x_hat[k - 1] + model.B @ U[k - 1], rtol=0, atol=1e-15)
        P_pred = model.A @ res.P[k - 1] @ model.A.T + model.Q
        np.testing.assert_allclose(res.P[k], P_pred, rtol=1e-13)
    # partial samples use only the finite channels
    assert set(res.nis_dof[:50]) == {2, 3}
    assert np.all(np.isfinite(res.innovations[0:50:4][:, 2]))  # v2 every 4th sample
    assert np.all(np.isnan(res.innovations[1:50:4][:, 2]))
    # time must advance, by at most max_gap; the input must be finite
    online = MultirateEKF(model, CH2, R2, X0_2, P0_2, DT, max_gap=0.5)
    online.step(t[0], U[0], Y[0])
    with pytest.raises(ValueError, match="not after the previous"):
        online.step(t[0], U[0], Y[0])
    with pytest.raises(ValueError, match="max_gap"):
        online.step(t[0] + 1e6, U[0], Y[0])
    with pytest.raises(ValueError, match="not finite"):
        online.step(t[1], [np.nan], Y[1])
    # an infinite reading is refused (issue 31: not taken as "not sampled"; NaN says that), the filter unchanged
    Yi = Y[1].copy()
    Yi[0] = np.inf
    with pytest.raises(ValueError, match=r"y: channel\(s\) \['x1'\] infinite"):
        online.step(t[1], U[1], Yi)
    online.step(t[1], U[1], Y[1])


# ----------------------------------------------------------------------------------------------- (d)
def test_nees_nis_consistent_over_monte_carlo():
    model = two_mass()
    n_runs, n = 50, 250
    E, NI, DOF = [], [], []
    for seed in range(n_runs):
        rng = np.random.default_rng(100 + seed)
        t, U, X, Y = simulate_linear(
            model, CH2, R2, X0_2, P0_2, n, rng, rates={"x2": 2, "v2": 5}, p_drop=0.02
        )
        res = MultirateEKF(model, CH2, R2, X0_2, P0_2, DT, store_P="full").run(t, U, Y)
        E.append(nees(X - res.x_hat, res.P))
        if seed == 0:  # the stats helper recomputes the filter's NIS from innovations and S
            v, d = nis(res.innovations, res.S)
            np.testing.assert_allclose(v, res.nis, rtol=1e-9)
            assert np.array_equal(d, res.nis_dof)
        NI.append(res.nis)
        DOF.append(res.nis_dof)
    c_nees = mc_consistency(np.array(E), 4)
    c_nis = mc_consistency(np.array(NI), np.array(DOF))
    assert c_nees.fraction_inside > 0.9, c_nees.fraction_inside
    assert c_nis.fraction_inside > 0.9, c_nis.fraction_inside
    assert c_nis.time_avg_inside, (c_nis.time_avg, c_nis.time_avg_lo, c_nis.time_avg_hi)
    assert abs(c_nees.time_avg / 4 - 1) < 0.05
    lo, hi = chi2_band(50 * 4, 50)
    assert lo < 4 < hi


# ----------------------------------------------------------------------------------------------- (e)
def test_steady_state_bound_equals_converged_covariance():
    model = two_mass()
    rng = np.random.default_rng(5)
    t, U, X, Y = simulate_linear(model, CH2, R2, X0_2, P0_2, 3000, rng)
    res = MultirateEKF(model, CH2, R2, X0_2, P0_2, DT, store_P="full").run(t, U, Y)
    A, H, Q = linearise(model, X0_2, U[0], DT, CH2)
    R = np.array([R2[c] for c in CH2]) ** 2
    P_prior, P_post = steady_state_covariance(A, Q, H, R, DT)
    np.testing.assert_allclose(res.P[-1], P_post, rtol=1e-8, atol=1e-8 * np.abs(P_post).max())
    # G form (Q = G G') gives the same bound
    Gam = model.B
    G = np.hstack([Gam * SIGMA_F, np.diag(np.sqrt([1e-12, 1e-12, 1e-9, 1e-9]))])
    _, P_post_g = steady_state_covariance(A, G, H, R, DT)
    np.testing.assert_allclose(P_post_g, P_post, rtol=1e-9)
    # the bound is the RMS error achieved in steady state (within sampling error)
    rms = rms_error(X[500:], res.x_hat[500:])
    b = bound_rms(P_post, slice(None))
    assert np.all((rms > 0.8 * b) & (rms < 1.25 * b)), rms / b
    assert np.allclose(bound_rms(P_post, np.eye(4)[[1, 3]]), b[[1, 3]])
    # continuous option == Van Loan discretised
    A_c, B_c = chain_continuous([1.0, 0.5], [400.0, 200.0], [0.6, 0.3])
    Ad, Qd = van_loan(A_c, B_c @ B_c.T * 0.3, DT)
    np.testing.assert_allclose(Ad, model.A, rtol=1e-10, atol=1e-14)
    Pc = steady_state_covariance(A_c, B_c @ B_c.T * 0.3, H, R, DT, continuous=True)[1]
    np.testing.assert_allclose(Pc, steady_state_covariance(Ad, Qd, H, R)[1], rtol=1e-9)


# ----------------------------------------------------------------------------------------------- (f)
def test_divergence_flag():
    truth = two_mass()
    rng = np.random.default_rng(11)
    t, U, X, Y = simulate_linear(truth, CH2, R2, X0_2, P0_2, 2000, rng, rates={"v2": 5})
    ok = MultirateEKF(truth, CH2, R2, X0_2, P0_2, DT).run(t, U, Y)
    assert not ok.nis_flagged and ok.nis_flagged_at is None and not ok.diverged
    wrong = two_mass(k_scale=10.0, q_scale=1e-6)
    bad = MultirateEKF(wrong, CH2, R2, X0_2, P0_2, DT).run(t, U, Y)
    assert bad.nis_flagged and 0 < bad.nis_flagged_at < t[-1] and not bad.diverged
    assert bad.flagged_intervals[0][0] == bad.nis_flagged_at
    with pytest.raises(FilterDivergedError):
        MultirateEKF(wrong, CH2, R2, X0_2, P0_2, DT, monitoring=Monitoring(divergence_action="raise")).run(t, U, Y)


def test_nis_monitor_needs_disjoint_confirmation():
    m = NISMonitor(window=10, confidence=0.999, confirm=2)
    # one huge outlier stays in the window for 10 updates but cannot fail two disjoint windows
    assert not any(m.push(1e6 if k == 15 else 1.0, 1) for k in range(200))
    m.reset()
    fired = [m.push(50.0, 1) for k in range(25)]
    assert not any(fired[:19]) and fired[19]


def test_nonfinite_raises_or_flags():
    class Blowup(LinearDiscreteModel):
        def predict(self, x, u, dt, u_next=None):
            xn, F, Q = super().predict(x, u, dt)
            return Prediction(xn * np.nan if self.k_bad else xn, F, Q)

    m = two_mass()
    bad = Blowup(m.A, m.B, m.C, m.Q, dt=DT)
    bad.k_bad = False
    ekf = MultirateEKF(bad, CH2, R2, X0_2, P0_2, DT)
    t = np.arange(5) * DT
    Y = np.zeros((5, 3))
    ekf.step(t[0], [0.0], Y[0])
    bad.k_bad = True
    with pytest.raises(FilterDivergedError):
        ekf.step(t[1], [0.0], Y[1])
    bad.k_bad = False
    ekf2 = MultirateEKF(bad, CH2, R2, X0_2, P0_2, DT, nonfinite="flag")
    bad.k_bad = True
    ekf2.step(t[0], [0.0], Y[0])  # first sample: no prediction
    res = ekf2.run(t, np.zeros((5, 1)), Y)
    assert res.nonfinite and res.diverged and res.diverged_at == t[1]
    assert np.all(np.isfinite(res.x_hat[0])) and np.all(np.isnan(res.x_hat[1:]))


# ----------------------------------------------------------------------------------------------- (g)
def test_covariance_symmetric_positive_definite(multirate_data):
    model, t, U, X, Y = multirate_data
    res = MultirateEKF(model, CH2, R2, X0_2, P0_2, DT, store_P="full").run(t, U, Y)
    assert np.array_equal(res.P, np.swapaxes(res.P, 1, 2))
    assert np.all(np.linalg.eigvalsh(res.P)[:, 0] > 0)
    assert np.allclose(res.P_diag, np.diagonal(res.P, axis1=1, axis2=2))
    # diagonal floor keeps P usable even from a degenerate prior
    ekf = MultirateEKF(model, CH2, R2, X0_2, np.zeros(4), DT, p_floor=1e-20)
    ekf.step(0.0, U[0], Y[0])
    assert np.all(np.diag(ekf.P) >= 1e-20)


# ----------------------------------------------------------------------------------------------- nonlinear
def test_pendulum_jacobians_exact():
    p = Pendulum()
    x, u = np.array([1.2, -0.7]), 0.3
    xn, F, G = p.step_full(x, u, DT)
    eps = 1e-6
    F_fd = np.column_stack(
        [(p.predict(x + eps * e, u, DT).x - p.predict(x - eps * e, u, DT).x) / (2 * eps) for e in np.eye(2)]
    )
    np.testing.assert_allclose(F, F_fd, rtol=1e-8, atol=2e-9)  # FD round-off ~1e-10
    h = 1e-4  # the input's central difference (round-off dominates below)
    G_fd = (p.predict(x, np.array([u + h]), DT).x - p.predict(x, np.array([u - h]), DT).x) / (2 * h)
    np.testing.assert_allclose(G, G_fd, rtol=1e-7, atol=2e-12)
    y, H = p.measure(x, ["omega", "bob_x"])
    assert y.shape == (2,) and H.shape == (2, 2) and y[0] == x[1]


def test_pendulum_ekf_tracks():
    p = Pendulum()
    rng = np.random.default_rng(21)
    n = 1000
    t = np.arange(n) * DT
    U = 0.5 * np.sin(2 * np.pi * 0.7 * t)[:, None]
    X = np.empty((n, 2))
    x = np.array([1.5, 0.0])
    for k in range(n):
        X[k] = x
        x = p.predict(x, U[k] + p.sigma_tau * rng.standard_normal(), DT).x
    ch = ("bob_x", "bob_y", "omega")
    R = {"bob_x": 2e-3, "bob_y": 2e-3, "omega": 0.05}
    Y = np.column_stack([p.measure(xk, ch)[0] for xk in X]).T + np.array(
        list(R.values())
    ) * rng.standard_normal((n, 3))
    Y[np.arange(n) % 5 != 0, 2] = np.nan  # gyro at 100 Hz
    x0 = np.array([1.2, 0.5])  # wrong initial guess
    res = MultirateEKF(p, ch, R, x0, np.diag([0.1, 1.0]), DT, store_P="full").run(t, U, Y)
    assert not res.diverged
    steady = slice(250, None)
    assert np.all(rms_error(X[steady], res.x_hat[steady]) < [5e-3, 0.1])
    # errors are of the size the filter claims (a single run's NEES average scatters widely: the omega error
    # is strongly time-correlated, so compare RMS with the reported standard deviations instead)
    sd = np.sqrt(res.P_diag[steady].mean(axis=0))
    assert np.all(rms_error(X[steady], res.x_hat[steady]) < 2.0 * sd)
    assert np.all(rms_error(X[steady], res.x_hat[steady]) > 0.5 * sd)
    mn, ex = res.mean_nis(250)
    assert 0.7 < mn / ex < 1.3
    assert np.all(max_error(X[steady], res.x_hat[steady]) < 5 * rms_error(X[steady], res.x_hat[steady]))


# ----------------------------------------------------------------------------------------------- tuning, stats
def test_zoh_torque_noise_matches_truth_covariance():
    m = two_mass()
    Gam = m.B
    Q = zoh_torque_noise(Gam[:, 0], SIGMA_F)
    np.testing.assert_allclose(Q, SIGMA_F**2 * Gam @ Gam.T)
    rng = np.random.default_rng(0)
    w = SIGMA_F * rng.standard_normal(20000)
    dx = np.array([m.predict(np.zeros(4), [wi], DT).x for wi in w[:2000]])
    np.testing.assert_allclose(np.cov(dx.T), Q, rtol=0.15, atol=1e-3 * np.abs(Q).max())


def test_fft_peaks_and_stats():
    fs = 500.0
    t = np.arange(4000) / fs
    s = (
        np.sin(2 * np.pi * 12.34 * t)
        + 0.5 * np.sin(2 * np.pi * 47.9 * t + 1)
        + 0.01 * np.random.default_rng(0).standard_normal(4000)
    )
    f = fft_peaks(t, s, fmax=100, n_peaks=2)
    np.testing.assert_allclose(f, [12.34, 47.9], rtol=2e-3)
    f2, a2 = fft_peaks(t, s, fmax=100, n_peaks=2, return_amplitudes=True)
    assert a2[0] > a2[1] and abs(a2[0] - 1) < 0.1
    matched, e = match_peaks([12.3, 48.0], f)
    assert np.all(e < 1.0)
    mu, sig = eq21_stats(np.zeros((3, 10)), np.ones((3, 10)))
    assert mu == 1 and sig == 0
    e2 = np.ones((5, 3))
    np.testing.assert_allclose(nees(e2, np.full((5, 3), 2.0)), 1.5)
    np.testing.assert_allclose(nees(e2, 2 * np.eye(3)), 1.5)
    assert nees(np.ones(3), 2 * np.eye(3)) == pytest.approx(1.5)


# ----------------------------------------------------------------------------------------------- speed
def test_per_update_cost_26_states(capsys):
    """Prints the filter's own cost per sample on 26 states (a linear model step); asserts nothing about time."""
    model = chain26()
    ch = tuple(model.C)
    R = dict(zip(ch, [1e-5, 1e-5, 1e-5, 1e-3]))
    rng = np.random.default_rng(2)
    x0, P0 = np.zeros(model.nx), np.eye(model.nx) * 1e-4
    t, U, X, Y = simulate_linear(model, ch, R, x0, P0, 1000, rng)
    ekf = MultirateEKF(model, ch, R, x0, P0, DT)
    t0 = time.perf_counter()
    for k in range(len(t)):
        ekf.step(t[k], U[k], Y[k])
    us = 1e6 * (time.perf_counter() - t0) / len(t)
    with capsys.disabled():
        print(f"\n26-state filter, per sample (predict + update, linear model): {us:.1f} us")
    assert not ekf.diverged

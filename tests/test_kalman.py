"""The compiled Kalman algebra (:mod:`exuflex.observer.kalman`) against NumPy expressions and a NumPy filter.

- kernels one by one against NumPy expressions, for every channel subset size;
- whole runs of a random 26-state linear model with multirate, missing and partial samples against the NumPy
  filter of ``tests/_oracles.py`` (rounding only), and of the six-bar's reduced observer;
- the fallbacks: an indefinite innovation covariance (LU solve), a singular one, non-finite states, model
  arrays of the wrong shape (the kernels do not check bounds).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

import _oracles as oracle
from exuflex.mechanism import load_mechanism
from exuflex.observer import FilterDivergedError, LinearDiscreteModel, MultirateEKF, Prediction, kalman
from exuflex.observer.session import ObserverConfig, make_observer
from exuflex.runs import read_run

ROOT = Path(__file__).resolve().parents[1]
DT = 1 / 500
NX, M = 26, 6


# ----------------------------------------------------------------------------------------------- helpers
def random_model(seed: int = 0, nx: int = NX, m: int = M) -> LinearDiscreteModel:
    """Lightly damped random rotation (an oscillating structure) with dense output rows and process noise."""
    rng = np.random.default_rng(seed)
    Qo, _ = np.linalg.qr(rng.standard_normal((nx, nx)))
    A = 0.998 * Qo
    B = 1e-3 * rng.standard_normal((nx, 1))
    C = {f"c{i}": rng.standard_normal(nx) for i in range(m)}
    L = 1e-3 * rng.standard_normal((nx, nx))
    return LinearDiscreteModel(A, B, C, L @ L.T + 1e-8 * np.eye(nx), dt=DT)


def simulate(model, R_std, n, rng, x0, P0):
    """Truth-driven measurements with every kind of gap: channels at lower rates, single missing entries
    (many different channel subsets), whole missing samples."""
    ch = tuple(model.C)
    H = np.array([model.C[c] for c in ch])
    Lq = np.linalg.cholesky(model.Q)
    t = np.arange(n) * DT
    U = np.sin(2 * np.pi * 2.0 * t)[:, None]
    x = x0 + np.linalg.cholesky(P0) @ rng.standard_normal(model.nx)
    Y = np.empty((n, len(ch)))
    for k in range(n):
        Y[k] = H @ x + np.array([R_std[c] for c in ch]) * rng.standard_normal(len(ch))
        x = model.A @ x + model.B @ U[k] + Lq @ rng.standard_normal(model.nx)
    Y[np.arange(n) % 3 != 0, 4] = np.nan  # a channel at a third of the rate
    Y[np.arange(n) % 2 != 0, 5] = np.nan  # and one at half
    Y[rng.random((n, len(ch))) < 0.1] = np.nan  # entries lost at random
    Y[rng.random(n) < 0.03] = np.nan  # whole samples lost
    return t, U, Y


def _linear_case(seed=3, n=600):
    model = random_model(seed)
    ch = tuple(model.C)
    R = {c: s for c, s in zip(ch, [0.02, 0.05, 0.03, 0.1, 0.04, 0.2])}
    x0, P0 = np.zeros(NX), 1e-2 * np.eye(NX)
    t, U, Y = simulate(model, R, n, np.random.default_rng(seed + 100), x0, P0)
    return model, ch, R, x0, P0, t, U, Y


def _assert_runs_agree(a, b, rtol):
    scale = np.abs(a.x_hat).max(axis=0)
    assert np.all(np.abs(a.x_hat - b.x_hat) <= rtol * scale)
    if a.P is not None:
        np.testing.assert_allclose(b.P, a.P, rtol=0, atol=rtol * np.abs(a.P).max())
    np.testing.assert_allclose(b.nis, a.nis, rtol=100 * rtol)
    np.testing.assert_array_equal(np.isnan(a.innovations), np.isnan(b.innovations))
    atol = rtol * np.nanmax(np.abs(a.innovations))
    np.testing.assert_allclose(b.innovations, a.innovations, rtol=0, atol=atol)
    np.testing.assert_allclose(b.S, a.S, rtol=0, atol=rtol * np.nanmax(np.abs(a.S)))
    np.testing.assert_array_equal(a.nis_dof, b.nis_dof)
    def counts(r):
        return r.n_missing, r.n_updates, r.diverged, r.nonfinite

    assert counts(a) == counts(b)


# ----------------------------------------------------------------------------------------------- kernels
@pytest.mark.parametrize("m", range(1, M + 1))
def test_update_kernel_equals_numpy_expressions(m):
    rng = np.random.default_rng(m)
    L = rng.standard_normal((NX, NX))
    P = L @ L.T / NX
    P = 0.5 * (P + P.T)
    H = rng.standard_normal((m, NX))
    Rd = rng.uniform(0.01, 0.1, m)
    x, y = rng.standard_normal(NX), rng.standard_normal(m)
    y_pred = H @ x + 0.1 * rng.standard_normal(m)
    # the update in NumPy expressions
    r = y - y_pred
    HP = H @ P
    S = HP @ H.T + np.diag(Rd)
    sol = np.linalg.solve(S, np.column_stack([HP, r]))
    K = sol[:, :NX].T
    A = P - K @ HP
    P_ref = A - (A @ H.T - K * Rd) @ K.T
    HP_out, r_out, S_out = np.empty((M, NX)), np.empty(m), np.empty((m, m))
    x_out, P_out = np.empty(NX), np.empty((NX, NX))
    nis, ok = kalman.update(x, P, y, y_pred, H, Rd, HP_out, r_out, S_out, x_out, P_out)
    assert ok
    np.testing.assert_allclose(r_out, r, rtol=1e-15)
    np.testing.assert_allclose(HP_out[:m], HP, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(S_out, S, rtol=1e-12)
    np.testing.assert_allclose(x_out, x + K @ r, rtol=1e-11, atol=1e-13)
    assert nis == pytest.approx(float(r @ sol[:, NX]), rel=1e-11)
    # the kernel returns the Joseph form transposed; symmetrised (as every sample ends) they are the same
    np.testing.assert_allclose(0.5 * (P_out + P_out.T), 0.5 * (P_ref + P_ref.T), rtol=0,
                               atol=1e-12 * np.abs(P).max())


@pytest.mark.parametrize("seed", range(4))
def test_condition_on_a_subset_is_the_update_with_those_rows_and_filterpys(seed):
    """:func:`kalman.condition_on` with a channel mask: bit for bit the update kernel and ``settle`` on the rows kept
    (selected in NumPy), and filterpy's ``KalmanFilter.update`` with those rows (an independent oracle)."""
    from filterpy.kalman import KalmanFilter

    rng = np.random.default_rng(seed)
    L = rng.standard_normal((NX, NX))
    P = np.ascontiguousarray(0.5 * (L @ L.T + (L @ L.T).T) / NX)
    H = rng.standard_normal((M, NX))
    Rd = rng.uniform(0.01, 0.1, M)
    x = rng.standard_normal(NX)
    y_pred = H @ x
    y = y_pred + 0.1 * rng.standard_normal(M)
    keep = rng.random(M) < 0.5
    keep[seed % M] = True
    floor = np.full(NX, 1e-18)
    x_out, P_out = np.empty(NX), np.empty((NX, NX))
    nis, how, finite, r, S = kalman.condition_on(keep, x, P, y, y_pred, H, Rd, floor, np.empty((M, NX)), x_out, P_out)
    assert how == kalman.CHOLESKY and finite and r.shape == (keep.sum(),)
    x_ref, P_ref, r_ref, S_ref = np.empty(NX), np.empty((NX, NX)), np.empty(keep.sum()), np.empty((keep.sum(),) * 2)
    Hk = np.ascontiguousarray(H[keep])
    nis_ref, _ = kalman.update(x, P, y[keep], y_pred[keep], Hk, Rd[keep], np.empty((M, NX)), r_ref, S_ref, x_ref, P_ref)
    kalman.settle(x_ref, P_ref, floor)
    assert nis == nis_ref and np.array_equal(r, r_ref) and np.array_equal(S, S_ref)
    assert np.array_equal(x_out, x_ref) and np.array_equal(P_out, P_ref)
    kf = KalmanFilter(dim_x=NX, dim_z=int(keep.sum()))
    kf.x, kf.P = x.copy(), P.copy()
    kf.update(y[keep], R=np.diag(Rd[keep]), H=Hk)
    np.testing.assert_allclose(x_out, kf.x.reshape(-1), rtol=0, atol=1e-10 * np.abs(kf.x).max())
    np.testing.assert_allclose(P_out, kf.P, rtol=0, atol=1e-9 * np.abs(kf.P).max())


def test_gate_leaves_out_a_minority_beyond_the_threshold():
    """:func:`kalman.gate`: channels beyond the threshold (or isolated beforehand) are left out while they are
    fewer than half; none within the hold-off (``n_over`` 0) unless isolated; all stay where half or more are off."""

    def chosen(z, n_over, keep=None):
        keep = np.ones(len(z), dtype=bool) if keep is None else np.array(keep)
        return kalman.gate(np.array(z, float), 9.0, n_over, keep), keep.tolist()

    assert chosen([0.1, 5.0, -0.2, 0.3], 1) == (3, [True, False, True, True])
    assert chosen([0.1, 5.0, -0.2, 0.3], 0) == (4, [True] * 4)  # the hold-off: no gating
    assert chosen([5.0, -5.0, 0.1, 0.2], 2) == (4, [True] * 4)  # half off: the filter, not the sensors
    assert chosen([0.1, 0.2, 0.3, 0.4], 0, [True, True, False, True]) == (3, [True, True, False, True])
    assert chosen([0.1, 5.0, 0.3, 0.4, 0.5], 1, [True, True, False, True, True]) == (3, [True, False, False, True, True])


def test_predict_and_settle_kernels_equal_numpy_expressions():
    rng = np.random.default_rng(1)
    F, Q = rng.standard_normal((NX, NX)), rng.standard_normal((NX, NX))
    L = rng.standard_normal((NX, NX))
    P = L @ L.T
    out = np.empty((NX, NX))
    kalman.predict_cov(F, P, Q, out, np.empty((NX, NX)))
    np.testing.assert_allclose(out, F @ P @ F.T + Q, rtol=0, atol=1e-13 * np.abs(out).max())
    # symmetrisation and the diagonal floor, scalar and per state
    for floor in (0.5, np.linspace(0.0, 1.0, NX)):
        ref = 0.5 * (out + out.T)
        np.fill_diagonal(ref, np.maximum(np.diag(ref), floor))
        got = out.copy()
        assert kalman.settle(np.zeros(NX), got, np.broadcast_to(floor, (NX,)).astype(float))
        np.testing.assert_array_equal(got, ref)
    bad = out.copy()
    bad[3, 7] = np.inf
    assert not kalman.settle(np.zeros(NX), bad, np.zeros(NX))
    assert not kalman.settle(np.full(NX, np.nan), out.copy(), np.zeros(NX))


# ----------------------------------------------------------------------------------------------- whole runs
def _oracle_agrees(model, ch, R, x0, P0, t, U, Y, res, rtol, p_floor=1e-18):
    X, P, N = oracle.numpy_filter(model, ch, R, x0, P0, t, U, Y, p_floor=p_floor)
    scale = np.abs(X).max(axis=0)
    assert np.all(np.abs(res.x_hat - X) <= rtol * scale)
    np.testing.assert_allclose(res.P, P, rtol=0, atol=rtol * np.abs(P).max())
    np.testing.assert_allclose(res.nis, N, rtol=100 * rtol)


def test_compiled_filter_equals_the_numpy_oracle_with_gaps():
    model, ch, R, x0, P0, t, U, Y = _linear_case()
    res = MultirateEKF(model, ch, R, x0, P0, DT, store_P="full").run(t, U, Y)
    assert len(set(map(tuple, np.isnan(Y)))) > 20  # many channel subsets were used
    assert not res.diverged and res.n_missing > 5
    _oracle_agrees(model, ch, R, x0, P0, t, U, Y, res, 1e-12)
    assert np.array_equal(res.P, np.swapaxes(res.P, 1, 2))  # exactly symmetric


def test_run_equals_online_steps_exactly():
    model, ch, R, x0, P0, t, U, Y = _linear_case(seed=5, n=300)
    ekf = MultirateEKF(model, ch, R, x0, P0, DT)
    res = ekf.run(t, U, Y)
    online = MultirateEKF(model, ch, R, x0, P0, DT)
    xs = []
    for k in range(len(t)):
        xs.append(online.step(t[k], U[k], Y[k]))
        if online.last_idx is not None:  # the per-sample bookkeeping run() reads
            assert np.array_equal(online.last_innovation, res.innovations[k, online.last_idx])
            assert online.last_nis == res.nis[k] and online.last_dof == res.nis_dof[k]
    assert np.array_equal(np.array(xs), res.x_hat)
    assert np.array_equal(ekf.run(t, U, Y).x_hat, res.x_hat)  # a second run (reset) is identical


def test_pure_steps_are_the_filters_step_and_filterpys():
    """``condition(predict(belief, model.predict(...)), model.measure(...), y, R)`` is the filter's ``step`` bit
    for bit (every channel and a subset), and equals filterpy's ``KalmanFilter`` predict/update (an independent
    oracle, Joseph form) on the linear model."""
    from filterpy.kalman import KalmanFilter

    from exuflex.observer.base import Belief

    model, ch, R, x0, P0, t, U, Y = _linear_case(seed=7, n=40)
    Y = Y[np.isfinite(Y).any(axis=1)]  # (an all-NaN sample is a prediction alone: not a step to compare here)
    t, U = t[: len(Y)], U[: len(Y)]
    ekf = MultirateEKF(model, ch, R, x0, P0, DT)
    Rd = np.array([R[c] ** 2 for c in ch])
    kf = KalmanFilter(dim_x=NX, dim_z=M)
    kf.x, kf.P, kf.F, kf.Q = x0.copy(), P0.copy(), model.A, model.Q
    b = Belief(x0, P0)
    for k in range(len(t)):
        x = ekf.step(t[k], U[k], Y[k])
        if k:
            b = kalman.predict(b, model.predict(b.x, U[k - 1], DT))
            kf.predict(u=U[k - 1], B=model.B)
        idx = np.flatnonzero(np.isfinite(Y[k]))
        if len(idx):
            meas = model.measure(b.x, [ch[i] for i in idx])
            b, inn = kalman.condition(b, meas, Y[k, idx], Rd[idx], floor=1e-18)
            assert inn.nis == ekf.last_nis and np.array_equal(inn.r, ekf.last_innovation)
            kf.update(Y[k, idx], R=np.diag(Rd[idx]), H=meas.H)
        assert np.array_equal(b.x, x) and np.array_equal(b.P, ekf.P)
        np.testing.assert_allclose(b.x, kf.x.reshape(-1), rtol=0, atol=1e-10 * np.abs(kf.x).max())
        np.testing.assert_allclose(b.P, kf.P, rtol=0, atol=1e-9 * np.abs(kf.P).max())
    assert ekf.belief.x.tolist() == b.x.tolist()


def test_per_state_floor_and_degenerate_prior():
    model = random_model(7)
    ch = tuple(model.C)
    R = dict.fromkeys(ch, 0.05)
    P0 = np.zeros(NX)
    P0[:3] = 1e-2
    t, U, Y = simulate(model, R, 200, np.random.default_rng(7), np.zeros(NX), np.diag(P0 + 1e-12))
    floor = np.full(NX, 1e-6)
    floor[::2] = 1e-4
    res = MultirateEKF(model, ch, R, np.zeros(NX), P0, DT, store_P="full", p_floor=floor).run(t, U, Y)
    _oracle_agrees(model, ch, R, np.zeros(NX), np.diag(P0), t, U, Y, res, 1e-9, p_floor=floor)
    assert np.all(res.P_diag >= floor)


def test_sixbar_observer_equals_the_numpy_oracle_within_a_thousandth_of_the_bound():
    """The six-bar's reduced observer: the compiled filter and the NumPy oracle filter over the same model agree
    within 1e-3 of the steady-state bound at every sample after the start-up (the model's refresh decisions
    follow the estimate, so rounding differences can grow; measured far below that)."""
    from exuflex.runs import held_torques
    from exuflex.scoring.bound import estimation_bound

    mech = load_mechanism(ROOT / "models" / "sixbar.toml")
    run = read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")
    obs = make_observer(mech, ObserverConfig())
    S, n = run.sensors, 600
    t, U, Y = S.t[:n], held_torques(S.select(run.motors).data[:n]), S.select(obs.channels).data[:n].copy()
    Y[100:104] = np.nan  # a gap
    Y[150:200:2, 3:] = np.nan  # gauges at half rate
    res = obs.ekf.run(t, U, Y)
    X, _, N = oracle.numpy_filter(obs.model, obs.channels, dict(zip(obs.channels, obs.ekf.R_std)), obs.ekf._x0,
                                  obs.ekf._P0, t, U, Y)
    bound = estimation_bound(obs)
    est_c, est_o = obs.physical(t, res.x_hat), obs.physical(t, X)
    after = t >= 0.3
    worst = max(np.abs(est_c[k][after] - est_o[k][after]).max() / bound[k] for k in bound)
    print(f"largest difference over the bound after the start-up: {worst:.2e}")
    assert worst <= 1e-3
    assert not res.diverged and res.n_missing == 4


# ----------------------------------------------------------------------------------------------- fallbacks
def test_indefinite_innovation_covariance_falls_back_to_lu(caplog):
    """A prior that is not positive definite makes S indefinite: the update solves it by LU, with a warning, and
    gives the NumPy formulas' result."""
    model = random_model(2)
    ch = tuple(model.C)
    R = dict.fromkeys(ch, 1e-3)
    P0 = -1e-2 * np.eye(NX)
    y = np.random.default_rng(0).standard_normal(M)
    ekf = MultirateEKF(model, ch, R, np.zeros(NX), np.eye(NX), DT)
    ekf._P = P0.copy()
    with caplog.at_level(logging.WARNING, logger="exuflex.observer.ekf"):
        x = ekf.step(0.0, [0.0], y)
    assert "not positive definite" in caplog.text
    H = np.array([model.C[c] for c in ch])
    Rm = 1e-6 * np.eye(M)
    S = H @ P0 @ H.T + Rm
    K = np.linalg.solve(S, H @ P0).T
    np.testing.assert_allclose(x, K @ y, rtol=1e-10)
    IKH = np.eye(NX) - K @ H
    P = IKH @ P0 @ IKH.T + K @ Rm @ K.T
    np.fill_diagonal(P, np.maximum(np.diag(P), 1e-18))  # the end-of-sample floor
    np.testing.assert_allclose(ekf.P, P, rtol=1e-8, atol=1e-14)


def test_singular_innovation_covariance_raises():
    model = LinearDiscreteModel(np.eye(1), None, {"a": [1.0]}, np.eye(1) * 1e-4, dt=DT)
    ekf = MultirateEKF(model, ["a"], {"a": 0.5}, [0.0], [1.0], DT)
    ekf._P = np.array([[-0.25]])  # S = P + R = 0
    with pytest.raises(FilterDivergedError, match="singular"):
        ekf.step(0.0, None, [1.0])


@pytest.mark.parametrize("action", ["raise", "flag"])
def test_nonfinite_state_is_raised_or_flagged(action):
    class Blowup(LinearDiscreteModel):
        bad_from = 3

        def predict(self, x, u, dt, u_next=None):
            xn, F, Q = super().predict(x, u, dt)
            self.calls = getattr(self, "calls", 0) + 1
            return Prediction(xn * np.nan if self.calls >= self.bad_from else xn, F, Q)

    base = random_model(4)
    ch = tuple(base.C)
    t = np.arange(8) * DT
    Y = np.zeros((8, M))
    model = Blowup(base.A, base.B, base.C, base.Q, dt=DT)
    ekf = MultirateEKF(model, ch, dict.fromkeys(ch, 0.1), np.zeros(NX), np.eye(NX), DT, nonfinite=action)
    if action == "raise":
        with pytest.raises(FilterDivergedError, match="non-finite"):
            ekf.run(t, np.zeros((8, 1)), Y)
        assert ekf.t == t[3] and ekf.nonfinite
    else:
        res = ekf.run(t, np.zeros((8, 1)), Y)
        assert res.diverged_at == t[3] and res.nonfinite
        assert np.isnan(res.x_hat).sum(axis=1).tolist() == [0, 0, 0] + [NX] * 5
        assert res.n_updates == 3 and res.n_missing == 4


def test_wrong_shapes_from_the_model_are_errors_not_crashes():
    """The kernels do not check bounds: the filter checks every array a model returns."""
    base = random_model(6)
    ch = tuple(base.C)

    class WrongF(LinearDiscreteModel):
        def predict(self, x, u, dt, u_next=None):
            xn, F, Q = super().predict(x, u, dt)
            return Prediction(xn, F[:-1], Q)

    class WrongH(LinearDiscreteModel):
        def measure(self, x, channels):
            y, H = super().measure(x, channels)
            return y, (H if len(channels) == M else H[:, :-1])

    for cls, Y in ((WrongF, np.zeros((2, M))), (WrongH, np.array([np.zeros(M), [np.nan] + [0.0] * (M - 1)]))):
        model = cls(base.A, base.B, base.C, base.Q, dt=DT)
        ekf = MultirateEKF(model, ch, dict.fromkeys(ch, 0.1), np.zeros(NX), np.eye(NX), DT)
        ekf.step(0.0, [0.0], Y[0])
        with pytest.raises(ValueError, match="expected"):
            ekf.step(DT, [0.0], Y[1])
    with pytest.raises(ValueError, match="p_floor"):
        MultirateEKF(base, ch, dict.fromkeys(ch, 0.1), np.zeros(NX), np.eye(NX), DT, p_floor=np.ones(3))

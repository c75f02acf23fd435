"""The compiled (numba) back-end of the multirate EKF against the numpy and filterpy back-ends.

The numba back-end evaluates the numpy back-end's formulas (covariance prediction, the Cholesky-solved
update in factored Joseph form, symmetrisation and diagonal floor) in compiled kernels; the back-ends may
differ only by rounding, and share all bookkeeping (innovations, NIS, missing samples, divergence).

- kernels one by one against the numpy expressions, for every channel subset size;
- whole runs of a random 26-state linear model with multirate, missing and partial samples and skipped
  grid points, and of the six-bar's reduced observer on the logged ERLS run;
- the fallbacks: an indefinite innovation covariance (LU solve), a singular one, non-finite states, model
  arrays of the wrong shape (the kernels do not check bounds), and a Python without numba.
"""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("numba")

from exuflex.mechanism import load_mechanism
from exuflex.observer import FilterDivergedError, LinearDiscreteModel, MultirateEKF, _compiled
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
    (many different channel subsets), whole missing samples, and skipped grid points (rows removed)."""
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
    keep = np.ones(n, bool)
    keep[[40, 41, 42, 150, 177]] = False  # skipped grid points: no call at all
    return t[keep], U[keep], Y[keep]


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
    # the numpy back-end's algebra (MultirateEKF._update)
    r = y - y_pred
    HP = H @ P
    S = HP @ H.T + np.diag(Rd)
    sol = np.linalg.solve(S, np.column_stack([HP, r]))
    K = sol[:, :NX].T
    A = P - K @ HP
    P_ref = A - (A @ H.T - K * Rd) @ K.T
    HP_out, r_out, S_out = np.empty((M, NX)), np.empty(m), np.empty((m, m))
    x_out, P_out = np.empty(NX), np.empty((NX, NX))
    nis, ok = _compiled.update(x, P, y, y_pred, H, Rd, HP_out, r_out, S_out, x_out, P_out)
    assert ok
    np.testing.assert_allclose(r_out, r, rtol=1e-15)
    np.testing.assert_allclose(HP_out[:m], HP, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(S_out, S, rtol=1e-12)
    np.testing.assert_allclose(x_out, x + K @ r, rtol=1e-11, atol=1e-13)
    assert nis == pytest.approx(float(r @ sol[:, NX]), rel=1e-11)
    # the kernel returns the Joseph form transposed; symmetrised (as every sample ends) they are the same
    np.testing.assert_allclose(0.5 * (P_out + P_out.T), 0.5 * (P_ref + P_ref.T), rtol=0,
                               atol=1e-12 * np.abs(P).max())


def test_predict_and_settle_kernels_equal_numpy_expressions():
    rng = np.random.default_rng(1)
    F, Q = rng.standard_normal((NX, NX)), rng.standard_normal((NX, NX))
    L = rng.standard_normal((NX, NX))
    P = L @ L.T
    out = np.empty((NX, NX))
    _compiled.predict_cov(F, P, Q, out, np.empty((NX, NX)))
    np.testing.assert_allclose(out, F @ P @ F.T + Q, rtol=0, atol=1e-13 * np.abs(out).max())
    # _fix_P of the numpy back-end, scalar and per-state floor
    model = random_model()
    for floor in (0.5, np.linspace(0.0, 1.0, NX)):
        ekf = MultirateEKF(model, tuple(model.C), dict.fromkeys(model.C, 0.1), np.zeros(NX), np.eye(NX),
                           p_floor=floor)
        ref = ekf._fix_P(out)
        got = out.copy()
        assert _compiled.settle(np.zeros(NX), got, np.broadcast_to(floor, (NX,)).astype(float))
        np.testing.assert_array_equal(got, ref)
    bad = out.copy()
    bad[3, 7] = np.inf
    assert not _compiled.settle(np.zeros(NX), bad, np.zeros(NX))
    assert not _compiled.settle(np.full(NX, np.nan), out.copy(), np.zeros(NX))


# ----------------------------------------------------------------------------------------------- whole runs
def test_backends_agree_on_random_model_with_gaps():
    model, ch, R, x0, P0, t, U, Y = _linear_case()
    res = {b: MultirateEKF(model, ch, R, x0, P0, DT, backend=b, store_P="full").run(t, U, Y)
           for b in ("numpy", "numba", "filterpy")}
    a = res["numpy"]
    assert a.n_missing > 5 and len(set(map(tuple, np.isnan(Y)))) > 20  # many channel subsets were used
    assert not a.diverged
    _assert_runs_agree(a, res["numba"], 1e-12)
    _assert_runs_agree(a, res["filterpy"], 1e-10)
    assert np.array_equal(res["numba"].P, np.swapaxes(res["numba"].P, 1, 2))  # exactly symmetric


def test_numba_run_equals_online_steps_exactly():
    model, ch, R, x0, P0, t, U, Y = _linear_case(seed=5, n=300)
    ekf = MultirateEKF(model, ch, R, x0, P0, DT, backend="numba")
    res = ekf.run(t, U, Y)
    online = MultirateEKF(model, ch, R, x0, P0, DT, backend="numba")
    xs = []
    for k in range(len(t)):
        xs.append(online.step(t[k], U[k], Y[k]))
        if online.last_idx is not None:  # the per-sample bookkeeping run() reads
            assert np.array_equal(online.last_innovation, res.innovations[k, online.last_idx])
            assert online.last_nis == res.nis[k] and online.last_dof == res.nis_dof[k]
    assert np.array_equal(np.array(xs), res.x_hat)
    assert np.array_equal(ekf.run(t, U, Y).x_hat, res.x_hat)  # a second run (reset) is identical


def test_per_state_floor_and_degenerate_prior_agree():
    model = random_model(7)
    ch = tuple(model.C)
    R = dict.fromkeys(ch, 0.05)
    P0 = np.zeros(NX)
    P0[:3] = 1e-2
    t, U, Y = simulate(model, R, 200, np.random.default_rng(7), np.zeros(NX), np.diag(P0 + 1e-12))
    floor = np.full(NX, 1e-6)
    floor[::2] = 1e-4
    a, b = (MultirateEKF(model, ch, R, np.zeros(NX), P0, DT, backend=be, store_P="full", p_floor=floor)
            .run(t, U, Y) for be in ("numpy", "numba"))
    _assert_runs_agree(a, b, 1e-12)
    assert np.all(b.P_diag >= floor)


def test_sixbar_observer_numba_equals_numpy():
    mech = load_mechanism(ROOT / "models" / "sixbar.toml")
    run = read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")
    numpy_obs = make_observer(mech, ObserverConfig(backend="numpy"))
    numba_obs = make_observer(mech, ObserverConfig(backend="numba"))
    S, n = run.sensors, 300
    t, U, Y = S.t[:n], S.select(run.motors).data[:n], S.select(numpy_obs.channels).data[:n].copy()
    Y[100:104] = np.nan  # a gap
    Y[150:200:2, 3:] = np.nan  # gauges at half rate
    a, b = numpy_obs.ekf.run(t, U, Y), numba_obs.ekf.run(t, U, Y)
    assert numba_obs.ekf.backend == "numba" and not a.diverged and a.n_missing == 4
    scale = np.abs(a.x_hat).max(axis=0)
    assert np.all(np.abs(a.x_hat - b.x_hat) <= 1e-9 * scale)
    np.testing.assert_allclose(b.nis, a.nis, rtol=1e-8)
    np.testing.assert_allclose(b.P, a.P, rtol=1e-8)
    np.testing.assert_array_equal(a.nis_dof, b.nis_dof)
    assert (a.n_missing, a.n_updates) == (b.n_missing, b.n_updates)


# ----------------------------------------------------------------------------------------------- fallbacks
def test_indefinite_innovation_covariance_falls_back_to_lu(caplog):
    """A prior that is not positive definite makes S indefinite: both back-ends solve it by LU."""
    model = random_model(2)
    ch = tuple(model.C)
    R = dict.fromkeys(ch, 1e-3)
    P0 = -1e-2 * np.eye(NX)
    y = np.random.default_rng(0).standard_normal(M)
    out = {}
    for b in ("numpy", "numba"):
        ekf = MultirateEKF(model, ch, R, np.zeros(NX), np.eye(NX), DT, backend=b)
        ekf.reset(P0=P0)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="exuflex.observer.ekf"):
            out[b] = (ekf.step(0.0, [0.0], y), ekf.P, ekf.last_nis)
        assert "not positive definite" in caplog.text
    np.testing.assert_allclose(out["numba"][0], out["numpy"][0], rtol=1e-10)
    np.testing.assert_allclose(out["numba"][1], out["numpy"][1], rtol=1e-10, atol=1e-14)
    assert out["numba"][2] == pytest.approx(out["numpy"][2], rel=1e-10)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_singular_innovation_covariance_raises(backend):
    model = LinearDiscreteModel(np.eye(1), None, {"a": [1.0]}, np.eye(1) * 1e-4, dt=DT)
    ekf = MultirateEKF(model, ["a"], {"a": 0.5}, [0.0], [1.0], DT, backend=backend)
    ekf.reset(P0=[[-0.25]])  # S = P + R = 0
    with pytest.raises(FilterDivergedError, match="singular"):
        ekf.step(0.0, None, [1.0])


@pytest.mark.parametrize("action", ["raise", "flag"])
def test_nonfinite_state_is_handled_like_numpy(action):
    class Blowup(LinearDiscreteModel):
        bad_from = 3

        def step(self, x, u, dt):
            xn, F = super().step(x, u, dt)
            self.calls = getattr(self, "calls", 0) + 1
            return (xn * np.nan if self.calls >= self.bad_from else xn), F

    base = random_model(4)
    ch = tuple(base.C)
    t = np.arange(8) * DT
    Y = np.zeros((8, M))
    out = {}
    for b in ("numpy", "numba"):
        model = Blowup(base.A, base.B, base.C, base.Q, dt=DT)
        ekf = MultirateEKF(model, ch, dict.fromkeys(ch, 0.1), np.zeros(NX), np.eye(NX), DT, backend=b,
                           nonfinite=action)
        if action == "raise":
            with pytest.raises(FilterDivergedError, match="non-finite"):
                ekf.run(t, np.zeros((8, 1)), Y)
            out[b] = (ekf.t, ekf.nonfinite)
        else:
            res = ekf.run(t, np.zeros((8, 1)), Y)
            out[b] = (res.diverged_at, res.n_missing, res.n_updates, np.isnan(res.x_hat).sum(axis=1).tolist())
    assert out["numba"] == out["numpy"]


def test_wrong_shapes_from_the_model_are_errors_not_crashes():
    """The kernels do not check bounds: the filter checks every array a model returns."""
    base = random_model(6)
    ch = tuple(base.C)

    class WrongF(LinearDiscreteModel):
        def step(self, x, u, dt):
            xn, F = super().step(x, u, dt)
            return xn, F[:-1]

    class WrongH(LinearDiscreteModel):
        def measure(self, x, channels):
            y, H = super().measure(x, channels)
            return y, (H if len(channels) == M else H[:, :-1])

    for cls, Y in ((WrongF, np.zeros((2, M))), (WrongH, np.array([np.zeros(M), [np.nan] + [0.0] * (M - 1)]))):
        model = cls(base.A, base.B, base.C, base.Q, dt=DT)
        ekf = MultirateEKF(model, ch, dict.fromkeys(ch, 0.1), np.zeros(NX), np.eye(NX), DT, backend="numba")
        ekf.step(0.0, [0.0], Y[0])
        with pytest.raises(ValueError, match="expected"):
            ekf.step(DT, [0.0], Y[1])
    with pytest.raises(ValueError, match="p_floor"):
        MultirateEKF(base, ch, dict.fromkeys(ch, 0.1), np.zeros(NX), np.eye(NX), DT, backend="numba",
                     p_floor=np.ones(3))


def test_without_numba_the_numba_backend_is_a_clear_error():
    code = """
import sys
sys.modules["numba"] = None  # import numba now fails
import numpy as np
from exuflex.observer import LinearDiscreteModel, MultirateEKF, _compiled
assert not _compiled.HAVE_NUMBA
_compiled.warm_up()
model = LinearDiscreteModel(np.eye(2), None, {"a": [1.0, 0.0]}, 1e-4 * np.eye(2))
try:
    MultirateEKF(model, ["a"], {"a": 0.1}, np.zeros(2), np.eye(2), backend="numba")
except ValueError as exc:
    print(exc)
ekf = MultirateEKF(model, ["a"], {"a": 0.1}, np.zeros(2), np.eye(2), backend="numpy")
print(ekf.step(0.0, None, [0.5]).round(6).tolist())
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert "backend='numba' needs the numba package: pip install numba" in out.stdout
    assert "[0.49505, 0.0]" in out.stdout  # K = 1 / (1 + 0.1^2): the numpy back-end runs


# ----------------------------------------------------------------------------------------------- speed
def test_per_step_cost_26_states(capsys):
    model, ch, R, x0, P0, t, U, Y = _linear_case(seed=8, n=1000)
    Y = Y.copy()
    Y[np.isnan(Y)] = 0.0  # every channel at every sample: the full-size update
    best = {}
    for b in ("numpy", "numba"):
        best[b] = np.inf
        for _ in range(3):
            ekf = MultirateEKF(model, ch, R, x0, P0, DT, backend=b)
            t0 = time.perf_counter()
            for k in range(len(t)):
                ekf.step(t[k], U[k], Y[k])
            best[b] = min(best[b], 1e6 * (time.perf_counter() - t0) / len(t))
    with capsys.disabled():
        print(f"\n26 states, 6 channels, per step (linear model): numpy {best['numpy']:.1f} us, "
              f"numba {best['numba']:.1f} us")
    assert best["numba"] < 1000.0  # sanity only: wall-clock figures on a shared machine are no test criterion

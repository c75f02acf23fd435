"""The whole-sample compiled kernel of the cached reduced observer (:mod:`exuflex.observer.fused`) equals the
step-by-step path (the model's step, process noise and measurement, then the filter's update) it replaces."""

from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer import held
from exuflex.observer.session import ObserverConfig, make_observer
from exuflex.runs import read_run

pytestmark = pytest.mark.skipif(not held.HAVE_NUMBA, reason="numba is not installed")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def setup():
    mech = load_mechanism(ROOT / "models" / "sixbar.toml")
    run = read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")
    return mech, run


def _run(obs, run, n, fused, Y=None):
    S = run.sensors
    obs.model.fused = fused
    t, U = S.t[:n], S.select(run.motors).data[:n]
    Y = S.select(obs.channels).data[:n] if Y is None else Y
    obs.ekf.reset()
    X = np.array([obs.ekf.step(t[k], U[k], Y[k]) for k in range(n)])
    Pd = obs.ekf.P.diagonal().copy()
    return X, Pd, obs.ekf.n_fused, obs.model.n_declined


def test_fused_samples_equal_the_step_by_step_path(setup):
    """The whole 3 s log with a gap and half-rate gauges (those samples take the step-by-step path): the
    estimates agree to rounding (measured: bit-identical)."""
    mech, run = setup
    obs = make_observer(mech, ObserverConfig(backend="numba"))
    n = len(run.sensors.t)
    Y = run.sensors.select(obs.channels).data[:n].copy()
    Y[100:104] = np.nan
    Y[150:200:2, 3:] = np.nan
    ref, P_ref, n_ref, _ = _run(obs, run, n, False, Y)
    fast, P_fast, n_fast, _ = _run(obs, run, n, True, Y)
    assert n_ref == 0 and n_fast > 0.95 * n
    scale = np.abs(ref).max(axis=0)
    assert np.all(np.abs(fast - ref) <= 1e-10 * scale)
    np.testing.assert_allclose(P_fast, P_ref, rtol=1e-9)


def test_declined_samples_take_the_step_by_step_path(setup):
    """With a tiny refresh radius every predicted state leaves the held configuration: the kernel declines
    (nothing changed), and the step-by-step path evaluates the configuration as it always does."""
    mech, run = setup
    obs = make_observer(mech, ObserverConfig(backend="numba"))
    m = obs.model
    m.refresh_min = m.refresh_rad = 1e-5
    ref, P_ref, _, _ = _run(obs, run, 60, False)
    m.n_declined = 0
    fast, P_fast, n_fast, n_declined = _run(obs, run, 60, True)
    assert n_declined > 10 and n_fast < 60 - 10
    scale = np.abs(ref).max(axis=0)
    assert np.all(np.abs(fast - ref) <= 1e-10 * scale)
    np.testing.assert_allclose(P_fast, P_ref, rtol=1e-9)


def test_run_loop_equals_the_step_path(setup):
    """``MultirateEKF.run`` filters the samples the fused kernel takes in one compiled loop
    (:func:`exuflex.observer.fused.cached_run`): the same estimates, covariances, innovations, NIS and counters,
    to the bit, as calling ``step`` per sample, on a log with missing samples, half-rate gauges and a skipped
    grid point (those samples leave the loop for ``step``)."""
    mech, run = setup
    obs = make_observer(mech, ObserverConfig(backend="numba"))
    ekf = obs.ekf
    S = run.sensors
    keep = np.ones(len(S.t), dtype=bool)
    keep[300] = False  # a skipped grid point: predicted through
    t, U = S.t[keep], S.select(run.motors).data[keep]
    Y = S.select(obs.channels).data[keep].copy()
    Y[100:104] = np.nan
    Y[150:200:2, 3:] = np.nan
    looped = []
    fused_run = obs.model.fused_run

    def counted(k0, *args):
        out = fused_run(k0, *args)
        looped.append(0 if out is None else out[0] - k0)
        return out

    obs.model.fused_run = counted
    res = ekf.run(t, U, Y)
    assert sum(looped) > 0.9 * len(t)  # most samples in the compiled loop
    n_loop = ekf.n_fused
    n_remap = obs.model.n_remap
    ekf.reset()
    X, Pd, innov, nis = [], [], [], []
    for k in range(len(t)):
        X.append(ekf.step(t[k], U[k], Y[k]))
        Pd.append(ekf.P.diagonal())
        full = ekf.last_idx is not None and len(ekf.last_idx) == ekf.m
        innov.append(ekf.last_innovation if full else np.full(ekf.m, np.nan))
        nis.append(ekf.last_nis if ekf.last_idx is not None else np.nan)
    assert n_loop == ekf.n_fused > 0.95 * len(t)
    assert obs.model.n_remap == 2 * n_remap
    assert res.n_updates == ekf.n_updates and res.n_missing == ekf.n_missing
    np.testing.assert_array_equal(res.x_hat, np.array(X))
    np.testing.assert_array_equal(res.P, np.array(Pd))
    np.testing.assert_array_equal(res.nis, np.array(nis))
    full = np.isfinite(res.innovations).all(axis=1)
    np.testing.assert_array_equal(res.innovations[full], np.array(innov)[full])

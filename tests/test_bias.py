"""Sensor-bias states (exuflex.observer.bias): an augmented linear system as oracle, and the six-bar with an
encoder offset present from the first sample."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer import LinearDiscreteModel, MultirateEKF
from exuflex.observer.bias import SensorBiasModel, with_bias_states
from exuflex.observer.ekf import Monitoring
from exuflex.observer.session import ObserverConfig, make_observer
from exuflex.scoring.run import observe_run
from exuflex.runs import read_run

ROOT = Path(__file__).resolve().parents[1]
REDUNDANT = ("q1", "q2", "q3", "q3rel", "c1", "c2", "c4")  # q3rel = q3 - q1 - pi on the parallelogram: q1 twice
DT = 0.01


def faulty(run, channel: str, t0: float, fault):
    """``run`` with ``fault`` (("offset", b)) on ``channel`` from time ``t0``."""
    s = run.sensors
    data = s.data.copy()
    j = s.names.index(channel)
    data[s.t >= t0, j] += fault[1]
    return dataclasses.replace(run, sensors=dataclasses.replace(s, data=data))


def _toy():
    """A damped oscillator with a position sensor 'p' and a velocity sensor 'v'."""
    w, z = 2 * np.pi * 1.5, 0.05
    A = np.array([[1.0, DT], [-w * w * DT, 1.0 - 2 * z * w * DT]])
    B = np.array([[0.0], [DT]])
    C = {"p": np.array([1.0, 0.0]), "v": np.array([0.0, 1.0])}
    Q = np.diag([1e-8, 1e-6])
    return LinearDiscreteModel(A, B, C, Q, DT)


def test_bias_model_is_the_augmented_linear_system():
    """[x; b] with b a random walk and y_p = C_p x + b equals the linear system built by hand."""
    inner, bstd = _toy(), 0.3
    m = SensorBiasModel(inner, ["p"], bias_std=bstd)
    A = np.block([[inner.A, np.zeros((2, 1))], [np.zeros((1, 2)), np.eye(1)]])
    B = np.vstack([inner.B, [[0.0]]])
    C = {"p": np.array([1.0, 0.0, 1.0]), "v": np.array([0.0, 1.0, 0.0])}
    Q = np.block([[inner.Q, np.zeros((2, 1))], [np.zeros((1, 2)), bstd**2 * DT * np.eye(1)]])
    oracle = LinearDiscreteModel(A, B, C, Q, DT)
    rng = np.random.default_rng(0)
    for _ in range(5):
        x, u = rng.standard_normal(3), rng.standard_normal(1)
        a, b = m.predict(x, u, DT), oracle.predict(x, u, DT)
        for k in range(3):
            np.testing.assert_allclose(a[k], b[k], rtol=0, atol=1e-15)
        for ch in (["p"], ["v"], ["v", "p"]):
            ma, mb = m.measure(x, ch), oracle.measure(x, ch)
            np.testing.assert_allclose(ma.y, mb.y, rtol=0, atol=1e-15)
            np.testing.assert_array_equal(ma.H, mb.H)
    # the EKF on the wrapper is the Kalman filter of the augmented system: identical estimates
    n = 300
    t = DT * np.arange(n)
    U = np.sin(2 * np.pi * 0.7 * t)[:, None]
    Y = np.column_stack([0.02 + 0.01 * rng.standard_normal(n), 0.05 * rng.standard_normal(n)])
    Y[::3, 1] = np.nan
    kw = dict(dt=DT, monitoring=Monitoring(nis_window=0, fault_window=0))
    x0, P0 = np.zeros(3), np.diag([1e-2, 1e-2, 0.1])
    ra = MultirateEKF(m, ("p", "v"), {"p": 0.01, "v": 0.05}, x0, P0, **kw).run(t, U, Y)
    rb = MultirateEKF(oracle, ("p", "v"), {"p": 0.01, "v": 0.05}, x0, P0, **kw).run(t, U, Y)
    np.testing.assert_allclose(ra.x_hat, rb.x_hat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ra.P_diag, rb.P_diag, rtol=0, atol=1e-14)


def test_bad_bias_arguments():
    with pytest.raises(ValueError, match="distinct channel names"):
        SensorBiasModel(_toy(), ["p", "p"])
    with pytest.raises(ValueError, match="bias_std"):
        SensorBiasModel(_toy(), ["p"], bias_std=-1.0)


@pytest.fixture(scope="module")
def sixbar():
    mech = load_mechanism(ROOT / "models" / "sixbar.toml")
    return mech, read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")


def test_offset_from_the_first_sample_is_estimated_with_a_second_reading(sixbar):
    """q1 read twice (q1, and q3rel = q3 - q1 - pi): a 0.06 rad q1 offset from t = 0 is estimated by q1's bias
    state within its standard deviation, and q1 is within twice its bound (1.92 measured); without the offset the
    bias estimate is consistent with zero."""
    mech, run = sixbar
    cfg = ObserverConfig(channels=REDUNDANT)
    obs = with_bias_states(make_observer(mech, cfg), ["q1"], bias0_std=0.1)
    i = obs.ekf.model.i_bias["q1"]
    for b in (0.06, 0.0):
        out = observe_run(mech, faulty(run, "q1", 0.0, ("offset", b)), cfg, observer=obs)
        res = out.estimate.result
        est, std = res.x_hat[-1, i], np.sqrt(res.P_diag[-1, i])
        assert std < 0.01 * 0.1  # observable: the prior's 0.1 rad shrinks a hundredfold
        assert abs(est - b) < 3 * std, (est, std)
        assert out.summary["ratio_to_bound"]["q1"] < 2.0, out.summary["ratio_to_bound"]
        assert not out.summary["channel_faults"]


def test_offset_from_the_first_sample_is_not_separable_with_one_reading(sixbar):
    """The default channels read q1 once: its bias state stays about as uncertain as its prior, and the q1
    estimate's own standard deviation covers its error (the offset is not hidden any more)."""
    mech, run = sixbar
    cfg = ObserverConfig()
    obs = with_bias_states(make_observer(mech, cfg), ["q1"], bias0_std=0.1)
    out = observe_run(mech, faulty(run, "q1", 0.0, ("offset", 0.06)), cfg, observer=obs)
    res = out.estimate.result
    i = obs.ekf.model.i_bias["q1"]
    assert np.sqrt(res.P_diag[-1, i]) > 0.3 * 0.1
    phys = out.estimate.physical
    k = phys.t >= out.summary["metrics_from_s"]
    err = phys["q1"][k] - np.interp(phys.t[k], run.truth.t, run.truth["q1"])
    assert np.all(np.abs(err) < 3 * np.sqrt(res.P_diag[k, 0]))

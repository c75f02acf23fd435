"""The full-order ERLS model as an observer model (:mod:`exuflex.observer.full`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.model import ErlsModel
from exuflex.erls.simulate import simulate
from exuflex.mechanism import load_mechanism
from exuflex.observer.base import DiscreteModel
from exuflex.observer.ekf import Monitoring, MultirateEKF
from exuflex.observer.full import FullObserverModel

MODEL = Path(__file__).resolve().parents[1] / "models" / "sixbar.toml"
DT = 2e-3


@pytest.fixture(scope="module")
def fm():
    return FullObserverModel(ErlsModel(load_mechanism(MODEL)))


def _state(fm, rng):
    x = fm.initial_state(fm.mech.q_ref, qd=[0.3, -0.2, 0.5])
    n, nq = fm.n, fm.nq
    x[nq:n] = 1e-5 * rng.standard_normal(n - nq)
    x[n + nq :] = 1e-3 * rng.standard_normal(n - nq)
    return x


def test_is_a_discrete_model_and_steps_like_the_erls_engine(fm):
    assert isinstance(fm, DiscreteModel)
    assert fm.nx == 2 * fm.model.n
    x = _state(fm, np.random.default_rng(0))
    u = np.array([1.0, -2.0, 0.01])
    xn, F, _ = fm.predict(x, u, DT)
    traj = simulate(fm.model.rhs, x, DT, lambda t: u, h=fm.h)
    np.testing.assert_allclose(xn, traj.y[-1], rtol=0, atol=1e-12)
    assert F.shape == (fm.nx, fm.nx)
    amp, hlam = fm.rk4_stability(x)
    assert amp <= 1.0  # the stiff axial modes are damped enough at 0.1 ms
    assert hlam > 2.0  # ... though they come close to RK4's limit 2.83 (seen 2.82: 4.5 kHz, zeta 0.26)


def test_step_jacobian_matches_finite_differences_in_the_elastic_block(fm):
    """F is the frozen linearisation: exact for elastic displacements and rates (K, C, dh/dv), which is
    what the filter needs; the q columns leave out dM/dq and are not checked."""
    rng = np.random.default_rng(1)
    x = _state(fm, rng)
    u = np.zeros(3)
    _, F, _ = fm.predict(x, u, DT)
    n, nq = fm.n, fm.nq
    cols = [nq + 2, nq + 10, n + nq + 3, n + nq + 12, n]  # u, u, u', u', q1'
    for j in cols:
        e = np.zeros(fm.nx)
        e[j] = 1e-7 if j < n else 1e-5
        fd = (fm.predict(x + e, u, DT).x - fm.predict(x - e, u, DT).x) / (2 * e[j])
        scale = np.max(np.abs(fd))
        assert np.max(np.abs(F[:, j] - fd)) < 0.05 * scale, j


def test_measurement_jacobian_and_values(fm):
    x = _state(fm, np.random.default_rng(2))
    fm.predict(x, np.zeros(3), DT)
    channels = [s.name for s in fm.mech.sensors]
    y, H = fm.measure(x, channels)
    assert y.shape == (len(channels),) and H.shape == (len(channels), fm.nx)
    for j in range(fm.n):  # positions: q (linearised rigid part) and u (exact)
        e = np.zeros(fm.nx)
        e[j] = 1e-7
        fd = (fm.measure(x + e, channels)[0] - fm.measure(x - e, channels)[0]) / 2e-7
        np.testing.assert_allclose(H[:, j], fd, atol=1e-6)
    np.testing.assert_allclose(H[:, fm.n :], 0.0)
    # encoders at rest on the rigid pose read the coordinates
    x0 = fm.initial_state(fm.mech.q_ref)
    fm.predict(x0, np.zeros(3), DT)
    yq, _ = fm.measure(x0, ["q1", "q2", "q3"])
    np.testing.assert_allclose(yq, fm.mech.q_ref, atol=1e-9)


def test_process_noise_is_symmetric_psd_and_scales_with_torque_noise(fm):
    x = _state(fm, np.random.default_rng(3))
    Q = fm.predict(x, None, DT).Q
    np.testing.assert_allclose(Q, Q.T, atol=1e-20)
    assert np.min(np.linalg.eigvalsh(Q)) > -1e-12 * np.max(np.abs(Q))
    assert np.trace(Q) > 0


def test_ekf_runs_on_the_full_model(fm):
    """Ten updates on a log simulated by the same model: finite estimates close to the truth."""
    mech = fm.mech
    x_true = fm.initial_state(mech.q_ref)
    chans = ("q1", "q2", "q3", "c1", "c2", "c4")
    R = {c: next(s.noise_std for s in mech.sensors if s.name == c) for c in chans}
    ekf = MultirateEKF(fm, chans, R, x_true, np.full(fm.nx, 1e-8), dt=DT, monitoring=Monitoring(nis_window=0))
    u = np.array([1.0, 1.0, 0.0])
    for k in range(10):
        y, _ = fm.measure(x_true, chans)
        xh = ekf.step(k * DT, u, y)
        x_true = fm.predict(x_true, u, DT).x
    assert np.all(np.isfinite(xh))
    # xh is the estimate at the last sample time, before the final truth step
    assert ekf.t == pytest.approx(9 * DT)

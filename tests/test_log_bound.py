"""The bound for the log at hand: the channels it samples and their rates, the log's interval; unobservable
channel sets named at once. Checked against independent paths: the single-rate bound of an observer built for
that channel set or interval, and the lifted Riccati equation for a periodic sampling pattern."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.scoring.bound import periodic_posterior, steady_state_covariance, unobservable_states
from exuflex.observer.session import ObserverConfig, make_observer
from exuflex.scoring.bound import UnobservableError, estimation_bound, steady_bound
from exuflex.scoring.run import observe_run
from exuflex.runs import Run, read_run
from exuflex.sensors import Signals
from exuflex.validate import check_run

ROOT = Path(__file__).resolve().parents[1]
MECH = load_mechanism(ROOT / "models" / "sixbar.toml")
SRC = read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")


@pytest.fixture(scope="module")
def obs():
    return make_observer(MECH)


def _blank(names) -> Run:
    S = SRC.sensors
    d = S.data.copy()
    for c in names:
        d[:, S.names.index(c)] = np.nan
    return Run(SRC.path, Signals(S.t, S.names, d, S.units), SRC.truth, dict(SRC.meta))


def _decimated(k: int) -> Run:
    S = SRC.sensors
    return Run(SRC.path, Signals(S.t[::k], S.names, S.data[::k], S.units), SRC.truth, dict(SRC.meta))


def test_periodic_posterior_equals_the_lifted_riccati_solution():
    """A channel every second interval: the period's mean posterior is (P+ + A P+ A' + Q) / 2 with P+ the DARE
    posterior of the system lifted over two intervals (A^2, A Q A' + Q)."""
    rng = np.random.default_rng(3)
    n = 4
    A = np.eye(n) + 0.05 * rng.standard_normal((n, n))
    A *= 0.98 / max(abs(np.linalg.eigvals(A)))
    G = rng.standard_normal((n, 2))
    Q = G @ G.T * 0.01 + 1e-4 * np.eye(n)
    H = rng.standard_normal((2, n))
    R = np.array([0.1, 0.2])
    P = periodic_posterior(A, Q, H, R, np.array([[True, True], [False, False]]), tol=1e-13)
    _, Pl = steady_state_covariance(A @ A, A @ Q @ A.T + Q, H, R)
    np.testing.assert_allclose(P, 0.5 * (Pl + A @ Pl @ A.T + Q), rtol=1e-8, atol=1e-12)
    # every interval, every channel: the DARE itself
    _, P1 = steady_state_covariance(A, Q, H, R)
    np.testing.assert_allclose(periodic_posterior(A, Q, H, R, np.ones((1, 2), bool), tol=1e-13), P1, rtol=1e-8)


def test_unobservable_states_pbh():
    """A double integrator seen through its velocity only: the position is unobservable, named."""
    dt = 0.01
    A = np.array([[1.0, dt], [0.0, 1.0]])
    assert unobservable_states(A, np.array([[0.0, 1.0]]), ["x", "v"]) == ["x"]
    assert unobservable_states(A, np.array([[1.0, 0.0]]), ["x", "v"]) == []


def test_blank_channel_bound_is_the_bound_without_it(obs):
    rep = check_run(MECH, _blank(["c4"]), obs.channels, dt=obs.ekf.dt)
    got = steady_bound(obs, log_check=rep)
    ref = steady_bound(make_observer(MECH, ObserverConfig(channels=("q1", "q2", "q3", "c1", "c2"))))
    assert got == pytest.approx(ref, rel=1e-9)
    full = steady_bound(obs)
    assert got["x25"] > 1.1 * full["x25"]  # c4 carries the tip's elastic motion


def test_half_rate_log_bound_is_the_bound_at_that_interval(obs):
    rep = check_run(MECH, _decimated(2), obs.channels, dt=obs.ekf.dt)
    got = steady_bound(obs, log_check=rep)
    ref = steady_bound(make_observer(MECH, ObserverConfig(dt=0.004)))
    assert got == pytest.approx(ref, rel=1e-9)


def test_gauges_only_names_the_unobservable_states_at_once(obs):
    rep = check_run(MECH, _blank(["q1", "q2", "q3"]), obs.channels, dt=obs.ekf.dt)
    with pytest.raises(UnobservableError, match=r"cannot observe .*q1.*rigid motion: add an encoder"):
        steady_bound(obs, log_check=rep)


def test_c4_blank_errors_within_1_5_of_that_logs_bound(obs):
    out = observe_run(MECH, _blank(["c4"]), observer=obs)
    assert out.summary["channels_used"] == ["q1", "q2", "q3", "c1", "c2"]
    worst = max(out.summary["ratio_to_bound"].items(), key=lambda kv: kv[1])
    assert worst[1] < 1.5, out.summary["ratio_to_bound"]


def test_250_hz_errors_within_1_5_of_that_logs_bound(obs):
    out = observe_run(MECH, _decimated(2), observer=obs)
    assert max(out.summary["ratio_to_bound"].values()) < 1.5, out.summary["ratio_to_bound"]

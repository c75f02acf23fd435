"""The bound along a record (:func:`exuflex.scoring.bound.riccati_track`, :func:`exuflex.scoring.bound.bound_track`).

Checked against independent paths: filterpy's Kalman filter and RTS smoother on a linear model (the bound of a
linear-Gaussian model is the Kalman filter's own covariance), the observer's own filter on that model, the
model's ``predict`` for the Jacobians the recursion takes, and the frozen steady state at a pose the trajectory
stays at.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from exuflex.mechanism import load_mechanism
from exuflex.observer import LinearDiscreteModel, MultirateEKF
from exuflex.scoring.bound import riccati_track
from exuflex.observer.session import ObserverConfig, make_observer, physical_names
from exuflex.runs import LogColumns
from exuflex.scoring.bound import _bound_model, _mid_q, _Sampled, _step_linearisation, _Trajectory, bound_track, estimation_bound, steady_bound
from exuflex.scoring.run import _scored, observe_run
from exuflex.runs import Run, read_run
from exuflex.sensors import Signals, truth_names

ROOT = Path(__file__).resolve().parents[1]
MECH = load_mechanism(ROOT / "models" / "sixbar.toml")
RUN = read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")


@pytest.fixture(scope="module")
def obs():
    return make_observer(MECH)


def _linear_case(n_steps=120, seed=4):
    """A stable random linear model (4 states, 2 channels), channel b at every third sample only, a sample with no
    channel at all; unequal intervals do not matter to a model discretised once (its F does not depend on dt)."""
    rng = np.random.default_rng(seed)
    n = 4
    A = np.eye(n) + 0.08 * rng.standard_normal((n, n))
    A *= 0.97 / max(abs(np.linalg.eigvals(A)))
    G = rng.standard_normal((n, 2))
    Q = G @ G.T * 0.01 + 1e-4 * np.eye(n)
    C = {"a": rng.standard_normal(n), "b": rng.standard_normal(n)}
    R = np.array([0.05, 0.2])
    sampled = np.ones((n_steps, 2), bool)
    sampled[np.arange(n_steps) % 3 != 0, 1] = False
    sampled[40] = False
    P0 = np.diag(rng.uniform(0.5, 2.0, n))
    t = np.arange(n_steps) * 0.01
    X = rng.standard_normal((n_steps, n))  # where it is linearised: irrelevant for a linear model
    return LinearDiscreteModel(A, None, C, Q), t, X, R, sampled, P0


def test_linear_bound_is_the_kalman_filters_covariance_filterpy_and_ours():
    """On a linear-Gaussian model the posterior Cramer-Rao bound is the Kalman filter's covariance: the recursion
    equals filterpy's ``KalmanFilter`` (Joseph form) sample by sample on a multirate schedule, and the observer's
    own filter on that model; its smoothed covariances equal filterpy's ``rts_smoother``'s."""
    model, t, X, R, sampled, P0 = _linear_case()
    n = model.nx
    full = lambda a, b, Xb, Pb: Pb.reshape(len(Pb), -1).copy()  # noqa: E731 - the whole covariance per sample
    track = riccati_track(model, t, X, None, ("a", "b"), R, P0, sampled, outputs=full, smooth=True, rows=17)
    kf = KalmanFilter(dim_x=n, dim_z=2)
    kf.F, kf.Q, kf.P = model.A, model.Q, P0.copy()
    H = np.array([model.C["a"], model.C["b"]])
    Ps, Fs, Qs = [], [], []
    for k in range(len(t)):
        if k:
            kf.predict()
        sel = sampled[k]
        if sel.any():
            kf.update(np.zeros(int(sel.sum())), R=np.diag(R[sel]), H=H[sel])
        Ps.append(kf.P.copy())
        Fs.append(model.A)
        Qs.append(model.Q)
    Ps = np.array(Ps)
    np.testing.assert_allclose(track.var.reshape(-1, n, n), Ps, rtol=1e-10, atol=1e-14)
    # the smoother: filterpy's on the same filtered covariances (its Fs[k], Qs[k] step k to k + 1)
    _, Psm, _, _ = kf.rts_smoother(np.zeros((len(t), n)), Ps, Fs=np.array(Fs), Qs=np.array(Qs))
    np.testing.assert_allclose(track.var_smoothed.reshape(-1, n, n), Psm, rtol=1e-9, atol=1e-14)
    # the observer's filter on the same model and schedule
    ekf = MultirateEKF(model, ("a", "b"), {"a": R[0] ** 0.5, "b": R[1] ** 0.5}, np.zeros(n), P0, dt=0.01)
    for k in range(len(t)):
        y = np.where(sampled[k], 0.0, np.nan)
        ekf.step(t[k], None, y)
        np.testing.assert_allclose(track.var[k].reshape(n, n), ekf.P, rtol=1e-10, atol=1e-14)


def test_the_recursions_jacobian_is_the_models_step_jacobian(obs):
    """The cached step's Jacobian and process noise without its sub-steps (:func:`_step_linearisation`) are those
    its ``predict`` returns, entry for entry, along the true trajectory (two models of their own, the same calls):
    a change to the step Jacobian in ``predict`` that the bound did not follow would show here."""
    S = RUN.sensors
    X = _Trajectory(obs, S.t, RUN.truth)[0:400]
    U = LogColumns.of(S, MECH.motor_names, hold=True)[0:400]
    a, b = _bound_model(obs), _bound_model(obs)
    lin = _step_linearisation(a)
    ks = range(1, 400)
    a.reset()  # (the models share the closure solver: one after the other, each from its reset)
    got = [lin(X[k - 1], U[k - 1], S.t[k] - S.t[k - 1]) for k in ks]
    b.reset()
    ref = [b.predict(X[k - 1], U[k - 1], S.t[k] - S.t[k - 1])[1:] for k in ks]
    for (F, Q), (Fr, Qr) in zip(got, ref, strict=True):
        np.testing.assert_array_equal(F, Fr)
        np.testing.assert_array_equal(Q, Qr)


def test_bound_along_the_truth_differs_little_from_the_bound_along_the_plan(obs):
    """The six-bar's ERLS log: the truth departs from the plan by the links' elastic motion; the bound's RMS over
    the scored samples moves by less than 1e-3 relative (measured 1.7e-4 at most, on q2) and no sample's
    standard deviation by more than 6 % (measured 2.9 %, on dx25): the plan is a good stand-in where no truth
    exists. And the two are not the same numbers: the truth does enter."""
    S = RUN.sensors
    U = LogColumns.of(S, MECH.motor_names, hold=True)
    along_truth, how = bound_track(obs, S.t, U, _Sampled(S, obs.channels), truth=RUN.truth)
    along_plan, how_plan = bound_track(obs, S.t, U, _Sampled(S, obs.channels))
    assert (how, how_plan) == ("truth", "plan")
    sel = _scored(S.t, obs.config.start_up, RUN.truth.t)
    rel = along_truth.rms(sel) / along_plan.rms(sel) - 1
    print(dict(zip(physical_names(MECH), np.round(rel, 6))))
    assert np.max(np.abs(rel)) < 1e-3
    assert np.max(np.abs(rel)) > 1e-6
    per_sample = np.sqrt(along_truth.var[sel] / along_plan.var[sel]) - 1
    assert np.max(np.abs(per_sample)) < 0.06


def test_steady_estimate_is_the_limit_of_the_bound_at_a_stationary_pose(obs):
    """A trajectory resting at one pose: the time-varying recursion converges to the frozen steady state
    (:func:`steady_bound` there), geometrically from the prior (relative difference 2e-4 at 2 s, 2e-5 at 3 s)."""
    q = _mid_q(MECH)
    t = np.arange(0.0, 3.0, 1.0 / MECH.sample_rate_hz)
    nq = len(q)
    rest = Signals(t, truth_names(MECH), np.hstack([np.tile(q, (len(t), 1)), np.zeros((len(t), nq + 4))]))
    track, _ = bound_track(obs, t, np.zeros((len(t), len(MECH.motors))), truth=rest)
    steady = steady_bound(obs, q=q)
    ref = np.array([steady[n] for n in physical_names(MECH)])
    err = [np.max(np.abs(np.sqrt(track.var[k]) / ref - 1)) for k in (len(t) // 3, 2 * len(t) // 3, len(t) - 1)]
    print(err)
    assert err[2] < 1e-4 and err[2] < err[1] < err[0]


def test_smoothed_bound_is_at_most_the_filtered_and_scores_the_smoother(obs):
    """The smoothed bound (RTS on the bound's covariances) is at most the filtered one at every sample and quantity,
    equal at the last sample; ``observe_run(smooth=True)`` scores the smoothed estimates against it and the
    filter's errors against the filtered bound."""
    out = observe_run(MECH, RUN, observer=obs, smooth=True, keep="physical")
    s = out.summary
    S = RUN.sensors
    track, _ = bound_track(obs, S.t, LogColumns.of(S, MECH.motor_names, hold=True), _Sampled(S, obs.channels),
                           truth=RUN.truth, smooth=True)
    assert np.all(track.var_smoothed <= track.var * (1 + 1e-9))
    np.testing.assert_allclose(track.var_smoothed[-1], track.var[-1], rtol=1e-12)
    sel = _scored(S.t, s["metrics_from_s"], RUN.truth.t)
    names = physical_names(MECH)
    assert s["bound_rms"] == pytest.approx(dict(zip(names, track.rms(sel, smoothed=True))), rel=1e-12)
    assert s["filtered_bound_rms"] == pytest.approx(dict(zip(names, track.rms(sel))), rel=1e-12)
    assert s["bound_kind"].startswith("smoothed posterior Cramer-Rao bound along the truth")
    for k in names:
        assert s["ratio_to_bound"][k] == pytest.approx(s["rms_error"][k] / s["bound_rms"][k])
        assert s["filtered_ratio_to_bound"][k] == pytest.approx(s["filtered_rms_error"][k] / s["filtered_bound_rms"][k])


def test_a_blank_channel_is_left_out_of_the_schedule():
    """A log whose gauge c4 is blank: its bound is that of an observer without c4 on the same log (the recursion
    updates each channel at the samples that hold it)."""
    S = RUN.sensors
    d = S.data.copy()
    d[:, S.names.index("c4")] = np.nan
    blank = Run(RUN.path, Signals(S.t, S.names, d, S.units), RUN.truth, dict(RUN.meta))
    with_c4 = make_observer(MECH)
    without = make_observer(MECH, ObserverConfig(channels=("q1", "q2", "q3", "c1", "c2")))
    got = estimation_bound(with_c4, blank)
    ref = estimation_bound(without, RUN)
    assert got == pytest.approx(ref, rel=1e-12)
    assert got["x25"] > 1.1 * estimation_bound(with_c4, RUN)["x25"]  # c4 carries the tip's elastic motion


def test_smoothed_bound_stays_bounded_with_an_undriven_damped_mode():
    """A mode that halves every sample and no process noise drives (a damped mode the torques do not excite), in a
    basis where it mixes with the others: the RTS gain is 2 along it and the RTS backward pass multiplies the
    rounding there by 4 a sample (on these filtered covariances its smoothed variances exceed the filtered ones by
    orders of magnitude: 8e2 to 1e11 over eight random bases); the modified Bryson-Frazier form stays at or
    below the filtered bound. (Where both hold they agree: the filterpy comparison of the multirate test.)"""
    from exuflex.observer.smoother import rts_backward

    T, _ = np.linalg.qr(np.random.default_rng(0).standard_normal((3, 3)))
    A = T @ np.array([[1.0, 0.01, 0.0], [0.0, 0.99, 0.0], [0.0, 0.0, 0.5]]) @ T.T
    Q = T @ np.diag([1e-6, 1e-4, 0.0]) @ T.T
    model = LinearDiscreteModel(A, None, {"y": T @ np.array([1.0, 0.0, 1.0])}, Q)
    n = 300
    t, X = np.arange(n) * 0.01, np.zeros((n, 3))
    full = lambda a, b, Xb, Pb: Pb.reshape(len(Pb), -1).copy()  # noqa: E731
    track = riccati_track(model, t, X, None, ("y",), np.array([1e-4]), np.eye(3), outputs=full, smooth=True)
    P, Ps = track.var.reshape(-1, 3, 3), track.var_smoothed.reshape(-1, 3, 3)
    d, ds = np.diagonal(P, axis1=1, axis2=2), np.diagonal(Ps, axis1=1, axis2=2)
    assert np.all(np.isfinite(ds)) and np.all(ds <= d * (1 + 1e-9))
    with np.errstate(all="ignore"):
        _, Prts = rts_backward(P, np.array([A] * n), np.array([Q] * n))
    assert np.nanmax(np.abs(np.diagonal(Prts, axis1=1, axis2=2)) / d) > 1e2


def _without_truth(tmp_path: Path, rows: int = 300) -> Path:
    """The first ``rows`` samples of the six-bar's run folder without its truth (a lab's log)."""
    import json

    src = ROOT / "tests" / "data" / "sixbar_erls_3s"
    out = tmp_path / "no_truth"
    out.mkdir()
    lines = (src / "sensors.csv").read_text().splitlines(keepends=True)
    (out / "sensors.csv").write_text("".join(lines[: rows + 1]))
    (out / "manoeuvre.toml").write_text((src / "manoeuvre.toml").read_text())
    meta = json.loads((src / "meta.json").read_text())
    meta["truth"] = []
    (out / "meta.json").write_text(json.dumps(meta))
    return out


def test_observe_scores_against_the_bound_and_leaves_the_plans_bound_to_bound(tmp_path, capsys):
    """``exuflex observe``: a log without a truth has nothing to score, and its bound (along the plan) costs about
    as much as the filter: it is computed with ``--bound`` only (the same figures as the library's default), while
    an unobservable channel set is still reported without it. With a truth the bound is always there."""
    import json

    from exuflex.cli import main
    from exuflex.cli.observe import run_manoeuvre

    bare = _without_truth(tmp_path)
    sixbar = str(ROOT / "models" / "sixbar.toml")
    assert main(["observe", sixbar, str(bare), "--json"]) == 0
    cap = capsys.readouterr()
    s = json.loads(cap.out)
    assert "bound_rms" not in s and "no truth: no bound (--bound" in cap.err
    assert main(["observe", sixbar, str(bare), "--json", "--bound"]) == 0
    s = json.loads(capsys.readouterr().out)
    run = read_run(bare)
    ref = observe_run(run_manoeuvre(MECH, run), run).summary  # (the plan of the manoeuvre file the run names)
    assert s["bound_for"]["along"] == "plan" and s["bound_rms"] == pytest.approx(ref["bound_rms"], rel=1e-12)
    assert main(["observe", sixbar, str(bare), "--json", "--channels", "c1,c2,c4"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert "cannot observe" in s["unobservable"] and "bound_rms" not in s
    assert main(["observe", sixbar, str(bare)]) == 0
    assert "no truth to score against and no bound" in capsys.readouterr().out
    with pytest.raises(ValueError, match="with_bound"):
        observe_run(MECH, read_run(bare), with_bound="plan")

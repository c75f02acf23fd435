"""The reduced-order EKF on the six-bar: bound, observability, offline = online, convergence, fast path.

The log is the paper's setting: the manoeuvre simulated by the full-order ERLS model with Table 3 noise
(``exuflex simulate models/sixbar.toml --engine erls --integrator rk4 --duration 3 --seed 1``, stored in
``tests/data/sixbar_erls_3s``). The Exudyn truth and the 50-run consistency study are in
``benchmarks/observer_accuracy.py`` and the slow tests.
"""

from pathlib import Path

import numpy as np
import pytest

from exuflex.data import paper_reference
from exuflex.manoeuvre import plan
from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, estimate, make_observer, physical_names
from exuflex.scoring.bound import estimation_bound, steady_bound
from exuflex.scoring.physical import physical_covariance
from exuflex.scoring.run import held_error_summary, metrics
from exuflex.runs import read_run
from exuflex.sensors import tip_point

MODELS = Path(__file__).resolve().parents[1] / "models"
DATA = Path(__file__).resolve().parent / "data"
DT = 0.002


@pytest.fixture(scope="module")
def sixbar():
    return load_mechanism(MODELS / "sixbar.toml")


@pytest.fixture(scope="module")
def observer(sixbar):
    return make_observer(sixbar)


@pytest.fixture(scope="module")
def erls_log():
    return read_run(DATA / "sixbar_erls_3s")


def _arrays(run, channels, n):
    S = run.sensors
    return S.t[:n], S.select(run.motors).data[:n], S.select(channels).data[:n]


def _independent_bound(mech, q, channels, dt, elastic_mass=None):
    """Steady-state Kalman filter on the full-order model (30 dofs) linearised at rest at q: exact ZOH
    discretisation of its state matrix, the measured torques' noise held over the interval as the process noise,
    the channels' rows by finite differences of the truth's sensor model (:func:`exuflex.sensors.sensor_channels`
    on :func:`~exuflex.sensors.erls_probe_record`), the Riccati recursion to its fixed point; RMS after an update.
    ``elastic_mass``: replaces the model's damping mass (the old convention ``M_uu``, for the stored reference)."""
    import scipy.linalg as sla

    from exuflex.erls.model import ErlsModel
    from exuflex.sensors import erls_probe_record, sensor_channels

    model = ErlsModel(mech)
    if elastic_mass is not None:
        model.elastic_mass = lambda cfg: elastic_mass(model, cfg)
    n, nq = model.n, model.nq
    cfg = model.configuration(q)
    A, Minv = model.state_matrix(cfg)
    B = np.zeros((2 * n, len(mech.motors)))
    B[n:] = Minv @ model.input_matrix(cfg)
    m = B.shape[1]
    E = sla.expm(np.block([[A, B], [np.zeros((m, 2 * n + m))]]) * dt)
    Ad, Bd = E[: 2 * n, : 2 * n], E[: 2 * n, 2 * n :]
    Qd = Bd @ np.diag([mo.noise_std**2 for mo in mech.motors]) @ Bd.T
    x0 = np.zeros(2 * n)
    x0[:nq] = q
    eps = 1e-7
    Y = np.vstack([x0] + [x0 + eps * e for e in np.eye(2 * n)])
    sig = sensor_channels(mech, erls_probe_record(model, np.arange(len(Y)) * 1e-3, Y))
    cols = [sig.names.index(c) for c in channels]
    C = ((sig.data[1:, cols] - sig.data[0, cols]) / eps).T
    R = np.diag([next(s for s in mech.sensors if s.name == c).noise_std ** 2 for c in channels])
    P = Qd.copy()
    for _ in range(100000):
        new = Ad @ (P - P @ C.T @ np.linalg.solve(C @ P @ C.T + R, C @ P)) @ Ad.T + Qd
        if np.allclose(new, P, rtol=1e-10, atol=1e-14 * np.abs(new).max()):
            break
        P = 0.5 * (new + new.T)
    P = P - P @ C.T @ np.linalg.solve(C @ P @ C.T + R, C @ P)
    out = {}
    for j, c in enumerate(mech.coordinate_names):
        out[c], out["d" + c] = np.sqrt(P[j, j]), np.sqrt(P[n + j, n + j])
    for name in ("x25", "y26"):
        i = model.index(name)
        out[name], out["d" + name] = np.sqrt(P[i, i]), np.sqrt(P[n + i, n + i])
    return out


def test_bound_matches_independent_riccati_solution(sixbar, observer):
    """The observer's bound (13-dof reduced model) at mid-path against an independent steady-state Kalman filter
    on the full-order model (:func:`_independent_bound`), within 10 %. The independent solution is itself checked
    against the team's stored one (``exuflex_reference``, 30 dofs), which used the earlier damping convention
    ``alpha M_uu + beta K_uu`` on the elastic block: with that convention it reproduces it within 5 %. (With the
    stated damping, ``docs/validity.md``, the rates and the tip are less damped and their bound is 19-33 % higher.)"""
    ref = paper_reference()["exuflex_reference"]["rms_bound_steady_state_kf"]
    stored = dict(zip(ref["columns"], ref["rows"]["mid-path, 30 dofs, encoders + gauges"]))
    from exuflex.scoring.bound import _mid_q

    q = _mid_q(sixbar)
    channels = ("q1", "q2", "q3", "c1", "c2", "c4")
    assert tuple(observer.channels) == channels
    old = _independent_bound(sixbar, q, channels, DT, elastic_mass=lambda m, cfg: m.T.T @ cfg.M_N @ m.T)
    for name, value in stored.items():
        assert old[name] == pytest.approx(value, rel=0.05), name
    expected = _independent_bound(sixbar, q, channels, DT)
    got = steady_bound(observer, q=q)  # the bound at mid-path, at rest
    for name, value in expected.items():
        assert got[name] == pytest.approx(value, rel=0.1), name


def test_observability_of_the_papers_sensor_set(sixbar, observer):
    qs = plan(sixbar, dt=0.5, t_end=3.0).q
    nx = observer.model.nx
    full = observability(observer.model, sixbar, ("q1", "q2", "q3", "c1", "c2", "c4"), qs)
    enc = observability(observer.model, sixbar, ("q1", "q2", "q3"), qs)
    gauges = observability(observer.model, sixbar, ("c1", "c2", "c4"), qs)
    assert np.all(full[0] == nx)
    assert not np.all(gauges[0] == nx)  # strain gauges cannot see the rigid positions
    assert np.all(enc[1] < 0.01 * full[1])  # encoders alone: barely observable

def observability(som, mech, channels, qs, rank_tol=1e-9):
    """``(rank, smallest singular value)`` per configuration ``qs`` of the observability matrix ``O = [H; H A; ...;
    H A^(n-1)]`` of the reduced model linearised over one interval at rest, on a scaled state (1 rad, 1 rad/s for
    the rigid coordinates, 1 mm and 0.1 m/s for the elastic ones) with each channel divided by its noise: a
    singular value of 1 is one noise standard deviation per unit of scaled state (the paper's argument for its
    encoders and strain gauges)."""
    nq, r = som.nq, som.r
    d = np.concatenate([np.ones(nq), np.full(r - nq, 1e-3), np.ones(nq), np.full(r - nq, 0.1)])
    noise = np.array([{s.name: s.noise_std for s in mech.sensors}[c] for c in channels])
    ranks, smin = [], []
    for q in np.atleast_2d(np.asarray(qs, float)):
        z = som.initial_state(q)
        A = som.frozen_interval(z, np.zeros(len(mech.motors)), 1.0 / mech.sample_rate_hz)[0].F
        As, M = A * d[None, :] / d[:, None], som.measure(z, channels)[1] * d[None, :] / noise[:, None]
        blocks = []
        for _ in range(som.nx):
            blocks.append(M)
            M = M @ As
        sv = np.linalg.svd(np.vstack(blocks), compute_uv=False)
        ranks.append(int(np.sum(sv > rank_tol * sv[0])))
        smin.append(float(sv[-1]))
    return np.array(ranks), np.array(smin)



def test_offline_run_equals_online_steps(sixbar, observer, erls_log):
    t, U, Y = _arrays(erls_log, observer.channels, 60)
    res = observer.ekf.run(t, U, Y)
    obs2 = make_observer(sixbar)
    online = np.array([obs2.ekf.step(t[k], U[k], Y[k]) for k in range(len(t))])
    np.testing.assert_array_equal(res.x_hat, online)


def test_rerun_of_a_reused_observer_is_identical(sixbar, observer, erls_log):
    """A run does not depend on what the observer did before (held configuration, cached rows, the closure
    solver used elsewhere in between): a study worker gives the same numbers whatever it did first."""
    t, U, Y = _arrays(erls_log, observer.channels, len(erls_log.sensors.t))
    a = observer.ekf.run(t[:40], U[:40], Y[:40]).x_hat
    observer.ekf.run(t[-10:], U[-10:], Y[-10:])  # another record in between, at the far end of the path
    b = observer.ekf.run(t[:40], U[:40], Y[:40]).x_hat
    np.testing.assert_array_equal(a, b)
    # the closure solver used elsewhere in between (another run's end of the path, an absolute-tip evaluation)
    q_end = np.array([erls_log.truth[n][-1] for n in sixbar.coordinate_names])
    observer.model.model.kin.pose(q_end)
    np.testing.assert_array_equal(observer.ekf.run(t[:40], U[:40], Y[:40]).x_hat, a)


def test_converges_from_wrong_start_within_twice_the_bound(sixbar, observer, erls_log):
    """0.05 rad off on every q at the start: after 0.3 s the errors are within 2x the bound, and the start is
    forgotten (the estimates equal those of a correctly started filter to well below the bound)."""
    t, U, Y = _arrays(erls_log, observer.channels, len(erls_log.sensors.t))
    q0 = erls_log.truth.data[0, :3]
    good = observer.physical(t, observer.ekf.run(t, U, Y).x_hat)
    observer.ekf.reset(x0=observer.model.initial_state(q0 + 0.05))
    res = observer.ekf.run(t, U, Y, reset=False)
    phys = observer.physical(res.t, res.x_hat)
    m = metrics(phys, erls_log.truth, start_up=0.3)
    forgotten = metrics(phys, good, start_up=0.3)["rms_error"]
    bound = estimation_bound(observer)
    for name in ("q1", "q2", "q3", "dq1", "dq2", "dq3"):
        assert m["rms_error"][name] < 2 * bound[name], (name, m["rms_error"][name], bound[name])
        assert forgotten[name] < 0.3 * bound[name], (name, forgotten[name], bound[name])
    assert not res.diverged


def test_cached_path_evaluates_few_configurations_and_tracks(sixbar, observer, erls_log):
    """The cached step evaluates the configuration a few dozen times in 3 s (against 1500 intervals) and its
    errors stay within 1.5 times the steady-state bound (its agreement with the exact reference: the slow
    ``test_fast_steps_agree_with_the_papers_rk4_reference``)."""
    t, U, Y = _arrays(erls_log, observer.channels, len(erls_log.sensors.t))
    before = observer.model.n_refresh
    fast = estimate(observer, t, U, Y)
    evaluations = observer.model.n_refresh - before
    err = metrics(fast.physical, erls_log.truth, start_up=0.3)["rms_error"]
    bound = estimation_bound(observer)
    print({name: round(err[name] / bound[name], 3) for name in err}, evaluations, "evaluations")
    assert evaluations < 100
    for name in physical_names(sixbar):
        assert err[name] < 1.6 * bound[name], (name, err[name], bound[name])


def test_torque_jump_between_samples_is_flagged_and_modelled(sixbar, observer, erls_log):
    """The stored log's computed torque jumps twice (the trapezoid's acceleration ends, at 0.08 s at a sample, at
    2.92 s 0.1 ms after one: the time law before its correction). Both are flagged, no other interval is, and
    with the jump's effect the innovations after 2.92 s stay consistent (without: NIS ~20 for 6 channels)."""
    t, U, Y = _arrays(erls_log, observer.channels, len(erls_log.sensors.t))
    jumps = make_observer(sixbar, ObserverConfig(jump_p=1e-6), cb=observer.model.rm.cb)
    res = jumps.ekf.run(t, U, Y)
    assert jumps.model.n_jumps == 2
    plain = make_observer(sixbar, ObserverConfig(jump_p=None, gate_p=None, fault_window=0), cb=observer.model.rm.cb)
    res0 = plain.ekf.run(t, U, Y)
    assert plain.model.n_jumps == 0
    after = (t > 2.92) & (t < 2.97)
    nis, nis0 = np.nanmean(res.nis[after]), np.nanmean(res0.nis[after])
    print(f"mean NIS 2.92-2.97 s: {nis:.2f} with the jump test, {nis0:.2f} without")
    assert nis < 9.0 < 2 * nis < nis0
    # before 2.92 s the two differ only through the start-up's jump (at a sample: the flagged interval takes it
    # within, the truth at its end): far below the estimation error after the start-up
    sel = (t >= 0.3) & (t < 2.92)
    pa, pb = jumps.physical(t[sel], res.x_hat[sel]), plain.physical(t[sel], res0.x_hat[sel])
    diff = metrics(pa, pb, start_up=0.0)["rms_error"]
    err = metrics(pb, erls_log.truth, start_up=0.0)["rms_error"]
    print({n: round(diff[n] / err[n], 3) for n in err})
    for name in physical_names(sixbar):
        assert diff[name] < 0.2 * err[name], (name, diff[name], err[name])


@pytest.mark.parametrize("method", ["cached", "rk4"])
def test_jump_moments_are_those_of_a_jump_at_a_uniform_sub_step(sixbar, observer, method):
    """input_jump_moments: the mean and covariance over j = 1..n of the response to the jump held over the last
    n - j RK4 sub-steps (``step_maps`` over n - j steps; none for j = n), with the matrices of the last step."""
    from exuflex.observer.expansion import step_maps
    from exuflex.observer.reduced import ReducedObserverModel

    som = ReducedObserverModel(observer.model.rm, method=method, jump_p=1e-6)
    z = som.initial_state(plan(sixbar, dt=1.5, t_end=1.5).q[1])
    z[som.r : som.r + 3] = [0.3, -0.2, 0.1]
    som.predict(z, np.array([1.0, 2.0, 0.0]), DT)
    d = np.array([-1.3, -14.0, 0.05])
    assert som.input_jump(np.zeros(3), d) is not None and som.input_jump(np.zeros(3), 1e-3 * d) is None
    mean, cov = som.input_jump_moments(d)
    Mr, Kr, Cr, Gr, h, n = som._interval_matrices
    assert n * h == pytest.approx(DT)
    if method == "rk4":
        m = som._last.mats
        assert np.array_equal(Mr, m.Mr) and np.array_equal(Kr, m.Kr)
    R = np.array([step_maps(np.linalg.inv(Mr), Kr, Cr, Gr, h, n - j)[2] @ d for j in range(1, n)]
                 + [np.zeros(som.nx)])
    np.testing.assert_allclose(mean, R.mean(axis=0), rtol=1e-9, atol=1e-12 * np.abs(R).max())
    np.testing.assert_allclose(cov, np.cov(R.T, bias=True), rtol=1e-8, atol=1e-12 * np.abs(cov).max())


def test_fft_of_estimated_tip_matches_the_truths_peaks(sixbar, observer, erls_log):
    """Significant spectral peaks (>= 10 % of the largest, 5-180 Hz) of the true tip elastic displacement are
    found in the estimate's spectrum within 2 % (paper Fig. 10)."""
    from exuflex.scoring.stats import fft_peaks, match_peaks

    t, U, Y = _arrays(erls_log, observer.channels, len(erls_log.sensors.t))
    phys = observer.physical(t, observer.ekf.run(t, U, Y).x_hat)
    sel = phys.t >= 0.3
    for name in ("x25", "y26"):
        truth = np.interp(phys.t[sel], erls_log.truth.t, erls_log.truth[name])
        ft, at = fft_peaks(phys.t[sel], truth, fmax=180.0, n_peaks=6, fmin=5.0, return_amplitudes=True)
        fe = fft_peaks(phys.t[sel], phys[name][sel], fmax=180.0, n_peaks=6, fmin=5.0)
        _, err = match_peaks(ft[at >= 0.1 * at.max()], fe)
        assert np.all(err < 2.0), (name, ft, fe, err)


def test_missing_samples_are_predictions_and_counted(sixbar, observer, erls_log):
    t, U, Y = _arrays(erls_log, observer.channels, 80)
    Y = Y.copy()
    Y[10:15] = np.nan  # a gap
    Y[20:40:2, 3:] = np.nan  # gauges at half rate
    res = observer.ekf.run(t, U, Y)
    assert res.n_missing == 5
    assert np.all(np.isfinite(res.x_hat))


def test_physical_names_follow_the_truth_columns(sixbar):
    assert physical_names(sixbar) == ("q1", "q2", "q3", "dq1", "dq2", "dq3", "x25", "y26", "dx25", "dy26")


def test_cli_observes_a_lab_csv_with_a_channel_map(tmp_path, erls_log, capsys):
    """A lab log: other column names, time in milliseconds, mapped on the command line."""
    import json

    from exuflex.cli import main

    S = erls_log.sensors
    cols = {"T1": "m1", "T2": "m2", "T3": "m3", "q1": "enc1", "q2": "enc2", "q3": "enc3", "c1": "sg1",
            "c2": "sg2", "c4": "sg4"}
    n = 400
    lines = ["t_ms," + ",".join(cols.values())]
    lines += [f"{S.t[k] * 1000:.6f}," + ",".join(repr(float(S[c][k])) for c in cols) for k in range(n)]
    (tmp_path / "lab.csv").write_text("\n".join(lines) + "\n")
    rc = main(["observe", str(MODELS / "sixbar.toml"), str(tmp_path / "lab.csv"), "--json", "--time-column", "t_ms",
               "--time-scale", "1e-3", "--map", ",".join(f"{k}={v}" for k, v in cols.items()),
               "--truth", str(DATA / "sixbar_erls_3s" / "truth.csv")])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["n_updates"] == n
    assert out["rms_error"]["q1"] < 3 * out["bound_rms"]["q1"]


@pytest.mark.slow
def test_fast_steps_agree_with_the_papers_rk4_reference(sixbar, observer, erls_log):
    """The paper's scheme (every RK4 stage with its own matrices: the exact reference) vs the cached step: after the
    0.3 s start-up the estimates differ by a fraction of the bound."""
    t, U, Y = _arrays(erls_log, observer.channels, 301)
    cb = observer.model.rm.cb
    ref = estimate(make_observer(sixbar, ObserverConfig(method="rk4"), cb=cb), t, U, Y).physical
    bound = estimation_bound(observer)
    est = estimate(make_observer(sixbar, ObserverConfig(method="cached"), cb=cb), t, U, Y).physical
    diff = metrics(est, ref, start_up=0.3)["rms_error"]
    print({name: round(diff[name] / bound[name], 3) for name in diff})
    for name in physical_names(sixbar):
        assert diff[name] < 0.5 * bound[name], (name, diff[name], bound[name])


def test_runaway_estimate_is_a_divergence_not_a_model_error(sixbar):
    """Encoders reading 0 rad (dead channels) under torques 1e5 times too large (a unit error in the log):
    the estimate runs away until the loops cannot close; that must surface as FilterDivergedError, never as
    a KinematicsError blaming the model file. With the right torques and dead encoders the run must not pass
    silently either: the NIS test flags it, or the estimate runs away into a FilterDivergedError (which of the two
    depends on the model's damping: with the stated damping, ``docs/validity.md``, the estimate goes non-finite
    at 18 ms; with the earlier ``alpha M_uu`` it settled on the wrong configuration)."""
    from exuflex.observer import FilterDivergedError

    obs = make_observer(sixbar)
    t = np.arange(200) * DT
    U = np.tile([-2.0, -5.0, 0.02], (len(t), 1))
    Y = np.zeros((len(t), len(obs.channels)))
    with np.errstate(over="ignore", invalid="ignore"), pytest.raises(FilterDivergedError):
        obs.ekf.run(t, 1e5 * U, Y)
    # the NIS test, without the per-channel gate (which, with half the channels dead from the first sample, may
    # reject the live ones' partners and let the estimate run away: a FilterDivergedError, never silent)
    plain = make_observer(sixbar, ObserverConfig(gate_p=None, fault_window=0), cb=obs.model.rm.cb)
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            res = plain.ekf.run(t, U, Y)
    except FilterDivergedError:
        return
    assert res.nis_flagged and not res.diverged and not res.nonfinite


def test_autocorrelation_time_of_white_and_correlated_sequences():
    from exuflex.scoring.stats import autocorrelation_time, mc_consistency

    rng = np.random.default_rng(3)
    white = rng.chisquare(6, size=(20, 2000))
    assert autocorrelation_time(white) == pytest.approx(1.0, abs=0.2)
    # AR(1) with coefficient a: tau = (1 + a) / (1 - a) = 19 for a = 0.9
    e = np.zeros((20, 4000))
    for k in range(1, e.shape[1]):
        e[:, k] = 0.9 * e[:, k - 1] + rng.normal(size=20)
    assert autocorrelation_time(e) == pytest.approx(19.0, rel=0.15)
    chk = mc_consistency(white, 6)
    assert chk.time_avg_lo_eff <= chk.time_avg <= chk.time_avg_hi_eff
    assert chk.time_avg_hi_eff - chk.time_avg_lo_eff == pytest.approx(chk.time_avg_hi - chk.time_avg_lo, rel=0.15)


@pytest.mark.slow
@pytest.mark.parametrize("engine", ["reduced", "erls"])
def test_filter_is_consistent(engine):
    """NEES (the 10 physical quantities) and NIS over 50 seeded runs, the truth the observer's own reduced model
    (engine "reduced") or the full-order ERLS model (the paper's setting), default settings (stated noise): the
    run averages stay inside their 95 % bands. The truncated modes and the cached step map add no measurable
    inconsistency (``benchmarks/observer_accuracy.py``, seeds 1000-1049: ERLS NEES 97.9 % of the steps, 10.20;
    NIS 94.7 %, 6.003)."""
    from exuflex.measure import measure
    from exuflex.scoring.stats import mc_consistency
    from exuflex.truth import plan_drive, simulate

    sixbar = load_mechanism(MODELS / "sixbar.toml")
    drive = plan_drive(sixbar, 3.0, 1e-4)
    lt = simulate(sixbar, drive, engine, 3.0, 1e-4)
    obs = make_observer(sixbar)
    obs.ekf.store_P = "full"
    names = physical_names(sixbar)
    nees_runs, nis_runs, dof = [], [], []
    for j in range(50):
        S = measure(sixbar, lt.clean, lt.torque_t, lt.torques, seed=2000 + j).signals
        res = obs.ekf.run(S.t, S.select(sixbar.motor_names).data, S.select(obs.channels).data)
        assert not res.diverged
        phys = obs.physical(res.t, res.x_hat)
        e = np.column_stack([phys[n] - np.interp(phys.t, lt.truth.t, lt.truth[n]) for n in names])
        P = physical_covariance(obs, res.x_hat, res.P)
        nees_runs.append(np.einsum("ki,ki->k", e, np.linalg.solve(P, e[:, :, None])[:, :, 0]))
        nis_runs.append(res.nis)
        dof.append(res.nis_dof)
    burn = 150
    cn = mc_consistency(np.array(nees_runs), len(names), burn_in=burn)
    ci = mc_consistency(np.array(nis_runs), np.array(dof), burn_in=burn)
    print(f"{engine}: NEES inside {cn.fraction_inside:.3f}, mean {cn.time_avg:.3f} band {cn.time_avg_lo_eff:.3f}.."
          f"{cn.time_avg_hi_eff:.3f}; NIS inside {ci.fraction_inside:.3f}, mean {ci.time_avg:.3f} band "
          f"{ci.time_avg_lo_eff:.3f}..{ci.time_avg_hi_eff:.3f}")
    assert cn.fraction_inside > 0.9 and ci.fraction_inside > 0.9
    assert cn.time_avg_lo_eff <= cn.time_avg <= cn.time_avg_hi_eff
    assert ci.time_avg_lo_eff <= ci.time_avg <= ci.time_avg_hi_eff


def test_measurement_rows_of_all_channels_equal_the_per_channel_rows(sixbar, erls_log):
    """The reduced observer's measurement rows for a tuple of channels (:class:`exuflex.observer.rows.ChannelRows`,
    all channels in a few array operations) equal those of :func:`exuflex.observer.rows.sensor_rows` channel by
    channel (the reference, shared with the full-order observer), at held configurations along the 3 s log's
    true states, for every kind of sensor the six-bar has (encoders, relative encoder, gauges, tip position)."""
    from exuflex.observer.rows import sensor_rows

    obs = make_observer(sixbar, ObserverConfig())
    m = obs.model
    channels = tuple(s.name for s in sixbar.sensors)
    truth = erls_log.truth
    Q = truth.select(list(sixbar.coordinate_names)).data[::100]
    for q in Q:
        iv = m._configuration(m.initial_state(q))
        c0, Hm = m._affine(iv, channels)
        cfg, Hu = iv.mats.rc.cfg, iv.mats.rc.H[m.nq :]
        for i, ch in enumerate(channels):
            kind, rigid, urow = sensor_rows(m.model, cfg, m.sensors[ch], m.link_names)
            row = np.zeros(m.nx)
            row[: m.r] = urow @ Hu
            c = 0.0
            if kind == "angle":
                rq = rigid @ iv.Sz_theta
                c = rigid @ iv.theta0 - rq @ iv.q0
                row[: m.nq] += rq
            elif kind == "point":
                c = rigid[0] - rigid[1] @ iv.q0
                row[: m.nq] += rigid[1]
            np.testing.assert_allclose(Hm[i], row, rtol=0, atol=1e-13 * np.abs(row).max())
            assert c0[i] == pytest.approx(c, rel=1e-13, abs=1e-15)


def test_a_blank_channel_and_a_channel_left_out_give_the_same_estimates(sixbar, observer, erls_log):
    """One path for every sample: the c4 column blank in the log, and c4 left out of the observer's channels,
    filter the same measurements the same way (relative difference <= 1e-9)."""
    n = 400
    t, U, Y = _arrays(erls_log, observer.channels, n)
    j = observer.channels.index("c4")
    blank = Y.copy()
    blank[:, j] = np.nan
    a = estimate(make_observer(sixbar, ObserverConfig(), cb=observer.model.rm.cb), t, U, blank).result.x_hat
    fewer = make_observer(sixbar, ObserverConfig(channels=tuple(c for c in observer.channels if c != "c4")),
                          cb=observer.model.rm.cb)
    b = estimate(fewer, t, U, np.delete(Y, j, axis=1)).result.x_hat
    scale = np.abs(a).max(axis=0)
    assert np.all(np.abs(a - b) <= 1e-9 * scale)


@pytest.fixture(scope="module")
def arm():
    """The single link (its tip master across the arm, in the link's frame: the tip rows turn with q)."""
    mech = load_mechanism(MODELS / "single_link.toml")
    return mech, make_observer(mech)


def _turning_states(observer, mech, n=201, dt=1e-3):
    """States along a line in q at constant rates, with a constant elastic deflection (zero elastic rates): the
    tip's deflection turns with its link."""
    som = observer.model
    nq, r = som.nq, som.r
    rng = np.random.default_rng(3)
    qd = np.linspace(0.9, 1.2, nq)
    t = np.arange(n) * dt
    Z = np.zeros((n, som.nx))
    Z[:, :nq] = np.asarray(mech.q_ref, float) + 0.3 + np.outer(t, qd)
    Z[:, nq:r] = 1e-3 * rng.standard_normal(r - nq)
    Z[:, r : r + nq] = qd
    return t, Z


def test_tip_rate_is_the_time_derivative_of_the_tip_deflection(arm):
    """The truth's tip rate is d/dt of the global elastic displacement (``p_tip' - J q'``), which turns with the
    link: along states whose elastic coordinates are constant while q turns, the estimated rate equals the central
    difference in time of the estimated displacement (not zero, which the rows times p' alone would give)."""
    mech, observer = arm
    t, Z = _turning_states(observer, mech)
    names = physical_names(mech)
    exact = observer.physical(t, Z, refresh_rad=0.0)  # the rows and their q-derivatives at every sample
    e = np.column_stack([exact[n] for n in names[2:4]])
    fd = (e[2:] - e[:-2]) / (t[2:] - t[:-2])[:, None]
    scale = np.max(np.abs(fd))
    assert scale > 1e-4  # a deflection of about a mm turning at about 1 rad/s
    # exact rows; the default's held derivatives between refreshes 1e-2 rad apart (first order in the rows, zeroth
    # in the turning term of the rate: about 1e-2 of it)
    for phys, tol in ((exact, 1e-3), (observer.physical(t, Z), 2e-2)):
        ed = np.column_stack([phys[n] for n in names[4:6]])
        assert np.max(np.abs(ed[1:-1] - fd)) < tol * scale
        disp = np.column_stack([phys[n] for n in names[2:4]])
        assert np.max(np.abs(disp - e)) < 1e-4 * np.max(np.abs(e))  # (1e-2 rad)^2 / 2 of the deflection


def test_physical_in_blocks_is_one_call_and_the_row_formula(arm):
    """:meth:`Observer.physical` on a record cut into blocks (``carry``) gives the numbers of one call on the whole
    record, bit for bit, with non-finite rows left NaN and not moving the evaluation; each row is the stated
    formula ``A p + C (G p)^2``, ``A p' + sum_i (dA/dq_i p) q'_i + C' (G p)^2 + 2 C ((G p) (G p' + G' p))``
    (``'``: along q') with ``A``, ``C``, ``G`` moved to first order from the evaluation in force (maps evaluated
    where q left the radius), computed here sample by sample."""
    mech, observer = arm
    t, Z = _turning_states(observer, mech, n=300)
    Z[[17, 18, 140]] = np.nan
    nq, r = observer.model.nq, observer.model.r
    whole = observer.physical(t, Z, refresh_rad=0.05)
    carry: dict = {}
    parts = [observer.physical(t[a:b], Z[a:b], refresh_rad=0.05, carry=carry).data
             for a, b in ((0, 1), (1, 18), (18, 100), (100, 300))]
    np.testing.assert_array_equal(np.vstack(parts), whole.data)
    names = physical_names(mech)
    tip = np.column_stack([whole[n] for n in names[2 * nq : 2 * nq + 4]])
    assert np.isnan(tip[[17, 18, 140]]).all() and np.isfinite(np.delete(tip, [17, 18, 140], axis=0)).all()
    tp = tip_point(mech)
    rows = None
    for k in np.flatnonzero(np.all(np.isfinite(Z), axis=1)):
        q, p, v = Z[k, :nq], Z[k, :r], Z[k, r : 2 * r]
        if rows is None or np.max(np.abs(q - rows[2])) > 0.05:
            at = observer.model.tip_maps(q, *tp)
            d = [np.array([(m1 - m0) / 1e-6 for m1 in (observer.model.tip_maps(q + 1e-6 * e, *tp)[i]
                                                        for e in np.eye(nq))]) for i, m0 in enumerate(at)]
            rows = (at, d, q.copy())
        A, C, G = (m + np.tensordot(q - rows[2], dm, axes=1) for m, dm in zip(rows[0], rows[1], strict=True))
        Ad, Cd, Gd = (np.tensordot(Z[k, r : r + nq], dm, axes=1) for dm in rows[1])
        g = G @ p
        want = np.concatenate([A @ p + C @ g**2, A @ v + Ad @ p + Cd @ g**2 + 2 * C @ (g * (G @ v + Gd @ p))])
        np.testing.assert_allclose(tip[k], want, rtol=1e-6, atol=1e-9 * np.abs(want).max())


def test_physical_covariance_is_the_physical_map_s_jacobian_squared(arm):
    """:func:`exuflex.scoring.physical.physical_covariance` with P = I is J J^T, J the Jacobian of :meth:`Observer.physical` at the state
    (central differences of the map, rows re-evaluated at every perturbed state); at rest in q (q' = 0, elastic
    rates not zero), where the map's linearisation leaves nothing out."""
    mech, observer = arm
    _, Z = _turning_states(observer, mech, n=1)
    nq, r, nx = observer.model.nq, observer.model.r, observer.model.nx
    z = Z[0]
    z[r : r + nq] = 0.0
    z[r + nq :] = np.linspace(-0.02, 0.03, nx - r - nq)
    k = len(physical_names(mech))
    J = np.empty((k, nx))
    for j in range(nx):
        h = 1e-7
        dz = np.zeros(nx)
        dz[j] = h
        J[:, j] = (observer.physical([0.0], [z + dz]).data[0] - observer.physical([0.0], [z - dz]).data[0]) / (2 * h)
    C = physical_covariance(observer, z[None], np.eye(nx)[None])[0]
    np.testing.assert_allclose(C, J @ J.T, rtol=1e-4, atol=1e-7 * np.abs(J @ J.T).max())


def test_bound_over_a_span_averages_the_configurations_scored_there(arm):
    """``steady_bound(span=...)`` is the RMS of the steady-state bounds at the midpoints of the span's parts:
    past the manoeuvre's end the mechanism rests at its final pose, so a span there gives the bound at that pose
    at rest; a span over the whole turn gives the RMS of the bounds at its midpoints' planned states."""
    from exuflex.scoring.bound import _bound_at

    mech, observer = arm
    d = mech.manoeuvre.duration
    final = plan(mech, dt=d / 100).q[-1]
    after = steady_bound(observer, span=(d + 0.1, d + 0.5), points=2)
    at_rest = _bound_at(observer, final)
    for name, v in at_rest.items():
        assert after[name] == pytest.approx(v, rel=1e-9, abs=1e-15), name
    over = steady_bound(observer, span=(0.0, d), points=2)
    p = plan(mech, dt=d / 800, t_end=d)
    per = [_bound_at(observer, p.q[k], p.qd[k]) for k in np.searchsorted(p.t, [0.25 * d, 0.75 * d])]
    for name in at_rest:
        assert over[name] == pytest.approx(np.sqrt(np.mean([b[name] ** 2 for b in per])), rel=1e-6), name


def test_the_held_models_error_is_measured_against_the_filters_uncertainty():
    """At each evaluation the cached step records the state error over one interval that the previous held
    model causes (against the exact configuration), relative to the filter's standard deviations: zero where
    the held configuration is the exact one, finite and recorded along a run."""
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.session import ObserverConfig, estimate, make_observer
    from exuflex.runs import held_torques
    from exuflex.runs import read_run

    mech = load_mechanism(MODELS / "sixbar.toml")
    run = read_run(DATA / "sixbar_short")
    obs = make_observer(mech, ObserverConfig())
    S = run.sensors
    estimate(obs, S.t, held_torques(S.select(mech.motor_names).data), S.select(obs.channels).data)
    som = obs.model
    summ = held_error_summary(som)
    assert summ["n"] == len(som.held_errors) > 0 and np.isfinite(summ["vs_std_max"])
    assert summ["map_n"] == len(som.map_errors) > 0 and summ["map_error_max"] >= summ["map_error_median"] > 0
    assert som.remap_min <= summ["map_radius"] <= som.remap_max
    iv = som._last
    z = obs.ekf.x
    same = som._held_error(iv, 0.0, iv, z, held_torques(S.select(mech.motor_names).data)[-1], 1 / mech.sample_rate_hz)
    assert same[0] == 0.0

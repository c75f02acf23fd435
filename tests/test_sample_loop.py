"""The compiled sample loop (:func:`exuflex.observer.loop.samples`) over a model's compiled step against the same
loop over the model's ``predict`` and ``measure`` (:meth:`MultirateEKF.step`).

:meth:`MultirateEKF.run` hands the samples it can to the loop with the model's compiled step and the others to
``step``, which hands the loop the model's own prediction and measurement; both must give the same numbers, bit for
bit, on a log that makes the run go back and forth between them: the six-bar's 3 s log with a torque step (the
hold-off), a spike (the gate), a blank sample, a late sample and a longer interval (the step map rebuilt for another
length), sensor faults with and without isolation, in every recording mode.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, make_observer
from exuflex.runs import held_torques
from exuflex.runs import read_run

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sixbar_log():
    mech = load_mechanism(ROOT / "models" / "sixbar.toml")
    run = read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")
    obs = make_observer(mech, ObserverConfig.for_model(mech))
    S = run.sensors
    return mech, obs, S.t.copy(), held_torques(S.select(mech.motor_names).data), S.select(obs.channels).data.copy()


def _step_by_step(ekf, t, U, Y, **kw):
    loop, ekf._loop = ekf._loop, None
    try:
        return ekf.run(t, U, Y, **kw)
    finally:
        ekf._loop = loop


def _same(a, b):
    for name in ("x_hat", "P", "nis", "nis_dof", "innovations", "S"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert np.array_equal(x, y, equal_nan=True), name
    for name in ("n_updates", "n_missing", "nis_flagged", "nis_flagged_at", "flagged_intervals", "channel_faults",
                 "n_rejected", "diverged", "nonfinite"):
        assert getattr(a, name) == getattr(b, name), name


def test_loop_is_step_on_the_sixbar_log(sixbar_log):
    _, obs, t, U, Y = sixbar_log
    ekf, model = obs.ekf, obs.model
    assert ekf._loop is not None
    counts = (model.n_refresh, model.n_remap)
    looped = ekf.run(t, U, Y)
    evaluations = (model.n_refresh - counts[0], model.n_remap - counts[1])
    _same(looped, _step_by_step(ekf, t, U, Y))
    # the same renewals in both
    assert (model.n_refresh - counts[0], model.n_remap - counts[1]) == tuple(2 * e for e in evaluations)
    np.testing.assert_array_equal(ekf.x, looped.x_hat[-1])


@pytest.mark.parametrize("store_P, innovations", [("full", True), ("none", False)])
def test_loop_is_step_where_the_log_sends_samples_back(sixbar_log, store_P, innovations):
    mech, obs, t, U, Y = sixbar_log
    n = 700
    t, U, Y = t[:n].copy(), U[:n].copy(), Y[:n].copy()
    U[300:, 0] += 0.5  # a torque step: the hold-off (gate and fault tests paused)
    Y[450, 1] += 50 * obs.ekf.R_std[1]  # a spike: gated
    Y[500, :] = np.nan  # a blank sample: a prediction only
    Y[520, 2] = np.nan  # one channel blank
    t[600:] += 0.3 * (t[1] - t[0])  # a late sample, then the grid shifted: two intervals of other lengths
    ekf = make_observer(mech, ObserverConfig.for_model(mech), cb=obs.model.rm.cb).ekf
    ekf.store_P = store_P
    looped = ekf.run(t, U, Y, innovations=innovations)
    assert looped.n_rejected[obs.channels[1]] >= 1 and ekf.jump_times
    _same(looped, _step_by_step(ekf, t, U, Y, innovations=innovations))


def test_loop_is_step_in_chunks(sixbar_log):
    """A log run in chunks (``reset=False``) gives the numbers of one run, through the loop as through step."""
    _, obs, t, U, Y = sixbar_log
    ekf = obs.ekf
    whole = ekf.run(t[:400], U[:400], Y[:400])
    first = ekf.run(t[:150], U[:150], Y[:150])
    second = ekf.run(t[150:400], U[150:400], Y[150:400], reset=False)
    np.testing.assert_array_equal(np.vstack([first.x_hat, second.x_hat]), whole.x_hat)


def test_loop_is_step_with_a_map_rebuilt_where_step_takes_over(sixbar_log):
    """Five channels (c4 left out): in the start-up the loop rebuilds the step map for a sample where it then stops
    (the measurement rows' radius left); resumed there, the model must keep that map for the sample, not rebuild
    it again (and step() as well, in the step-by-step run)."""
    mech, obs, t, U, Y = sixbar_log
    channels = tuple(c for c in obs.channels if c != "c4")
    ekf = make_observer(mech, ObserverConfig(channels=channels), cb=obs.model.rm.cb).ekf
    keep = [obs.channels.index(c) for c in channels]
    n = 400
    _same(ekf.run(t[:n], U[:n], Y[:n, keep]), _step_by_step(ekf, t[:n], U[:n], Y[:n, keep]))


@pytest.mark.parametrize("estimator, theta0, tau", [("ekf-payload", 1.0, None), ("ekf-payload", 1.8, None),
                                                     ("ekf-input", None, None), ("ekf-input", None, 0.2)])
def test_augmented_loop_is_step(sixbar_log, estimator, theta0, tau):
    """The augmented estimators through the compiled loop: the same numbers as ``step``. The payload scale held at
    the start (its intervals in the loop too, with the noise its uncertainty causes; the model's own step takes the
    one whose linearity test releases it), learned near 1 (the nominal step map) and started at 1.8 (the scaled
    system's maps, rebuilt in the loop); the torque disturbances as a random walk and as a Gauss-Markov process.
    On the log's first 0.6 s and with the torque step, spike, blank and late samples; the record of the
    covariance's scale column too."""
    mech, obs, t, U, Y = sixbar_log
    ekf = make_observer(mech, ObserverConfig(estimator=estimator, input_tau=tau), cb=obs.model.rm.cb).ekf
    model = ekf.model
    assert ekf._loop is not None
    x0 = ekf.x0
    if theta0 is not None:
        x0[model.i_theta] = theta0
    n = 700
    t2, U2, Y2 = t[:n].copy(), U[:n].copy(), Y[:n].copy()
    U2[300:, 0] += 0.5
    Y2[450, 1] += 50 * obs.ekf.R_std[1]
    Y2[500, :] = np.nan
    Y2[520, 2] = np.nan
    t2[600:] += 0.3 * (t2[1] - t2[0])
    for tt, UU, YY in ((t[:300], U[:300], Y[:300]), (t2, U2, Y2)):
        calls = []
        predict = model.predict
        model.predict = lambda *a, **k: calls.append(1) or predict(*a, **k)
        try:
            looped = ekf.run(tt, UU, YY, x0=x0)
        finally:
            del model.predict
        held = getattr(model, "n_held", 0)
        if theta0 is not None:
            assert model.released and (held > 0) == (theta0 == 1.0)
        if len(tt) == 300:
            assert len(calls) <= 2  # the loop took the intervals, held ones too (the model's step: the release)
        stepped = _step_by_step(ekf, tt, UU, YY, x0=x0)
        _same(looped, stepped)
        assert getattr(model, "n_held", 0) == held
        if theta0 is not None:
            assert np.array_equal(looped.P_theta, stepped.P_theta)


def test_smoother_forward_pass_is_the_loop(sixbar_log):
    """The RTS smoother's forward pass goes through the compiled loop (its predictions recorded there) and gives
    the numbers of ``step``: the smoothed means and covariances bit for bit."""
    from exuflex.observer.smoother import rts_smooth

    _, obs, t, U, Y = sixbar_log
    ekf, model = obs.ekf, obs.model
    n = 400
    calls = []
    predict = model.predict
    model.predict = lambda *a, **k: calls.append(1) or predict(*a, **k)
    try:
        looped = rts_smooth(ekf, t[:n], U[:n], Y[:n])
    finally:
        del model.predict
    assert len(calls) < n // 4  # the loop took most intervals
    loop, ekf._loop = ekf._loop, None
    try:
        stepped = rts_smooth(ekf, t[:n], U[:n], Y[:n])
    finally:
        ekf._loop = loop
    for name in ("x_hat", "P", "x_filt", "P_filt", "nis"):
        assert np.array_equal(getattr(looped, name), getattr(stepped, name), equal_nan=True), name


def _run_counting_steps(ekf, t, U, Y, **kw):
    """``ekf.run`` of the log, and the samples it handed to ``step`` (the rest went through the compiled loop)."""
    stepped = []
    step = ekf.step
    ekf.step = lambda tk, *a: stepped.append(int(np.searchsorted(t, tk))) or step(tk, *a)
    try:
        return ekf.run(t, U, Y, **kw), stepped
    finally:
        del ekf.step


def test_loop_takes_gated_blank_and_partial_samples(sixbar_log):
    """A spike the gate leaves out, a blank sample (a prediction only) and samples with a channel missing stay in
    the compiled loop (the update redone without the gated channel, the channels sampled alone), and so do the
    samples whose measurement rows the model rebuilds (the loop stops there, the model makes the rows for the
    prediction and the loop resumes at that sample): ``step`` takes only the first sample, with the same numbers.
    The log's own input step stays in the loop too (the hold-off starts there)."""
    mech, obs, t, U, Y = sixbar_log
    n = 640
    t, U, Y = t[:n].copy(), U[:n].copy(), Y[:n].copy()
    Y[450, 1] += 50 * obs.ekf.R_std[1]
    Y[500, :] = np.nan
    Y[520, 2] = np.nan
    Y[530:560:3, 4] = np.nan
    ekf = make_observer(mech, ObserverConfig.for_model(mech), cb=obs.model.rm.cb).ekf
    rebuilds = ekf.model.n_rows
    looped, stepped = _run_counting_steps(ekf, t, U, Y)
    rebuilds = ekf.model.n_rows - rebuilds
    assert stepped == [0] and rebuilds > 3
    # the log's own input step (at 0.08 s): the hold-off set in the loop, the step recorded
    k_step = int(np.searchsorted(t, ekf.jump_times[0]))
    assert k_step not in stepped and looped.nis_dof[k_step] == len(obs.channels)
    assert looped.n_rejected[obs.channels[1]] == 1 and looped.nis_dof[520] == 5 and looped.nis_dof[500] == 0
    assert np.isnan(looped.innovations[520, 2]) and np.isnan(looped.S[520, 2]).all()
    _same(looped, _step_by_step(ekf, t, U, Y))


def test_loop_takes_samples_while_a_sensor_fault_is_open(sixbar_log):
    """An offset on one channel from the middle of the log: the sensor-fault windows find it, and the samples after
    stay in the compiled loop with the fault open (the monitor's verdicts counted there; ``step`` takes the
    samples where a verdict opens or changes a fault) with the numbers of ``step``."""
    mech, obs, t, U, Y = sixbar_log
    n = 700
    t, U, Y = t[:n].copy(), U[:n].copy(), Y[:n].copy()
    Y[300:, 2] += 6 * obs.ekf.R_std[2]
    ekf = make_observer(mech, ObserverConfig.for_model(mech), cb=obs.model.rm.cb).ekf
    assert ekf.faults is not None and not ekf.isolate
    looped, stepped = _run_counting_steps(ekf, t, U, Y)
    found = [f for f in looped.channel_faults if f["channel"] == obs.channels[2]]
    assert found and found[0]["start"] < t[-100]
    assert len([k for k in stepped if t[k] > found[0]["start"]]) < 10
    _same(looped, _step_by_step(ekf, t, U, Y))


def test_rows_rebuilt_at_partial_samples_as_step_rebuilds_them(sixbar_log):
    """Measurement rows rebuilt in the loop at samples where a channel is blank: made from the channels sampled there
    (their error sets the next radius), as ``step``'s update makes them: the numbers of ``step``, and ``step``
    takes only the first sample."""
    mech, obs, t, U, Y = sixbar_log
    n = 400
    t, U, Y = t[:n], U[:n], Y[:n].copy()
    Y[::2, obs.channels.index("c4")] = np.nan
    ekf = make_observer(mech, ObserverConfig.for_model(mech), cb=obs.model.rm.cb).ekf
    rebuilds = ekf.model.n_rows
    looped, stepped = _run_counting_steps(ekf, t, U, Y)
    assert stepped == [0] and ekf.model.n_rows - rebuilds > 3
    _same(looped, _step_by_step(ekf, t, U, Y))


def test_loop_takes_isolation_and_a_channel_missing_and_back(sixbar_log):
    """With isolation on: an offset on one channel (found, and the channel left out of the updates from the sample
    that finds it), another channel silent for 0.6 s (found missing) and sampled again (the fault cleared, its
    window emptied). Every sample but the first goes through the model's compiled step, with the numbers of its
    ``predict`` and ``measure``; the isolated channel's samples after the finding are left out (counted)."""
    mech, obs, t, U, Y = sixbar_log
    n = 900
    t, U, Y = t[:n].copy(), U[:n].copy(), Y[:n].copy()
    Y[300:, 2] += 6 * obs.ekf.R_std[2]
    Y[400:700, 4] = np.nan
    ekf = make_observer(mech, ObserverConfig.for_model(mech, fault_isolation=True), cb=obs.model.rm.cb).ekf
    assert ekf.isolate
    looped, stepped = _run_counting_steps(ekf, t, U, Y)
    assert stepped == [0]
    kinds = {(f["channel"], f["kind"]) for f in looped.channel_faults}
    assert (obs.channels[2], "offset") in kinds and (obs.channels[4], "missing") in kinds
    missing = next(f for f in looped.channel_faults if f["kind"] == "missing")
    assert t[400] < missing["start"] < t[699] and missing["end"] == t[700]
    offset = next(f for f in looped.channel_faults if f["channel"] == obs.channels[2])
    k_found = int(np.searchsorted(t, offset["start"]))
    isolated = looped.nis_dof[k_found:] < np.isfinite(Y[k_found:]).sum(axis=1)
    assert isolated.mean() > 0.5 and looped.n_rejected[obs.channels[2]] >= isolated.sum()
    _same(looped, _step_by_step(ekf, t, U, Y))


def test_indefinite_innovation_covariance_stays_in_the_loop(sixbar_log, caplog):
    """A prior whose covariance is not positive definite makes the first updates' ``S`` indefinite: the loop
    solves them by LU (the filter warns) instead of handing them back, with the numbers of the run through the
    model's ``predict`` and ``measure``."""
    mech, obs, t, U, Y = sixbar_log
    ekf = make_observer(mech, ObserverConfig.for_model(mech), cb=obs.model.rm.cb).ekf
    P0 = ekf.P0
    P0[0, 0] = -10 * P0[0, 0] - 1e-2
    n = 50
    with caplog.at_level(logging.WARNING, logger="exuflex.observer.ekf"):
        looped, stepped = _run_counting_steps(ekf, t[:n], U[:n], Y[:n], P0=P0)
    assert "not positive definite" in caplog.text and stepped == [0] and not looped.diverged
    _same(looped, _step_by_step(ekf, t[:n], U[:n], Y[:n], P0=P0))

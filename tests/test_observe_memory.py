"""``observe`` on a long log: the record filtered in chunks (exuflex.observer.session.estimate_chunks) gives the
numbers and files of the whole record at once, and keeps per sample only what the summary needs."""

from __future__ import annotations

import dataclasses
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer import session
from exuflex.scoring.output import EstimatesWriter, write_outcome
from exuflex.observer.session import make_observer
from exuflex.runs import LogColumns, held_torques
from exuflex.scoring.run import observe_run
from exuflex.runs import Run, read_run
from exuflex.sensors import Signals

ROOT = Path(__file__).resolve().parents[1]
SIXBAR = ROOT / "models" / "sixbar.toml"
RUN = ROOT / "tests" / "data" / "sixbar_erls_3s"
TIMING = ("wall_s", "real_time_factor", "basis_s")


def _forward_fill(U: np.ndarray) -> np.ndarray:
    """Reference hold: each non-finite value replaced by the last finite one above it, or the first below."""
    out = U.copy()
    for j in range(U.shape[1]):
        fin = np.flatnonzero(np.isfinite(U[:, j]))
        for k in range(len(U)):
            before = fin[fin <= k]
            out[k, j] = U[before[-1], j] if len(before) else U[fin[0], j]
    return out


@pytest.mark.parametrize("seed", range(4))
def test_log_columns_hold_block_by_block(seed):
    """Blocks of any size, in order or not, hold torques as the whole table does (the reference fill)."""
    rng = np.random.default_rng(seed)
    data = rng.standard_normal((60, 4))
    data[rng.random(data.shape) < 0.3] = np.nan
    data[:5, 1] = np.nan  # leading gap: the first finite value
    data[-7:, 2] = np.inf
    data[[0, 1, 2], 3] = [1.0, 2.0, 3.0]
    cols = LogColumns(data, [1, 2, 3], ("a", "b", "c"), hold=True)
    ref = _forward_fill(data[:, 1:])
    for step in (1, 7, 13, 60):
        got = np.vstack([cols[a : a + step] for a in range(0, 60, step)])
        assert np.array_equal(got, ref)
    assert np.array_equal(cols[31:40], ref[31:40]) and np.array_equal(cols[5:9], ref[5:9])  # out of order
    assert np.array_equal(held_torques(data[:, 1:]), ref)
    assert np.array_equal(LogColumns(data, [0])[3:9], data[3:9, :1], equal_nan=True)  # no hold: the rows as they are
    data[:, 2] = np.nan
    with pytest.raises(ValueError, match="torque column b has no finite sample"):
        LogColumns(data, [1, 2], ("a", "b"), hold=True)


@pytest.fixture(scope="module")
def sixbar():
    mech = load_mechanism(SIXBAR)
    return mech, make_observer(mech)


def _with_torque_gaps(run: Run) -> Run:
    """The run with its first torque blank at the start and across a chunk boundary (rows 95-99)."""
    S = run.sensors
    data = S.data.copy()
    j = S.names.index(run.motors[0])
    data[[0, 95, 96, 97, 98, 99], j] = np.nan
    return dataclasses.replace(run, sensors=Signals(S.t, S.names, data, S.units))


def test_streamed_observe_equals_the_whole_record(sixbar, tmp_path, monkeypatch):
    """Filtered 97 rows at a time, keeping only the summary, with estimates.csv written as it runs: the same
    file (byte for byte, full covariance), the same summary and NIS sequence as the whole record at once."""
    mech, obs = sixbar
    run = _with_torque_gaps(read_run(RUN))
    obs.ekf.store_P = "full"
    whole = observe_run(mech, run, observer=obs, with_bound=False)
    write_outcome(tmp_path / "whole", mech, run, whole, observer=obs)
    monkeypatch.setattr(session, "CHUNK_ROWS", 97)
    outs = {}
    for keep in ("summary", "physical"):
        with EstimatesWriter(tmp_path / keep, mech, observer=obs) as writer:
            outs[keep] = observe_run(mech, run, observer=obs, with_bound=False, keep=keep, sink=writer)
        assert writer.rows_written == len(run.sensors.t)
        a = (tmp_path / "whole" / "estimates.csv").read_bytes()
        assert (tmp_path / keep / "estimates.csv").read_bytes() == a
    for out in outs.values():
        assert {k: v for k, v in out.summary.items() if k not in TIMING} == \
            {k: v for k, v in whole.summary.items() if k not in TIMING}
        res = out.estimate.result
        assert res.x_hat is None and res.P is None and res.S is None
        assert np.array_equal(res.nis, whole.estimate.result.nis, equal_nan=True)
        assert np.array_equal(res.nis_dof, whole.estimate.result.nis_dof)
    # the physical estimates: kept for figures, and where a truth scores them
    assert np.array_equal(outs["physical"].estimate.physical.data, whole.estimate.physical.data, equal_nan=True)
    assert np.array_equal(outs["summary"].estimate.physical.data, whole.estimate.physical.data, equal_nan=True)
    no_truth = dataclasses.replace(run, truth=None)
    assert observe_run(mech, no_truth, observer=obs, with_bound=False, keep="summary").estimate.physical is None


def test_a_failed_streamed_run_leaves_no_file(sixbar, tmp_path):
    mech, obs = sixbar
    run = read_run(RUN)

    def fail(chunk):
        raise RuntimeError("stop")

    with pytest.raises(RuntimeError, match="stop"):
        with EstimatesWriter(tmp_path / "o", mech, observer=obs) as writer:
            observe_run(mech, run, observer=obs, with_bound=False, keep="summary",
                        sink=lambda ch: (writer(ch), fail(ch)))
    assert not (tmp_path / "o").exists()


def _at_rest(run: Run, mech, n: int, seed: int = 0) -> Run:
    """``n`` samples of the six-bar at rest where the 3 s run ends (torques and curvatures zero, angles and tip
    at their last values) with each channel's noise from the model file, from t = 0; no truth."""
    S = run.sensors
    noise = {m.name: m.noise_std for m in mech.motors} | {s.name: s.noise_std for s in mech.sensors}
    rest = np.array([0.0 if name[0] in "Tc" else v for name, v in zip(S.names, S.data[-1], strict=True)])
    std = np.array([noise.get(name, 0.0) for name in S.names])
    data = rest + std * np.random.default_rng(seed).standard_normal((n, len(rest)))
    return dataclasses.replace(run, sensors=Signals(0.002 * np.arange(n), S.names, data, S.units), truth=None)


def test_streamed_observe_memory_per_sample(sixbar, monkeypatch):
    """The memory model of the streamed path (keep="summary", no truth): per sample it keeps the NIS and its
    degrees of freedom (8 + 2 bytes) and nothing else, and its peak grows by at most four floats a sample (the
    log check's working arrays), where the filter's whole record takes 768 bytes (estimates, P diagonal, innovations, S, NIS). Measured with
    traced allocations (tracemalloc) as the slope between two lengths of a log at rest (the filter's model
    refreshes little, so that its own records stay constant), the process and one chunk cancelling; the filter
    is handed one chunk of rows at a time."""
    mech, obs = sixbar
    run = read_run(RUN)
    q_end = np.array([run.truth[name][-1] for name in mech.coordinate_names])
    obs = make_observer(mech, x0=obs.model.initial_state(q_end), cb=obs.model.rm.cb)
    obs.ekf.store_P = "none"
    monkeypatch.setattr(session, "CHUNK_ROWS", 128)
    seen = []

    def sink(chunk):
        seen.append(len(chunk.result.t))
        assert chunk.result.S is None

    observe_run(mech, _at_rest(run, mech, 100), observer=obs, with_bound=False, keep="summary")  # first uses
    got = []
    for n in (3 * 128, 9 * 128):  # whole chunks: the last one's transients cancel too
        log = _at_rest(run, mech, n)
        seen.clear()
        tracemalloc.start()
        out = observe_run(mech, log, observer=obs, with_bound=False, keep="summary", sink=sink)
        got.append(tracemalloc.get_traced_memory())
        tracemalloc.stop()
        assert sum(seen) == n and max(seen) == 128
    res = out.estimate.result
    assert out.estimate.physical is None and res.x_hat is None and res.innovations is None
    assert res.t is log.sensors.t  # the log's times, not a copy
    kept = res.nis.itemsize + res.nis_dof.itemsize
    assert kept == 10
    held, peak = ((b - a) / (6 * 128) for a, b in zip(*got, strict=True))
    # held: the kept arrays, and a few hundred bytes a chunk the interpreter and numba's dispatcher keep for reuse
    # (their free lists and per-call caches: C allocations no Python object holds, more with the compiled sample
    # loop's calls)
    assert held <= kept + 1024 / 128, (held, peak)
    # peak: what is held, or the log check's working arrays (a few floats a sample at once), whichever is more
    assert peak <= 4 * 8, (held, peak)


def test_streamed_ukf_equals_the_whole_record(sixbar, monkeypatch):
    """The unscented filter run in chunks (its run() continued from one block to the next) gives its numbers."""
    from exuflex.observer.session import ObserverConfig

    mech, obs = sixbar
    ukf = make_observer(mech, ObserverConfig.for_model(mech, estimator="ukf"), cb=obs.model.rm.cb)
    run = read_run(ROOT / "tests" / "data" / "sixbar_short")
    whole = observe_run(mech, run, observer=ukf, with_bound=False)
    monkeypatch.setattr(session, "CHUNK_ROWS", 7)
    part = observe_run(mech, run, observer=ukf, with_bound=False, keep="physical")
    assert np.array_equal(part.estimate.physical.data, whole.estimate.physical.data, equal_nan=True)
    assert np.array_equal(part.estimate.result.nis, whole.estimate.result.nis, equal_nan=True)
    assert part.summary["rms_error"] == whole.summary["rms_error"]

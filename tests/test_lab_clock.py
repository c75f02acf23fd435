"""Lab clocks: time-stamp jitter and clock drift within the documented tolerance (validate.RATE_TOL,
validate.JITTER_TOL) are accepted and measured, a wrong rate is rejected; messages name the real file and
point to the command line's --time-scale; the log keeps its own time stamps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.errors import LogFormatError
from exuflex.mechanism import load_mechanism
from exuflex.runs import Run, read_run
from exuflex.sensors import Signals
from exuflex.validate import JITTER_TOL, RATE_TOL, check_run

ROOT = Path(__file__).resolve().parents[1]
SRC = read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")
MECH = load_mechanism(ROOT / "models" / "sixbar.toml")
DT = 1.0 / MECH.sample_rate_hz


def _retimed(t, path=None) -> Run:
    S = SRC.sensors
    return Run(Path(path or SRC.path), Signals(np.asarray(t), S.names, S.data, S.units), None, dict(SRC.meta))


def _clock(jitter_s=0.0, ppm=0.0, seed=0, uniform=True):
    k = np.arange(len(SRC.sensors.t))
    rng = np.random.default_rng(seed)
    j = rng.uniform(-jitter_s, jitter_s, len(k)) if uniform else jitter_s * rng.standard_normal(len(k))
    return k * DT * (1 + ppm * 1e-6) + j


@pytest.mark.parametrize("jitter_s,ppm", [(1e-6, 0.0), (10e-6, 0.0), (0.0, 1.0), (0.2e-3, 500.0), (0.2e-3, -500.0)],
                         ids=["1 us jitter", "10 us jitter", "1 ppm drift", "0.2 ms jitter 500 ppm", "-500 ppm"])
def test_jitter_and_drift_within_tolerance_are_accepted(jitter_s, ppm):
    t = _clock(jitter_s, ppm)
    rep = check_run(MECH, _retimed(t))
    # the clock line and the jitter about it are measured (least squares through t against the sample index)
    assert rep.clock_drift_ppm == pytest.approx(ppm, abs=max(0.05, 3 * jitter_s / DT / len(t) ** 1.5 * 1e6 * 2))
    assert rep.jitter_max_s <= 1.1 * jitter_s + 1e-9  # about the fitted line: slightly above the drawn bound
    # every row keeps its place on the grid: index k
    assert np.array_equal(rep.sample_index, np.arange(len(t)))
    np.testing.assert_allclose(rep.grid_times(), np.arange(len(t)) * DT, rtol=0, atol=1e-12)


@pytest.mark.parametrize("rate_hz", [499.0, 501.0, 400.0, 1000.0, 333.0])
def test_a_wrong_rate_is_rejected(rate_hz):
    t = np.arange(len(SRC.sensors.t)) / rate_hz
    with pytest.raises(LogFormatError, match=r"sensors\.csv: .*(clock runs at|sampled every).*model.sample_rate_hz"):
        check_run(MECH, _retimed(t))


def test_tolerances_separate_drift_from_a_wrong_rate():
    assert 500e-6 < RATE_TOL < 2e-3  # 500 ppm accepted; 499 Hz at a 500 Hz model (2000 ppm) rejected
    assert 0.2e-3 / DT < JITTER_TOL < 0.5  # +-0.2 ms at 500 Hz accepted; half an interval would be ambiguous


def test_a_whole_multiple_rate_with_jitter_is_accepted():
    t = _clock(0.1e-3, 100.0)[::2]
    S = SRC.sensors
    run = Run(SRC.path, Signals(t, S.names, S.data[::2], S.units), None, dict(SRC.meta))
    rep = check_run(MECH, run)
    assert rep.interval_s == pytest.approx(2 * DT, rel=1e-3)
    assert np.array_equal(rep.sample_index, 2 * np.arange(len(t)))


def test_messages_name_the_csv_file_and_the_flag(tmp_path):
    lab = tmp_path / "lab.csv"
    t_ms = np.arange(len(SRC.sensors.t)) * DT * 1000.0
    with pytest.raises(LogFormatError, match=r"lab\.csv: time steps of 2 .* --time-scale 1e-3") as exc:
        check_run(MECH, _retimed(t_ms, lab))
    assert "lab.csv/sensors.csv" not in str(exc.value) and "read_csv_log" not in str(exc.value)

"""A lab's CSV log read as a run of a mechanism (exuflex.runs.read_lab_run), and the first-compile notice's test."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.errors import LogFormatError
from exuflex.mechanism import load_mechanism
from exuflex.runs import read_lab_run, read_run

ROOT = Path(__file__).resolve().parents[1]
MECH = load_mechanism(ROOT / "models" / "sixbar.toml")
MAP = {"T1": "m1", "T2": "m2", "T3": "m3", "q1": "e1", "c1": "g1"}


def _log(path: Path, cols=MAP) -> Path:
    run = read_run(ROOT / "tests" / "data" / "sixbar_short")
    S = run.sensors
    with open(path, "w") as f:
        f.write(",".join(["Time_ms"] + list(cols.values())) + "\n")
        for k in range(len(S.t)):
            f.write(",".join([f"{S.t[k] * 1e3:.6f}"] + [repr(float(S[c][k])) for c in cols]) + "\n")
    return path


def test_the_log_becomes_a_run_with_the_models_names(tmp_path):
    run = read_lab_run(_log(tmp_path / "lab.csv"), MECH, MAP, time_column="Time_ms", time_scale=1e-3)
    ref = read_run(ROOT / "tests" / "data" / "sixbar_short").sensors
    assert run.motors == ("T1", "T2", "T3") and run.meta["sensors"] == ["q1", "c1"] and run.truth is None
    assert np.allclose(run.sensors.t, ref.t, atol=1e-9) and np.array_equal(run.sensors["q1"], ref["q1"])


def test_errors_name_the_argument_and_what_was_expected(tmp_path):
    p = _log(tmp_path / "lab.csv")
    with pytest.raises(LogFormatError, match=r"^--map: 'q9' is not a motor or sensor of sixbar"):
        read_lab_run(p, MECH, {**MAP, "q9": "e1"}, time_column="Time_ms", columns_name="--map")
    no_torque = _log(tmp_path / "lab2.csv", {"q1": "q1"})
    with pytest.raises(LogFormatError, match=r"missing column\(s\) \['T1', 'T2', 'T3'\]"):
        read_lab_run(no_torque, MECH, {"q1": "q1"}, time_column="Time_ms")
    with pytest.raises(LogFormatError, match=r"needs the measured torques \['T1', 'T2', 'T3'\].*columns\)$"):
        read_lab_run(no_torque, MECH, time_column="Time_ms")
    with pytest.raises(LogFormatError, match=r"no time column 'time'.*time_column=.*--time-column NAME\)$"):
        read_lab_run(p, MECH, MAP)



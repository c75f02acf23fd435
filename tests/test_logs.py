"""Bad sensor logs: each defect is either handled as documented or rejected with a clear LogFormatError.

Run folders are small copies of ``tests/data/sixbar_short`` (the six-bar, 0.06 s, ERLS engine, seed 7) edited
by hand. See docs/robustness.md for the table of classes.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from exuflex.cli import main
from exuflex.errors import LogFormatError
from exuflex.mechanism import load_mechanism
from exuflex.observer.session import default_channels
from exuflex.runs import read_csv_log, read_exudyn_sensor, read_run
from exuflex.sensors import Signals
from exuflex.validate import check_log, check_run

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "tests" / "data" / "sixbar_short"
MODEL = ROOT / "models" / "sixbar.toml"


@pytest.fixture(scope="module")
def mech():
    return load_mechanism(MODEL)


def _copy(tmp_path: Path, name: str = "run") -> Path:
    d = tmp_path / name
    shutil.copytree(SRC, d)
    return d


def _rows(d: Path) -> list[list[str]]:
    return [ln.split(",") for ln in (d / "sensors.csv").read_text().splitlines()]


def _write(d: Path, rows: list[list[str]]) -> None:
    (d / "sensors.csv").write_text("\n".join(",".join(r) for r in rows) + "\n")


def _set_col(rows, name, f):
    i = rows[0].index(name)
    for k, r in enumerate(rows[1:]):
        r[i] = f(k, r[i])
    return rows


def _set_time(rows, f):
    for k, r in enumerate(rows[1:]):
        r[0] = repr(f(k, float(r[0])))
    return rows


# ------------------------------------------------------------------ rejected by the reader (read_run)
READER_CASES = [
    ("missing channel", lambda r: [row[:-1] for row in r], r"missing column\(s\) \['tip_y'\]"),
    ("NaN sample", lambda r: _set_col(r, "c2", lambda k, v: "nan" if k == 4 else v),
     r"line 6, column 'c2': 'nan' is not a finite number \(leave the cell empty"),
    ("inf sample", lambda r: _set_col(r, "q1", lambda k, v: "inf" if k == 2 else v), r"line 4, column 'q1': 'inf'"),
    ("text in a cell", lambda r: _set_col(r, "q2", lambda k, v: "n/a" if k == 3 else v), r"'n/a' is not a number"),
    ("duplicated timestamp", lambda r: r[:5] + [r[4]] + r[5:], r"'time' is not strictly increasing at line 6"),
    ("non-monotonic time", lambda r: r[:3] + [r[4], r[3]] + r[5:], r"not strictly increasing at line 5 \(0\.006 then 0\.004\)"),
    ("empty time cell", lambda r: _set_time(r, lambda k, t: t) and [r[0], [""] + r[1][1:]] + r[2:],
     r"line 2, column 'time': empty cell"),
    ("empty torque cell", lambda r: _set_col(r, "T2", lambda k, v: "" if k == 7 else v),
     r"torque column 'T2' has an empty cell at data row 8"),
    ("wrong number of fields", lambda r: r[:3] + [r[3][:-2]] + r[4:], r"line 4: 11 fields, expected 13"),
    ("header only", lambda r: r[:1], r"no data rows"),
    ("time not first", lambda r: [row[1:] + row[:1] for row in r], r"first column is 'T1', expected 'time'"),
    ("duplicate column", lambda r: [row + [row[4]] for row in r], r"duplicate column\(s\) \['q1'\]"),
]


@pytest.mark.parametrize("cls,edit,match", READER_CASES, ids=[c[0] for c in READER_CASES])
def test_reader_rejects(tmp_path, cls, edit, match):
    d = _copy(tmp_path)
    _write(d, edit(_rows(d)))
    with pytest.raises(LogFormatError, match=match):
        read_run(d)


def test_empty_and_undecodable_files(tmp_path):
    d = _copy(tmp_path)
    (d / "sensors.csv").write_text("")
    with pytest.raises(LogFormatError, match="sensors.csv: empty file"):
        read_run(d)
    (d / "sensors.csv").write_bytes(b"time,T1\n0,\xff\xfe\n")
    with pytest.raises(LogFormatError, match="sensors.csv: not UTF-8 text"):
        read_run(d)
    shutil.rmtree(d)
    d = _copy(tmp_path)
    (d / "meta.json").write_text((SRC / "meta.json").read_text()[:200])  # truncated (killed writer)
    with pytest.raises(LogFormatError, match="meta.json: not valid JSON"):
        read_run(d)
    for field, value, match in (("units", "SI", "'units' is not an object"), ("truth", "q1", "'truth' is not a list"),
                                ("motors", [1, 2], "'motors' missing or not a list")):
        meta = json.loads((SRC / "meta.json").read_text())
        meta[field] = value
        (d / "meta.json").write_text(json.dumps(meta))
        with pytest.raises(LogFormatError, match=match):
            read_run(d)


def test_byte_order_mark_and_crlf_are_accepted(tmp_path):
    d = _copy(tmp_path)
    text = (SRC / "sensors.csv").read_text()
    (d / "sensors.csv").write_bytes(("\ufeff" + text.replace("\n", "\r\n")).encode("utf-8"))
    run = read_run(d)
    np.testing.assert_array_equal(run.sensors.data, read_run(SRC).sensors.data)


# ------------------------------------------------------------------ checked for the observer (validate)
def test_clean_log_passes(mech):
    rep = check_run(mech, read_run(SRC), default_channels(mech))
    assert rep.n_samples == 31 and rep.n_gaps == 0 and not rep.warnings


VALIDATE_CASES = [
    ("time in milliseconds", lambda r: _set_time(r, lambda k, t: t * 1000), r"milliseconds\?"),
    ("log at another rate", lambda r: _set_time(r, lambda k, t: t / 2), r"sampled every 0\.001 s \(1000 Hz\)"),
    ("jitter beyond the tolerance", lambda r: _set_time(r, lambda k, t: t + (7e-4 if k == 5 else 0.0)),
     r"data row 6: time 0\.0107 is \+0\.\d+ ms off the log's clock .* jitter tolerance is 0\.25 of the 0\.002 s"),
    ("epoch time stamps", lambda r: _set_time(r, lambda k, t: 1.7e9 + t), r"epoch times\?"),
    ("gap longer than allowed", lambda r: _set_time(r, lambda k, t: t + (5.0 if k >= 10 else 0.0)),
     r"a gap of 5\.002 s between data row 10 .* split the log"),
    ("degrees instead of radians", lambda r: _set_col(r, "q1", lambda k, v: repr(float(v) * 180 / np.pi)),
     r"data row 1, channel 'q1': .* outside the channel's full scale \+-8 .*degrees\?"),
    ("glitch", lambda r: _set_col(r, "c1", lambda k, v: "1000000.0" if k == 10 else v),
     r"data row 11, channel 'c1': 1000000\.0 is outside"),
    ("torque in N mm", lambda r: _set_col(r, "T1", lambda k, v: repr(float(v) * 1000)),
     r"channel 'T1'.*outside the channel's full scale \+-50"),
    ("all observer channels empty", lambda r: [row[:4] + [""] * 9 if i else row for i, row in enumerate(r)],
     r"none of the observer's channels"),
]


@pytest.mark.parametrize("cls,edit,match", VALIDATE_CASES, ids=[c[0] for c in VALIDATE_CASES])
def test_check_run_rejects(tmp_path, mech, cls, edit, match):
    d = _copy(tmp_path)
    _write(d, edit(_rows(d)))
    with pytest.raises(LogFormatError, match=match):
        check_run(mech, read_run(d), default_channels(mech))


def test_channel_missing_for_the_observer(tmp_path, mech):
    """meta.json does not list c4 and sensors.csv lacks it: read_run accepts, the observer check does not."""
    d = _copy(tmp_path)
    rows = _rows(d)
    i = rows[0].index("c4")
    _write(d, [row[:i] + row[i + 1 :] for row in rows])
    meta = json.loads((d / "meta.json").read_text())
    meta["sensors"].remove("c4")
    (d / "meta.json").write_text(json.dumps(meta))
    run = read_run(d)
    with pytest.raises(LogFormatError, match=r"missing channel\(s\) \['c4'\]"):
        check_run(mech, run, default_channels(mech))


def test_fewer_torque_columns_than_motors(tmp_path, mech):
    """meta.json lists one torque for the six-bar's three motors: an error naming the file and the motors
    (found by the fuzz campaign: the observer would have driven two motors with nothing)."""
    d = _copy(tmp_path)
    meta = json.loads((d / "meta.json").read_text())
    meta["sensors"] += meta["motors"][1:]
    meta["motors"] = meta["motors"][:1]
    (d / "meta.json").write_text(json.dumps(meta))
    run = read_run(d)
    with pytest.raises(LogFormatError, match=r"sensors.csv: 1 torque column\(s\) \['T1'\], but the model .* has 3 motors"):
        check_run(mech, run, default_channels(mech))


def test_gaps_empty_rows_and_unsampled_channels_are_counted(tmp_path, mech):
    d = _copy(tmp_path)
    rows = _rows(d)
    rows = rows[:8] + rows[12:]  # 4 samples missing after data row 7
    rows = _set_col(rows, "c4", lambda k, v: "")  # never sampled
    for r in rows[15:17]:
        r[4:] = [""] * 9  # no sensor sample at all
    _write(d, rows)
    rep = check_run(mech, read_run(d), default_channels(mech))
    assert (rep.n_gaps, rep.n_skipped) == (1, 4) and rep.longest_gap_s == pytest.approx(0.01)
    assert rep.never_sampled == ("c4",) and rep.n_empty_rows == 2
    assert len(rep.warnings) == 3


def test_half_rate_log_is_a_warning(mech):
    t = np.arange(10) * 0.004
    sig = Signals(t, ("T1", "T2", "T3", "q1"), np.zeros((10, 4)))
    rep = check_log(mech, sig, ["q1"], dt=0.002, check_full_scale=False)
    assert rep.n_skipped == 9 and any("sampled every 0.004 s" in w for w in rep.warnings)


# ------------------------------------------------------------------ handled by the observer (documented)
def _observe(d: Path, capsys) -> dict:
    rc = main(["observe", str(MODEL), str(d), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    return json.loads(out.out.replace("NaN", "null"))


def test_observer_predicts_through_gaps_and_reports_them(tmp_path, capsys):
    d = _copy(tmp_path)
    rows = _rows(d)
    _write(d, rows[:8] + rows[12:])  # a 10 ms gap: 4 prediction-only intervals
    s = _observe(d, capsys)
    assert s["n_missing"] == 4 and s["n_updates"] == 27 and not s["diverged"]


def test_observer_counts_rows_without_samples(tmp_path, capsys):
    d = _copy(tmp_path)
    rows = _rows(d)
    for r in rows[5:8]:
        r[4:] = [""] * 9
    _write(d, rows)
    s = _observe(d, capsys)
    assert s["n_missing"] == 3 and s["n_updates"] == 28


def test_observer_uses_a_slower_channel_when_present(tmp_path, capsys):
    d = _copy(tmp_path)
    _write(d, _set_col(_rows(d), "c1", lambda k, v: v if k % 5 == 0 else ""))  # c1 at 100 Hz
    s = _observe(d, capsys)
    assert s["n_updates"] == 31 and s["n_missing"] == 0 and not s["diverged"]


def test_cli_rejects_bad_logs_in_one_line(tmp_path, capsys):
    d = _copy(tmp_path)
    _write(d, _set_col(_rows(d), "q3", lambda k, v: "inf" if k == 3 else v))
    assert main(["observe", str(MODEL), str(d)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "sensors.csv: line 5, column 'q3'" in err
    assert main(["observe", str(MODEL), str(tmp_path / "nowhere")]) == 2
    assert "run folder does not exist" in capsys.readouterr().err


# ------------------------------------------------------------------ other readers
def test_generic_log_time_in_ms_and_channels(tmp_path):
    p = tmp_path / "lab.csv"
    p.write_text("t_ms;enc1\n0;1.0\n2;1.1\n4;1.2\n")
    sig = read_csv_log(p, {"q1": "enc1"}, time_column="t_ms", time_scale=1e-3, delimiter=";")
    np.testing.assert_allclose(sig.t, [0, 0.002, 0.004])
    with pytest.raises(ValueError, match=r"time_scale \(--time-scale\): expected a positive number"):
        read_csv_log(p, time_column="t_ms", time_scale=0.0, delimiter=";")
    p.write_text("t_ms;enc1\n0;1.0\n2;inf\n")
    with pytest.raises(LogFormatError, match="'inf' is not a finite number"):
        read_csv_log(p, time_column="t_ms", delimiter=";")
    p.write_text("t_ms;enc1\n0;1.0\n;1.1\n")
    with pytest.raises(LogFormatError, match=r"line 3, column 't_ms': empty cell"):
        read_csv_log(p, time_column="t_ms", delimiter=";")


def test_exudyn_sensor_file_duplicates_and_binary(tmp_path):
    p = tmp_path / "s.txt"
    p.write_text("#header\n0,1\n0,2\n0.001,3\n0.0005,4\n")
    with pytest.raises(LogFormatError, match="not strictly increasing"):
        read_exudyn_sensor(p)
    p.write_bytes(b"\x00\x01binary")
    with pytest.raises(LogFormatError):
        read_exudyn_sensor(p)

"""Sensor, motor and coordinate names are CSV column headers of the run files: restricted at load."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from exuflex.cli import main
from exuflex.mechanism import ModelFileError, parse_mechanism
from exuflex.mechanism.loader import column_name_problem
from exuflex.runs import read_signals_csv, write_signals_csv
from exuflex.sensors import Signals

MODELS = Path(__file__).resolve().parents[1] / "models"


def _doc() -> dict:
    with open(MODELS / "sixbar.toml", "rb") as fh:
        return tomllib.load(fh)


BAD = [("time", "the run files' time column"), ("tip,x", "no comma"), ("tip\nx", "control character"),
       ("tip\tx", "control character"), ("   ", "not blank"), (" q1", "leading or trailing"), ('tip"x', "double quote"),
       ("tip\r", "leading or trailing")]


@pytest.mark.parametrize("table,index", [("sensors", 7), ("motors", 1), ("coordinates", 2)])
@pytest.mark.parametrize("name,phrase", BAD, ids=[repr(b[0]) for b in BAD])
def test_bad_column_names_are_refused(table, index, name, phrase):
    doc = _doc()
    doc[table][index]["name"] = name
    with pytest.raises(ModelFileError) as ei:
        parse_mechanism(doc, "names.toml")
    msg = str(ei.value)
    assert msg.startswith(f"names.toml: {table}[{index}].name: expected a name usable as a CSV column header ("), msg
    assert phrase in msg and "\n" not in msg


def test_sensor_named_like_a_motor_is_refused():
    doc = _doc()
    doc["sensors"][4]["name"] = "T2"
    with pytest.raises(ModelFileError, match=r"^names\.toml: sensors\[4\]\.name: expected a name not used by "
                                             r"motors\[1\] .*sensors\.csv.*got 'T2'$"):
        parse_mechanism(doc, "names.toml")


def test_names_with_spaces_inside_are_accepted():
    doc = _doc()
    doc["sensors"][7]["name"] = "tip x (m)"
    assert parse_mechanism(doc, "ok.toml").sensors[7].name == "tip x (m)"


@settings(max_examples=300, deadline=None)
@given(st.text(min_size=1, max_size=8))
def test_every_accepted_name_survives_the_csv_round_trip(tmp_path_factory, name):
    """Property: a name column_name_problem accepts is read back from a written sensors file unchanged."""
    if column_name_problem(name) is not None or name == "other":
        return
    path = tmp_path_factory.mktemp("csv") / "s.csv"
    sig = Signals(np.array([0.0, 0.002]), (name, "other"), np.array([[1.0, 2.0], [3.0, 4.0]]))
    write_signals_csv(path, sig)
    back = read_signals_csv(path)
    assert back.names == (name, "other") and np.array_equal(back.data, sig.data)


def test_cli_one_line(tmp_path, capsys):
    bad = tmp_path / "names.toml"
    bad.write_text((MODELS / "sixbar.toml").read_text().replace('name = "tip_x"', 'name = "tip,x"'))
    assert main(["simulate", str(bad), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "sensors[7].name: expected a name usable as a CSV column header" in err
    assert not (tmp_path / "r").exists()

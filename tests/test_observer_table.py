"""The model file's ``[observer]`` table: parsed and checked by the loader, applied under the command line's
options and over the observer's defaults, written back by the model writer."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tomllib
from pathlib import Path

import pytest

from exuflex.mechanism import ModelFileError, ObserverSpec, parse_mechanism
from exuflex.mechanism.spec import ESTIMATOR_NAMES
from exuflex.mechanism.writer import mechanism_document
from exuflex.observer.session import ESTIMATORS, ObserverConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _toml import dumps  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SIXBAR = tomllib.loads((ROOT / "models" / "sixbar.toml").read_text())
TABLE = {"channels": ["q1", "q2", "c1"], "method": "rk4", "q_scale": 2.0, "q_extra_std": 1e-3, "q0_std": 0.02,
         "gate_p": 1e-4, "fault_window": 50, "fault_isolation": True, "estimator": "ekf-payload", "start_up": 0.5,
         "payload_nominal_p": 0.9, "payload0_std": 0.3}


def _with(table) -> dict:
    doc = dict(SIXBAR)
    doc["observer"] = table
    return doc


def test_the_table_sets_the_observers_settings_over_the_defaults():
    mech = parse_mechanism(_with(TABLE), "six.toml")
    cfg = ObserverConfig.for_model(mech)
    assert cfg.channels == ("q1", "q2", "c1") and cfg.method == "rk4" and cfg.q_scale == 2.0
    assert cfg.q_extra_std == 1e-3 and cfg.q0_std == 0.02 and cfg.gate_p == 1e-4 and cfg.fault_window == 50
    assert cfg.fault_isolation is True and cfg.estimator == "ekf-payload" and cfg.start_up == 0.5
    assert cfg.payload_nominal_p == 0.9 and cfg.payload0_std == 0.3
    assert cfg.qd0_std == ObserverConfig().qd0_std  # not in the table: the default
    # explicit settings (the command line's) win over the file
    assert ObserverConfig.for_model(mech, q_scale=3.0).q_scale == 3.0
    # a file without the table: exactly the defaults
    assert ObserverConfig.for_model(parse_mechanism(SIXBAR, "six.toml")) == ObserverConfig()


def test_the_command_lines_options_override_the_file_and_the_rest_comes_from_it():
    from exuflex.cli import observe

    p = argparse.ArgumentParser()
    observe.add_parser(p.add_subparsers())
    mech = parse_mechanism(_with(TABLE), "six.toml")
    args = p.parse_args(["observe", "m.toml", "run", "--q-scale", "5", "--method", "cached", "--jump-p", "1e-4"])
    cfg = observe._config(args, mech)
    assert cfg.q_scale == 5.0 and cfg.method == "cached" and cfg.jump_p == 1e-4  # given on the command line
    assert cfg.channels == ("q1", "q2", "c1") and cfg.estimator == "ekf-payload"  # from the file


@pytest.mark.parametrize("table, field", [
    ({"q_scle": 2.0}, "observer.q_scle"),
    ({"channels": ["q1", "nope"]}, "observer.channels[1]"),
    ({"channels": ["q1", "q1"]}, "observer.channels[1]"),
    ({"channels": []}, "observer.channels"),
    ({"method": "euler"}, "observer.method"),
    ({"estimator": "pf"}, "observer.estimator"),
    ({"q_scale": -1.0}, "observer.q_scale"),
    ({"h": 0}, "observer.h"),
    ({"gate_p": 0.7}, "observer.gate_p"),
    ({"jump_p": 0.0}, "observer.jump_p"),
    ({"fault_window": 1}, "observer.fault_window"),
    ({"fault_isolation": "yes"}, "observer.fault_isolation"),
    ({"start_up": "0.3"}, "observer.start_up"),
    ({"payload_nominal_p": 1.5}, "observer.payload_nominal_p"),
    ({"payload_std": 0.0}, "observer.payload_std"),
])
def test_a_bad_entry_is_a_one_line_error_naming_the_file_and_the_field(table, field):
    with pytest.raises(ModelFileError) as err:
        parse_mechanism(_with(table), "six.toml")
    msg = str(err.value)
    assert msg.startswith(f"six.toml: {field}: expected") and "\n" not in msg


def test_the_writer_keeps_the_table():
    mech = parse_mechanism(_with(TABLE), "six.toml")
    doc = mechanism_document(mech)
    assert doc["observer"]["channels"] == TABLE["channels"]
    back = parse_mechanism(tomllib.loads(dumps(doc)), "six.toml")
    assert back.observer == mech.observer


def test_the_table_names_only_the_observers_settings():
    fields = {f.name for f in dataclasses.fields(ObserverConfig)}
    assert set(ObserverSpec.__dataclass_fields__) <= fields
    assert ESTIMATOR_NAMES == ESTIMATORS


def test_make_observer_without_a_config_uses_the_table():
    from exuflex.observer.session import make_observer

    obs = make_observer(parse_mechanism(_with({"channels": ["q1", "q2", "q3", "c1"], "q_scale": 2.0}), "six.toml"))
    assert obs.channels == ("q1", "q2", "q3", "c1") and obs.config.q_scale == 2.0

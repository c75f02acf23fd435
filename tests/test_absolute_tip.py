"""Absolute tip position and velocity (rigid + elastic): the helper and the payload study's tip_* quantities."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.kinematics import Kinematics, KinematicsError
from exuflex.mechanism import load_mechanism
from exuflex.sensors import ABSOLUTE_TIP_NAMES, Signals, absolute_tip, tip_point, truth_names

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "sixbar.toml"
ABS = ("tip_x", "tip_y", "dtip_x", "dtip_y")


@pytest.fixture(scope="module")
def mech():
    return load_mechanism(MODEL)


def _smooth_states(mech, t, elastic=None) -> Signals:
    """q(t) = q_ref + a sin(w t) (and its exact rate), tip elastic columns ``elastic`` (default zero)."""
    a, w = np.array([0.12, -0.07, 0.2]), np.array([2.0, 3.0, 5.0])
    q = np.asarray(mech.q_ref, float) + a * np.sin(w * t[:, None])
    qd = a * w * np.cos(w * t[:, None])
    e = np.zeros((len(t), 4)) if elastic is None else elastic
    return Signals(t, truth_names(mech), np.hstack([q, qd, e]))


def test_zero_elastic_is_the_rigid_point_and_the_velocity_its_derivative(mech):
    t = np.linspace(0.0, 1.0, 2001)
    s = _smooth_states(mech, t)
    tip = absolute_tip(mech, s)
    assert tip.names == ABSOLUTE_TIP_NAMES == ABS and tip.units == ("m", "m", "m/s", "m/s")
    kin = Kinematics(mech)
    link, station = tip_point(mech)
    for k in range(0, len(t), 97):
        pose = kin.pose(s.data[k, :3])
        p, dp = kin.point(pose, link, station)
        np.testing.assert_allclose(tip.data[k, :2], p, rtol=0, atol=1e-12)
        np.testing.assert_allclose(tip.data[k, 2:], dp @ s.data[k, 3:6], rtol=0, atol=1e-12)
    # the velocity is the time derivative of the position (central differences, O(dt^2) ~ 1e-7 m/s here)
    dt = t[1] - t[0]
    fd = (tip.data[2:, :2] - tip.data[:-2, :2]) / (2 * dt)
    scale = np.abs(tip.data[:, 2:]).max()
    assert scale > 0.05
    np.testing.assert_allclose(tip.data[1:-1, 2:], fd, rtol=0, atol=1e-5 * scale)


def test_elastic_columns_add_and_bad_samples_are_nan(mech):
    t = np.linspace(0.0, 0.2, 11)
    e = np.column_stack([1e-3 * np.sin(30 * t), -2e-3 * np.cos(30 * t), 3e-2 * np.cos(30 * t), 6e-2 * np.sin(30 * t)])
    rigid = absolute_tip(mech, _smooth_states(mech, t)).data
    s = _smooth_states(mech, t, e)
    np.testing.assert_allclose(absolute_tip(mech, s).data, rigid + e, rtol=0, atol=1e-12)
    s.data[3, 1] = np.nan  # a non-finite estimate: that sample only
    out = absolute_tip(mech, s, on_error="nan").data
    assert np.isnan(out[3]).all() and np.isfinite(np.delete(out, 3, axis=0)).all()
    with pytest.raises(KeyError, match="x25"):
        absolute_tip(mech, Signals(t, truth_names(mech)[:6], s.data[:, :6]))
    with pytest.raises(ValueError, match="on_error"):
        absolute_tip(mech, s, on_error="ignore")


def test_unsolvable_pose_raises_or_gives_nan(mech):
    class Failing(Kinematics):
        def solve(self, q, z0=None, **kw):
            if q[2] > np.asarray(self.mech.q_ref)[2] + 0.15:
                raise KinematicsError("cannot close (test)")
            return super().solve(q, z0, **kw)

    t = np.linspace(0.0, 0.5, 51)
    s = _smooth_states(mech, t)
    bad = s["q3"] > np.asarray(mech.q_ref)[2] + 0.15
    assert 0 < bad.sum() < len(t)
    out = absolute_tip(mech, s, kinematics=Failing(mech), on_error="nan").data
    assert np.isnan(out[bad]).all() and np.isfinite(out[~bad]).all()
    np.testing.assert_allclose(out[~bad], absolute_tip(mech, s).data[~bad], rtol=0, atol=1e-12)
    with pytest.raises(KinematicsError, match="absolute tip at t = "):
        absolute_tip(mech, s, kinematics=Failing(mech))


@pytest.fixture(scope="module")
def quick_study(tmp_path_factory):
    from exuflex.cli import main

    out = tmp_path_factory.mktemp("abs_tip") / "s"
    code = main(["study", "payload", str(MODEL), "--quick", "--levels", "0,100", "--runs", "2", "--duration", "0.2",
                 "--out", str(out), "--no-progress"])
    assert code == 0
    return out


def test_quick_study_has_absolute_tip_quantities(quick_study, capsys):
    out = quick_study
    s = json.loads((out / "summary.json").read_text())
    assert [q for q in s["quantities"] if q in ABS] == list(ABS)
    assert {"x25", "q3"} <= set(s["quantities"])
    assert s["tip_quantities"] == {"elastic": ["x25", "y26", "dx25", "dy26"], "absolute": list(ABS)}
    assert "ABSOLUTE" in s["tip_readings"] and "ELASTIC" in s["tip_readings"]
    for lv in s["levels"]:
        assert lv["n_diverged"] == 0
        for q in ABS:
            assert lv["eq21"][q]["n_runs"] == lv["n_runs"] == 2
            assert 0 < lv["eq21"][q]["mu"] < 0.05 and 0 < lv["eq21"][q]["sigma"] < 0.05
        # the absolute tip error includes the lever of the joint errors: well above the elastic one
        assert lv["eq21"]["tip_x"]["mu"] > 3 * lv["eq21"]["x25"]["mu"]
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert len(rows) == 4
    for stat in ("mean_abs", "std_abs", "rms", "max"):
        for q in ABS:
            assert float(rows[0][f"{stat}_{q}"]) > 0
    run = json.loads(next((out / "runs").glob("L00-*/run_0000.json")).read_text())
    assert set(ABS) <= set(run["mean_abs"])
    assert (out / "fig_payload.png").exists()


def test_truth_absolute_tip_is_the_recorded_tip_point(quick_study):
    """On the truth, rigid(q) + elastic gives back the tip point the engine recorded (clean tip sensors)."""
    from exuflex.study.runner import _load_truth, with_absolute_tip
    from exuflex.truth import TruthRecord

    mech = load_mechanism(MODEL)
    for f in sorted((quick_study / "truth").glob("L*/truth.npz")):
        lt = with_absolute_tip(mech, _load_truth(f, {}))
        assert isinstance(lt, TruthRecord) and all(q in lt.truth for q in ABS)
        for q in ("tip_x", "tip_y"):
            np.testing.assert_allclose(lt.truth[q], lt.clean[q], rtol=0, atol=1e-9)
        assert with_absolute_tip(mech, lt) is lt  # added once


def test_cli_table_and_figure_rows(quick_study, capsys):
    from exuflex.cli.study import print_summary
    from exuflex.study.runner import figure_rows

    s = json.loads((quick_study / "summary.json").read_text())
    print_summary(s)
    text = capsys.readouterr().out
    assert "mu tip_x" in text and "mu dtip_y" in text and "mu x25" in text and "rigid + elastic" in text
    rows = figure_rows(s)
    order = list(dict.fromkeys(r["quantity"] for r in rows))
    assert order[-8:] == ["x25", "tip_x", "y26", "tip_y", "dx25", "dtip_x", "dy26", "dtip_y"]
    titles = {r["quantity"]: r["title"] for r in rows}
    assert "rigid + elastic" in titles["tip_x"] and "elastic displacement" in titles["x25"]

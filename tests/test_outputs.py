"""Outputs of ``exuflex observe --out`` and ``exuflex plot``: estimates.csv with a standard deviation per quantity
and the absolute tip position, files readable by everyone, the summary table with units."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np

from exuflex.cli import main
from exuflex.mechanism import load_mechanism
from exuflex.observer.session import make_observer
from exuflex.scoring.run import observe_run
from exuflex.runs import read_run, read_signals_csv
from exuflex.sensors import absolute_tip

ROOT = Path(__file__).resolve().parents[1]
SIXBAR = str(ROOT / "models" / "sixbar.toml")
RUN = ROOT / "tests" / "data" / "sixbar_short"


def test_estimates_csv_columns_and_standard_deviations(tmp_path, capsys):
    assert main(["observe", SIXBAR, str(RUN), "--out", str(tmp_path / "o"), "--no-plots"]) == 0
    out = capsys.readouterr().out
    assert "quantity     unit" in out and "rad/s" in out
    est = read_signals_csv(tmp_path / "o" / "estimates.csv")
    for n in ("q1", "dq1", "x25", "tip_x", "dtip_y", "std_q1", "std_dq3", "std_x25", "std_dy26", "std_tip_x"):
        assert n in est.names, n
    # the joint standard deviations equal the filter's posterior variances stored diagonally (another storage path)
    mech = load_mechanism(SIXBAR)
    obs = make_observer(mech)
    res = observe_run(mech, read_run(RUN), observer=obs, with_bound=False).estimate.result
    r = obs.model.r
    np.testing.assert_allclose(est["std_q1"], np.sqrt(res.P_diag[:, 0]), rtol=1e-9)
    np.testing.assert_allclose(est["std_dq2"], np.sqrt(res.P_diag[:, r + 1]), rtol=1e-9)
    # the absolute tip is the rigid tip at q plus the elastic displacement
    tip = absolute_tip(mech, est, on_error="nan")
    np.testing.assert_allclose(est["tip_x"], tip["tip_x"], rtol=0, atol=1e-12)
    # the absolute tip's standard deviation is at least that of its elastic part alone
    assert np.all(est["std_tip_x"] >= 0) and np.all(np.isfinite(est["std_tip_x"]))
    mode = stat.S_IMODE(os.stat(tmp_path / "o" / "estimates.csv").st_mode)
    assert mode & 0o044 == 0o044, oct(mode)  # group and others may read (0644 under the usual umask)


def test_plot_command_on_a_run_folder_and_a_lab_csv(tmp_path, capsys):
    assert main(["plot", SIXBAR, str(RUN), "--out", str(tmp_path / "f")]) == 0
    names = {p.name for p in (tmp_path / "f").iterdir()}
    assert {"fig_torques.png", "fig_measurements.png", "fig_trajectory.png", "fig_joint_states.png"} <= names
    lab = tmp_path / "lab.csv"
    lines = (RUN / "sensors.csv").read_text().splitlines()
    lab.write_text("\n".join(["t_ms" + lines[0][4:]] + [
        ",".join([repr(float(r.split(",")[0]) * 1e3)] + r.split(",")[1:]) for r in lines[1:]]) + "\n")
    assert main(["plot", SIXBAR, str(lab), "--time-column", "t_ms", "--time-scale", "1e-3"]) == 0
    assert (tmp_path / "lab_figures" / "fig_measurements.png").exists()

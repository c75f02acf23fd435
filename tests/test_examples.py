"""The examples run as tests (scikit-fem's habit), each checked against an independent path to its numbers."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", ROOT / "examples" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_own_lab_log_equals_the_run_folder(tmp_path, monkeypatch):
    """Renamed columns, a ms time column and a comment line change nothing: the estimates equal those of the same
    log read as a run folder."""
    import exuflex as xf

    ex = _load("own_lab_log")
    monkeypatch.setattr(ex, "HERE", tmp_path)
    summary = ex.main([])
    assert Path(tmp_path / "data" / "lab_sixbar.csv").exists()
    mech = xf.load_mechanism(ROOT / "models" / "sixbar.toml")
    # the lab log has no truth: its bound runs along the plan, so the run folder's without its truth
    folder = xf.read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")
    ref = xf.observe_run(mech, xf.Run(folder.path, folder.sensors, None, folder.meta))
    assert summary["nis_mean"] == pytest.approx(ref.summary["nis_mean"], rel=1e-9)
    assert summary["bound_rms"] == pytest.approx(ref.summary["bound_rms"], rel=1e-9)


def test_online_loop_equals_the_offline_run():
    import exuflex as xf

    ex = _load("online_loop")
    online = ex.main(300)
    mech = xf.load_mechanism(ROOT / "models" / "sixbar.toml")
    obs = xf.make_observer(mech)
    run = xf.read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")
    S = run.sensors
    res = obs.ekf.run(S.t[:300], S.select(mech.motor_names).data[:300], S.select(obs.channels).data[:300])
    np.testing.assert_allclose(online, obs.physical(res.t, res.x_hat).data, rtol=1e-9, atol=1e-12)


def test_own_mechanism(tmp_path):
    """A model file from scratch: modes, a simulated run and the observer, which tracks its encoder."""
    ex = _load("own_mechanism")
    s = ex.main(["--out", str(tmp_path), "--duration", "0.3"])
    assert s["channels"] == ["q1", "c_root"]
    assert not s["diverged"]
    # errors within a few times the bound over a 0.3 s run (0.15 s after the start-up left out)
    assert all(r < 5 for r in s["ratio_to_bound"].values()), s["ratio_to_bound"]

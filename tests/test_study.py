"""Mismatch studies: resume after an interruption, executor equivalence, overrides, aggregation (eq. 21)."""

from __future__ import annotations

import csv
import importlib.util
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from exuflex.errors import UsageError
from exuflex.mechanism import load_mechanism
from exuflex.study import OverrideError, StudySpec, apply_overrides, parse_set, payload_levels, run_study
from exuflex.study import runner as study_runner

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "sixbar.toml"


def _copy_truth(src, out, command="study"):
    """The truth cache of the study ``src`` copied into ``out``, a study folder (exuflex's: its mark lists it)."""
    from exuflex.runs import output_folder

    with output_folder(out, command, mode="resume"):
        shutil.copytree(src / "truth", out / "truth")


def _studies(name):
    spec = importlib.util.spec_from_file_location(f"studies_{name}", ROOT / "studies" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _tiny(runs=2, levels=(0, 100)):
    return StudySpec(model=str(MODEL), levels=payload_levels(levels), runs=runs, duration=0.1, engine="exudyn")


@pytest.fixture(scope="module")
def done_study(tmp_path_factory):
    out = tmp_path_factory.mktemp("study")
    return run_study(_tiny(), out)


def _numbers(rows):
    return [(r["level_index"], r["run"], r["seed"], r["mean_abs"], r["std_abs"], r["rms"], r["nis_mean"]) for r in rows]


def test_study_files_and_eq21(done_study):
    from exuflex.plots import study_figure

    out = done_study.out
    assert (out / "results.csv").exists() and (out / "summary.json").exists()
    assert not (out / "fig_payload.png").exists()  # the library does not plot
    assert study_figure(done_study.summary, out) == out / "fig_payload.png" and (out / "fig_payload.png").exists()
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert len(rows) == 4
    s = json.loads((out / "summary.json").read_text())
    assert s["model"]["sha256"] and s["versions"]["numpy"] and s["settings"]["base_seed"] == 0
    assert [lv["seeds"] for lv in s["levels"]] == [[0, 1], [0, 1]]
    assert [lv["payload_scale"] for lv in s["levels"]] == [1.0, 2.0]
    for lv in s["levels"]:
        rs = [r for r in done_study.rows if r["level_index"] == lv["index"]]
        for q in ("x25", "dq1", "tip_x", "dtip_y"):  # tip_x ...: absolute tip (rigid + elastic)
            assert lv["eq21"][q]["mu"] == pytest.approx(np.mean([r["mean_abs"][q] for r in rs]))
            assert lv["eq21"][q]["sigma"] == pytest.approx(np.mean([r["std_abs"][q] for r in rs]))
            assert 0 < lv["eq21"][q]["mu"] < 1
    for lv in s["levels"]:
        assert lv["n_diverged"] == 0 and 0 <= lv["n_nis_flagged"] <= lv["n_runs"]
        assert 0 < lv["max_q_error_rad"] < 0.05
    assert "lost the mechanism" in s["divergence"]
    assert {"diverged", "nis_flagged"} <= set(rows[0])
    # the truth differs between levels, the noise seeds do not
    t0 = np.load(next((out / "truth").glob("L00-*/truth.npz")))["truth_data"]
    t1 = np.load(next((out / "truth").glob("L01-*/truth.npz")))["truth_data"]
    assert not np.array_equal(t0, t1)


def test_resume_after_interruption(done_study, tmp_path):
    class Stop(Exception):
        pass

    seen = []

    def stop_after_two(r):
        seen.append(r)
        if len(seen) == 2:
            raise Stop

    out = tmp_path / "s"
    _copy_truth(done_study.out, out)  # the truth cache is exercised by the fixture
    with pytest.raises(Stop):
        run_study(_tiny(), out, on_result=stop_after_two)
    files = sorted((out / "runs").glob("*/run_*.json"))
    assert len(files) == 2
    mtimes = {f: f.stat().st_mtime_ns for f in files}
    before = study_runner.OBSERVER_RUNS
    time.sleep(0.01)
    res = run_study(_tiny(), out)
    assert (res.n_computed, res.n_reused) == (2, 2)
    assert study_runner.OBSERVER_RUNS - before == 2  # finished runs are not recomputed
    assert {f: f.stat().st_mtime_ns for f in files} == mtimes  # nor rewritten
    assert _numbers(res.rows) == _numbers(done_study.rows)  # and the result equals an uninterrupted study
    # a third call computes nothing; more runs reuse the finished ones (and the cached truth)
    assert run_study(_tiny(), out).n_computed == 0
    more = run_study(_tiny(runs=3), out)
    assert (more.n_computed, more.n_reused) == (2, 4)


def test_changed_settings_are_not_reused(done_study, tmp_path):
    out = tmp_path / "s"
    shutil.copytree(done_study.out, out)
    spec = _tiny()
    from dataclasses import replace

    with pytest.raises(UsageError, match=r"other settings \(differing: settings.start_up_s\); use another folder"):
        run_study(replace(spec, start_up=0.02), out)
    assert json.loads((out / "study.json").read_text())["settings"]["start_up_s"] != 0.02  # left as it was
    res = run_study(replace(spec, start_up=0.02), tmp_path / "other")
    assert res.n_computed == 4 and res.n_reused == 0


def test_a_running_study_locks_its_folder(done_study, tmp_path):
    """While one study holds the folder (its lock), a second one into it is refused before any work; once the
    lock is released the same settings resume."""
    from exuflex.study.runner import study_lock

    out = tmp_path / "s"
    shutil.copytree(done_study.out, out)
    with study_lock(out):
        with pytest.raises(UsageError, match="another study is running in this folder"):
            run_study(_tiny(), out)
    assert run_study(_tiny(), out).n_computed == 0


def test_process_pool_gives_the_same_numbers(done_study, tmp_path):
    out = tmp_path / "s"
    _copy_truth(done_study.out, out)  # cached truth: only the runs are recomputed
    res = run_study(_tiny(), out, workers=2)
    assert res.n_computed == 4
    assert _numbers(res.rows) == _numbers(done_study.rows)
    assert len({r["worker"] for r in res.rows}) >= 1


def test_divergence_is_a_lost_track_not_an_nis_flag():
    from exuflex.study.runner import TRACK_LOST_RAD, diverged

    coords = ("q1", "q2")

    def row(e1, e2, nonfinite=False, nis=False):
        return {"max": {"q1": e1, "q2": e2, "x25": 1.0}, "nonfinite": nonfinite, "nis_flagged": nis}

    assert not diverged(row(1e-3, 2e-3, nis=True), coords)  # inconsistent, still tracking
    assert diverged(row(1e-3, 2 * TRACK_LOST_RAD), coords)  # lost the mechanism
    assert diverged(row(1e-3, float("nan")), coords)
    assert diverged(row(1e-3, 1e-3, nonfinite=True), coords)


def test_overrides():
    m = load_mechanism(MODEL)
    m2 = apply_overrides(m, {"links.L1.diameter": 0.031, "damping.alpha": 2, "sensors.c1.noise_std": 1e-4,
                             "payload.mass": 0.1, "masses.12.mass": 2.0, "materials.aluminium.E": 70e9})
    s = m2.link("L1").section
    assert s.diameter == 0.031 and s.A == pytest.approx(np.pi * 0.031**2 / 4) and s.I == pytest.approx(np.pi * 0.031**4 / 64)
    assert m2.damping.alpha == 2.0 and m2.payload.mass == 0.1
    assert {x.name: x for x in m2.sensors}["c1"].noise_std == 1e-4
    assert next(x for x in m2.masses if x.node == 12).mass == 2.0
    assert all(lk.material.E == 70e9 for lk in m2.links)
    assert m.link("L1").section.diameter == 0.03  # the nominal model is unchanged


@pytest.mark.parametrize("path,value,words", [
    ("links.L9.diameter", 0.03, ["links.L9.diameter", "L1"]),
    ("links.L1.diam", 0.03, ["links.L1.diam", "diameter"]),
    ("damping.gamma", 1.0, ["damping.gamma", "alpha"]),
    ("sensors.c9.noise_std", 1.0, ["sensors.c9.noise_std", "c1"]),
    ("payload.mass", "heavy", ["payload.mass", "number"]),
    ("links.L1.diameter", -1.0, ["links.L1.diameter", "positive"]),
    ("nonsense", 1.0, ["nonsense"]),
    ("sensors.c1", 1.0, ["sensors.c1"]),
])
def test_override_errors_name_the_field(path, value, words):
    with pytest.raises(OverrideError) as ei:
        apply_overrides(load_mechanism(MODEL), {path: value})
    for w in words:
        assert w in str(ei.value)


def test_parse_set():
    assert parse_set("links.L1.diameter=0.03,0.031") == ("links.L1.diameter", [0.03, 0.031])
    assert parse_set("gravity=[0;-9.81],[0;0]") == ("gravity", [(0, -9.81), (0, 0)])
    with pytest.raises(OverrideError, match="FIELD=V1"):
        parse_set("links.L1.diameter")


def test_cli_errors(tmp_path, capsys):
    from exuflex.cli import main

    assert main(["study", "sweep", str(MODEL), "--out", str(tmp_path), "--set", "links.L1.diam=0.03"]) == 2
    assert "links.L1.diam" in capsys.readouterr().err
    assert main(["study", "payload", str(MODEL), "--out", str(tmp_path), "--runs", "0"]) == 2
    assert main(["study", "payload", str(MODEL), "--out", str(tmp_path / "e"), "--estimators", "ekf,kalman"]) == 2
    assert "estimators (--estimators): expected names among ekf, ukf, ekf-payload, ekf-input, imm; got kalman" in capsys.readouterr().err


def test_studies_script_quick(done_study, tmp_path):
    mod = _studies("payload")
    _copy_truth(done_study.out, tmp_path)  # same model, levels and duration
    res = mod.compute(tmp_path, mod.QUICK)
    assert res.n_computed == 4
    assert mod.plot(res.summary, tmp_path / "f.png").exists()


@pytest.mark.slow
def test_killed_cli_study_resumes(tmp_path):
    out = tmp_path / "s"
    cmd = [sys.executable, "-m", "exuflex", "study", "payload", str(MODEL), "--levels", "0,100", "--runs", "4",
           "--duration", "0.1", "--out", str(out), "--no-progress"]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t0 = time.time()
    while not list((out / "runs").glob("*/run_*.json")) and time.time() - t0 < 120:
        time.sleep(0.05)
    p.kill()
    p.wait()
    first = {f: f.stat().st_mtime_ns for f in (out / "runs").glob("*/run_*.json")}
    assert first and len(first) < 8
    r = subprocess.run(cmd, capture_output=True, text=True, check=True)
    assert f"{8 - len(first)} run(s) computed, {len(first)} reused" in r.stdout
    assert all(f.stat().st_mtime_ns == m for f, m in first.items())


@pytest.mark.slow
def test_dask_local_cluster(done_study, tmp_path):
    distributed = pytest.importorskip("distributed")
    out = tmp_path / "s"
    _copy_truth(done_study.out, out)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True) as cluster:
        res = run_study(_tiny(), out, scheduler=cluster.scheduler_address)
    assert _numbers(res.rows) == _numbers(done_study.rows)


def test_estimator_studies_share_the_truths(done_study, tmp_path):
    """``--estimators``: one study per estimator on the level truths simulated once; the plain EKF's study is the
    ordinary one, the payload EKF's runs report the payload scale; the figure draws them side by side."""
    from exuflex.plots import payload_study_figure
    from exuflex.study import estimator_figure_rows, run_estimator_studies

    out = tmp_path / "est"
    _copy_truth(done_study.out, out, "study-estimators")
    n_truth = len(list((out / "truth").glob("L*/truth.npz")))
    res = run_estimator_studies(_tiny(runs=1), out, ["ekf", "ekf-payload"])
    assert list(res) == ["ekf", "ekf-payload"]
    assert len(list((out / "truth").glob("L*/truth.npz"))) == n_truth  # no truth simulated again
    assert (out / "ekf-payload" / "truth").resolve() == (out / "truth").resolve()
    first = [n for n in _numbers(done_study.rows) if n[1] == 0]
    assert _numbers(res["ekf"].rows) == first  # the same seeds on the same truths: the same numbers
    for r in res["ekf-payload"].rows:
        assert r["parameters"]["payload_scale_std"] > 0 and np.isfinite(r["parameters"]["payload_scale"])
    rows = estimator_figure_rows({e: r.summary for e, r in res.items()})
    assert {r["series"] for r in rows} == {"ekf", "ekf-payload"}
    assert payload_study_figure(rows, out / "fig.png").exists()
    with pytest.raises(ValueError, match="expected names among"):
        run_estimator_studies(_tiny(runs=1), out, ["ekf", "kalman"])
    with pytest.raises(ValueError, match="each at most once"):
        run_estimator_studies(_tiny(runs=1), out, ["ekf", "ekf"])

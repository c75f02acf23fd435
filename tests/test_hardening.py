"""The second hardening pass (issue 31): no overwrite of data exuflex did not write, bounds before work, studies
that die cleanly, strict JSON, argument errors naming the parameter. Each case of the issue is a test here;
the generated campaign over these kinds is ``tests/test_hardening_campaign.py``."""

from __future__ import annotations

import json
import re
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from exuflex.cli import main
from exuflex.errors import UsageError
from exuflex.runs import OUTPUT_MARK, dump_json, output_folder

from _sentinels import stop_work

ROOT = Path(__file__).resolve().parents[1]
SIXBAR = str(ROOT / "models" / "sixbar.toml")
RUN = ROOT / "tests" / "data" / "sixbar_short"


@pytest.fixture
def no_work(monkeypatch):
    """Every command's work replaced by a sentinel (the checks before it run as usual)."""
    stop_work(monkeypatch)


# ------------------------------------------------------------------------------------------ folders a lab owns
def _lab_folder(tmp_path: Path, kind: str) -> Path:
    d = tmp_path / kind
    d.mkdir()
    if kind == "sensors_only":  # a lab's own measured log, no meta.json
        (d / "sensors.csv").write_text("time,T1,q1\n0,0.1,0.2\n0.001,0.1,0.2\n")
    elif kind == "measured_meta":  # a meta.json saying the run is measured
        shutil.copy(RUN / "sensors.csv", d / "sensors.csv")
        meta = json.loads((RUN / "meta.json").read_text())
        meta["engine"] = "measured"
        meta["truth"] = []
        meta.pop("versions", None)
        (d / "meta.json").write_text(json.dumps(meta))
    elif kind == "notes":
        (d / "notes.txt").write_text("calibration 3 March\n")
    return d


def _snapshot(d: Path) -> dict:
    return {p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


LAB_KINDS = ("sensors_only", "measured_meta", "notes")
WRITERS = {
    "simulate": lambda out, *extra: ["simulate", SIXBAR, "--out", out, "--engine", "erls", *extra],
    "observe": lambda out, *extra: ["observe", SIXBAR, str(RUN), "--out", out, *extra],
    "study": lambda out, *extra: ["study", "payload", SIXBAR, "--quick", "--out", out, "--no-progress", *extra],
    "reproduce": lambda out, *extra: ["reproduce", "--quick", "--out", out, "--no-progress", *extra],
    "plot": lambda out, *extra: ["plot", SIXBAR, str(RUN), "--out", out, *extra],
}


@pytest.mark.parametrize("kind", LAB_KINDS)
@pytest.mark.parametrize("command", sorted(WRITERS))
@pytest.mark.parametrize("overwrite", [False, True])
def test_a_folder_exuflex_did_not_write_is_never_written(tmp_path, capsys, no_work, kind, command, overwrite):
    d = _lab_folder(tmp_path, kind)
    before = _snapshot(d)
    extra = ["--overwrite"] if overwrite and command != "plot" else []
    rc = main(WRITERS[command](str(d), *extra))
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "exuflex did not write" in err and "--out" in err, err
    assert _snapshot(d) == before and not (d / OUTPUT_MARK).exists()


@pytest.mark.parametrize("command", sorted(WRITERS))
def test_out_that_is_a_file_is_refused_at_once(tmp_path, capsys, no_work, command):
    f = tmp_path / "result.txt"
    f.write_text("keep me\n")
    for out in (f, f / "sub"):
        assert main(WRITERS[command](str(out))) == 2
        err = capsys.readouterr().err
        assert f"{f} is a file" in err, err
    assert f.read_text() == "keep me\n"


def test_an_earlier_result_is_replaced_only_with_overwrite(tmp_path, capsys):
    """Another model's run (an exuflex result) is refused; --overwrite replaces it (its files removed first)."""
    out = tmp_path / "run"
    other = str(ROOT / "models" / "fourbar.toml")
    assert main(["simulate", other, "--out", str(out), "--engine", "reduced", "--duration", "0.02", "--seed", "1",
                 "--no-progress"]) == 0
    (out / "plan.csv").write_text("t\n")  # as if an earlier --write-plan: an exuflex file (the mark lists it)
    mark = json.loads((out / OUTPUT_MARK).read_text())
    mark["files"].append("plan.csv")
    (out / OUTPUT_MARK).write_text(json.dumps(mark))
    before = _snapshot(out)
    capsys.readouterr()
    args = ["simulate", SIXBAR, "--out", str(out), "--engine", "reduced", "--duration", "0.02", "--seed", "1",
            "--no-progress"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "earlier exuflex result (written by simulate)" in err and "--overwrite" in err, err
    assert _snapshot(out) == before
    assert main(args + ["--overwrite"]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["mechanism"] == "sixbar"
    assert not (out / "plan.csv").exists()  # the earlier result's files went with it
    assert sorted(json.loads((out / OUTPUT_MARK).read_text())["files"]) == ["meta.json", "sensors.csv", "truth.csv"]


def test_a_folder_with_an_own_file_added_later_is_refused_even_with_overwrite(tmp_path, capsys):
    out = tmp_path / "run"
    with output_folder(out, "simulate"):
        (out / "sensors.csv").write_text("time\n0\n")
    (out / "my_notes.txt").write_text("mine\n")
    with pytest.raises(UsageError, match=r"exuflex did not write \(my_notes.txt\)"):
        with output_folder(out, "simulate", overwrite=True):
            pass
    assert (out / "my_notes.txt").read_text() == "mine\n" and (out / "sensors.csv").exists()


def test_output_folder_removes_what_it_made_on_failure_and_keeps_a_resumable_study(tmp_path):
    with pytest.raises(RuntimeError), output_folder(tmp_path / "new", "simulate"):
        raise RuntimeError("the work failed")
    assert not (tmp_path / "new").exists()
    s = tmp_path / "study"
    with output_folder(s, "study", mode="resume"):
        (s / "study.json").write_text("{}")
    with output_folder(s, "study", mode="resume"):  # a study resumes its own folder without --overwrite
        pass
    with pytest.raises(UsageError, match="written by study"):
        with output_folder(s, "simulate"):
            pass
    assert (s / "study.json").exists()


def test_observe_refuses_to_write_into_the_folder_it_reads(tmp_path, capsys, no_work):
    run = tmp_path / "run"
    shutil.copytree(RUN, run)
    assert main(["observe", SIXBAR, str(run), "--out", str(run), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert "holds the input" in err, err
    assert (run / "sensors.csv").exists()


def test_plot_of_a_lab_folder_writes_beside_it(tmp_path, capsys):
    d = _lab_folder(tmp_path, "measured_meta")
    before = _snapshot(d)
    assert main(["plot", SIXBAR, str(d)]) == 0
    assert _snapshot(d) == before
    assert (tmp_path / "measured_meta_figures" / "fig_torques.png").exists()


def test_write_run_never_writes_over_a_lab_log(tmp_path):
    from exuflex.runs import read_run, write_run

    d = _lab_folder(tmp_path, "sensors_only")
    run = read_run(RUN)
    with pytest.raises(UsageError, match="exuflex did not write"):
        write_run(d, run.sensors, run.truth, run.meta)
    assert (d / "sensors.csv").read_text().startswith("time,T1,q1")


# ------------------------------------------------------------------------------------------ strict JSON
def test_dump_json_is_strict():
    text = dump_json({"a": float("nan"), "b": [np.inf, -np.inf, np.float64(1.5)], "c": np.array([1.0, np.nan]),
                      "d": np.int64(3), "e": np.bool_(True), "f": Path("x")})
    assert json.loads(text, parse_constant=lambda c: pytest.fail(f"bare {c}")) == {
        "a": None, "b": [None, None, 1.5], "c": [1.0, None], "d": 3, "e": True, "f": "x"}
    with pytest.raises(TypeError):
        dump_json({"x": object()})


# ------------------------------------------------------------------------------------------ studies
def test_levels_empty_or_repeated_are_refused(tmp_path, capsys, no_work):
    for levels, why in (("", "none empty"), (" ", "none empty"), ("0,,50", "none empty"),
                        ("0,0", "given twice"), ("0,0.0", "given twice"), ("0,-100", "leaves no payload"),
                        ("nan", "finite"), ("a", "percentages")):
        rc = main(["study", "payload", SIXBAR, "--quick", "--out", str(tmp_path / "s"), "--levels", levels])
        err = capsys.readouterr().err
        assert rc == 2 and why in err and "--levels" in err, (levels, err)
        assert not (tmp_path / "s").exists()
    assert main(["study", "sweep", SIXBAR, "--quick", "--out", str(tmp_path / "s"),
                 "--set", "links.L1.diameter=0.03,0.03"]) == 2
    assert "given twice" in capsys.readouterr().err


def test_workers_are_capped_at_the_cores_and_the_tasks(monkeypatch, caplog):
    import concurrent.futures as cf

    from exuflex.study import runner

    seen = {}

    class Pool:
        def __init__(self, max_workers, **kw):
            seen["workers"] = max_workers
            seen.update(kw)

        def __enter__(self):
            return self

        def __exit__(self, *a):
            return False

    monkeypatch.setattr(cf, "ProcessPoolExecutor", Pool)
    monkeypatch.setattr(runner._compile, "prepare", lambda **k: None)
    with runner.make_executor(1000):
        pass
    assert seen["workers"] == (os.cpu_count() or 1)
    assert seen["initializer"] is runner._worker_init
    assert "1000 asked" in caplog.text


_STUDY_CHILD = textwrap.dedent("""
    import sys, time
    from exuflex.study import runner
    from exuflex.study.runner import study_lock, make_executor
    from pathlib import Path
    out = Path(sys.argv[1])
    with study_lock(out), make_executor(2) as (ex, n):
        futs = [ex.submit(time.sleep, 0.01) for _ in range(4)]
        for f in futs:
            f.result()
        import multiprocessing
        print(" ".join(str(p.pid) for p in multiprocessing.active_children()), flush=True)
        time.sleep(60)
""")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped by its new parent) is not alive
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="kill -9 of a process group member, Linux")
def test_a_study_killed_with_9_leaves_no_workers_and_its_lock_is_taken_over(tmp_path, caplog):
    out = tmp_path / "study"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen([sys.executable, "-c", _STUDY_CHILD, str(out)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        workers = [int(w) for w in p.stdout.readline().split()]
        assert len(workers) == 2 and all(_alive(w) for w in workers)
        os.kill(p.pid, signal.SIGKILL)
        p.wait()
        deadline = time.monotonic() + 10
        while any(_alive(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_alive(w) for w in workers), "the workers outlived their study"
    finally:
        if p.poll() is None:
            p.kill()
    from exuflex.study.runner import study_lock

    assert (out / ".study.lock").read_text().startswith(f"pid {p.pid}")
    with study_lock(out):  # the dead study's lock: taken over, with a message naming it
        pass
    assert f"pid {p.pid} no longer runs" in caplog.text


def test_truth_timings_are_kept_across_resumes(tmp_path):
    from exuflex.study import StudySpec, payload_levels, run_study

    spec = StudySpec(model=SIXBAR, levels=payload_levels([0]), runs=1, engine="reduced", duration=0.06)
    first = run_study(spec, tmp_path / "s").summary["levels"][0]["truth_timings"]
    assert first and "truth_s" in first
    again = run_study(spec, tmp_path / "s")  # every run finished: nothing simulated, the provenance kept
    assert again.n_computed == 0
    assert again.summary["levels"][0]["truth_timings"] == first


# ------------------------------------------------------------------------------------------ the API's arguments
@pytest.fixture(scope="module")
def sixbar():
    import exuflex as xf

    return xf.load_mechanism(SIXBAR)


@pytest.fixture(scope="module")
def filt(sixbar):
    import exuflex as xf

    return xf.make_observer(sixbar, xf.ObserverConfig()).ekf


def test_api_argument_errors_name_the_parameter(sixbar):
    import exuflex as xf

    run = xf.read_run(RUN)
    cases = [
        (lambda: xf.load_mechanism(123), r"^path: expected the path of a model file .* got int"),
        (lambda: xf.load_mechanism(sixbar), r"^path: .*already loaded"),
        (lambda: xf.read_lab_run(RUN / "sensors.csv", SIXBAR), r"^mech: expected an exuflex.mechanism.Mechanism, got str"),
        (lambda: xf.read_lab_run(RUN / "sensors.csv", sixbar, "T1=a"), r"^columns: expected a mapping"),
        (lambda: xf.read_lab_run(42, sixbar), r"^path: expected a path"),
        (lambda: xf.make_observer(sixbar, "q_scale=1"), r"^config: expected an exuflex.ObserverConfig or None, got str"),
        (lambda: xf.observe_run(sixbar, run, observer="x"), r"^observer: expected an exuflex.Observer .* got str"),
        (lambda: xf.observe_run(sixbar, run, config={"q_scale": 1}), r"^config: expected .* got dict"),
    ]
    for call, match in cases:
        with pytest.raises(UsageError, match=match):
            call()


def test_filter_step_arguments_are_checked_at_the_call(filt):
    nan = np.full(filt.m, np.nan)
    filt.reset()
    cases = [
        ((0.0, np.zeros(3), {"q1": 1.0}), r"^y: expected an array of 6 values in channel order"),
        ((0.0, None, nan), r"^u: expected the input sample .* got None \(a missing torque is not zero"),
        ((0.0, [0.0, np.nan, 0.0], nan), r"^u: the input sample .* not finite"),
        ((0.0, np.zeros(2), nan), r"^u: expected 3 input values \(one per motor\), got 2"),
        ((0.0, np.zeros(4), nan), r"^u: expected 3 input values"),
        ((0.0, "abc", nan), r"^u: expected an array"),
        ((0.0, np.zeros(3), np.r_[np.inf, np.zeros(5)]), r"^y: channel\(s\) \['q1'\] infinite"),
        ((0.0, np.zeros(3), np.zeros(5)), r"^y: measurement has shape \(5,\)"),
        ((0.0, np.zeros(3), "q1"), r"^y: expected an array"),
        (("a", np.zeros(3), nan), r"^t: expected the sample time in s \(a number\), got str"),
        ((None, np.zeros(3), nan), r"^t: expected the sample time"),
        ((float("nan"), np.zeros(3), nan), r"^t: the sample time nan is not finite"),
    ]
    for args, match in cases:
        with pytest.raises(UsageError, match=match):
            filt.step(*args)
    x = filt.step(0.0, np.zeros(3), nan)  # the refused calls changed nothing: the first sample is still accepted
    assert x.shape == (filt.nx,) and np.isfinite(x).all()


def test_an_infinite_measurement_in_a_record_is_refused(filt):
    n = 5
    t = np.arange(n) * filt.dt
    Y = np.full((n, filt.m), np.nan)
    Y[3, 2] = -np.inf
    filt.reset()
    with pytest.raises(ValueError, match=r"row 3 .* infinite measurement"):
        filt.run(t, np.zeros((n, 3)), Y)


# ------------------------------------------------------------------------------------------ model files
def test_a_byte_order_mark_is_accepted(tmp_path):
    from exuflex.mechanism import load_mechanism

    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf" + Path(SIXBAR).read_bytes())
    assert load_mechanism(p).name == "sixbar"


def test_a_missing_coordinate_is_named(tmp_path):
    from exuflex.mechanism import ModelFileError, load_mechanism

    text = Path(SIXBAR).read_text()
    block = '[[coordinates]]\nname = "q1"\nlink = "L1"\njoint = "O"\n'
    assert block in text
    p = tmp_path / "m.toml"
    p.write_text(text.replace(block, ""))
    with pytest.raises(ModelFileError, match=r"coordinates: .*mobility \(3.*the file has 2 \(q2, q3\); 1 \[\[coordinates\]\] "
                       "entry missing"):
        load_mechanism(p)


# ------------------------------------------------------------------------------------------ sampling and logs
def _decimated(tmp_path: Path, every: int) -> Path:
    from exuflex.runs import read_run, write_run
    from exuflex.sensors import Signals

    run = read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")
    S = run.sensors
    k = np.arange(0, len(S.t), every)
    out = tmp_path / f"every{every}"
    write_run(out, Signals(S.t[k], S.names, S.data[k], S.units), run.truth,
              {key: v for key, v in run.meta.items() if key != "units"})
    return out


def test_a_log_sampled_below_the_models_modes_is_refused_or_flagged(tmp_path, capsys):
    run = _decimated(tmp_path, 50)  # the six-bar's 500 Hz log at 10 Hz
    assert main(["observe", SIXBAR, str(run)]) == 2
    err = capsys.readouterr().err
    assert "cannot support the estimate" in err and "(q1, 10 Hz)" in err and "--allow-undersampled" in err, err
    assert main(["observe", SIXBAR, str(run), "--allow-undersampled", "--json"]) == 0
    cap = capsys.readouterr()
    s = json.loads(cap.out)
    assert s["sampling"]["undersampled"] and s["sampling"]["needed_hz"] > 2 * 100
    assert s["nis_inconsistent"] == (s["nis_inconsistent"] or s["nis_whole_log_flag"])  # the flags agree
    assert "not supported by the log" in cap.err


def test_the_whole_log_nis_test():
    from exuflex.scoring.run import nis_whole_log_flag

    assert not nis_whole_log_flag(6.0, 6.0, 10)  # consistent
    assert not nis_whole_log_flag(12.0, 6.0, 1000)  # twice the expectation: the windowed test's domain
    assert nis_whole_log_flag(20.0, 6.0, 1000)  # above 3 x the chi-square bound (6.52 a sample over 1000)
    assert nis_whole_log_flag(10113.0, 2.0, 3)  # orders of magnitude above, however few updates
    assert nis_whole_log_flag(35.9, 6.0, 31)  # 6 times the expectation over 31 updates
    assert not nis_whole_log_flag(float("nan"), 6.0, 10) and not nis_whole_log_flag(60.0, 6.0, 0)
    # at the exact quantile (scipy.stats)
    from scipy.stats import chi2

    for k in (1, 2, 6, 60, 6000):
        exact = chi2.isf(1e-6, k)
        lo, hi = exact * 0.999 / k, exact * 1.001 / k
        assert not nis_whole_log_flag(lo, 1.0, k, factor=1) and nis_whole_log_flag(hi, 1.0, k, factor=1), k


def test_a_column_mapped_to_two_channels_is_named(sixbar):
    from exuflex.errors import LogFormatError
    from exuflex.runs import read_lab_run

    with pytest.raises(LogFormatError, match=r"--map: the column 'c1' is mapped to the channels \['c1', 'c4'\]"):
        read_lab_run(RUN / "sensors.csv", sixbar, {"c1": "c1", "c4": "c1"}, columns_name="--map")


def test_an_unmapped_text_column_is_ignored_with_a_note(tmp_path, sixbar, caplog):
    from exuflex.runs import read_lab_run, read_run

    run = read_run(RUN)
    lines = (RUN / "sensors.csv").read_text().splitlines()
    text = [lines[0] + ",status"] + [ln + ",OK" for ln in lines[1:]]
    p = tmp_path / "lab.csv"
    p.write_text("\n".join(text) + "\n")
    for cols in (None, {"q1": "q1"}):
        lab = read_lab_run(p, sixbar, cols)
        assert "status" not in lab.sensors.names
        np.testing.assert_array_equal(lab.sensors["q1"], run.sensors["q1"])
    assert "['status'] not mapped to a channel and not numbers: ignored" in caplog.text


def test_a_channel_clipped_at_full_scale_is_named(sixbar):
    import dataclasses

    from exuflex.runs import read_run
    from exuflex.sensors import Signals
    from exuflex.validate import check_run

    run = read_run(RUN)
    S = run.sensors
    fs = 0.5 * float(np.nanmax(np.abs(S["c1"])))
    data = S.data.copy()
    i = S.names.index("c1")
    data[:, i] = np.clip(data[:, i], -fs, fs)
    mech = dataclasses.replace(sixbar, sensors=tuple(dataclasses.replace(s, full_scale=fs) if s.name == "c1" else s
                                                    for s in sixbar.sensors))
    clipped = dataclasses.replace(run, sensors=Signals(S.t, S.names, data, S.units))
    rep = check_run(mech, clipped, ("q1", "c1"))
    assert 0 < rep.saturated["c1"] <= 1
    assert any("channel 'c1'" in w and "at its full scale" in w and "clipped" in w for w in rep.warnings)
    assert "c1" not in check_run(sixbar, run, ("q1", "c1")).saturated


# ------------------------------------------------------------------------------------------ bounds before work
BOUNDS = [
    (["modes", SIXBAR, "--reduced", "--along", "100000000"], r"along \(--along\): 100000000 means 1e\+08 configurations"),
    (["design", SIXBAR, "--candidates", "100000000"], r"n_candidates \(--candidates\): 100000000 means 5e\+08 candidate"),
    (["observe", SIXBAR, str(RUN), "--substep", "1e-9"], r"h \(--substep\): the RK4 sub-step 1e-09 s is below"),
    (["study", "payload", SIXBAR, "--runs", "1000000000000", "--out", "OUT"], r"runs \(--runs\): .* observer runs"),
    (["simulate", SIXBAR, "--duration", "1e5", "--h", "1e-3", "--out", "OUT"], r"duration \(--duration\): .* steps"),
]


@pytest.mark.parametrize("argv, match", BOUNDS, ids=[b[0][0] for b in BOUNDS])
def test_sizes_a_user_types_are_bounded_before_work(tmp_path, capsys, argv, match):
    import re
    import tracemalloc

    argv = [a.replace("OUT", str(tmp_path / "out")) for a in argv]
    tracemalloc.start()
    rc = main(argv)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    err = capsys.readouterr().err
    assert rc == 2 and re.search(match, err) and "expected" in err, err
    assert len([ln for ln in err.splitlines() if ": error: " in ln]) == 1
    assert peak < 200 * 2**20  # refused before any allocation of the size asked for
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------------ provenance
def _run_copy(tmp_path: Path, src: Path = RUN, **meta_changes) -> Path:
    d = tmp_path / "run"
    shutil.copytree(src, d)
    meta = json.loads((d / "meta.json").read_text())
    meta.update(meta_changes)
    (d / "meta.json").write_text(json.dumps(meta))
    return d


def test_a_run_of_another_model_is_refused_or_named(tmp_path, capsys):
    fourbar = str(ROOT / "models" / "fourbar.toml")
    assert main(["observe", fourbar, str(RUN)]) == 2
    err = capsys.readouterr().err
    assert "meta.json says the run is of the mechanism 'sixbar'" in err and "--accept-other-model" in err, err
    from exuflex.validate import check_provenance

    import exuflex as xf

    run = xf.read_run(RUN)
    _, notes = check_provenance(xf.load_mechanism(fourbar), run, accept_other_model=True)
    assert any("observed with 'fourbar'" in n for n in notes)


def test_a_run_folders_units_are_honoured(tmp_path, sixbar):
    import exuflex as xf
    from exuflex.errors import LogFormatError
    from exuflex.validate import check_provenance

    meta = json.loads((RUN / "meta.json").read_text())
    units = meta["units"]
    units["sensors.csv"]["q1"] = "deg"
    d = _run_copy(tmp_path, units=units)
    lines = (d / "sensors.csv").read_text().splitlines()
    i = lines[0].split(",").index("q1")
    rows = [lines[0]] + [",".join(repr(float(c) * 180 / np.pi) if j == i and c else c
                                  for j, c in enumerate(ln.split(","))) for ln in lines[1:]]
    (d / "sensors.csv").write_text("\n".join(rows) + "\n")
    run, notes = check_provenance(sixbar, xf.read_run(d))
    np.testing.assert_allclose(run.sensors["q1"], xf.read_run(RUN).sensors["q1"], rtol=1e-12)
    assert any("'q1' converted from deg to rad" in n for n in notes)
    units["sensors.csv"]["c1"] = "furlongs"
    (d / "meta.json").write_text(json.dumps(dict(meta, units=units)))
    with pytest.raises(LogFormatError, match=r"column 'c1' in 'furlongs'; expected '1/m'"):
        check_provenance(sixbar, xf.read_run(d))


def test_a_late_truth_and_a_truth_that_is_a_log_are_refused(tmp_path, capsys):
    from exuflex.runs import read_run, write_run
    from exuflex.sensors import Signals

    run = read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")
    T = run.truth
    late = tmp_path / "late"
    write_run(late, run.sensors, Signals(T.t + 0.1, T.names, T.data, T.units),
              {k: v for k, v in run.meta.items() if k != "units"})
    assert main(["observe", SIXBAR, str(late)]) == 2
    err = capsys.readouterr().err
    assert re.search(r"the truth is 0.09\d* s late against the log", err), err
    assert main(["observe", SIXBAR, str(RUN / "sensors.csv"), "--truth", str(RUN / "sensors.csv")]) == 2
    assert "not a truth" in capsys.readouterr().err
    assert main(["observe", SIXBAR, str(RUN / "sensors.csv"), "--truth", str(tmp_path / "none.csv")]) == 2
    assert "none.csv: no such file" in capsys.readouterr().err


@pytest.mark.parametrize("opt", [["--time-column", "zzz"], ["--truth", "x.csv"], ["--map", "q1=a"],
                                 ["--time-scale", "1e-3"], ["--delimiter", ";"], ["--decimal", ","]])
def test_lab_csv_options_on_a_run_folder_are_refused(capsys, opt):
    assert main(["observe", SIXBAR, str(RUN), *opt]) == 2
    err = capsys.readouterr().err
    assert f"{opt[0]}: options of a lab CSV log, but" in err and "is a run folder" in err, err


def test_a_cell_with_an_underscore_is_not_a_number(tmp_path):
    from exuflex.errors import LogFormatError
    from exuflex.runs import read_csv_log

    p = tmp_path / "a.csv"
    p.write_text("time,q1\n0,1\n0.002,1_0\n")
    with pytest.raises(LogFormatError, match=r"line 3, column 'q1': '1_0' is not a number"):
        read_csv_log(p)


# ------------------------------------------------------------------------------------------ singular paths
def test_a_tip_line_to_an_open_chains_full_reach_is_refused():
    import math

    from exuflex.erls.kinematics import Kinematics, KinematicsError
    from exuflex.manoeuvre import plan
    from exuflex.mechanism import LinkPoint, Manoeuvre, load_mechanism

    arm = load_mechanism(ROOT / "models" / "serial_arm.toml")
    reach = sum(lk.length for lk in arm.links)
    lk = arm.links[-1]
    z = Kinematics(arm).pose(np.array([-0.3, 1.8])).z
    i = len(arm.links) - 1
    p0 = np.array([z[3 * i] + lk.length * math.cos(z[3 * i + 2]), z[3 * i + 1] + lk.length * math.sin(z[3 * i + 2])])
    g = np.array(arm.joints[0].ground)
    d = (p0 - g) / np.linalg.norm(p0 - g)

    def line(to):
        return Manoeuvre("tip_line", 1.0, "quintic", tip=LinkPoint(lk.name, lk.length),
                         points=(tuple(map(float, p0)), tuple(map(float, g + to * d))))

    plan(arm, line(0.95 * reach), dt=1e-3)  # short of the reach: planned
    with pytest.raises(KinematicsError, match=r"reaches a singular configuration at t = 1 s, .*path Jacobian"):
        plan(arm, line(reach), dt=1e-3)


def test_a_slider_crank_driven_to_its_toggle_position_is_refused(tmp_path):
    import math

    from exuflex.erls.kinematics import KinematicsError
    from exuflex.manoeuvre import plan
    from exuflex.mechanism import load_mechanism

    src = (ROOT / "models" / "slider_crank.toml").read_text()
    limit = -math.asin(0.1 / 0.4)  # the rod's steepest angle: the crank square to the slider's axis
    text = (src.replace('[[coordinates]]\nname = "q1"\nlink = "crank"\njoint = "O"',
                        '[[coordinates]]\nname = "q1"\nlink = "rod"\njoint = "A"')
            .replace("q_ref = [1.5707963267948966]", "q_ref = [-0.2]")
            .replace("q_star = [1.5707963267948966]", "q_star = [-0.2]")
            .replace("angle_guess = 1.5707963267948966", "angle_guess = 0.9"))
    text = re.sub(r"rules = \[.*\]", f'rules = [{{ coordinate = "q1", start = -0.2, end = {limit!r} }}]', text)
    p = tmp_path / "rod_driven.toml"
    p.write_text(text)
    with pytest.raises(KinematicsError, match=r"reaches a singular configuration"):
        plan(load_mechanism(p), dt=1e-3)


# ------------------------------------------------------------------------------------------ solver failures
def test_a_truth_solver_failure_names_its_likely_cause_in_the_input(tmp_path, capsys, monkeypatch):
    import exuflex.groundtruth

    def failing(*a, **k):  # the solver's own failure (Exudyn's Newton stalls on some such inputs)
        raise RuntimeError("Exudyn dynamic solver failed before t = 0.1 s")

    monkeypatch.setattr(exuflex.groundtruth, "simulate_truth", failing)
    rc = main(["simulate", SIXBAR, "--out", str(tmp_path / "r"), "--payload-scale", "1e6", "--duration", "0.1",
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "internal error" not in err and "a bug" not in err, err
    assert re.search(r"the exudyn truth's solver failed .*the likely cause is in the input: payload.mass \(times "
                     r"--payload-scale\) = 4.6e\+04 kg", err), err
    assert not (tmp_path / "r").exists()  # nothing left behind


def test_solver_failure_names_each_field():
    import dataclasses
    from types import SimpleNamespace

    import exuflex as xf
    from exuflex.errors import SimulationError
    from exuflex.truth.engines import solver_failure

    mech = xf.load_mechanism(SIXBAR)
    drive = SimpleNamespace(tau=np.zeros((3, 3)))
    err = solver_failure(mech, drive, "exudyn", 1e-4, RuntimeError("boom"))
    assert isinstance(err, SimulationError) and "no input far out of range" in str(err) and "--h" in str(err)
    heavy = dataclasses.replace(mech, gravity=(0.0, -9.81e4))
    assert "model.gravity = [0.0, -98100.0] m/s^2, 1e+04 g" in str(solver_failure(heavy, drive, "erls", 1e-4,
                                                                                  RuntimeError("x")))
    tiny = dataclasses.replace(mech, links=(dataclasses.replace(mech.links[0], length=1e-4),) + mech.links[1:])
    assert f"links.{mech.links[0].name}.length = 0.0001 m" in str(solver_failure(tiny, drive, "erls", 1e-4,
                                                                                 RuntimeError("x")))
    fs = mech.motors[0].full_scale
    strong = SimpleNamespace(tau=np.full((3, 3), 1e3 * fs))
    assert f"the planned torque of {mech.motors[0].name} peaks at" in str(solver_failure(mech, strong, "exudyn", 1e-4,
                                                                                         RuntimeError("x")))


# ------------------------------------------------------------------------------------------ model files, studies
def test_an_encoder_relative_to_its_own_link_is_refused(tmp_path):
    from exuflex.mechanism import ModelFileError, load_mechanism

    text = Path(SIXBAR).read_text()
    assert 'relative_to = "L4"' in text
    p = tmp_path / "m.toml"
    p.write_text(text.replace('relative_to = "L4"', 'relative_to = "L5"'))
    with pytest.raises(ModelFileError, match=r"relative_to: expected another link at joint .* than the encoder's own "
                                             r"link 'L5' \(one of \['L4'\]\), got 'L5'"):
        load_mechanism(p)


def test_payload_levels_on_a_model_without_payload_mass_are_refused(tmp_path):
    from exuflex.study import StudySpec, payload_levels, run_study

    text = Path(SIXBAR).read_text()
    p = tmp_path / "m.toml"
    p.write_text(re.sub(r"(\[payload\][^\[]*?mass\s*=\s*)[0-9.eE+-]+", r"\g<1>0.0", text, count=1))
    with pytest.raises(UsageError, match=r"levels \(--levels\): the levels scale the payload, but .* a payload of "
                                         r"mass 0: every level would be the same truth"):
        run_study(StudySpec(model=str(p), levels=payload_levels([0, 50]), runs=1, engine="reduced", duration=0.06),
                  tmp_path / "s")
    assert not (tmp_path / "s").exists()


def test_a_log_too_short_to_score_is_named(tmp_path, capsys):
    lines = (RUN / "sensors.csv").read_text().splitlines()
    one, three = tmp_path / "one.csv", tmp_path / "three.csv"
    one.write_text("\n".join(lines[:2]) + "\n")
    three.write_text("\n".join(lines[:4]) + "\n")
    assert main(["observe", SIXBAR, str(one)]) == 2
    assert "one data row: too short to filter or score; expected at least 2 samples" in capsys.readouterr().err
    assert main(["observe", SIXBAR, str(three), "--json"]) == 0
    assert "only 3 samples: too short to score" in capsys.readouterr().err

"""Sensor channels, true states, measurements, run folders and ``exuflex simulate``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from exuflex.cli import main
from exuflex.erls.model import ErlsModel
from exuflex.erls.sensing import SecondOrderPlan
from exuflex.errors import LogFormatError
from exuflex.manoeuvre import plan
from exuflex.measure import ADC_BITS, measure, quantise
from exuflex.mechanism import LinkPoint, load_mechanism
from exuflex.probes import ProbeRecord, probes_for
from exuflex.runs import read_csv_log, read_exudyn_sensor, read_run, write_run
from exuflex.sensors import (
    Signals,
    erls_probe_record,
    sensor_channels,
    tip_dof_names,
    tip_point,
    true_states,
    truth_names,
)

MODEL = Path(__file__).resolve().parents[1] / "models" / "sixbar.toml"


@pytest.fixture(scope="module")
def mech():
    return load_mechanism(MODEL)


@pytest.fixture(scope="module")
def model(mech):
    return ErlsModel(mech)


@pytest.fixture(scope="module")
def rigid(mech, model):
    """A rigid motion along the planned manoeuvre: ERLS states with u = u' = 0."""
    pl = plan(mech, dt=0.05, t_end=1.0)
    n = model.n
    Y = np.zeros((len(pl.t), 2 * n))
    Y[:, : model.nq] = pl.q
    Y[:, n : n + model.nq] = pl.qd
    return pl, erls_probe_record(model, pl.t, Y)


# ------------------------------------------------------------------------------------------ probes and truth
def test_erls_probe_rates_are_time_derivatives(mech, model):
    rng = np.random.default_rng(0)
    q0, u0 = np.array(mech.q_ref), rng.normal(0, 1e-3, model.ne)
    qd, ud = rng.normal(0, 0.5, model.nq), rng.normal(0, 1e-2, model.ne)
    eps = 1e-6
    ts = np.array([-eps, 0.0, eps])
    Y = np.array([np.concatenate([q0 + t * qd, u0 + t * ud, qd, ud]) for t in ts])
    rec = erls_probe_record(model, ts, Y)
    for p in probes_for(mech):
        fd = (rec.values[p.key][2] - rec.values[p.key][0]) / (2 * eps)
        np.testing.assert_allclose(rec.rates[p.key][1], fd, atol=1e-8, err_msg=p.key)
    # values agree with the model's own output rows
    cfg = model.configuration(q0)
    for name in ("c1", "c2", "c4"):
        s = next(s for s in mech.sensors if s.name == name)
        key = f"curvature:{s.link}@{s.station:.9g}"
        assert rec.values[key][1, 0] == pytest.approx(
            model.curvature_row(cfg, s.link, s.station) @ u0, abs=1e-15
        )
    # the tip truth of an ERLS state is its tip node's elastic dofs plus their second order (the foreshortening)
    tr = true_states(mech, rec)
    so = SecondOrderPlan(model, [tip_point(mech)]).at(cfg.pose, qd)
    w, wd = so.values(u0)[0], so.rates(u0, ud)[0]
    assert np.abs(w[:2]).max() > 1e-8  # (of the order of the slopes squared times the links' lengths)
    for k, name in enumerate(("x25", "y26")):
        assert tr[name][1] == pytest.approx(u0[model.dofs.index(name)] + w[k], abs=1e-12)
        assert tr["d" + name][1] == pytest.approx(ud[model.dofs.index(name)] + wd[k], abs=1e-12)
    np.testing.assert_allclose(tr.data[1, :3], q0, atol=1e-12)


def test_rigid_motion_has_zero_tip_elastic_displacement(mech, rigid):
    pl, rec = rigid
    tr = true_states(mech, rec)
    assert tr.names == ("q1", "q2", "q3", "dq1", "dq2", "dq3", "x25", "y26", "dx25", "dy26")
    np.testing.assert_allclose(tr.data[:, :3], pl.q, atol=1e-12)
    np.testing.assert_allclose(tr.data[:, 3:6], pl.qd, atol=1e-12)
    np.testing.assert_allclose(tr.data[:, 6:], 0.0, atol=1e-12)


def test_clean_sensor_channels(mech, rigid):
    pl, rec = rigid
    ch = sensor_channels(mech, rec)
    assert ch.names == tuple(s.name for s in mech.sensors)
    np.testing.assert_allclose(ch["q1"], pl.q[:, 0], atol=1e-12)
    np.testing.assert_allclose(ch["q3"], pl.q[:, 2], atol=1e-12)
    # link 4 points along q1 + pi: the relative encoder reads q3 - q1 - pi
    np.testing.assert_allclose(ch["q3rel"], pl.q[:, 2] - pl.q[:, 0] - np.pi, atol=1e-12)
    np.testing.assert_allclose(ch["c1"], 0.0, atol=1e-15)
    man = mech.manoeuvre
    phi = man.phi_start + (man.phi_end - man.phi_start) * pl.s
    np.testing.assert_allclose(ch["tip_x"], man.centre[0] + man.radius * np.cos(phi), atol=1e-10)
    assert ch.unit("c4") == "1/m" and ch.unit("q1") == "rad"


def test_angles_are_put_on_the_coordinate_branch(mech, rigid):
    _, rec = rigid
    shifted = ProbeRecord(
        rec.t,
        {k: (v - 2 * np.pi if k.startswith("slope") else v) for k, v in rec.values.items()},
        rec.rates,
    )
    np.testing.assert_allclose(true_states(mech, shifted).data, true_states(mech, rec).data, atol=1e-12)


def test_tip_names(mech):
    assert tip_dof_names(mech) == ("x25", "y26")
    off_node = mech.replace(manoeuvre=dataclasses.replace(mech.manoeuvre, tip=LinkPoint("L5", 0.1)))
    assert tip_dof_names(off_node) == ("tip_ex", "tip_ey")
    assert truth_names(off_node)[-2:] == ("dtip_ex", "dtip_ey")


# ------------------------------------------------------------------------------------------ measurement
def _zero_clean(mech, n):
    t = np.arange(n) / mech.sample_rate_hz
    names = tuple(s.name for s in mech.sensors)
    return Signals(t, names, np.zeros((n, len(names))), ("",) * len(names))


def test_noise_statistics_and_seed(mech):
    n = 20000
    clean = _zero_clean(mech, n)
    tt = clean.t
    meas = measure(mech, clean, tt, np.zeros((n, 3)), seed=7, quantisation=False)
    sig = meas.signals
    assert meas.seed == 7
    assert sig.names[:3] == ("T1", "T2", "T3")
    std = {m.name: m.noise_std for m in mech.motors} | {s.name: s.noise_std for s in mech.sensors}
    for name, sd in std.items():
        y = sig[name]
        if sd == 0:
            assert np.all(y == 0), name
            continue
        # sample std within 5 sigma of its sampling distribution (sd / sqrt(2 n)), mean within 5 sigma
        assert abs(y.std() / sd - 1) < 5 / np.sqrt(2 * n), name
        assert abs(y.mean()) < 5 * sd / np.sqrt(n), name
    # Table 3 values are what the model carries
    assert std["T1"] == 0.2 and std["q3"] == 1e-2 and std["c4"] == 1.5e-4
    # same seed, same noise; different seed, different noise
    again = measure(mech, clean, tt, np.zeros((n, 3)), seed=7, quantisation=False).signals
    np.testing.assert_array_equal(again.data, sig.data)
    other = measure(mech, clean, tt, np.zeros((n, 3)), seed=8, quantisation=False).signals
    assert not np.allclose(other.data, sig.data)
    assert measure(mech, clean, tt, np.zeros((n, 3))).seed > 0  # fresh seed recorded


def test_quantisation_step_and_clipping():
    fs = 1.0e6  # a large full scale so the quantum is visible
    step = 2 * fs / 2**ADC_BITS
    y = np.linspace(-3.3, 3.3, 1001)
    yq = quantise(y, fs)
    np.testing.assert_allclose(yq / step, np.round(yq / step), atol=1e-9)
    assert np.max(np.abs(yq - y)) <= step / 2 + 1e-12
    assert len(np.unique(yq)) > 50
    np.testing.assert_array_equal(quantise(np.array([2.0, -2.0]), 1.0), [1.0 - 2 / 2**ADC_BITS, -1.0])
    assert quantise(y, None) is y
    with pytest.raises(ValueError, match="full_scale must be positive"):
        quantise(y, 0.0, name="q1")


def test_measure_uses_sensor_full_scale_and_rate(mech):
    sensors = tuple(
        dataclasses.replace(s, full_scale=1e5, rate_hz=100.0) if s.name == "c1" else s for s in mech.sensors
    )
    m2 = mech.replace(sensors=sensors)
    n = 101
    clean = _zero_clean(m2, n)
    clean.data[:, list(clean.names).index("c1")] = 0.01 * np.arange(n)
    tau_t = np.arange(0, 0.2001, 1e-4)
    tau = np.column_stack([tau_t, -tau_t, 0 * tau_t])
    sig = measure(m2, clean, tau_t, tau, seed=1, noise=False).signals
    c1 = sig["c1"]
    assert np.isnan(c1[1:5]).all() and not np.isnan(c1[::5]).any()  # 100 Hz out of 500 Hz
    step = 2 * 1e5 / 2**ADC_BITS
    np.testing.assert_allclose(c1[::5], np.round(0.05 * np.arange(len(c1[::5])) / step) * step)
    np.testing.assert_allclose(sig["T1"], sig.t, atol=50 * 2 / 2**ADC_BITS)  # zero-order hold of the table
    with pytest.raises(ValueError, match="exceeds the base sample rate"):
        bad = mech.replace(sensors=tuple(dataclasses.replace(s, rate_hz=1000.0) for s in mech.sensors))
        measure(bad, clean, tau_t, tau, seed=1)


# ------------------------------------------------------------------------------------------ run folders
def _run(tmp_path, mech):
    t = np.arange(6) * 0.002
    names = ("T1", "T2", "T3", "q1", "c1")
    data = np.arange(30, dtype=float).reshape(6, 5) / 7
    data[1, 4] = np.nan  # not sampled
    sensors = Signals(t, names, data, ("N m",) * 3 + ("rad", "1/m"))
    truth = Signals(t, ("q1", "dq1"), np.column_stack([t, t**2]), ("rad", "rad/s"))
    out = write_run(
        tmp_path / "run", sensors, truth, {"engine": "test", "seed": 3}, motors=("T1", "T2", "T3")
    )
    return out, sensors, truth


def test_run_round_trip(tmp_path, mech):
    out, sensors, truth = _run(tmp_path, mech)
    assert sorted(p.name for p in out.iterdir()) == [".exuflex.json", "meta.json", "sensors.csv", "truth.csv"]
    assert (out / "sensors.csv").read_text().splitlines()[0] == "time,T1,T2,T3,q1,c1"
    run = read_run(out)
    np.testing.assert_array_equal(run.sensors.t, sensors.t)
    np.testing.assert_array_equal(run.sensors.data, sensors.data)  # bit-exact, NaN in place
    np.testing.assert_array_equal(run.truth.data, truth.data)
    assert run.meta["seed"] == 3 and run.meta["format"] == "exuflex-run/1"
    assert set(run.meta["versions"]) >= {"numpy", "scipy", "filterpy", "exudyn", "exuflex"}
    assert run.inputs.names == ("T1", "T2", "T3") and run.outputs.names == ("q1", "c1")
    assert run.sensors.unit("c1") == "1/m" and run.truth.unit("dq1") == "rad/s"
    assert not list(out.glob(".*.tmp"))  # no temporary files left


def _edit(path: Path, old: str, new: str) -> None:
    path.write_text(path.read_text().replace(old, new, 1))


def test_reader_errors(tmp_path, mech):
    out, _, _ = _run(tmp_path, mech)
    sensors_csv = out / "sensors.csv"
    good = sensors_csv.read_text()
    _edit(sensors_csv, ",c1\n", ",cX\n")
    with pytest.raises(LogFormatError, match=r"sensors\.csv: missing column\(s\) \['c1'\]"):
        read_run(out)
    sensors_csv.write_text(good)
    lines = good.splitlines()
    lines[3] = lines[3].rsplit(",", 1)[0] + ",nan"
    sensors_csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogFormatError, match=r"line 4, column 'c1': 'nan' is not a finite number"):
        read_run(out)
    lines = good.splitlines()
    lines[3], lines[4] = lines[4], lines[3]
    sensors_csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogFormatError, match="'time' is not strictly increasing at line 5"):
        read_run(out)
    lines = good.splitlines()
    lines[2] = ",".join(["0.002", ""] + lines[2].split(",")[2:])
    sensors_csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogFormatError, match="torque column 'T1' has an empty cell"):
        read_run(out)
    sensors_csv.write_text("")
    with pytest.raises(LogFormatError, match="sensors.csv: empty file"):
        read_run(out)
    sensors_csv.write_text("time,T1,T2,T3,q1,c1\n")
    with pytest.raises(LogFormatError, match="no data rows"):
        read_run(out)
    sensors_csv.write_text(good)
    _edit(out / "truth.csv", "time,q1,dq1", "time,q1,dqX")
    with pytest.raises(LogFormatError, match=r"truth\.csv: missing column\(s\) \['dq1'\]"):
        read_run(out)
    (out / "meta.json").unlink()
    with pytest.raises(FileNotFoundError, match="meta.json: missing"):
        read_run(out)


def test_generic_csv_reader(tmp_path):
    p = tmp_path / "lab.csv"
    p.write_text("# lab rig\nt_ms;enc1;gauge\n0;1.0;0.5\n2;1.1;\n4;1.2;0.7\n")
    sig = read_csv_log(p, {"q1": "enc1", "c1": "gauge"}, time_column="t_ms", time_scale=1e-3, delimiter=";")
    np.testing.assert_allclose(sig.t, [0, 0.002, 0.004])
    assert sig.names == ("q1", "c1") and np.isnan(sig["c1"][1])
    with pytest.raises(LogFormatError, match=r"missing column\(s\) \['enc2'\] \(for channel\(s\) \['q2'\]\)"):
        read_csv_log(p, {"q2": "enc2"}, time_column="t_ms", delimiter=";")
    with pytest.raises(LogFormatError, match="no time column 'time'"):
        read_csv_log(p, delimiter=";")


def test_exudyn_sensor_reader(tmp_path):
    p = tmp_path / "sensor.txt"
    p.write_text(
        "#Exudyn implicit second order time integration sensor output file\n"
        "#OutputVariableType = Position\n"
        "#columns contain: time, comma separated sensor values (e.g, x,y,z position coordinates)\n"
        "#number of sensor values = 3\n#\n"
        "0,0,0,0\n0,0,0,0\n0.002,2e-06,0,0\n0.004,8e-06,1,0"
    )
    sig = read_exudyn_sensor(p, ["x", "y", "z"])
    np.testing.assert_allclose(sig.t, [0, 0.002, 0.004])
    np.testing.assert_allclose(sig["y"], [0, 0, 1])
    assert read_exudyn_sensor(p).names == ("v0", "v1", "v2")
    with pytest.raises(LogFormatError, match="3 value column"):
        read_exudyn_sensor(p, ["x"])
    p.write_text("#header only\n")
    with pytest.raises(LogFormatError, match="no data rows"):
        read_exudyn_sensor(p)


# ------------------------------------------------------------------------------------------ CLI
def test_cli_simulate_erls(tmp_path):
    out = tmp_path / "sim"
    rc = main(
        ["simulate", str(MODEL), "--out", str(out), "--engine", "erls", "--duration", "0.05", "--seed", "5"]
    )
    assert rc == 0
    assert sorted(p.name for p in out.iterdir()) == [".exuflex.json", "meta.json", "sensors.csv", "truth.csv"]
    run = read_run(out)
    assert run.sensors.names == (
        "T1",
        "T2",
        "T3",
        "q1",
        "q2",
        "q3",
        "q3rel",
        "c1",
        "c2",
        "c4",
        "tip_x",
        "tip_y",
    )
    assert run.truth.names == ("q1", "q2", "q3", "dq1", "dq2", "dq3", "x25", "y26", "dx25", "dy26")
    np.testing.assert_allclose(run.sensors.t, np.arange(26) * 0.002, atol=1e-12)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["engine"] == "erls" and meta["seed"] == 5 and meta["mechanism"] == "sixbar"
    assert len(meta["model"]["sha256"]) == 64 and meta["settings"]["payload_scale"] == 1.0
    # the trapezoid's first ramp excites mm-level tip vibration (sixbar.md: x25 ~ +-1 mm, y26 ~ -3..1 mm)
    e = np.abs(run.truth.data[:, 6:8]).max()
    assert 1e-5 < e < 5e-3
    # truth starts at the plan's initial configuration, at rest
    np.testing.assert_allclose(run.truth.data[0, 3:], 0.0, atol=1e-12)


def test_cli_simulate_rejects_bad_arguments(tmp_path, capsys):
    rc = main(["simulate", str(MODEL), "--out", str(tmp_path / "x"), "--engine", "erls", "--duration", "-1"])
    assert rc == 2
    assert "argument --duration: expected a positive finite number, got '-1'" in capsys.readouterr().err
    rc = main(["simulate", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "x"), "--engine", "erls"])
    assert rc == 2


def test_exudyn_and_erls_engines_give_comparable_truths(tmp_path):
    """Same manoeuvre, two independent formulations: the truths agree (0.04 s of the first ramp)."""
    pytest.importorskip("exudyn")
    from exuflex.truth import simulate_run

    runs = {}
    for engine in ("erls", "exudyn"):
        runs[engine] = read_run(simulate_run(MODEL, tmp_path / engine, engine=engine, duration=0.04, seed=1))
    a, b = runs["erls"].truth, runs["exudyn"].truth
    common, ia, ib = np.intersect1d(np.round(a.t, 9), np.round(b.t, 9), return_indices=True)
    assert len(common) >= 19
    da, db = a.data[ia], b.data[ib]
    np.testing.assert_allclose(db[:, :3], da[:, :3], atol=1e-4)  # q (rad)
    peak_a, peak_b = np.abs(da[:, 6:8]).max(0), np.abs(db[:, 6:8]).max(0)  # tip elastic x25, y26 (m)
    np.testing.assert_allclose(peak_b, peak_a, rtol=0.1)
    assert runs["exudyn"].meta["engine"] == "exudyn"


def test_cli_simulate_needs_a_manoeuvre(tmp_path, capsys):
    text = MODEL.read_text()
    start = text.index("[manoeuvre]")
    end = text.index("[reduction]")
    model = tmp_path / "no_manoeuvre.toml"
    model.write_text(text[:start] + text[end:])
    rc = main(["simulate", str(model), "--out", str(tmp_path / "x"), "--engine", "erls"])
    assert rc == 2
    assert "manoeuvre: expected a [manoeuvre] table to simulate" in capsys.readouterr().err


def test_simulate_runs_measures_one_truth_with_each_seed(tmp_path):
    """One truth, several noise seeds: every folder holds the same truth, and each seed's log is the one
    ``simulate_run`` writes with that seed (the truth's motion does not depend on the seed)."""
    from exuflex.truth import simulate_run, simulate_runs

    a, b = simulate_runs(MODEL, {3: tmp_path / "s3", 4: tmp_path / "s4"}, engine="erls", duration=0.02)
    single = read_run(simulate_run(MODEL, tmp_path / "one", engine="erls", duration=0.02, seed=4))
    ra, rb = read_run(a), read_run(b)
    np.testing.assert_array_equal(ra.truth.data, rb.truth.data)
    assert (ra.meta["seed"], rb.meta["seed"]) == (3, 4)
    assert not np.array_equal(ra.sensors.data, rb.sensors.data)
    np.testing.assert_array_equal(rb.sensors.data, single.sensors.data)
    np.testing.assert_array_equal(rb.truth.data, single.truth.data)

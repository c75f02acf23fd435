"""Bad model files, filter health and crash safety (docs/robustness.md lists what each test shows)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _toml  # noqa: E402

from exuflex.cli import main  # noqa: E402
from exuflex.erls.kinematics import KinematicsError  # noqa: E402
from exuflex.errors import EXPECTED_ERRORS, LogFormatError  # noqa: E402
from exuflex.mechanism import ModelFileError, load_mechanism, parse_mechanism  # noqa: E402
from exuflex.observer import FilterDivergedError, LinearDiscreteModel, MultirateEKF, Prediction  # noqa: E402
from exuflex.observer.ekf import Monitoring  # noqa: E402
from exuflex.runs import atomic_write_text, read_run, write_run  # noqa: E402
from exuflex.sensors import Signals  # noqa: E402
from exuflex.validate import check_configurations  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"


def _doc(name: str) -> dict:
    with open(MODELS / f"{name}.toml", "rb") as fh:
        return tomllib.load(fh)


def _short_rocker(doc: dict, length: float) -> dict:
    """The four-bar with its rocker (link 2, B at its end) shortened to ``length``; dependent stations fixed."""
    doc["links"][2]["length"] = length
    doc["joints"][2]["points"][1]["station"] = length
    for entry in doc["masses"]:
        if entry.get("link") == "rocker":
            entry["station"] = 0.0  # masses sit at nodes
    for entry in doc["sensors"]:
        if entry.get("link") == "rocker" and "station" in entry:
            entry["station"] = min(entry["station"], length / 2)
    return doc


def _stray(doc: dict) -> None:
    """Two extra links pinned to each other but to nothing else."""
    for n in ("S1", "S2"):
        doc["links"].append({"name": n, "length": 0.2, "material": "aluminium", "diameter": 0.01, "n_elements": 1})
    doc["joints"].append({"name": "S", "points": [{"link": "S1", "station": 0.2}, {"link": "S2", "station": 0.0}]})


# ------------------------------------------------------------------------ model files, library level
# (class, model, edit(doc), field named, phrase of what was expected)
MODEL_CLASSES = [
    ("missing key", "sixbar", lambda d: d["links"][1].pop("material"), "links[1].material", "required key"),
    ("missing table", "sixbar", lambda d: d.pop("model"), "model", "required key"),
    ("unknown key", "sixbar", lambda d: d["sensors"][0].update(nosie_std=0.1), "sensors[0].nosie_std", "known keys"),
    ("wrong type", "sixbar", lambda d: d["damping"].update(alpha="1.5"), "damping.alpha", "finite number"),
    ("bool for number", "sixbar", lambda d: d["links"][0].update(length=True), "links[0].length", "finite number"),
    ("NaN number", "sixbar", lambda d: d["materials"][0].update(E=float("nan")), "materials[0].E", "finite number"),
    ("wrong units (mm)", "sixbar", lambda d: d["links"][3].update(diameter=24.0), "links[3].diameter", "mm by mistake"),
    ("wrong units (GPa)", "sixbar", lambda d: d["materials"][0].update(E=69.0), "materials[0].E", "Pa"),
    ("wrong units (g/cm^3)", "sixbar", lambda d: d["materials"][0].update(rho=2.7), "materials[0].rho", "kg/m^3"),
    ("non-positive length", "sixbar", lambda d: d["links"][4].update(length=0.0), "links[4].length", "positive"),
    ("non-positive section", "sixbar", lambda d: d["links"][2].update(diameter=-0.016), "links[2].diameter",
     "positive"),
    ("joint at no node", "sixbar", lambda d: d["joints"][3]["points"][1].update(station=0.55),
     "joints[3].points[1].station", "stations"),
    ("joint on unknown link", "sixbar", lambda d: d["joints"][4]["points"][1].update(link="L6"),
     "joints[4].points[1].link", "link name"),
    ("joint with one point", "sixbar", lambda d: d["joints"][1].update(points=[{"link": "L1", "station": 0.5}]),
     "joints[1].points", "at least two link points"),
    ("joints that do not connect", "sixbar", _stray, "joints", "not connected: ['S1', 'S2']"),
    ("mobility mismatch", "sixbar", lambda d: (d["coordinates"].pop(2), d["model"].update(q_ref=[1.08, 2.63]),
                                               d["manoeuvre"].update(rules=[]), d["reduction"].pop("q_star")),
     "coordinates", "mobility (3"),
    ("master that does not exist", "sixbar", lambda d: d["reduction"].update(masters=["x14", "y99"]),
     "reduction.masters[1]", "elastic dof name"),
    ("master node name that does not exist", "sixbar", lambda d: d["reduction"].update(masters=["node99.x"]),
     "reduction.masters[0]", "elastic dof name"),
    ("duplicate name", "sixbar", lambda d: d["sensors"][1].update(name="q1"), "sensors[1].name",
     "not used by sensors[0]"),
    ("reference to a missing coordinate", "sixbar",
     lambda d: d["manoeuvre"]["rules"][0].update(coordinate="q9"), "manoeuvre.rules[0].coordinate",
     "ERLS coordinate name"),
    ("q_ref of wrong length", "sixbar", lambda d: d["model"].update(q_ref=[1.0]), "model.q_ref", "list of 3"),
    ("empty array of links", "single_link", lambda d: d.update(links=[]), "links", "at least one [[links]] table"),
]


@pytest.mark.parametrize("cls,model,edit,field,expected", MODEL_CLASSES, ids=[c[0] for c in MODEL_CLASSES])
def test_model_file_class_names_file_and_field(cls, model, edit, field, expected):
    doc = _doc(model)
    edit(doc)
    with pytest.raises(ModelFileError) as ei:
        parse_mechanism(doc, f"bad_{model}.toml")
    msg = str(ei.value)
    assert msg.startswith(f"bad_{model}.toml: {field}: expected"), msg
    assert expected in msg, msg
    assert "\n" not in msg


def test_loop_that_cannot_close_names_q_ref():
    mech = parse_mechanism(_short_rocker(_doc("fourbar"), 0.05), "noclose.toml")  # 0.05 + 0.5 < |A - O4|
    with pytest.raises(ModelFileError, match=r"^noclose\.toml: model\.q_ref: expected .*loop cannot close"):
        check_configurations(mech)


def test_singular_configuration_names_q_ref():
    """Rocker 0.25 m: at q = pi coupler and rocker are stretched in line (toggle), a singular configuration that
    the kinematics' default threshold (cond 1e8) lets through (cond ~1.6e7)."""
    doc = _short_rocker(_doc("fourbar"), 0.25)
    doc["model"]["q_ref"] = [np.pi]
    mech = parse_mechanism(doc, "toggle.toml")
    with pytest.raises(ModelFileError, match=r"^toggle\.toml: model\.q_ref: expected .*singularit"):
        check_configurations(mech)


@pytest.mark.parametrize("name", ["sixbar", "fourbar", "single_link"])
def test_shipped_models_pass_the_configuration_check(name):
    check_configurations(load_mechanism(MODELS / f"{name}.toml"))


def test_expected_errors_cover_the_input_errors():
    for e in (ModelFileError, KinematicsError, LogFormatError, FileNotFoundError):
        assert issubclass(e, EXPECTED_ERRORS)


# ------------------------------------------------------------------------ model files through the CLI
def _cli(argv, capsys):
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def _assert_one_error(err: str, *needles: str):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert 1 <= len(lines) <= 2, err
    assert "Traceback" not in err
    for n in needles:
        assert n in err, (n, err)


CLI_CLASSES = [
    ("unknown key", lambda d: d["links"][0].update(colour="red"), "links[0].colour"),
    ("missing key", lambda d: d["motors"][0].pop("joint"), "motors[0].joint"),
    ("wrong units", lambda d: d["links"][2].update(diameter=16.0), "links[2].diameter"),
    ("disconnected", _stray, "joints"),
    ("bad master", lambda d: d["reduction"].update(masters=["x14", "x999"]), "reduction.masters[1]"),
]


@pytest.mark.parametrize("cls,edit,field", CLI_CLASSES, ids=[c[0] for c in CLI_CLASSES])
@pytest.mark.parametrize("command", ["modes", "simulate", "observe"])
def test_cli_model_errors_are_one_line_exit_2(tmp_path, capsys, cls, edit, field, command):
    doc = _doc("sixbar")
    edit(doc)
    path = tmp_path / "bad.toml"
    path.write_text(_toml.dumps(doc))
    argv = {
        "modes": ["modes", str(path)],
        "simulate": ["simulate", str(path), "--out", str(tmp_path / "run"), "--engine", "erls"],
        "observe": ["observe", str(path), str(ROOT / "tests" / "data" / "sixbar_short")],
    }[command]
    rc, out, err = _cli(argv, capsys)
    assert rc == 2
    _assert_one_error(err, str(path), f": {field}: expected")
    assert not (tmp_path / "run").exists()


def test_cli_file_level_errors(tmp_path, capsys):
    rc, _, err = _cli(["modes", str(tmp_path / "missing.toml")], capsys)
    assert rc == 2
    _assert_one_error(err, "missing.toml", "expected an existing TOML model file")
    bad = tmp_path / "syntax.toml"
    bad.write_text("[model]\nname = \n")
    rc, _, err = _cli(["modes", str(bad)], capsys)
    assert rc == 2
    _assert_one_error(err, "syntax.toml", "(syntax)", "valid TOML")
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe\x00[model]")
    rc, _, err = _cli(["modes", str(binary)], capsys)
    assert rc == 2
    _assert_one_error(err, "binary.toml")
    rc, _, err = _cli(["modes", str(tmp_path)], capsys)  # a folder
    assert rc == 2
    _assert_one_error(err, str(tmp_path))


def test_cli_loop_that_cannot_close(tmp_path, capsys):
    path = tmp_path / "noclose.toml"
    path.write_text(_toml.dumps(_short_rocker(_doc("fourbar"), 0.05)))
    rc, _, err = _cli(["modes", str(path)], capsys)
    assert rc == 2
    _assert_one_error(err, str(path), "cannot close")


def test_cli_debug_shows_the_traceback(tmp_path):
    doc = _doc("sixbar")
    doc["links"][0]["colour"] = "red"
    path = tmp_path / "bad.toml"
    path.write_text(_toml.dumps(doc))
    with pytest.raises(ModelFileError):
        main(["--debug", "modes", str(path)])


# ------------------------------------------------------------------------ filter health
def _toy_ekf(**kw):
    """Constant-velocity model observed in position: the smallest model with a meaningful covariance."""
    dt = 0.01
    A = np.array([[1.0, dt], [0.0, 1.0]])
    model = LinearDiscreteModel(A=A, B=np.zeros((2, 1)), C={"pos": np.array([1.0, 0.0])},
                                Q=np.diag([1e-8, 1e-4]))
    store_P = kw.pop("store_P", "diag")
    return MultirateEKF(model, ["pos"], {"pos": 0.01}, np.zeros(2), np.diag([1.0, 1.0]), dt=dt, store_P=store_P,
                        monitoring=Monitoring(**kw))


def _toy_record(n=600, bias_from=None, bias=1.0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    y = 0.01 * rng.standard_normal(n)
    if bias_from is not None:
        y[bias_from:] += bias
    return t, np.zeros((n, 1)), y[:, None]


def test_covariance_stays_symmetric_positive_definite_under_abuse():
    """Outliers, long missing stretches and a tiny R: P symmetric, positive definite, finite at every sample."""
    ekf = _toy_ekf(store_P="full", divergence_action="flag")
    t, U, Y = _toy_record(400)
    Y[50] = 1e6  # outlier
    Y[100:180] = np.nan  # long gap (prediction only)
    Y[300::7] = -1e3
    res = ekf.run(t, U, Y)
    for P in res.P:
        assert np.all(np.isfinite(P))
        np.testing.assert_array_equal(P, P.T)
        assert np.linalg.eigvalsh(P).min() > 0
    assert res.n_missing == 80 and res.n_updates == 320


def test_nis_divergence_is_flagged_with_its_time():
    ekf = _toy_ekf(nis_window=50)
    t, U, Y = _toy_record(600, bias_from=300, bias=0.2)
    res = ekf.run(t, U, Y)
    assert res.nis_flagged and not res.diverged and not res.nonfinite
    assert 3.0 <= res.nis_flagged_at <= 4.5  # after the bias, within two windows
    consistent = _toy_ekf(nis_window=50).run(*_toy_record(600))
    assert not consistent.nis_flagged and consistent.nis_flagged_at is None and consistent.flagged_intervals == []


class _BlowUp(LinearDiscreteModel):
    """A linear model whose step map returns NaN from its ``bad_from``-th call on (a numerical failure)."""

    def predict(self, x, u, dt, u_next=None):
        self.calls = getattr(self, "calls", 0) + 1
        xn, F, Q = super().predict(x, u, dt)
        return Prediction(np.full_like(xn, np.nan) if self.calls >= self.bad_from else xn, F, Q)


def _blowup_ekf(**kw):
    model = _BlowUp(A=np.eye(2), B=np.zeros((2, 1)), C={"pos": np.array([1.0, 0.0])}, Q=np.eye(2) * 1e-6)
    model.bad_from = 5
    return MultirateEKF(model, ["pos"], {"pos": 0.01}, np.zeros(2), np.eye(2), dt=0.01, **kw)


def test_non_finite_never_leaves_silently():
    t, U, Y = _toy_record(20)
    with pytest.raises(FilterDivergedError, match="non-finite"):
        _blowup_ekf().run(t, U, Y)  # default: raise
    res = _blowup_ekf(nonfinite="flag").run(t, U, Y)
    assert res.nonfinite and res.diverged and res.diverged_at == pytest.approx(0.05)
    bad = ~np.isfinite(res.x_hat).all(axis=1)
    assert np.isfinite(res.x_hat[~bad]).all() and np.isnan(res.x_hat[bad]).all()
    assert res.t[bad].min() == res.diverged_at  # no NaN before the flagged time
    assert res.summary()["nonfinite"] is True


def test_cli_reports_nis_inconsistency_not_divergence(tmp_path, capsys):
    """A strain-gauge gain error (c1 reads 1.5x; at 2x the filter goes non-finite, which raises): the run
    completes with finite estimates; the result names c1 as a faulty sensor with the time, not a divergence.

    (A constant encoder offset at rest is *not* a divergence: it is indistinguishable from another rest
    position, and the filter rightly absorbs it.)"""
    from exuflex.runs import read_run, write_run
    from exuflex.sensors import Signals

    src = read_run(Path(__file__).resolve().parent / "data" / "sixbar_erls_3s")
    S, n = src.sensors, 501
    data = S.data[:n].copy()
    data[:, S.names.index("c1")] *= 1.5
    run = write_run(tmp_path / "run", Signals(S.t[:n], S.names, data, S.units), None, dict(src.meta),
                    motors=src.motors)
    rc, out, err = _cli(["observe", str(MODELS / "sixbar.toml"), str(run), "--json"], capsys)
    assert rc == 0
    s = json.loads(out)
    assert s["diverged"] is False and s["diverged_at"] is None
    # the sensor-fault tests name the channel (and the gate keeps it out of the estimate): no NIS flag needed
    assert s["channel_faults"][0]["channel"] == "c1" and s["channel_faults"][0]["start"] < 1.0
    assert s["n_rejected"]["c1"] > 0
    assert "diverged" not in err


def _rest_run(path: Path, n: int, bias: dict | None = None, seed: int = 1) -> Path:
    """A log of the six-bar at rest at its manoeuvre's start (zero torque: an equilibrium, no gravity)."""
    from exuflex.manoeuvre import plan
    from exuflex.observer.session import default_channels

    mech = load_mechanism(MODELS / "sixbar.toml")
    q0 = np.asarray(plan(mech, dt=mech.manoeuvre.duration, t_end=0.0).q[0])
    chans = default_channels(mech)
    rng = np.random.default_rng(seed)
    t = np.arange(n) / mech.sample_rate_hz
    sd = {s.name: s.noise_std for s in mech.sensors}
    cols = []
    for c in chans:
        clean = q0[list(mech.coordinate_names).index(c)] if c in mech.coordinate_names else 0.0
        cols.append(clean + sd[c] * rng.standard_normal(n) + (bias or {}).get(c, 0.0))
    data = np.column_stack([np.zeros((n, len(mech.motors)))] + cols)
    sig = Signals(t, tuple(mech.motor_names) + chans, data)
    return write_run(path, sig, None, {"engine": "test"}, motors=mech.motor_names)


# ------------------------------------------------------------------------ crash safety
def test_atomic_write_keeps_the_old_file_when_interrupted(tmp_path, monkeypatch):
    target = tmp_path / "result.json"
    atomic_write_text(target, "old\n")

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_text(target, "new\n" * 1000)
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]  # no temporary file left


def test_interrupted_run_rewrite_is_not_mistaken_for_complete(tmp_path, monkeypatch):
    """Overwriting a run folder and interrupted after sensors.csv: no meta.json, so read_run refuses it
    (before the fix the old meta.json made new sensors + old truth look like one complete run)."""
    import exuflex.runs as runs

    run = Path(_rest_run(tmp_path / "run", n=5))
    t = np.arange(5) * 0.002
    sig = Signals(t, ("T1", "q1"), np.ones((5, 2)))
    truth = Signals(t, ("q1",), np.ones((5, 1)))
    real = runs.write_signals_csv
    calls = []

    def interrupted(path, s):
        calls.append(Path(path).name)
        if Path(path).name == "truth.csv":
            raise KeyboardInterrupt
        real(path, s)

    monkeypatch.setattr(runs, "write_signals_csv", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_run(run, sig, truth, {"engine": "test"}, motors=("T1",))
    assert calls == ["sensors.csv", "truth.csv"]
    with pytest.raises(FileNotFoundError, match="meta.json: missing"):
        read_run(run)
    assert not list(run.glob(".*.tmp"))


def test_cli_ctrl_c_is_reported_and_keeps_finished_files(tmp_path, capsys, monkeypatch):
    import exuflex.cli.simulate as sim

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(sim, "simulate_run", interrupted)
    rc, _, err = _cli(["simulate", str(MODELS / "sixbar.toml"), "--out", str(tmp_path / "r")], capsys)
    assert rc == 130 and "interrupted" in err and "Traceback" not in err


_KILL_SCRIPT = r"""
import sys
from exuflex.runs import atomic_write_text
path = sys.argv[1]
i = 0
while True:
    i += 1
    atomic_write_text(path, ("%d\n" % i) * 200000 + "END\n")
    print(i, flush=True)
"""


def test_sigkill_during_writes_leaves_only_complete_files(tmp_path):
    """Kill -9 a process rewriting a 1 MB file in a loop: the file is always whole (ends with END)."""
    target = tmp_path / "big.txt"
    p = subprocess.Popen([sys.executable, "-c", _KILL_SCRIPT, str(target)], stdout=subprocess.PIPE, text=True)
    try:
        for _ in range(3):  # let it complete a few writes, then kill it mid-write
            p.stdout.readline()
        os.kill(p.pid, signal.SIGKILL)
    finally:
        p.wait(timeout=30)
    text = target.read_text()
    assert text.endswith("END\n")
    assert len(set(text.splitlines()[:-1])) == 1
    # only hidden temporaries may remain beside it, never a partial target
    assert all(q.name == "big.txt" or re.match(r"\.big\.txt\..*\.tmp$", q.name) for q in tmp_path.iterdir())

"""Manoeuvre kinds beyond the paper's: waypoints, trajectory files, tip lines and polylines, tip paths on a 2-dof
five-bar, measured-torque input; the manoeuvre file override of ``exuflex simulate`` and of study sweeps."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.kinematics import Kinematics
from exuflex.manoeuvre import _hermite5, computed_torque, plan, torque_table, write_trajectory
from exuflex.mechanism import Manoeuvre, ModelFileError, load_manoeuvre, load_mechanism, read_samples

ROOT = Path(__file__).resolve().parents[1]
SIXBAR = ROOT / "models" / "sixbar.toml"
FIVEBAR = ROOT / "tests" / "data" / "fivebar_tip.toml"  # 2 dof, tool tip on an arc


@pytest.fixture(scope="module")
def six():
    return load_mechanism(SIXBAR)


@pytest.fixture(scope="module")
def five():
    return load_mechanism(FIVEBAR)


@pytest.fixture(scope="module")
def short_arc(six):
    """The six-bar's arc in 0.5 s with a quintic law, on a 1 ms grid."""
    return plan(six, dataclasses.replace(six.manoeuvre, duration=0.5, time_law="quintic"), dt=1e-3)


def _tip(mech, q, link, station):
    kin = Kinematics(mech)
    return np.array([kin.point(kin.pose(qk), link, station)[0] for qk in q])


def _fd_check(pl, tol=2e-4, skip=()):
    """q' and q'' agree with central differences of q and q' (smooth plans; ``skip``: grid points where the
    third derivative jumps, e.g. waypoints, whose differences of q' are off by O(dt))."""
    dt = pl.dt
    ok = np.ones(len(pl.t) - 2, bool)
    ok[[k - 1 for k in skip if 0 < k < len(pl.t) - 1]] = False
    scale_d, scale_dd = np.abs(pl.qd).max(), np.abs(pl.qdd).max()
    np.testing.assert_allclose(((pl.q[2:] - pl.q[:-2]) / (2 * dt))[ok], pl.qd[1:-1][ok], atol=tol * scale_d)
    np.testing.assert_allclose(((pl.qd[2:] - pl.qd[:-2]) / (2 * dt))[ok], pl.qdd[1:-1][ok], atol=10 * tol * scale_dd)


# ------------------------------------------------------------------------------------------ interpolation
def test_quintic_hermite_reproduces_quintics():
    rng = np.random.default_rng(0)
    c = rng.standard_normal((6, 3))
    t = np.linspace(0.0, 1.2, 97)
    ts = np.array([0.0, 0.3, 0.5, 1.2])

    def f(x, d=0):
        return sum(np.prod(range(k - d + 1, k + 1)) * c[k] * x[:, None] ** (k - d) for k in range(d, 6))

    y, yd, ydd = _hermite5(ts, f(ts), f(ts, 1), f(ts, 2), t)
    for got, d in ((y, 0), (yd, 1), (ydd, 2)):
        np.testing.assert_allclose(got, f(t, d), atol=1e-12 * np.abs(f(t, d)).max())


# ------------------------------------------------------------------------------------------ trajectory files
def test_trajectory_file_round_trips(six, short_arc, tmp_path):
    """A plan written with its rates plans back to the same q, q', q'' on the same grid (quintic Hermite through
    the samples is exact at them); written without rates, q is still exact at the samples and the spline's
    rates are close."""
    f = tmp_path / "arc.csv"
    write_trajectory(f, short_arc)
    man = load_manoeuvre(f, six)
    assert man.kind == "trajectory" and man.duration == 0.5
    back = plan(six, man, dt=1e-3)
    np.testing.assert_array_equal(back.q, short_arc.q)
    np.testing.assert_allclose(back.qd, short_arc.qd, rtol=0, atol=1e-14 * np.abs(short_arc.qd).max())
    np.testing.assert_allclose(back.qdd, short_arc.qdd, rtol=0, atol=1e-13 * np.abs(short_arc.qdd).max())
    # the torque is the plan's
    np.testing.assert_allclose(computed_torque(six, back), computed_torque(six, short_arc), rtol=0, atol=1e-10)
    g = tmp_path / "arc_values.csv"
    write_trajectory(g, short_arc, rates=False)
    values = plan(six, load_manoeuvre(g, six), dt=1e-3)
    np.testing.assert_array_equal(values.q, short_arc.q)
    assert np.abs(values.qd - short_arc.qd).max() < 1e-4 * np.abs(short_arc.qd).max()


def test_tip_trajectory_file_gives_the_tip_plan(six, short_arc, tmp_path):
    """A table of tip_x, tip_y and q3 (the six-bar's third coordinate): the inverse kinematics recovers q1, q2."""
    xy = _tip(six, short_arc.q, "L5", 0.282)
    f = tmp_path / "tip.csv"
    rows = ["t,tip_x,tip_y,q3"] + [",".join(repr(float(v)) for v in (t, x, y, q3))
                                   for t, (x, y), q3 in zip(short_arc.t, xy, short_arc.q[:, 2], strict=True)]
    f.write_text("\n".join(rows) + "\n")
    pl = plan(six, load_manoeuvre(f, six), dt=1e-3)
    np.testing.assert_allclose(pl.q, short_arc.q, rtol=0, atol=1e-11)
    assert np.abs(pl.qd - short_arc.qd).max() < 1e-4 * np.abs(short_arc.qd).max()


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("t,q1,q2,q3\n0,1,2,3\n0.1,1,x,3\n", r"bad\.csv: line 3, column q2: expected a finite number, got 'x'"),
        ("time,q1,q2,q3\n0,1,2,3\n", r"bad\.csv: line 1, column 1: expected the header 't'"),
        ("t,q1,q2,q3\n0,1,2,3\n0.1,1,2\n", r"bad\.csv: line 3: expected 4 values"),
        ("t,q1,q2,q3\n0,1,2,3\n0.2,1,2,3\n0.2,1,2,3\n", r"bad\.csv: line 4, column t: expected a time after 0\.2"),
        ("t,q1,q2,q3\n0.1,1,2,3\n0.2,1,2,3\n", r"bad\.csv: line 2, column t: expected 0"),
        ("t,q1,q2\n0,1,2\n1,1,2\n", r"bad\.csv: \(header\): expected a column for every coordinate"),
        ("t,q1,q2,q9\n0,1,2,3\n1,1,2,3\n", r"bad\.csv: column q9: expected a coordinate name"),
        ("t,q1,q2,q3,dq1,dq2,dq3\n0,1,2,3,0,0,0\n1,1,2,3,0,0,0\n", r"bad\.csv: column ddq1: expected the rates"),
        ("t,T1,T2\n0,1,2\n1,1,2\n", r"bad\.csv: \(header\): expected a column for every motor"),
        ("t,q1,q2,q3\n0,1,2,3\n", r"bad\.csv: \(file\): expected a header row and at least 2 rows"),
    ],
)
def test_bad_sample_files_name_line_and_column(six, tmp_path, text, match):
    f = tmp_path / "bad.csv"
    f.write_text(text)
    with pytest.raises(ModelFileError, match=match):
        load_manoeuvre(f, six)


def test_missing_file_named_from_the_model(tmp_path, six):
    with pytest.raises(ModelFileError, match=r"nothere\.csv: \(file\): expected an existing CSV file"):
        read_samples(tmp_path / "nothere.csv")
    doc = tmp_path / "m.toml"
    doc.write_text('[manoeuvre]\nkind = "trajectory"\nfile = "nothere.csv"\n')
    with pytest.raises(ModelFileError, match=r"nothere\.csv: \(file\)"):
        load_manoeuvre(doc, six)


# ------------------------------------------------------------------------------------------ waypoints
@pytest.mark.parametrize("interp", ["quintic", "spline"])
def test_waypoints_pass_through_and_are_smooth(six, interp):
    q0 = np.array(six.q_ref)
    times = (0.0, 0.4, 1.0)
    way = (tuple(q0), tuple(q0 + [0.05, -0.03, 0.2]), tuple(q0 - [0.02, 0.0, 0.1]))
    man = Manoeuvre("waypoints", 1.0, times=times, waypoints=way, interpolation=interp)
    pl = plan(six, man, dt=5e-4, t_end=1.2)
    k = [round(t / pl.dt) for t in times]
    np.testing.assert_allclose(pl.q[k], way, atol=1e-13)
    np.testing.assert_allclose(pl.qd[[0, k[-1]]], 0.0, atol=1e-12)  # rest at both ends
    np.testing.assert_allclose(pl.q[k[-1]:], np.tile(way[-1], (len(pl.t) - k[-1], 1)), atol=1e-13)
    if interp == "quintic":  # rest at every waypoint
        np.testing.assert_allclose(pl.qd[k], 0.0, atol=1e-12)
        np.testing.assert_allclose(pl.qdd[k], 0.0, atol=1e-9)
    else:  # C2 through the interior waypoint, and moving there
        assert np.abs(pl.qd[k[1]]).max() > 0.01
        np.testing.assert_allclose(pl.qdd[k[1] - 1], pl.qdd[k[1] + 1], atol=2e-3 * np.abs(pl.qdd).max())
    _fd_check(dataclasses.replace(pl, t=pl.t[: k[-1]], q=pl.q[: k[-1]], qd=pl.qd[: k[-1]], qdd=pl.qdd[: k[-1]]),
              skip=k[1:2])


def test_waypoints_from_the_model_file(tmp_path, six):
    doc = tmp_path / "way.toml"
    doc.write_text('[manoeuvre]\nkind = "waypoints"\ntimes = [0.0, 0.5]\ninterpolation = "spline"\n'
                   "waypoints = [[1.0821, 2.6354, 4.7123], [1.1, 2.6, 4.8]]\n")
    man = load_manoeuvre(doc, six)
    assert man.kind == "waypoints" and man.duration == 0.5 and man.interpolation == "spline"
    doc.write_text('[manoeuvre]\nkind = "waypoints"\ntimes = [0.0, 0.5]\nwaypoints = [[1.0, 2.6], [1.1, 2.6, 4.8]]\n')
    with pytest.raises(ModelFileError, match=r"way\.toml: manoeuvre\.waypoints\[0\]: expected 3 numbers"):
        load_manoeuvre(doc, six)


# ------------------------------------------------------------------------------------------ tip paths
def test_tip_arc_on_the_two_dof_five_bar(five):
    """No rules at all (both coordinates follow the tip): the tip runs on the arc, rates match differences."""
    man = five.manoeuvre
    assert man.kind == "tip_arc" and man.rules == ()
    pl = plan(five, dt=1e-3)
    xy = _tip(five, pl.q[::10], man.tip.link, man.tip.station)
    phi = man.phi_start + (man.phi_end - man.phi_start) * pl.s[::10]
    target = np.asarray(man.centre) + man.radius * np.stack([np.cos(phi), np.sin(phi)], 1)
    np.testing.assert_allclose(xy, target, atol=1e-10)
    _fd_check(pl)
    tau = computed_torque(five, pl)
    np.testing.assert_allclose(tau[-1], 0.0, atol=1e-9)  # at rest at the end (quintic law)


def test_tip_polyline_and_line_rest_at_their_corners(five):
    tip = five.manoeuvre.tip
    p0 = tuple(_tip(five, [np.array(five.q_ref)], tip.link, tip.station)[0])
    pts = (p0, (0.33, 0.64), (0.28, 0.62), (0.30, 0.67))
    man = Manoeuvre("tip_polyline", 0.6, "quintic", tip=tip, points=pts)
    pl = plan(five, man, dt=1e-3)
    L = np.hypot(*np.diff(np.array(pts), axis=0).T)
    corners = np.r_[0.0, np.cumsum(0.6 * L / L.sum())]
    k = np.round(corners / pl.dt).astype(int)
    np.testing.assert_allclose(_tip(five, pl.q[k], tip.link, tip.station), pts, atol=2e-3)  # grid vs corner times
    exact = [i for i, c in zip(k, corners, strict=True) if abs(i * pl.dt - c) < 1e-12]
    np.testing.assert_allclose(_tip(five, pl.q[exact], tip.link, tip.station),
                               np.array(pts)[[list(k).index(i) for i in exact]], atol=1e-10)
    line = plan(five, Manoeuvre("tip_line", 0.3, "cycloidal", tip=tip, points=pts[:2]), dt=1e-3)
    xy = _tip(five, line.q[::30], tip.link, tip.station)
    d = np.array(pts[1]) - np.array(pts[0])
    cross = (xy - pts[0]) @ np.array([-d[1], d[0]]) / np.hypot(*d)
    np.testing.assert_allclose(cross, 0.0, atol=1e-10)  # on the straight line


def test_tip_path_needs_two_free_coordinates():
    from exuflex.mechanism import LinkPoint

    single = load_mechanism(ROOT / "models" / "single_link.toml")
    lk = single.links[0]
    man = Manoeuvre("tip_line", 1.0, "quintic", tip=LinkPoint(lk.name, lk.length), points=((0.5, 0.0), (0.4, 0.1)))
    with pytest.raises(ModelFileError, match=r"manoeuvre\.rules: expected exactly 2 coordinates without rules"):
        plan(single, man, dt=0.1)


# ------------------------------------------------------------------------------------------ torque input
def test_torque_table_interpolates_and_holds(five):
    man = Manoeuvre("torque", 0.3, columns=("T2", "T1"), samples=((0.0, 1.0, 2.0), (0.2, 3.0, 4.0), (0.3, 0.0, 0.0)))
    tau = torque_table(five, man, np.array([0.0, 0.1, 0.2, 0.25, 0.5]))
    np.testing.assert_allclose(tau, [[2, 1], [3, 2], [4, 3], [2, 1.5], [0, 0]])  # columns in motor order T1, T2
    pl = plan(five, man, dt=0.1)  # no planned motion: rest at q_ref
    np.testing.assert_array_equal(pl.q, np.tile(five.q_ref, (4, 1)))
    np.testing.assert_array_equal(pl.qd, 0.0)


# ------------------------------------------------------------------------------------------ runs
def test_five_bar_tip_arc_simulates_and_torque_file_reproduces_it(five, tmp_path):
    """``exuflex simulate`` of the five-bar's tip arc (Exudyn truth): the true tip follows the arc up to the
    links' deflection; its computed torques written as a measured-torque file and given by ``--manoeuvre``
    drive the same truth (the table is linear between its own grid points, so the torques are the same)."""
    from exuflex.truth import simulate_run
    from exuflex.runs import read_run

    d = 0.2
    a = simulate_run(FIVEBAR, tmp_path / "arc", duration=d, seed=1)
    run_a = read_run(a)
    meta = json.loads((a / "meta.json").read_text())
    assert meta["settings"]["manoeuvre"]["kind"] == "tip_arc"
    assert {"plan_s", "torque_s", "plan_and_torque_s", "truth_s"} <= set(meta["settings"]["timings"])
    truth = run_a.truth
    pl = plan(five, dt=1e-3, t_end=d)
    qt = truth.select(["q1", "q2"]).data
    qp = np.stack([np.interp(truth.t, pl.t, pl.q[:, j]) for j in range(2)], 1)
    assert np.abs(qt - qp).max() < 5e-3  # rigid plan vs flexible truth under open-loop torque
    # the torque table as a measured-torque file
    pl_h = plan(five, dt=1e-4, t_end=d)
    tau = computed_torque(five, pl_h)
    f = tmp_path / "torques.csv"
    lines = ["t," + ",".join(five.motor_names)] + [",".join(repr(float(v)) for v in (t, *u))
                                                   for t, u in zip(pl_h.t, tau, strict=True)]
    f.write_text("\n".join(lines) + "\n")
    q0 = [float(v) for v in pl_h.q[0]]
    doc = tmp_path / "torque.toml"
    doc.write_text(f'[manoeuvre]\nkind = "torque"\nfile = "torques.csv"\nq0 = [{q0[0]!r}, {q0[1]!r}]\n')
    b = simulate_run(FIVEBAR, tmp_path / "torque", seed=1, manoeuvre=doc)
    meta_b = json.loads((b / "meta.json").read_text())
    assert meta_b["settings"]["manoeuvre"]["kind"] == "torque"
    assert meta_b["settings"]["manoeuvre"]["file"].endswith("torques.csv")
    run_b = read_run(b)
    np.testing.assert_allclose(run_b.truth.data, truth.data, rtol=0, atol=1e-9 * np.abs(truth.data).max())
    # exuflex observe takes the run's manoeuvre (its start) from the run's record
    from exuflex.cli.observe import run_manoeuvre

    assert run_manoeuvre(five, run_a) is five
    observed = run_manoeuvre(five, run_b).manoeuvre
    assert observed.kind == "torque" and observed.q0 == tuple(q0)


def test_simulate_writes_a_plan_that_plans_again(five, tmp_path):
    """``exuflex simulate --write-plan`` writes plan.csv; as ``--manoeuvre`` it plans the same q, q', q''."""
    from exuflex.cli import main

    run = tmp_path / "run"
    assert main(["simulate", str(FIVEBAR), "--out", str(run), "--duration", "0.05", "--seed", "1",
                 "--write-plan"]) == 0
    written = plan(five, dt=1e-4, t_end=0.05)
    again = plan(five, load_manoeuvre(run / "plan.csv", five), dt=1e-4)
    np.testing.assert_array_equal(again.q, written.q)
    np.testing.assert_allclose(again.qd, written.qd, rtol=0, atol=1e-14 * np.abs(written.qd).max())
    np.testing.assert_allclose(again.qdd, written.qdd, rtol=0, atol=1e-13 * np.abs(written.qdd).max())


def test_simulate_reports_a_bad_manoeuvre_file_in_one_line(tmp_path, capsys):
    from exuflex.cli import main

    f = tmp_path / "traj.csv"
    f.write_text("t,q1,q2\n0,2.3,0.8\n0.1,2.3,zero\n")
    assert main(["simulate", str(FIVEBAR), "--out", str(tmp_path / "run"), "--manoeuvre", str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert err.endswith("traj.csv: line 3, column q2: expected a finite number, got 'zero'")


@pytest.mark.slow
def test_five_bar_tip_arc_simulates_and_observes(tmp_path):
    """The five-bar's whole tip arc through ``exuflex simulate`` and ``exuflex observe``: every estimated
    quantity's RMS error within 3 times the filter's own RMS bound."""
    from exuflex.cli import main

    run = tmp_path / "run"
    assert main(["simulate", str(FIVEBAR), "--out", str(run), "--seed", "3"]) == 0
    out = tmp_path / "obs"
    assert main(["observe", str(FIVEBAR), str(run), "--out", str(out), "--no-plots", "--json"]) == 0
    summary = json.loads((out / "result.json").read_text())
    ratios = summary["ratio_to_bound"]
    assert ratios and max(ratios.values()) < 3.0, ratios


# ------------------------------------------------------------------------------------------ study overrides
def test_sweep_over_the_manoeuvre_plans_each_level(six):
    """``--set manoeuvre.*`` levels get their own plan and computed torque (other overrides keep the nominal
    drive: the controller does not know the truth's parameters)."""
    from exuflex.study import parse_set
    from exuflex.study.runner import Level, drive_mech, sweep_levels
    from exuflex.truth import plan_drive

    levels = sweep_levels([parse_set("manoeuvre.rules.q3.end=4.9,5.2"), parse_set("manoeuvre.duration=2.0")])
    assert levels[0].overrides == (("manoeuvre.rules.q3.end", 4.9), ("manoeuvre.duration", 2.0))
    drives = [plan_drive(drive_mech(six, lv), 0.3, 1e-3) for lv in levels]
    assert np.abs(drives[0].tau - drives[1].tau).max() > 1e-3
    for lv, d in zip(levels, drives, strict=True):
        end = lv.overrides[0][1]
        man = dataclasses.replace(six.manoeuvre, duration=2.0, rules=(("q3", six.manoeuvre.rules[0][1], end),))
        pl = plan(six, man, dt=1e-3, t_end=0.3)
        np.testing.assert_allclose(d.tau, computed_torque(six, pl), rtol=0, atol=1e-12)
    other = Level("E", 1.0, (("links.L1.diameter", 0.031),))
    assert drive_mech(six, other) is six


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("manoeuvre.rules.q9.end", 1.0, r"manoeuvre\.rules\.q9\.end: no rule for 'q9'; the manoeuvre has rules for"),
        ("manoeuvre.rules.q3.middle", 1.0, r"expected manoeuvre\.rules\.<coordinate>\.<start\|end>"),
        ("manoeuvre.ramp_time", 2.0, r"manoeuvre\.ramp_time: expected a ramp time in \(0, duration/2 = 1\.5\] s"),
        ("manoeuvre.time_law", "linear", r"expected a time law, one of"),
        ("manoeuvre.waypoints", 1.0, r"set in a manoeuvre file"),
    ],
)
def test_manoeuvre_override_errors(six, field, value, match):
    from exuflex.study import OverrideError, apply_overrides

    with pytest.raises(OverrideError, match=match):
        apply_overrides(six, {field: value})


def test_plan_errors_name_the_manoeuvre_file(tmp_path, five):
    doc = tmp_path / "corners.toml"
    doc.write_text('[manoeuvre]\nkind = "tip_polyline"\nduration = 0.4\nramp_time = 0.15\n'
                   'tip = { link = "dist1", station = 0.675 }\npoints = [[0.2995, 0.6693], [0.33, 0.64], [0.28, 0.62]]\n')
    man = load_manoeuvre(doc, five)
    with pytest.raises(ModelFileError, match=r"corners\.toml: manoeuvre\.ramp_time: expected at most half the "
                       r"shortest segment's time 0\.17\d* s"):
        plan(five, man, dt=0.01)


def test_a_run_keeps_its_manoeuvre_file(five, tmp_path):
    """``simulate --manoeuvre FILE`` copies the file into the run folder (``manoeuvre.toml``, named in meta.json):
    exuflex observe starts the run where that manoeuvre starts after the original file is gone."""
    from exuflex.cli.observe import run_manoeuvre
    from exuflex.runs import MANOEUVRE_FILE, read_run
    from exuflex.truth import simulate_run

    doc = tmp_path / "joint.toml"
    doc.write_text('[manoeuvre]\nkind = "joint"\nduration = 0.05\ntime_law = "trapezoid"\nramp_time = 0.01\n'
                   'rules = [{ coordinate = "q1", start = 2.0, end = 2.01 }, '
                   '{ coordinate = "q2", start = 0.7, end = 0.71 }]\n')
    out = simulate_run(FIVEBAR, tmp_path / "run", seed=1, manoeuvre=doc)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["settings"]["manoeuvre"]["copy"] == MANOEUVRE_FILE
    assert (out / MANOEUVRE_FILE).read_text() == doc.read_text()
    doc.unlink()
    man = run_manoeuvre(five, read_run(out)).manoeuvre
    assert man.kind == "joint" and man.duration == 0.05
    assert [r[1] for r in man.rules] == [2.0, 0.7]

"""The mechanism gallery (``models/*.toml``): every file loads, its loops close at ``q_ref`` and along its
manoeuvre, and the manoeuvre's rigid computed torque is consistent with the rigid model's energy.

These checks are cheap (the default suite); the whole chain on each mechanism (Exudyn truth, observer, 3 seeds)
is the ``slow`` test at the end of this file and ``benchmarks/gallery.py``.
"""

from __future__ import annotations

import importlib.util
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.kinematics import Kinematics
from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import ErlsModel
from exuflex.manoeuvre import computed_torque, plan
from exuflex.mechanism import elastic_dofs, load_mechanism
from exuflex.validate import check_configurations

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
GALLERY = sorted(p.name for p in MODELS.glob("*.toml") if "manoeuvre" in tomllib.loads(p.read_text()))
"""The gallery: every model file with a manoeuvre (``spin_up.toml`` is a benchmark of the ERLS model alone)."""


def test_the_gallery_holds_the_issue_s_mechanisms():
    assert {"sixbar.toml", "fourbar.toml", "single_link.toml", "serial_arm.toml", "fivebar.toml", "three_link_arm.toml",
            "l_arm.toml"} <= set(GALLERY)


def _closure_errors(mech, kin: Kinematics, q) -> tuple[float, float]:
    """Largest violation of a joint (distance between the link points it joins; from its ground pin, or from its
    sliding line for a prismatic joint; a weld's angle error in m at its first link's length) and largest error of
    a coordinate (angle or slide), from the pose's link origins and angles (independent of the closure's
    residual)."""
    pose = kin.pose(np.asarray(q, float))
    ang = dict(zip(kin.link_names, pose.link_angles, strict=True))
    length = {lk.name: lk.length for lk in mech.links}
    gap = 0.0
    for j in mech.joints:
        pts = [kin.point(pose, p.link, p.station)[0] for p in j.points]
        gap = max(gap, max(float(np.linalg.norm(p - pts[0])) for p in pts))
        kind = getattr(j, "kind", "revolute")
        if j.ground is not None and kind == "revolute":
            gap = max(gap, float(np.linalg.norm(pts[0] - np.asarray(j.ground, float))))
        elif kind == "prismatic":
            d, ax = pts[0] - np.asarray(j.ground, float), np.asarray(j.axis, float)
            gap = max(gap, abs(float(ax[0] * d[1] - ax[1] * d[0])))  # distance from the sliding line
        elif kind == "weld":
            a, b = j.points[0].link, j.points[1].link
            gap = max(gap, length[a] * abs(float(np.angle(np.exp(1j * (ang[b] - ang[a] - j.angle))))))
    err = 0.0
    for k, c in enumerate(mech.coordinates):
        if getattr(c, "kind", "angle") == "slide":
            j = next(jt for jt in mech.joints if jt.name == c.joint)
            p = kin.point(pose, j.points[0].link, j.points[0].station)[0]
            err = max(err, abs(float(np.dot(j.axis, p - np.asarray(j.ground, float))) - c.offset - q[k]))
            continue
        a = ang[c.link] - (ang[c.relative_to] if c.relative_to else 0.0) - c.offset
        err = max(err, abs(float(np.angle(np.exp(1j * (a - q[k]))))))
    return gap, err


@pytest.mark.parametrize("name", GALLERY)
def test_gallery_model_assembles_at_q_ref_and_along_its_manoeuvre(name):
    mech = load_mechanism(MODELS / name)
    check_configurations(mech)
    assert mech.manoeuvre is not None, "a gallery model has a manoeuvre"
    dofs = elastic_dofs(mech)
    masters = mech.reduction.masters
    if not masters:  # none named: the automatic choice (exuflex.reduction.masters) finds some
        from exuflex.reduction import automatic_masters

        masters = automatic_masters(ErlsModel(mech), np.asarray(mech.q_ref, float)[None])
        assert masters, "a gallery model names masters or has joints off the ground or free tips to choose them at"
    for m in masters:
        dofs.locate(m)  # raises on a master that is no elastic dof (global or link-frame name)
    assert {s.kind for s in mech.sensors} >= {"encoder", "curvature"}
    kin = Kinematics(mech)
    gap, err = _closure_errors(mech, kin, mech.q_ref)
    assert gap < 1e-10 and err < 1e-10
    d = mech.manoeuvre.duration
    pl = plan(mech, dt=d / 300)
    for k in range(0, len(pl.t), 10):
        gap, err = _closure_errors(mech, kin, pl.q[k])
        assert gap < 1e-9 and err < 1e-9, (pl.t[k], gap, err)
    # the planned rates are the derivative of the planned angles: central differences agree within
    # dt/2 max|q''| (an acceleration jump inside the stencil) and O(dt^2) elsewhere
    dq = (pl.q[2:] - pl.q[:-2]) / (2 * pl.dt)
    assert np.max(np.abs(dq - pl.qd[1:-1])) < 0.5 * pl.dt * np.max(np.abs(pl.qdd)) + 1e-3 * np.max(np.abs(pl.qd))
    np.testing.assert_allclose(pl.qd[[0, -1]], 0, atol=1e-9)  # rest to rest
    if mech.manoeuvre.kind == "joint":
        for c, a, b in mech.manoeuvre.rules:
            i = mech.coordinate_names.index(c)
            assert pl.q[0, i] == pytest.approx(a, abs=1e-12) and pl.q[-1, i] == pytest.approx(b, abs=1e-12)


@pytest.mark.parametrize("name", GALLERY)
def test_gallery_table_of_models_readme_gives_the_modes_at_q_ref(name):
    """models/README.md lists every gallery file with its modes below 180 Hz at q_ref (motors free)."""
    rows = [ln for ln in (MODELS / "README.md").read_text().splitlines() if ln.startswith(f"| `{name}` |")]
    assert len(rows) == 1, f"models/README.md: no table row for {name}"
    cell = re.sub(r"\(.*?\)", "", rows[0].split("|")[-2]).replace("Hz", "")  # "(analytic: ...)" aside
    listed = [float(v) for v in cell.split(",")]
    mech = load_mechanism(MODELS / name)
    f = modal_analysis(ErlsModel(mech), np.asarray(mech.q_ref, float)).below(180.0)
    np.testing.assert_allclose(listed, f, atol=0.006)


@pytest.mark.parametrize("name", GALLERY)
def test_gallery_computed_torque_does_no_net_work_rest_to_rest(name):
    """The rigid computed torque drives the rigid model from rest to rest in a plane without gravity and
    without rigid-body damping: the motors' work int tau . q' dt (the torque's generalised force on q is
    tau through W^T B, the same map the inverse dynamics uses) is the kinetic energy's change, zero; each
    half of the manoeuvre does work equal to the kinetic energy at mid-time, 1/2 q'^T M_qq q'."""
    mech = load_mechanism(MODELS / name)
    if any(g != 0 for g in mech.gravity):
        pytest.skip("gravity does work")
    pl = plan(mech, dt=mech.manoeuvre.duration / 1500)
    tau = computed_torque(mech, pl)
    model = ErlsModel(mech)
    nq = len(mech.coordinates)
    power, energy = np.empty(len(pl.t)), np.empty(len(pl.t))
    for k in range(len(pl.t)):
        cfg = model.configuration(pl.q[k])
        power[k] = (model.input_matrix(cfg)[:nq] @ tau[k]) @ pl.qd[k]
        energy[k] = 0.5 * pl.qd[k] @ model.mass(cfg)[:nq, :nq] @ pl.qd[k]
    work = np.concatenate([[0.0], np.cumsum(0.5 * (power[1:] + power[:-1]) * pl.dt)])
    scale = np.max(energy)
    assert scale > 0
    # the trapezoid rule: O(dt^2) on smooth stretches, at most dt/2 |jump| at each of the time law's four
    # acceleration jumps (the torque jumps there, the rate does not)
    tol = 4 * pl.dt * np.max(np.abs(power)) + 1e-4 * scale
    assert np.max(np.abs(work - energy)) < tol
    assert abs(work[-1]) < tol


# ------------------------------------------------------------------------------------------ the whole chain
def _benchmark():
    spec = importlib.util.spec_from_file_location("benchmarks_gallery", ROOT / "benchmarks" / "gallery.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# Gallery models that do not meet issue 15's acceptance with the observer as it is (measured with
# ``python benchmarks/gallery.py``, Exudyn truth, seeds 1-3; the script prints the table): expected to pass once
# the filter core and the reduction of issue 15 are done.
KNOWN_SHORT: dict[str, str] = {
    "sixbar": "every RMS error within 1.5x its bound on the Exudyn truth, seeds 1-3 (worst 1.34, 1.36, 1.17 since the "
              "cached step holds its configurations undeformed and the elastic coordinates at the interval's "
              "midpoint, docs/step_jacobian.md; 1.73, 1.66, 1.50 before), but the default path's q1 RMS error is "
              "1.11x and 1.14x the rk4 reference's on seeds 1 and 2 (the criterion: within 10 %): q held at the "
              "interval's start (the exact model held so, its elastic coordinates at the midpoint, gives the "
              "cached step's figures on tests/data/sixbar_erls_3s; advancing q too costs the slider-crank, whose "
              "step Jacobian lacks dM/dq q'; docs/step_jacobian.md)",
    "three_link_arm": ("the wrist and elbow angles' RMS errors are 3.0-4.6x their bounds with the cached step on both truths "
                       "(docs/acceptance.md; since the cached step's change, worst per seed ERLS 1.44, 2.71, 1.30 and "
                       "Exudyn 2.94, 4.89, 1.25: docs/step_jacobian.md). With the exact step (method='rk4') q3 stays at 1.14-1.67x on the ERLS truth, "
                       "seeds 1-3, and at up to 1.67x (10 seeds, 7 above 1.3) on the observer's own reduced model as the truth: a "
                       "deterministic error, not truncation or scatter. Noiseless logs, rk4: q3's error is 0.92 of its "
                       "bound on the ERLS truth, 0.83 on the reduced truth and 0.54 on a reduced truth stepped by the "
                       "filter's own rk4 map, +1.0-1.5 bound during the acceleration ramp and -1.0 to -1.9 during the "
                       "deceleration, unchanged with 8 interior modes, a torque table held per sample, or the step "
                       "Jacobian's q-columns by central differences; the estimate's encoder reading errs as its q3 "
                       "(not a definition mismatch): cause not pinned down (issue 28 items 1-2)"),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", [
    pytest.param(n, marks=pytest.mark.xfail(reason=KNOWN_SHORT[n], strict=False)) if n in KNOWN_SHORT else n
    for n in (Path(g).stem for g in GALLERY)])
def test_whole_chain_on_the_gallery_meets_the_acceptance(name):
    """Exudyn truth, 3 seeds, the observer with default settings: every RMS error after the start-up within 1.5x
    the observer's own bound, the time-averaged NIS within 10 % of the channel count, no flag, and the default
    path's RMS errors within 10 % of the exact reference path's."""
    bench = _benchmark()
    rows = [bench.run_chain(name, seed) for seed in bench.SEEDS]
    bad = {r["seed"]: {k: v for k, v in r["acceptance"].items() if not isinstance(v, bool)}
           for r in rows if not r["acceptance"]["passed"]}
    assert not bad, bad
    for r in rows:  # the criteria themselves, from the raw figures
        assert max(r["ratio_to_bound"].values()) <= 1.5
        assert abs(r["nis_mean"] / r["nis_expected"] - 1) <= 0.1
        assert not r["diverged"] and not r["nonfinite"]
        assert all(abs(v - 1) <= 0.1 for v in r["default_over_reference"].values())


def test_seed_statistics_mean_percentile_and_paired_excess():
    """The over-the-seeds figures of ``--acceptance``: each quantity's mean and 90th percentile over the seeds, the
    paired excess over the consistent truth (per seed the difference, its mean and the standard error of the mean),
    and the verdict from the means (a run above the limit does not fail a model whose mean is within it)."""
    bench = _benchmark()
    a = [1.0, 1.4, 1.1, 1.3]  # erls, per seed
    b = [0.9, 1.2, 1.1, 1.0]  # the consistent truth, same seeds

    def row(engine, seed, v):
        return {"engine": engine, "model": "m", "seed": seed, "ratio_to_bound": {"q1": v, "dq1": 1.0},
                "nis_mean": 2.0 + 0.1 * seed, "nis_expected": 2.0, "diverged": False, "nonfinite": False}

    rows = [row("erls", s, v) for s, v in enumerate(a, 1)] + [row(bench.CONSISTENT, s, v) for s, v in enumerate(b, 1)]
    st = bench.seed_statistics(rows, 90)
    e = st[("erls", "m")]
    q = e["quantities"]["q1"]
    assert q["mean"] == pytest.approx(np.mean(a))
    assert q["p"] == pytest.approx(np.percentile(a, 90))
    d = np.subtract(a, b)
    assert q["excess"] == pytest.approx(d.mean())
    assert q["excess_se"] == pytest.approx(d.std(ddof=1) / 2.0)
    assert e["worst"] == "q1" and e["n"] == 4
    assert e["nis_mean"] == pytest.approx(np.mean([1.05, 1.1, 1.15, 1.2]))
    assert e["passed"] is False  # NIS / channels 1.125 on average: more than 10 % above 1
    assert "excess" not in st[(bench.CONSISTENT, "m")]["quantities"]["q1"]
    for r in rows:
        r["nis_mean"] = 2.0
    st = bench.seed_statistics(rows, 90)
    assert st[("erls", "m")]["passed"] is True  # mean 1.2 within 1.25 although seed 2's run is at 1.4
    assert bench._seeds("1-3,7") == [1, 2, 3, 7]

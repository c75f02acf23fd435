"""Prismatic joints, welds and masses at an offset: closed-form kinematics, an independent bent-beam model,
the parallel-axis theorem, energy consistency and the model file's errors."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_energy import _power_terms, _random_state  # noqa: E402

from exuflex.erls.elements import beam_mass, beam_stiffness, rotation  # noqa: E402
from exuflex.erls.kinematics import Kinematics  # noqa: E402
from exuflex.erls.modal import modal_analysis  # noqa: E402
from exuflex.erls.model import ErlsModel  # noqa: E402
from exuflex.mechanism import ModelFileError, elastic_dofs, load_mechanism, parse_mechanism  # noqa: E402

MODELS = Path(__file__).resolve().parents[1] / "models"
R_CRANK, L_ROD = 0.1, 0.4  # models/slider_crank.toml


def _slider_crank_closed_form(q):
    """Rod angle phi, slider x_B and dx_B/dq, d2x_B/dq2 of a centred slider-crank (B on the x axis)."""
    r, l = R_CRANK, L_ROD
    phi = math.asin(-r * math.sin(q) / l)
    dphi = -r * math.cos(q) / (l * math.cos(phi))
    ddphi = (r * math.sin(q) + l * math.sin(phi) * dphi**2) / (l * math.cos(phi))
    x = r * math.cos(q) + l * math.cos(phi)
    dx = -r * math.sin(q) - l * math.sin(phi) * dphi
    ddx = -r * math.cos(q) - l * math.cos(phi) * dphi**2 - l * math.sin(phi) * ddphi
    return phi, x, dx, ddx


@pytest.mark.parametrize("q", [1.5707963267948966, 0.3, 2.5, 4.0, 5.9])
def test_rigid_slider_crank_matches_its_closed_form(q):
    """Slider position, rod angle and their first and second derivatives in q (S and dS/dt at q' = 1)."""
    kin = Kinematics(load_mechanism(MODELS / "slider_crank.toml"))
    phi, x, dx, ddx = _slider_crank_closed_form(q)
    pose = kin.pose([q])
    th_rod = pose.z[5]
    assert math.remainder(th_rod - phi, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
    p, Sp = kin.point(pose, "rod", L_ROD)
    np.testing.assert_allclose(p, [x, 0.0], atol=1e-13)
    np.testing.assert_allclose(Sp[:, 0], [dx, 0.0], atol=1e-12)
    _, Sd = kin.rates(pose, [1.0])
    k = list(kin.node_ids).index(kin.mech.node_at("rod", L_ROD))
    np.testing.assert_allclose(Sd[3 * k : 3 * k + 2, 0], [ddx, 0.0], atol=1e-11)


def test_slider_crank_elastic_dofs_at_the_slider():
    """The slider node keeps its displacement along the axis (an elastic dof) and loses the normal one."""
    mech = load_mechanism(MODELS / "slider_crank.toml")
    dofs = elastic_dofs(mech)
    node = mech.node_at("rod", L_ROD)
    assert f"node{node}.x" in dofs.node_names and f"node{node}.theta" in dofs.node_names
    assert f"node{node}.y" not in dofs.node_names


def _doc_slide_driven():
    """The slider-crank driven at the slider: q = x_B (a slide coordinate), the crank angle dependent."""
    import tomllib

    doc = tomllib.loads((MODELS / "slider_crank.toml").read_text())
    doc["coordinates"] = [{"name": "s", "joint": "B", "offset": 0.0}]
    doc["model"]["q_ref"] = [0.4]
    doc["motors"] = []
    doc["sensors"] = [s for s in doc["sensors"] if s["kind"] != "encoder"]
    doc["manoeuvre"]["rules"] = [{"coordinate": "s", "start": 0.4, "end": 0.45}]
    doc["reduction"]["q_star"] = [0.4]
    doc["links"][0]["angle_guess"] = 1.3
    doc["links"][1]["angle_guess"] = -0.25
    return doc


def test_slide_coordinate_closure_and_dofs():
    """q = x_B: the crank angle from the cosine rule, and the slider node's translations both fixed."""
    mech = parse_mechanism(_doc_slide_driven(), "slide.toml")
    assert mech.coordinates[0].kind == "slide"
    kin = Kinematics(mech)
    for x in (0.35, 0.4, 0.45):
        pose = kin.pose([x])
        c = (x * x + R_CRANK**2 - L_ROD**2) / (2 * x * R_CRANK)
        assert pose.z[2] == pytest.approx(math.acos(c), abs=1e-12)
        np.testing.assert_allclose(kin.point(pose, "rod", L_ROD)[0], [x, 0.0], atol=1e-13)
        np.testing.assert_allclose(kin.point(pose, "rod", L_ROD)[1][:, 0], [1.0, 0.0], atol=1e-12)
    node = mech.node_at("rod", L_ROD)
    names = elastic_dofs(mech).node_names
    assert f"node{node}.x" not in names and f"node{node}.y" not in names


def _welded_arm(offset=(0.0, 0.0), inertia=0.0, n=(4, 3), angle=math.pi / 2):
    """An L-shaped arm: link a from a hub pin, link b welded to its end at ``angle``; a tip mass at ``offset``."""
    return {
        "model": {"name": "l_arm", "q_ref": [0.3]},
        "materials": [{"name": "steel", "E": 2.1e11, "rho": 7850.0}],
        "links": [
            {"name": "a", "length": 0.5, "material": "steel", "diameter": 0.012, "n_elements": n[0]},
            {"name": "b", "length": 0.3, "material": "steel", "diameter": 0.01, "n_elements": n[1]},
        ],
        "joints": [
            {"name": "O", "points": [{"link": "a", "station": 0.0}], "ground": [0.0, 0.0]},
            {"name": "W", "kind": "weld", "angle": angle,
             "points": [{"link": "a", "station": 0.5}, {"link": "b", "station": 0.0}]},
        ],
        "coordinates": [{"name": "q1", "link": "a", "joint": "O"}],
        "motors": [{"name": "T1", "joint": "O", "link": "a"}],
        "masses": [{"link": "b", "station": 0.3, "mass": 0.2, "inertia": inertia, "offset": list(offset)}],
    }


def _bent_beam_frequencies(q, angle, n, tip_mass):
    """An independent model of the L-arm: one chain of beam elements in the global frame with a single node at
    the corner (no weld, no ERLS coordinates), pinned at the hub (x, y fixed); frequencies above the rigid
    rotation about the pin."""
    E, rho = 2.1e11, 7850.0
    segs = [(0.5, 0.012, q, n[0]), (0.3, 0.01, q + angle, n[1])]
    nn = n[0] + n[1] + 1
    K, M = np.zeros((3 * nn, 3 * nn)), np.zeros((3 * nn, 3 * nn))
    node = 0
    for L, d, th, ne in segs:
        A, I = math.pi * d * d / 4, math.pi * d**4 / 64
        Rm = rotation(th)
        for _ in range(ne):
            idx = np.r_[3 * node : 3 * node + 6]
            K[np.ix_(idx, idx)] += Rm @ beam_stiffness(E * A, E * I, L / ne) @ Rm.T
            M[np.ix_(idx, idx)] += Rm @ beam_mass(rho * A, L / ne) @ Rm.T
            node += 1
    M[3 * node, 3 * node] += tip_mass
    M[3 * node + 1, 3 * node + 1] += tip_mass
    free = np.r_[2 : 3 * nn]  # hub translations fixed
    w2 = sla.eigh(K[np.ix_(free, free)], M[np.ix_(free, free)], eigvals_only=True)
    return np.sqrt(np.clip(np.sort(w2), 0, None))[1:] / (2 * np.pi)


@pytest.mark.parametrize("angle", [math.pi / 2, 2.2])
def test_welded_arm_modes_equal_a_single_bent_beam(angle):
    """The two welded links (ERLS: two nodes at the corner sharing x, y and theta, a weld closure equation) have
    the modes of one bent beam assembled directly (motors free, all modes)."""
    n = (4, 3)
    mech = parse_mechanism(_welded_arm(n=n, angle=angle), "l_arm.toml")
    for q in (0.3, 1.7):
        f = modal_analysis(ErlsModel(mech), [q]).frequencies_hz
        ref = _bent_beam_frequencies(q, angle, n, 0.2)
        np.testing.assert_allclose(f, ref, rtol=1e-9)


def test_weld_closure_keeps_the_angle():
    kin = Kinematics(parse_mechanism(_welded_arm(angle=2.2), "l_arm.toml"))
    pose = kin.pose([0.7])
    assert pose.z[5] - pose.z[2] == pytest.approx(2.2, abs=1e-12)
    np.testing.assert_allclose(pose.Sz[[2, 5], 0], [1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(kin.point(pose, "b", 0.0)[0], 0.5 * np.array([math.cos(0.7), math.sin(0.7)]),
                               atol=1e-13)


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.05, 0.0), (0.04, -0.03)])
def test_offset_mass_parallel_axis(offset):
    """The rigid rotation's inertia about the hub (the q-q entry of M): beams about their ends
    (rho A L^3 / 3 and the parallel axis for the bent link b) plus m |d|^2 + J for the mass point at distance
    |d| from the hub."""
    J = 1.5e-4
    mech = parse_mechanism(_welded_arm(offset=offset, inertia=J), "l_arm.toml")
    model = ErlsModel(mech)
    q = 0.4
    M = model.mass(model.configuration([q]))
    rhoA = [7850.0 * math.pi * d * d / 4 for d in (0.012, 0.01)]
    La, Lb = 0.5, 0.3
    # link b: its centre at (La, Lb / 2) in link a's frame (welded at 90 deg)
    beams = rhoA[0] * La**3 / 3 + rhoA[1] * Lb * (Lb**2 / 12 + La**2 + (Lb / 2) ** 2)
    a, b = offset
    point = np.array([La, 0.0]) + np.array([-b, Lb + a])  # link b's frame: axis +y of a, normal -x of a
    assert M[0, 0] == pytest.approx(beams + 0.2 * point @ point + J, rel=1e-12)


@pytest.mark.parametrize("damped", [False, True])
def test_power_balance_with_joints_and_offset_masses(damped):
    """dE/dt = motor power - damping power with a weld and a mass at an offset (velocity forces of the offset mass
    through its rotating frame), and on the slider-crank (prismatic joint)."""
    from exuflex.mechanism import Damping

    mechs = [parse_mechanism(_welded_arm(offset=(0.04, -0.03), inertia=1e-4), "l_arm.toml"),
             load_mechanism(MODELS / "slider_crank.toml")]
    rng = np.random.default_rng(11)
    for mech in mechs:
        mech = mech.replace(damping=Damping(3.0, 1e-5) if damped else Damping(0.0, 0.0))
        model = ErlsModel(mech)
        for _ in range(3):
            y = _random_state(model, rng)
            tau = rng.standard_normal(len(mech.motors))
            dE, p_motor, p_damp = _power_terms(model, y, tau)
            scale = np.abs(dE).sum() + abs(p_motor) + abs(p_damp)
            assert abs(dE.sum() - p_motor - p_damp) < 1e-9 * scale


def _errors():
    import tomllib

    base = tomllib.loads((MODELS / "slider_crank.toml").read_text())

    def edit(fn):
        import copy

        d = copy.deepcopy(base)
        fn(d)
        return d

    def tilt(d):
        d["joints"][2]["axis"] = [1.0, 0.2]

    def weld3(d):
        d["joints"][1]["kind"] = "weld"
        d["joints"][1]["angle"] = 0.0
        d["joints"][1]["points"].append({"link": "rod", "station": 0.2})

    def slider_on_pin(d):
        d["sensors"][1]["joint"] = "A"

    def unknown_kind(d):
        d["joints"][1]["kind"] = "spherical"

    def no_axis(d):
        del d["joints"][2]["axis"]
        del d["sensors"][1]

    def mobility(d):
        d["joints"][2]["kind"] = "revolute"  # a ground pin: 2 equations, no mobility left
        del d["joints"][2]["axis"]
        del d["sensors"][1]

    def weld_ground(d):
        d["joints"][1]["kind"] = "weld"
        d["joints"][1]["angle"] = 0.0
        d["joints"][1]["ground"] = [0.0, 0.1]

    def shared_node(d):
        d["links"][0]["nodes"] = [1, 2, 3]
        d["links"][1]["nodes"] = [3] + list(range(20, 28))

    return [
        (edit(shared_node), r"links\[1\]\.nodes: expected node ids not used by link 'crank' \(links joined rigidly: "
                            r"a \[\[joints\]\] table with kind = \"weld\"\)"),
        (edit(tilt), r"joints\[2\]\.axis: expected a direction along the global x or y axis"),
        (edit(weld3), r"joints\[1\]\.points: expected exactly two link points"),
        (edit(slider_on_pin), r"sensors\[1\]\.joint: expected a prismatic joint name, one of \['B'\]"),
        (edit(unknown_kind), r"joints\[1\]\.kind: expected one of \['revolute', 'prismatic', 'weld'\]"),
        (edit(no_axis), r"joints\[2\]\.axis: expected this required key"),
        (edit(mobility), r"coordinates: expected as many ERLS coordinates as the mechanism's mobility \(0,"),
        (edit(weld_ground), r"joints\[1\]\.ground: expected no ground position on a weld"),
    ]


@pytest.mark.parametrize("case", range(8))
def test_model_file_errors(case):
    doc, match = _errors()[case]
    with pytest.raises(ModelFileError, match=r"^sc\.toml: " + match):
        parse_mechanism(doc, "sc.toml")


# ------------------------------------------------------------------------------------------ Exudyn truth
def test_slider_crank_modes_agree_with_exudyn():
    """The ERLS slider-crank (every element split in 2) against Exudyn's ANCF model (8 elements per link), motors
    free, modes below 1 kHz at three crank angles: within 0.5 % (the issue's acceptance on converged meshes)."""
    pytest.importorskip("exudyn")
    from exuflex.groundtruth import exudyn_frequencies
    from exuflex.mechanism import refine_mechanism

    mech = load_mechanism(MODELS / "slider_crank.toml")
    model = ErlsModel(refine_mechanism(mech, 2))
    for q in (math.pi / 2, 0.3, 4.0):
        fe = modal_analysis(model, [q]).below(1000.0)
        fx = exudyn_frequencies(mech, [q], elements_per_link=8)[: len(fe)]
        assert len(fe) >= 3
        np.testing.assert_allclose(fx, fe, rtol=5e-3)


@pytest.mark.parametrize("angle", [math.pi / 2, 2.2])
def test_welded_arm_modes_agree_with_exudyn(angle):
    """A weld in Exudyn (ANCF slopes r'_b = R(angle) r'_a) against the ERLS weld: the first five modes within
    0.05 % on 8 elements per link."""
    pytest.importorskip("exudyn")
    from exuflex.groundtruth import exudyn_frequencies

    mech = parse_mechanism(_welded_arm(n=(8, 6), angle=angle), "l_arm.toml")
    fe = modal_analysis(ErlsModel(mech), [0.3]).frequencies_hz[:5]
    fx = exudyn_frequencies(mech, [0.3], elements_per_link=8)[:5]
    np.testing.assert_allclose(fx, fe, rtol=5e-4)


def test_offset_mass_modes_agree_with_exudyn():
    """A mass at an offset (Exudyn: a rigid body centred at the mass point, welded to the ANCF node's rotation
    ``atan2(y', x')``) against the ERLS rigid offset: the first six modes within 0.05 %."""
    pytest.importorskip("exudyn")
    from exuflex.groundtruth import exudyn_frequencies

    mech = parse_mechanism(_welded_arm(offset=(0.04, -0.03), inertia=1e-4, n=(8, 6)), "l_arm.toml")
    fe = modal_analysis(ErlsModel(mech), [0.3]).frequencies_hz[:6]
    fx = exudyn_frequencies(mech, [0.3], elements_per_link=8)[:6]
    np.testing.assert_allclose(fx, fe, rtol=5e-4)


def test_offset_mass_eq2_coriolis_annihilates_rigid_motion():
    """Eq. 2's ``M_G`` with a mass at an offset (its gyroscopic matrix ``m N_p^T G2 N_p``) vanishes on the
    mechanism's rigid velocity fields, ``M_G S = 0``, as for the beam elements."""
    mech = parse_mechanism(_welded_arm(offset=(0.04, -0.03), inertia=1e-4), "l_arm.toml")
    m = ErlsModel(mech, form="eq2")
    cfg = m.configuration([0.7])
    MG = m.coriolis_matrix(cfg, np.array([1.3]))
    assert np.abs(MG).max() > 0
    assert np.abs(MG @ cfg.pose.S).max() < 1e-12 * np.abs(MG).max()


def test_slide_coordinate_reads_back_from_probes_and_from_exudyn():
    """q = x_B (a slide coordinate) read back as the truth's coordinate from the ERLS probes of deformed states (the
    slider node has no elastic translation: q exactly) and from an Exudyn model built at q; the slider sensor reads
    the same."""
    from exuflex.sensors import erls_probe_record, sensor_channels, true_states

    doc = _doc_slide_driven()
    doc["sensors"].append({"name": "xs", "kind": "slider", "joint": "B"})
    mech = parse_mechanism(doc, "slide.toml")
    model = ErlsModel(mech)
    rng = np.random.default_rng(5)
    Y = np.zeros((3, 2 * model.n))
    Y[:, 0] = [0.38, 0.41, 0.44]
    Y[:, 1 : model.n] = 1e-4 * rng.standard_normal((3, model.ne))
    Y[:, model.n] = [0.2, -0.1, 0.3]
    Y[:, model.n + 1 :] = 1e-2 * rng.standard_normal((3, model.ne))
    rec = erls_probe_record(model, np.arange(3) * 1e-3, Y)
    truth = true_states(mech, rec)
    np.testing.assert_allclose(truth["s"], Y[:, 0], atol=1e-14)
    np.testing.assert_allclose(truth["ds"], Y[:, model.n], atol=1e-13)
    np.testing.assert_allclose(sensor_channels(mech, rec)["xs"], Y[:, 0], atol=1e-14)
    assert truth.unit("s") == "m" and truth.unit("ds") == "m/s"
    pytest.importorskip("exudyn")
    from exuflex.groundtruth import build_truth

    tm = build_truth(mech, [0.42], elements_per_link=2, damping=None)
    np.testing.assert_allclose(tm.coordinate_values(), [0.42], atol=1e-12)


def _two_link_arm():
    """The L-arm with a revolute elbow instead of the weld and a relative elbow coordinate q2."""
    d = _welded_arm(n=(6, 4))
    d["joints"][1] = {"name": "E", "points": [{"link": "a", "station": 0.5}, {"link": "b", "station": 0.0}]}
    d["links"][1]["angle_guess"] = 1.5
    d["model"]["q_ref"] = [0.3, 1.2]
    d["coordinates"].append({"name": "q2", "link": "b", "joint": "E", "relative_to": "a"})
    return parse_mechanism(d, "arm.toml")


@pytest.mark.parametrize("case", ["relative", "slide"])
def test_locked_modes_agree_with_exudyn(case):
    """Motors locked (q held) in Exudyn against the ERLS: a relative coordinate (its constraint spans the two nodes
    at the joint) and a slide coordinate (the slider's position held); the first three modes within 0.01 %."""
    pytest.importorskip("exudyn")
    from exuflex.groundtruth import exudyn_frequencies

    if case == "relative":
        mech, q, epl = _two_link_arm(), [0.3, 1.2], 6
    else:
        mech, q, epl = parse_mechanism(_doc_slide_driven(), "slide.toml"), [0.4], 8
    fe = modal_analysis(ErlsModel(mech), q, locked=True).frequencies_hz[:3]
    fx = exudyn_frequencies(mech, q, elements_per_link=epl, locked=True)[:3]
    np.testing.assert_allclose(fx, fe, rtol=1e-4)

"""Mechanism files: the three models load; every malformed file is rejected naming file and field."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import ModelFileError, elastic_dofs, load_mechanism, parse_mechanism, refine_mechanism

MODELS = Path(__file__).resolve().parents[1] / "models"
NAMES = ("sixbar", "single_link", "fourbar", "slider_crank")


def _doc(name: str) -> dict:
    with open(MODELS / f"{name}.toml", "rb") as fh:
        return tomllib.load(fh)


@pytest.mark.parametrize("name", NAMES)
def test_models_load(name):
    mech = load_mechanism(MODELS / f"{name}.toml")
    assert mech.name == name
    assert len(mech.q_ref) == len(mech.coordinates)
    dofs = elastic_dofs(mech)
    for m in mech.reduction.masters:
        dofs.locate(m)  # every master is a real elastic dof
    assert mech.sensors and mech.motors and mech.manoeuvre is not None and mech.payload is not None


def test_sixbar_numbering_matches_paper():
    """The paper's masters x14, y15 (node 8), theta24 (node 12), x25, y26 (tip node 14)."""
    dofs = elastic_dofs(load_mechanism(MODELS / "sixbar.toml"))
    assert dofs.n == 27
    assert [dofs.node_name(m) for m in ("x14", "y15", "theta24", "x25", "y26")] == [
        "node8.x", "node8.y", "node12.theta", "node14.x", "node14.y"
    ]


def test_link_frame_masters_by_name_and_by_point():
    """``node5.transverse`` and the point ``{ link, station, direction }`` name the same dof; a joint's second
    node names the joint's shared translation in its own link's frame."""
    doc = _doc("single_link")
    doc["reduction"]["masters"] = [{"link": "arm", "station": 1.0, "direction": "transverse"}, "node5.theta"]
    mech = parse_mechanism(doc, "point.toml")
    assert mech.reduction.masters == ("node5.transverse", "node5.theta")
    d = elastic_dofs(load_mechanism(MODELS / "fourbar.toml"))
    a, b = d.locate("node3.transverse"), d.locate("node2.transverse")  # joint A: coupler's and crank's node
    assert a.pair == b.pair == (d.index("node2.x"), d.index("node2.y"))
    assert (a.frame_node, b.frame_node) == (3, 2) and a.index == b.index == d.index("node2.y")
    assert d.locate("node2.axial").index == d.index("node2.x") and d.locate("node9.theta").frame_node is None


def test_n_elements_equals_explicit_stations():
    doc = _doc("single_link")
    doc["links"][0].pop("n_elements")
    doc["links"][0]["stations"] = [0.0, 0.25, 0.5, 0.75, 1.0]
    a = parse_mechanism(doc, "explicit.toml")
    b = load_mechanism(MODELS / "single_link.toml")
    assert a.links[0].stations == b.links[0].stations and a.links[0].node_ids == b.links[0].node_ids


def test_refine_keeps_node_ids_and_masters():
    mech = load_mechanism(MODELS / "sixbar.toml")
    fine = refine_mechanism(mech, 3)
    assert all(set(a.node_ids) <= set(b.node_ids) for a, b in zip(mech.links, fine.links))
    assert sum(lk.n_elements for lk in fine.links) == 3 * sum(lk.n_elements for lk in mech.links)
    assert fine.reduction.masters[0] == "node8.x"
    d = elastic_dofs(fine)
    for m in fine.reduction.masters:
        d.index(m)


# ---------------------------------------------------------------------- malformed files
def _edit(doc: dict, path: str, value) -> dict:
    """Set (or delete, for value=DELETE) the entry at a dotted path like ``links.2.diameter``."""
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]
    node = doc
    for k in keys[:-1]:
        node = node[k]
    if value is DELETE:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return doc


DELETE = object()

CASES = [
    # (model, dotted path, new value, field named in the message, phrase of what was expected)
    ("sixbar", "links.0.length", DELETE, "links[0].length", "required key"),
    ("sixbar", "model.name", DELETE, "model.name", "required key"),
    ("sixbar", "links.1.colour", "red", "links[1].colour", "known keys"),
    ("sixbar", "model.sample_rate", 500.0, "model.sample_rate", "known keys"),
    ("sixbar", "links.0.length", -0.5, "links[0].length", "positive number in m"),
    ("sixbar", "links.0.length", "0.5", "links[0].length", "finite number"),
    ("sixbar", "links.2.diameter", 16.0, "links[2].diameter", "mm by mistake"),
    ("sixbar", "materials.0.E", 69.0, "materials[0].E", "Pa"),
    ("sixbar", "masses.0.mass", -1.0, "masses[0].mass", ">= 0"),
    ("sixbar", "masses.0.node", 99, "masses[0].node", "existing node id"),
    ("sixbar", "joints.1.points.0.link", "L9", "joints[1].points[0].link", "link name"),
    ("sixbar", "joints.1.points.0.station", 0.3, "joints[1].points[0].station", "stations"),
    ("sixbar", "motors.2.reaction", DELETE, "motors[2].reaction", "reaction link"),
    ("sixbar", "coordinates.0.joint", "B", "coordinates[0].joint", "takes part in"),
    ("sixbar", "sensors.4.kind", "strain", "sensors[4].kind", "one of"),
    ("sixbar", "damping.alpha", -1.0, "damping.alpha", ">= 0"),
    ("sixbar", "reduction.masters", ["x14", "x99"], "reduction.masters[1]", "elastic dof name"),
    ("sixbar", "reduction.masters", "x14", "reduction.masters", "list of elastic dof names"),
    ("sixbar", "reduction.masters", ["node14.sideways"], "reduction.masters[0]", "elastic dof name"),
    ("sixbar", "reduction.masters", ["node1.transverse"], "reduction.masters[0]", "elastic dof name"),
    ("single_link", "reduction.masters", [{"link": "arm", "station": 1.0, "direction": "y"}],
     "reduction.masters[0].direction", "'axial', 'transverse' or 'theta'"),
    ("single_link", "reduction.masters", [{"link": "arm", "station": 0.6, "direction": "axial"}],
     "reduction.masters[0].station", "stations"),
    ("sixbar", "model.q_ref", [1.0, 2.0], "model.q_ref", "list of 3 numbers"),
    ("sixbar", "manoeuvre.ramp_time", 2.0, "manoeuvre.ramp_time", "ramp time"),
    ("single_link", "links.0.n_elements", 0, "links[0].n_elements", "positive integer"),
    ("single_link", "links.0.n_elements", 2.5, "links[0].n_elements", "an integer"),
    ("single_link", "links.0.stations", [0.0, 0.6, 0.4, 1.0], "links[0].n_elements", "either stations or n_elements"),
    ("fourbar", "coordinates", [], "coordinates", "at least one ERLS coordinate"),
    ("fourbar", "joints.1.points", "A", "joints[1].points", "a list of points"),
    ("fourbar", "joints.1.points", [{"link": "crank", "station": 0.15}], "joints[1].points", "at least two link points"),
    ("fourbar", "manoeuvre.rules", "q1", "manoeuvre.rules", "a list of rules"),
    ("fourbar", "manoeuvre.rules", ["q1"], "manoeuvre.rules[0]", "an inline table"),
    ("fourbar", "manoeuvre.rules", [], "manoeuvre.rules", "one rule per ERLS coordinate"),
    ("fourbar", "manoeuvre.time_law", "sine", "manoeuvre.time_law", "one of"),
    ("fourbar", "sensors.2.relative_to", "crank", "sensors[2].relative_to", "a link at joint 'B'"),
    ("fourbar", "reduction.q_star", [1.0, 2.0], "reduction.q_star", "list of 1 numbers"),
    ("fourbar", "reduction.n_interior", -2, "reduction.n_interior", "non-negative integer"),
    ("fourbar", "links.0.material", "steel", "links[0].material", "a material name"),
    ("fourbar", "materials.0.rho", 2.7, "materials[0].rho", "kg/m^3"),
    ("fourbar", "links.1.A", 1e-4, "links[1].A", "either diameter or A and I"),
]


@pytest.mark.parametrize("model,path,value,field,expected", CASES, ids=[c[3] + "=" + repr(c[2])[:12] for c in CASES])
def test_bad_field_is_named(model, path, value, field, expected):
    doc = _edit(_doc(model), path, value)
    with pytest.raises(ModelFileError, match=rf"^bad_{model}\.toml: {re.escape(field)}: expected .*{re.escape(expected)}"):
        parse_mechanism(doc, f"bad_{model}.toml")


def test_disconnected_link():
    """A link joined only to another link that never reaches the ground."""
    doc = _doc("fourbar")
    doc["links"].append({"name": "stray", "length": 0.2, "material": "aluminium", "diameter": 0.01, "n_elements": 1})
    doc["links"].append({"name": "stray2", "length": 0.2, "material": "aluminium", "diameter": 0.01, "n_elements": 1})
    doc["joints"].append({"name": "S", "points": [{"link": "stray", "station": 0.2}, {"link": "stray2", "station": 0.0}]})
    with pytest.raises(ModelFileError, match=r"^loose\.toml: joints: expected .*not connected: \['stray', 'stray2'\]"):
        parse_mechanism(doc, "loose.toml")


def test_unsorted_stations():
    doc = _doc("single_link")
    doc["links"][0].pop("n_elements")
    doc["links"][0]["stations"] = [0.0, 0.6, 0.4, 1.0]
    with pytest.raises(ModelFileError, match=r"^s\.toml: links\[0\]\.stations: expected ascending stations from 0"):
        parse_mechanism(doc, "s.toml")


def test_mobility_mismatch():
    """A second coordinate on the one-dof four-bar."""
    doc = _doc("fourbar")
    doc["coordinates"].append({"name": "q2", "link": "rocker", "joint": "O4"})
    doc["model"]["q_ref"] = [1.57, 1.97]
    doc.pop("manoeuvre")
    doc["reduction"].pop("q_star")
    with pytest.raises(ModelFileError, match=r"^mob\.toml: coordinates: expected as many ERLS coordinates .*mobility \(1"):
        parse_mechanism(doc, "mob.toml")


def test_no_ground():
    doc = _doc("single_link")
    doc["joints"][0].pop("ground")
    doc["joints"][0]["points"].append({"link": "arm", "station": 1.0})
    doc.pop("motors")
    with pytest.raises(ModelFileError, match=r"^g\.toml: joints"):
        parse_mechanism(doc, "g.toml")


def test_file_errors(tmp_path):
    with pytest.raises(ModelFileError, match=r"nope\.toml: \(file\): expected an existing TOML model file"):
        load_mechanism(tmp_path / "nope.toml")
    bad = tmp_path / "syntax.toml"
    bad.write_text("[model\nname = 'x'\n")
    with pytest.raises(ModelFileError, match=r"syntax\.toml: \(syntax\): expected valid TOML"):
        load_mechanism(bad)


def test_loaded_values_are_si():
    mech = load_mechanism(MODELS / "fourbar.toml")
    cr = mech.link("crank")
    assert cr.section.A == pytest.approx(np.pi * 0.025**2 / 4)
    assert cr.section.I == pytest.approx(np.pi * 0.025**4 / 64)
    assert mech.payload.mass == 0.15 and mech.node_location(mech.payload.node) == ("coupler", 0.7)
    assert mech.link("coupler").stations[4] == 0.5


SECTION_CASES = [
    ({"diameter": 0.02, "inner_diameter": 0.02}, "links[1].inner_diameter", "smaller than the outer diameter"),
    ({"inner_diameter": 0.01}, "links[1].diameter", "outer diameter"),
    ({"width": 0.01}, "links[1].height", "this required key"),
    ({"width": 0.01, "height": 0.02, "diameter": 0.012}, "links[1].width", "no width or height with a diameter"),
    ({"diameter": 0.012, "mesh_size": 2.0}, "links[1].mesh_size", "smaller than the link length"),
]


@pytest.mark.parametrize("section,field,expected", SECTION_CASES, ids=[c[1] + str(i) for i, c in enumerate(SECTION_CASES)])
def test_bad_section_is_named(section, field, expected):
    doc = _doc("fourbar")
    link = doc["links"][1]
    link.pop("diameter")
    link.update(section)
    with pytest.raises(ModelFileError, match=rf"^s\.toml: {re.escape(field)}: expected .*{re.escape(expected)}"):
        parse_mechanism(doc, "s.toml")


def test_solid_sections_area_and_inertia():
    """Tube and rectangle: A and I from the closed forms; the shape is kept for the solid mesh."""
    doc = _doc("fourbar")
    doc["links"][1].update(diameter=0.02, inner_diameter=0.016)
    doc["links"][2].pop("diameter")
    doc["links"][2].update(width=0.01, height=0.02)
    mech = parse_mechanism(doc, "s.toml")
    tube, rect = mech.links[1].section, mech.links[2].section
    assert tube.shape == "tube" and tube.A == pytest.approx(np.pi * (0.02**2 - 0.016**2) / 4)
    assert tube.I == pytest.approx(np.pi * (0.02**4 - 0.016**4) / 64)
    assert rect.shape == "rectangle" and rect.A == pytest.approx(2e-4) and rect.I == pytest.approx(0.01 * 0.02**3 / 12)
    assert mech.links[0].section.shape == "round"


def _cantilever_root_curvature(L: float, n: int, w: float, EI: float) -> float:
    """The two-node cubic beam elements' curvature at the clamped root of a cantilever under a uniform load
    (consistent load vector), a NumPy oracle independent of the ERLS model."""
    h = L / n
    k = EI / h**3 * np.array([[12, 6 * h, -12, 6 * h], [6 * h, 4 * h * h, -6 * h, 2 * h * h],
                              [-12, -6 * h, 12, -6 * h], [6 * h, 2 * h * h, -6 * h, 4 * h * h]])
    f = w * h * np.array([0.5, h / 12, 0.5, -h / 12])
    K, F = np.zeros((2 * n + 2, 2 * n + 2)), np.zeros(2 * n + 2)
    for e in range(n):
        K[2 * e : 2 * e + 4, 2 * e : 2 * e + 4] += k
        F[2 * e : 2 * e + 4] += f
    u = np.zeros(2 * n + 2)
    u[2:] = np.linalg.solve(K[2:, 2:], F[2:])
    v2, t2 = u[2], u[3]  # the first element's far node (the root's are zero)
    return 6 * v2 / h**2 - 2 * t2 / h  # v''(0) of the Hermite cubic


@pytest.mark.parametrize("n", [1, 2, 5, 20])
def test_gauge_sag_error_is_w_h2_over_12EI_at_a_node(n):
    """The derivation of :func:`gauge_sag_length`: the cubic elements' curvature at a node under a uniform load
    errs by ``w h^2 / (12 EI)`` (the nodal values exact, the quartic bubble's curvature at the element's end),
    whatever the rest of the mesh: the cantilever's root curvature against the exact ``w L^2 / (2 EI)``."""
    L, w, EI = 0.8, 2.0, 30.0
    exact = w * L**2 / (2 * EI)
    got = _cantilever_root_curvature(L, n, w, EI)
    np.testing.assert_allclose(exact - got, w * (L / n) ** 2 / (12 * EI), rtol=0, atol=1e-10 * exact)  # (round-off)


def test_gauge_rule_refines_next_to_the_gauges_under_gravity_only():
    """The gauge rule (:func:`exuflex.mechanism.refine.gauge_mesh`): under gravity every curvature gauge's
    neighbouring elements are within :func:`gauge_sag_length` (its sag reading within a tenth of the noise) and no
    added element is shorter than half of it, the model file's nodes kept with their ids; without gravity the
    mechanism is returned as it is."""
    from exuflex.mechanism.refine import GAUGE_SAG_TOL, gauge_mesh, gauge_sag_length

    root = Path(__file__).resolve().parents[1]
    own = load_mechanism(root / "benchmarks/models/drooping_fourbar.toml")
    mech = gauge_mesh(own)
    for lk0, lk in zip(own.links, mech.links, strict=True):
        kept = dict(zip(lk.node_ids, lk.stations, strict=True))
        assert all(abs(kept[i] - s) < 1e-12 for i, s in zip(lk0.node_ids, lk0.stations, strict=True))
    assert mech.link("coupler").n_elements > own.link("coupler").n_elements
    for s in mech.sensors:
        if s.kind != "curvature":
            continue
        h = gauge_sag_length(mech, s)
        lk = mech.link(s.link)
        w = lk.material.rho * lk.section.A * 9.81
        np.testing.assert_allclose(w * h**2 / (12 * lk.material.E * lk.section.I), GAUGE_SAG_TOL * s.noise_std)
        st = np.asarray(lk.stations)
        i = int(np.argmin(abs(st - s.station)))
        assert abs(st[i] - s.station) < 1e-12
        assert st[i] - st[i - 1] <= h * (1 + 1e-9) and st[i + 1] - st[i] <= h * (1 + 1e-9)
        assert min(np.diff(st)) >= 0.5 * h * (1 - 1e-9)
    flat = load_mechanism(root / "models/fourbar.toml")
    assert gauge_mesh(flat) is flat

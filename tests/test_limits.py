"""Size and conditioning limits checked when a model file is loaded (:mod:`exuflex.mechanism.limits`)."""

from __future__ import annotations

import math
import re
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sl

sys.path.insert(0, str(Path(__file__).parent))
import _toml  # noqa: E402

from exuflex.cli import main  # noqa: E402
from exuflex.erls.elements import beam_mass, beam_stiffness  # noqa: E402
from exuflex.erls.modal import modal_analysis  # noqa: E402
from exuflex.erls.model import ErlsModel  # noqa: E402
from exuflex.mechanism import (MAX_ELEMENTS, ModelFileError, load_mechanism, parse_mechanism,  # noqa: E402
                               refine_mechanism, remesh_mechanism, remeshed_element_count)
from exuflex.mechanism.limits import band_damping_ratio, element_frequency_bound, limit_errors  # noqa: E402

MODELS = Path(__file__).resolve().parents[1] / "models"


def _doc(name: str) -> dict:
    with open(MODELS / f"{name}.toml", "rb") as fh:
        return tomllib.load(fh)


def _one_line(exc) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


@pytest.mark.parametrize("path", sorted(MODELS.glob("*.toml")), ids=lambda p: p.stem)
def test_gallery_is_within_the_limits(path):
    assert limit_errors(load_mechanism(path)) == []


@pytest.mark.parametrize("length", [0.5, 0.07, 0.003])
def test_element_frequency_bound_is_the_element_eigenvalue(length):
    """Closed form against the eigenvalues of the element matrices of exuflex.erls.elements."""
    lk = load_mechanism(MODELS / "sixbar.toml").links[3]
    E, rho, A, I = lk.material.E, lk.material.rho, lk.section.A, lk.section.I
    lam = sl.eigh(beam_stiffness(E * A, E * I, length), beam_mass(rho * A, length), eigvals_only=True)
    assert element_frequency_bound(lk, length) == pytest.approx(math.sqrt(lam.max()), rel=1e-9)


@pytest.mark.parametrize("name", ["single_link", "sixbar"])
def test_assembled_frequencies_stay_below_the_element_bound(name):
    """Irons' theorem: no frequency of the assembled model exceeds the largest element frequency."""
    mech = load_mechanism(MODELS / f"{name}.toml")
    f = modal_analysis(ErlsModel(mech)).frequencies_hz
    bound = max(element_frequency_bound(lk, b - a) for lk in mech.links
                for a, b in zip(lk.stations, lk.stations[1:]))
    assert 2 * np.pi * f.max() <= bound
    assert 2 * np.pi * f.max() > 0.1 * bound  # a bound of the right order, not a vacuous one


def test_band_damping_ratio_is_rayleighs():
    """The six-bar's damping is designed as 1 % at 13.28 and 159.36 Hz (models/sixbar.toml)."""
    mech = load_mechanism(MODELS / "sixbar.toml")
    a, b = mech.damping.alpha, mech.damping.beta
    for f in (13.28, 159.36):
        w = 2 * np.pi * f
        assert a / (2 * w) + b * w / 2 == pytest.approx(0.01, rel=1e-9)
    w = 2 * np.pi * 180.0
    assert band_damping_ratio(mech) == pytest.approx(a / (2 * w) + b * w / 2, rel=1e-12)


@pytest.mark.parametrize("key,value", [("beta", 1e12), ("alpha", 1e12), ("beta", 1.0), ("alpha", 2.3e4)])
def test_damping_far_above_critical_is_refused(key, value):
    doc = _doc("sixbar")
    doc["damping"][key] = value
    with pytest.raises(ModelFileError) as ei:
        parse_mechanism(doc, "damp.toml")
    msg = _one_line(ei)
    assert msg.startswith("damp.toml: damping: expected Rayleigh coefficients") and "at most 1 at the band" in msg


def test_damping_just_below_critical_is_accepted():
    doc = _doc("sixbar")
    w = 2 * np.pi * 180.0
    doc["damping"] = {"alpha": 0.0, "beta": 0.99 * 2 / w}
    assert band_damping_ratio(parse_mechanism(doc, "ok.toml")) == pytest.approx(0.99)


def test_a_hundred_thousand_elements_are_refused_before_the_mesh_is_built():
    doc = _doc("single_link")
    doc["links"][0]["n_elements"] = 100_000
    with pytest.raises(ModelFileError) as ei:
        parse_mechanism(doc, "fine.toml")
    msg = _one_line(ei)
    assert msg.startswith("fine.toml: links[0].n_elements: expected at most 1000 beam elements") and \
        msg.endswith("got 100000")


def test_too_many_stations_in_all_links_are_refused():
    doc = _doc("fourbar")
    for lk in doc["links"]:
        lk.pop("stations", None)
        lk.pop("nodes", None)
        lk["n_elements"] = 400
    with pytest.raises(ModelFileError, match=r"^fb\.toml: links\[2\]\.n_elements: expected at most 1000 .*"
                                             r"that makes 1200 with the links before it, got 400$"):
        parse_mechanism(doc, "fb.toml")


@pytest.mark.parametrize("edit,why", [
    (lambda lk: lk.update(n_elements=1000), "far too short element"),  # 1 mm elements on a 1 m link
    (lambda lk: (lk.pop("n_elements"), lk.update(stations=[0.0, 1e-4, 0.25, 0.5, 1.0])),
     "0.0001 m element"),  # one sliver element at the hub
], ids=["1000 elements", "sliver"])
def test_stiffness_ratio_is_limited(edit, why):
    doc = _doc("single_link")
    edit(doc["links"][0])
    with pytest.raises(ModelFileError) as ei:
        parse_mechanism(doc, "stiff.toml")
    msg = _one_line(ei)
    assert msg.startswith("stiff.toml: links[0]: expected a stiffness ratio") and why in msg
    ratio = float(re.search(r"got ([0-9.e+]+)$", msg).group(1))
    assert ratio > 1e5


def test_refinement_is_limited():
    mech = load_mechanism(MODELS / "sixbar.toml")
    n = sum(lk.n_elements for lk in mech.links)
    assert remeshed_element_count(mech, 8) == sum(lk.n_elements for lk in remesh_mechanism(mech, 8).links)
    with pytest.raises(ValueError, match=f"expected at most {MAX_ELEMENTS} .*that makes {n * 112}"):
        refine_mechanism(mech, 112)
    with pytest.raises(ValueError, match=f"expected at most {MAX_ELEMENTS}"):
        remesh_mechanism(mech, 500)


def test_cli_one_line_errors(tmp_path, capsys):
    doc = _doc("sixbar")
    doc["damping"]["beta"] = 1e12
    bad = tmp_path / "damp.toml"
    bad.write_text(_toml.dumps(doc))
    for argv in (["modes", str(bad)], ["simulate", str(bad), "--out", str(tmp_path / "r")],
                 ["simulate", str(MODELS / "sixbar.toml"), "--out", str(tmp_path / "r"), "--elements-per-link",
                  "300"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and ("damping: expected" in err or "--elements-per-link): 300 per link" in err)
    assert not (tmp_path / "r").exists()

"""Truth options: the Exudyn mesh (model file's, or N elements per link), beam formulation, locked-motor
eigenvalues, a hub inertia without a spurious mode, and what ``meta.json`` records of them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from exuflex.cli import main
from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism, remesh_mechanism

MODELS = Path(__file__).resolve().parents[1] / "models"


@pytest.fixture(scope="module")
def fourbar():
    return load_mechanism(MODELS / "fourbar.toml")


def test_remesh_keeps_nodes_and_bounds_element_length(fourbar):
    for n in (1, 4, 8):
        fine = remesh_mechanism(fourbar, n)
        for old, new in zip(fourbar.links, fine.links):
            assert set(old.node_ids) <= set(new.node_ids)  # every original node kept, with its id
            st = np.asarray(new.stations)
            for nid, s in zip(old.node_ids, old.stations):
                assert st[list(new.node_ids).index(nid)] == pytest.approx(s)
            assert new.n_elements >= n and np.max(np.diff(st)) <= old.length / n * (1 + 1e-12)
    # the crank's single element split in 8; the coupler's 0.125 m elements in 2 (0.7 / 8 = 0.0875 m)
    fine = remesh_mechanism(fourbar, 8)
    assert [lk.n_elements for lk in fine.links] == [8, 12, 9]
    with pytest.raises(ValueError, match="elements per link must be an integer >= 1"):
        remesh_mechanism(fourbar, 0)


exudyn = pytest.importorskip("exudyn")

from exuflex.groundtruth import exudyn_frequencies, link_mesh_stations


def test_file_mesh_is_the_mechanisms_own(fourbar):
    for lk in fourbar.links:
        np.testing.assert_allclose(link_mesh_stations(fourbar, lk.name, "file"), lk.stations, atol=1e-12)
    with pytest.raises(ValueError, match="elements_per_link must be an integer >= 1, 'file' or None"):
        link_mesh_stations(fourbar, "crank", "fine")


@pytest.mark.parametrize("locked", [False, True], ids=["free", "locked"])
def test_exudyn_modes_equal_erls_on_the_same_mesh(fourbar, locked):
    """ANCF and ERLS elements share the cubic bending field: on one mesh, motors free or locked, every mode below
    500 Hz agrees (seen within 0.002 %); locked differs from free (the locked rocker/coupler modes drop)."""
    mech = remesh_mechanism(fourbar, 8)
    f_erls = modal_analysis(ErlsModel(mech), locked=locked).below(500.0)
    f_exu = exudyn_frequencies(mech, elements_per_link="file", locked=locked)
    f_exu = f_exu[f_exu < 500.0]
    assert len(f_exu) == len(f_erls) == 6
    np.testing.assert_allclose(f_exu, f_erls, rtol=2e-4)
    f_free = modal_analysis(ErlsModel(mech)).below(500.0)
    assert locked == (abs(f_erls[3] / f_free[3] - 1) > 0.1)  # locking the crank moves the 4th mode 365 -> 264 Hz


def test_rigid_hub_adds_no_spurious_mode(fourbar):
    """The crank's motor rotor (J = 0.01 kg m^2) on the ANCF slopes as diag(J, J) also gives the slope's stretch
    inertia: a mode below 500 Hz that the ERLS (J on the node's rotation) has not, falling as the mesh is refined
    (seen 435 Hz at 8, 308 Hz at 16 elements per link). The rigid hub body has none, at every mesh."""
    for n in (8, 16):
        mech = remesh_mechanism(fourbar, n)
        f_erls = modal_analysis(ErlsModel(mech)).below(500.0)
        rigid = exudyn_frequencies(mech, elements_per_link="file", hub="rigid")
        slopes = exudyn_frequencies(mech, elements_per_link="file", hub="slopes")
        rigid, slopes = rigid[rigid < 500.0], slopes[slopes < 500.0]
        np.testing.assert_allclose(rigid, f_erls, rtol=2e-4)
        assert len(slopes) == len(f_erls) + 1
        spurious = slopes[int(np.argmax([np.min(np.abs(f_erls / f - 1)) for f in slopes]))]  # farthest from all
        assert np.min(np.abs(f_erls / spurious - 1)) > 0.03 and spurious < 450.0


def test_geometrically_exact_beams_converge_to_the_same_modes():
    """Linear GE beams need a fine mesh: 32 elements on the single link are within 0.2 % of the cubic ERLS."""
    mech = remesh_mechanism(load_mechanism(MODELS / "single_link.toml"), 32)
    f_erls = modal_analysis(ErlsModel(mech)).below(180.0)
    f_ge = exudyn_frequencies(mech, elements_per_link="file", formulation="gebeam")[: len(f_erls)]
    np.testing.assert_allclose(f_ge, f_erls, rtol=2e-3)


def test_cli_modes_locked_exudyn(capsys):
    assert main(["modes", str(MODELS / "fourbar.toml"), "--locked", "--exudyn", "--elements-per-link", "8",
                 "--fmax", "300", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    ex = rep["exudyn"]
    assert ex["locked"] and ex["beam"] == "ancf" and ex["elements_per_link"] == 8 and ex["n_elements"] == 29
    np.testing.assert_allclose(ex["frequencies_hz"], rep["full"]["frequencies_hz"], rtol=5e-3)


def test_cli_simulate_records_truth_options(tmp_path):
    out = tmp_path / "ge"
    assert main(["simulate", str(MODELS / "fourbar.toml"), "--out", str(out), "--duration", "0.01", "--seed", "1",
                 "--beam", "ge", "--elements-per-link", "16"]) == 0
    truth = json.loads((out / "meta.json").read_text())["settings"]["truth"]
    assert truth["engine"] == "exudyn" and truth["beam"] == "ge" and truth["formulation"] == "gebeam"
    assert truth["elements_per_link"] == 16
    # crank and rocker 16 elements, the coupler 12 + 5 (its joint at 0.5 m is a node: 0.5 and 0.2 m split into
    # elements of at most 0.7 / 16 m); 3 coordinates per node; on GE beams the rotor's J sits on the rotation
    assert truth["n_coordinates"] == 3 * (17 + 18 + 17)
    out = tmp_path / "file"
    assert main(["simulate", str(MODELS / "fourbar.toml"), "--out", str(out), "--duration", "0.01", "--seed", "1",
                 "--elements-per-link", "file"]) == 0
    truth = json.loads((out / "meta.json").read_text())["settings"]["truth"]
    # the file's nodes (crank 2, coupler 7, rocker 4) x 4 coordinates, plus the rotor's rigid body (x, y, phi)
    assert truth["elements_per_link"] == "file" and truth["hub_inertia"] == "rigid body welded to the node"
    assert truth["n_coordinates"] == 4 * 13 + 3


def test_cli_rejects_bad_mesh_argument(capsys):
    assert main(["simulate", str(MODELS / "fourbar.toml"), "--out", "x", "--elements-per-link", "0"]) == 2
    assert "expected a positive integer or 'file', got '0'" in capsys.readouterr().err


def test_default_exudyn_mesh_is_never_coarser_than_the_model_file(tmp_path):
    """The default Exudyn mesh (:func:`exuflex.truth.exudyn_mesh`) gives every link at least 4 elements and at
    least as many as the model file's most refined link (the slider-crank's rod: 8); a default run records it."""
    from exuflex.groundtruth import link_mesh_stations
    from exuflex.truth import EXUDYN_ELEMENTS_PER_LINK, exudyn_mesh

    for path in sorted(MODELS.glob("*.toml")):
        mech = load_mechanism(path)
        n = exudyn_mesh(mech)
        finest = max(len(lk.stations) - 1 for lk in mech.links)
        assert n == max(EXUDYN_ELEMENTS_PER_LINK, finest), path.name
        for lk in mech.links:
            assert len(link_mesh_stations(mech, lk.name, n)) - 1 >= max(n, len(lk.stations) - 1), (path.name, lk.name)
    out = tmp_path / "slider"
    assert main(["simulate", str(MODELS / "slider_crank.toml"), "--out", str(out), "--duration", "0.01", "--seed",
                 "1"]) == 0
    assert json.loads((out / "meta.json").read_text())["settings"]["truth"]["elements_per_link"] == 8

"""Damping as stated: every free elastic mode has the model file's Rayleigh ratio ``alpha / (2 w) + beta w / 2``,
in the ERLS model (both forms, from the state matrix's eigenvalues) and in the Exudyn truth (from Exudyn's
linearised system), with no force on rigid motion; the truth builds its damper from its own matrices only.

The oracle is the formula; the ratios are read from eigenvalues computed here (ERLS) or by
:func:`exuflex.groundtruth.modal_damping` (Exudyn's ``ComputeLinearizedSystem``).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla

from exuflex.erls.modal import aligned_ratios, damping_ratios, modal_analysis
from exuflex.erls.model import FORMS, ErlsModel
from exuflex.mechanism import load_mechanism

sys.path.insert(0, str(Path(__file__).parent))
from _toml import dumps

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
FMAX = 180.0
GALLERY = ("sixbar", "fourbar", "serial_arm", "fivebar", "slider_crank", "single_link")

# a mechanism written for these tests from models/README.md: a two-link arm in the vertical plane, steel upper
# link, aluminium forearm, hub and elbow inertias, a payload at an offset with its own inertia
FRESH_ARM = {
    "model": {"name": "fresh_arm", "description": "two-link arm written for the damping tests",
              "sample_rate_hz": 1000.0, "q_ref": [0.4, -0.9], "gravity": [0.0, -9.81]},
    "materials": [{"name": "steel", "E": 210.0e9, "rho": 7850.0}, {"name": "alu", "E": 70.0e9, "rho": 2700.0}],
    "links": [{"name": "a", "length": 0.7, "material": "steel", "diameter": 0.018, "n_elements": 5,
               "angle_guess": 0.4},
              {"name": "b", "length": 0.45, "material": "alu", "diameter": 0.014, "n_elements": 3,
               "angle_guess": -0.5}],
    "joints": [{"name": "S", "points": [{"link": "a", "station": 0.0}], "ground": [0.0, 0.0]},
               {"name": "E", "points": [{"link": "a", "station": 0.7}, {"link": "b", "station": 0.0}]}],
    "coordinates": [{"name": "q1", "link": "a", "joint": "S"},
                    {"name": "q2", "link": "b", "joint": "E", "relative_to": "a"}],
    "motors": [{"name": "T1", "joint": "S", "link": "a", "noise_std": 0.02, "full_scale": 20.0},
               {"name": "T2", "joint": "E", "link": "b", "reaction": "a", "noise_std": 0.01, "full_scale": 10.0}],
    "masses": [{"link": "a", "station": 0.0, "mass": 0.4, "inertia": 0.03},
               {"link": "a", "station": 0.7, "mass": 0.8, "inertia": 0.002}],
    "payload": {"link": "b", "station": 0.45, "mass": 0.3, "inertia": 0.001, "offset": [0.03, 0.01]},
    "damping": {"alpha": 3.0, "beta": 2.0e-5},
    "sensors": [{"name": "q1", "kind": "encoder", "link": "a", "joint": "S", "noise_std": 1.0e-3,
                 "full_scale": 8.0}],
}


@pytest.fixture(scope="module")
def fresh_arm(tmp_path_factory):
    path = tmp_path_factory.mktemp("fresh") / "fresh_arm.toml"
    path.write_text(dumps(FRESH_ARM))
    return path


def _model_paths(fresh):
    return [MODELS / f"{name}.toml" for name in GALLERY] + [fresh]


def _rayleigh(mech, f_hz):
    w = 2 * np.pi * np.asarray(f_hz)
    return mech.damping.alpha / (2 * w) + mech.damping.beta * w / 2


def _state_matrix_ratios(model, q):
    """Natural frequencies (Hz) and ratios of the oscillating eigenvalues of the state matrix, computed here."""
    A, _ = model.state_matrix(model.configuration(q))
    s = sla.eigvals(A)
    s = s[(s.imag > 0) & (np.abs(s) > 2 * np.pi * 0.5)]
    s = s[np.argsort(np.abs(s))]
    return np.abs(s) / (2 * np.pi), -s.real / np.abs(s)


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("which", [*GALLERY, "fresh"])
def test_erls_free_modes_have_the_rayleigh_ratio(form, which, fresh_arm):
    """Both forms, at q_ref and at a second configuration: each mode below 180 Hz has alpha / (2 w) + beta w / 2
    (exact up to round-off) at its undamped frequency, and the library's aligned report says the same. The
    stiffness-proportional damping acts on the linear elastic stiffness: under gravity the modes also hold the
    static axial loads' geometric stiffness, which moves the ratios by ``-beta phi^T K_G phi / (2 w)``, checked
    here on the model without it (and that the shift stays below 1e-3 of the ratio)."""
    path = fresh_arm if which == "fresh" else MODELS / f"{which}.toml"
    mech = load_mechanism(path)
    if mech.gravity and any(mech.gravity):
        for q in (mech.q_ref, np.asarray(mech.q_ref) + 0.1):
            geo = ErlsModel(mech, form=form)
            f0 = modal_analysis(geo, q).below(FMAX)
            zeta = _state_matrix_ratios(geo, q)[1][: len(f0)]
            np.testing.assert_allclose(zeta, _rayleigh(mech, f0), rtol=1e-3)
    model = ErlsModel(mech, form=form, geometric=False)
    for q in (mech.q_ref, None):
        if q is None:  # a second configuration: a tenth of a radian (or a centimetre) away
            q = np.asarray(mech.q_ref) + 0.1 * np.where([c.kind == "slide" for c in mech.coordinates], 0.1, 1.0)
        f0 = modal_analysis(model, q).below(FMAX)
        assert len(f0) >= 1
        f, zeta = _state_matrix_ratios(model, q)
        f, zeta = f[: len(f0)], zeta[: len(f0)]
        np.testing.assert_allclose(f, f0, rtol=1e-8)  # modal damping: |s| = w
        np.testing.assert_allclose(zeta, _rayleigh(mech, f0), rtol=1e-8)
        np.testing.assert_allclose(aligned_ratios(f0, *damping_ratios(model, q)), zeta, rtol=1e-8)


@pytest.mark.parametrize("form", FORMS)
def test_erls_damping_does_no_work_on_rigid_motion(form):
    """C [a; 0] = 0: a rigid motion of the mechanism (u' = 0) meets no damping force, in both forms; and
    the Lagrange form's dissipation is alpha |S a* + T u'|^2_{M_N} for the momentum-matching rigid motion a*:
    a counter-rotation of the ERLS that leaves the bodies' motion rigid is not damped."""
    mech = load_mechanism(MODELS / "sixbar.toml")
    model = ErlsModel(mech, form=form)
    cfg = model.configuration(mech.q_ref)
    C = model.damping(cfg)
    nq = model.nq
    scale = np.abs(C).max()
    assert np.abs(C[:, :nq]).max() <= 1e-12 * scale
    if form != "lagrange":
        return
    rng = np.random.default_rng(3)
    ud = rng.standard_normal(model.ne)
    S, T, M_N = cfg.pose.S, model.T, cfg.M_N
    a, *_ = np.linalg.lstsq(np.linalg.cholesky(M_N).T @ S, -np.linalg.cholesky(M_N).T @ (T @ ud), rcond=None)
    b = S @ a + T @ ud
    assert ud @ model.elastic_mass(cfg) @ ud == pytest.approx(b @ M_N @ b, rel=1e-9)
    # the rigid part alone: T u' = S a0 is not representable (W has full rank); a u' whose field is nearly the
    # rigid motion S a0 has a small M_e energy against its M_uu energy
    a0 = rng.standard_normal(nq)
    ud0 = np.linalg.lstsq(T, S @ a0, rcond=None)[0]
    ratio = (ud0 @ model.elastic_mass(cfg) @ ud0) / (ud0 @ (T.T @ M_N @ T) @ ud0)
    assert ratio < 0.5


def test_net_forces_apply_the_damping_matrix():
    """The Lagrange form's damping in net_forces (matrix-vector products) equals C v from damping()."""
    mech = load_mechanism(MODELS / "serial_arm.toml")
    model = ErlsModel(mech)
    cfg = model.configuration(mech.q_ref)
    rng = np.random.default_rng(0)
    x = np.concatenate([mech.q_ref, 1e-4 * rng.standard_normal(model.ne)])
    v = rng.standard_normal(model.n)
    tau = np.zeros(len(mech.motors))
    undamped = mech.replace(damping=type(mech.damping)(0.0, 0.0))
    m0 = ErlsModel(undamped)
    diff = m0.net_forces(m0.configuration(mech.q_ref), x, v, tau) - model.net_forces(cfg, x, v, tau)
    np.testing.assert_allclose(diff, model.damping(cfg, x) @ v, rtol=1e-9, atol=1e-12 * np.abs(diff).max())


# ------------------------------------------------------------------ the Exudyn truth
exudyn_missing = False
try:
    from exuflex.groundtruth import build_truth, modal_damping
    from exuflex.groundtruth.builder import _exu

    _exu()
except ImportError:  # pragma: no cover
    exudyn_missing = True

needs_exudyn = pytest.mark.skipif(exudyn_missing, reason="exudyn is not installed")


@needs_exudyn
@pytest.mark.parametrize("which", ["sixbar", "fourbar", "slider_crank", "fresh"])
def test_truth_free_modes_have_the_rayleigh_ratio(which, fresh_arm):
    """Exudyn's linearised system (M, K, D of ComputeLinearizedSystem, projected on the constraints): each
    damped mode below 180 Hz has the formula's ratio at its own frequency (seen exact to 1e-6)."""
    mech = load_mechanism(fresh_arm if which == "fresh" else MODELS / f"{which}.toml")
    f, zeta = modal_damping(mech, elements_per_link=4, fmax=FMAX)
    assert len(f) >= 1
    np.testing.assert_allclose(zeta, _rayleigh(mech, f), rtol=1e-4)


@needs_exudyn
def test_truth_damper_leaves_rigid_motion_alone(fresh_arm):
    """D R = 0 for the truth's rigid mechanism motions R, which are the null space of its linearised stiffness
    within its constraints (Exudyn's K and constraint null space): n_q of them, strain-free."""
    mech = load_mechanism(fresh_arm)
    tm = build_truth(mech, elements_per_link=4, explicit_damping=False)
    c = tm.coordinates()
    R = tm.rigid_motions(c)
    assert R.shape == (tm.n_coordinates, len(mech.coordinates))
    _, K, _, Cq, _ = tm.mbs.ComputeLinearizedSystem(returnConstraintJacobian=True, returnConstraintNullspace=True)
    Cq = np.asarray(Cq)
    assert np.abs(Cq.T @ R).max() <= 1e-9 * np.abs(R).max()  # the rigid motions satisfy all joints
    assert np.abs(np.asarray(K) @ R).max() <= 1e-6 * np.abs(np.asarray(K)).max() * np.abs(R).max()
    np.testing.assert_allclose(tm.D_alpha @ R, 0.0, atol=1e-10 * np.abs(tm.D_alpha).max() * np.abs(R).max())


def test_truth_does_not_read_the_erls_model():
    """The ground-truth package neither imports ErlsModel nor reads its damping (the observer's): the truth's
    damping comes from its own bodies."""
    for path in (ROOT / "exuflex" / "groundtruth").glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and "erls.model" in node.module:
                pytest.fail(f"{path.name} imports {node.module}")
            if isinstance(node, ast.Name | ast.Attribute) and getattr(node, "id", getattr(node, "attr", "")) in (
                    "ErlsModel", "elastic_mass"):
                pytest.fail(f"{path.name} uses {getattr(node, 'id', getattr(node, 'attr', ''))}")


@needs_exudyn
def test_truth_damping_survives_a_broken_erls_model(monkeypatch):
    """With the ERLS model's damping, elastic mass and constructor made to fail, the truth still builds its
    damper and gives the stated ratios."""
    import exuflex.erls.model as erls_model

    def boom(*_a, **_k):
        raise AssertionError("the truth read the ERLS model")

    monkeypatch.setattr(erls_model.ErlsModel, "__init__", boom)
    monkeypatch.setattr(erls_model.ErlsModel, "damping", boom)
    monkeypatch.setattr(erls_model.ErlsModel, "elastic_mass", boom)
    mech = load_mechanism(MODELS / "fourbar.toml")
    f, zeta = modal_damping(mech, elements_per_link=4, fmax=FMAX)
    np.testing.assert_allclose(zeta, _rayleigh(mech, f), rtol=1e-4)


@pytest.mark.parametrize("compiled", [False, True])
def test_reduced_damping_is_the_full_damping_projected(compiled):
    """``C_r = J^T C(H p) J`` with the full-order Lagrange form's damping at the deformed state ``x = H p`` (the
    strain-rate law: rigid rows and columns too), NumPy and compiled paths, on the serial arm away from q*."""
    from exuflex.reduction import CraigBampton, ReducedModel

    mech = load_mechanism(MODELS / "serial_arm.toml")
    model = ErlsModel(mech)
    rm = ReducedModel(CraigBampton(model))
    model.compiled = rm.cb.compiled = rm.compiled = compiled
    try:
        rng = np.random.default_rng(5)
        p = np.concatenate([np.asarray(mech.q_ref) + 0.2, 1e-4 * rng.standard_normal(rm.r - rm.nq)])
        mats, _ = rm.held(p, rng.standard_normal(rm.r))
        expected = mats.J.T @ model.damping(mats.rc.cfg, mats.rc.H @ p) @ mats.J
        np.testing.assert_allclose(mats.Cr, expected, rtol=0, atol=1e-10 * np.abs(expected).max())
    finally:
        model.compiled = rm.cb.compiled = rm.compiled = True


@pytest.mark.parametrize("which", ["serial_arm", "three_link_arm"])
def test_locked_ratios_hold_the_same_constraint_as_locked_frequencies(which):
    """``exuflex modes --locked`` reports frequencies from :func:`modal_analysis` and ratios from
    :func:`damping_ratios`: on models with relative encoders (readings ``q + G u``) both must hold the readings,
    not q (holding q moves the serial arm's locked modes from 11.5 / 21.5 / 91.2 Hz to 14.1 / 19.1 / 145.7 Hz).
    The damped eigenvalues' ``|s|`` meet the undamped frequencies up to the damping's O(zeta^2) coupling."""
    mech = load_mechanism(MODELS / f"{which}.toml")
    model = ErlsModel(mech, geometric=False)
    f0 = modal_analysis(model, locked=True).below(FMAX)
    f, _ = damping_ratios(model, locked=True)
    np.testing.assert_allclose(f[: len(f0)], f0, rtol=1e-4)

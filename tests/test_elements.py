"""Beam element matrices: symmetry, rigid-body null space, positive definiteness, shape functions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from exuflex.erls.elements import GENERATOR, beam_mass, beam_stiffness, hermite_curvature_row, rotation
from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism

MODELS = Path(__file__).resolve().parents[1] / "models"


@st.composite
def props(draw):
    """(EA, EI, L, rho A, angle) of a solid circular rod of realistic material and size."""
    E, rho = draw(st.floats(1e9, 3e11)), draw(st.floats(1e3, 2e4))
    d, L = draw(st.floats(1e-3, 0.1)), draw(st.floats(1e-2, 2.0))
    A, I = np.pi * d**2 / 4, np.pi * d**4 / 64
    return E * A, E * I, L, rho * A, draw(st.floats(-np.pi, np.pi))



def _rigid_modes(L: float, theta: float) -> np.ndarray:
    """Global x, y translations and a small rotation about node 1 of an element at angle theta (6, 3)."""
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros((6, 3))
    R[[0, 3], 0] = 1.0
    R[[1, 4], 1] = 1.0
    R[:, 2] = [0.0, 0.0, 1.0, -L * s, L * c, 1.0]
    return R


@settings(max_examples=60, deadline=None)
@given(props())
def test_element_properties(p):
    EA, EI, L, rhoA, theta = p
    R = rotation(theta)
    K = R @ beam_stiffness(EA, EI, L) @ R.T
    M = R @ beam_mass(rhoA, L) @ R.T
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-12 * np.abs(K).max())
    np.testing.assert_allclose(M, M.T, rtol=0, atol=1e-14 * np.abs(M).max())
    # exactly three rigid in-plane modes: x, y translation and rotation
    Z = _rigid_modes(L, theta)
    assert np.abs(K @ Z).max() <= 1e-9 * np.abs(K).max() * max(1.0, L)
    w = np.linalg.eigvalsh(K)
    tol = 1e-6 * min(EA / L, EI / L**3)  # below the softest deformation mode, above round-off
    assert np.sum(np.abs(w) <= tol) == 3
    assert w.min() >= -tol
    # mass positive definite, and it carries the element's mass in every translation
    assert np.linalg.eigvalsh(M).min() > 0
    for k in (0, 1):
        assert Z[:, k] @ M @ Z[:, k] == pytest.approx(rhoA * L, rel=1e-12)
    # rotation moment of inertia about node 1 of a slender rod: rho A L^3 / 3 (no section rotary inertia)
    assert Z[:, 2] @ M @ Z[:, 2] == pytest.approx(rhoA * L**3 / 3, rel=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.floats(-np.pi, np.pi), st.floats(1e-3, 1e-2))
def test_rotation_generator(theta, h):
    """dR/dtheta = R G (used by the model's rotating-frame terms)."""
    dR = (rotation(theta + h) - rotation(theta - h)) / (2 * h)
    np.testing.assert_allclose(dR, rotation(theta) @ GENERATOR, atol=h**2)
    np.testing.assert_allclose(rotation(theta) @ rotation(theta).T, np.eye(6), atol=1e-14)


@pytest.mark.parametrize("xi", [0.0, 0.25, 0.5, 0.9, 1.0])
def test_curvature_row_is_exact_on_cubics(xi):
    """For v(s) = a + b s + c s^2 + d s^3 the row gives v''(xi L) exactly."""
    L = 0.37
    a, b, c, d = 0.1, -0.3, 0.7, 1.9
    v = lambda s: a + b * s + c * s**2 + d * s**3
    dv = lambda s: b + 2 * c * s + 3 * d * s**2
    dofs = np.array([0.0, v(0), dv(0), 0.0, v(L), dv(L)])
    assert hermite_curvature_row(L, xi) @ dofs == pytest.approx(2 * c + 6 * d * xi * L, rel=1e-12)


def test_static_cantilever_tip_deflection():
    """One cubic element reproduces the exact cantilever tip deflection P L^3 / (3 EI)."""
    EA, EI, L, P = 1e6, 250.0, 0.8, 3.0
    K = beam_stiffness(EA, EI, L)[3:, 3:]
    u = np.linalg.solve(K, [0.0, P, 0.0])
    assert u[1] == pytest.approx(P * L**3 / (3 * EI), rel=1e-12)
    assert u[2] == pytest.approx(P * L**2 / (2 * EI), rel=1e-12)


@pytest.mark.parametrize("name", ["sixbar", "single_link", "fourbar"])
def test_assembled_matrices(name):
    """Assembled M(q) symmetric positive definite; K_uu positive definite (the ERLS removes rigid motion)."""
    model = ErlsModel(load_mechanism(MODELS / f"{name}.toml"))
    cfg = model.configuration(model.mech.q_ref)
    M, K = model.mass(cfg), model.stiffness(cfg)
    np.testing.assert_allclose(M, M.T, atol=1e-12 * np.abs(M).max())
    np.testing.assert_allclose(K, K.T, atol=1e-12 * np.abs(K).max())
    assert np.linalg.eigvalsh(M).min() > 0
    Kuu = K[model.nq :, model.nq :]
    assert np.linalg.eigvalsh(Kuu).min() > 0
    assert not K[: model.nq].any() and not K[:, : model.nq].any()


@pytest.mark.skipif(__import__("exuflex.erls._assembly").erls._assembly.configuration is None,
                    reason="numba is not installed")
def test_compiled_configuration_equals_the_kinematics_path():
    """The configuration in one compiled call (:func:`exuflex.erls._assembly.configuration`: closure, pose
    sensitivities, nodal matrices, W) equals the reference path (the NumPy kinematics and assembly) along the
    six-bar's 3 s manoeuvre (true states of ``tests/data/sixbar_erls_3s``, every 50th sample, warm-started from
    the previous one as in the observer), and leaves the same warm start behind."""
    from exuflex.runs import read_run

    mech = load_mechanism(MODELS / "sixbar.toml")
    truth = read_run(Path(__file__).resolve().parent / "data" / "sixbar_erls_3s").truth
    Q = truth.select(list(mech.coordinate_names)).data[::50]
    fast, ref = ErlsModel(mech), ErlsModel(mech)
    ref.compiled = ref.kin.compiled = False
    for q in Q:
        a, b = fast.configuration(q), ref.configuration(q)
        for x, y in [(a.pose.z, b.pose.z), (a.pose.Sz, b.pose.Sz), (a.pose.r, b.pose.r), (a.pose.S, b.pose.S),
                     (a.pose.Jinv, b.pose.Jinv), (a.R, b.R), (a.M_N, b.M_N), (a.K_N, b.K_N), (a.W, b.W)]:
            assert x.shape == y.shape
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * np.abs(y).max())
        assert a.pose.cond == pytest.approx(b.pose.cond, rel=1e-9)
        np.testing.assert_allclose(fast.kin._last[1], ref.kin._last[1], rtol=0, atol=1e-12)

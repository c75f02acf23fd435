"""The full-order model's two forms of the velocity forces (:mod:`exuflex.erls.model`): eq. 2 as written and the
energy-consistent Lagrange form, against the analytic centrifugal load, their structure and finite differences."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.model import FORMS, ErlsModel
from exuflex.mechanism import load_mechanism, refine_mechanism
from exuflex.reduction import CraigBampton, ReducedModel

MODELS = Path(__file__).resolve().parents[1] / "models"


def _centrifugal_load(m: ErlsModel, theta: float, omega: float) -> np.ndarray:
    """Consistent nodal load (N,) of the centrifugal force ``rhoA omega^2 s`` (and ``m omega^2 s`` of the lumped
    masses) on a single link spinning at ``omega`` about its hub (station 0) at angle ``theta``: per element
    ``[a, a + L]`` the linear axial shape functions give ``rhoA omega^2 L (a/2 + L/6, a/2 + L/3)``."""
    lk = m.mech.links[0]
    rhoA = lk.material.rho * lk.section.A
    axis = np.array([np.cos(theta), np.sin(theta)])
    nodes = list(m.mech.node_ids)
    f = np.zeros(m.N)
    for a in range(lk.n_elements):
        s0, L = lk.stations[a], lk.stations[a + 1] - lk.stations[a]
        na, nb = nodes.index(lk.node_ids[a]), nodes.index(lk.node_ids[a + 1])
        f[3 * na : 3 * na + 2] += rhoA * omega**2 * L * (s0 / 2 + L / 6) * axis
        f[3 * nb : 3 * nb + 2] += rhoA * omega**2 * L * (s0 / 2 + L / 3) * axis
    for lm in m.mech.all_masses():
        i = nodes.index(lm.node)
        f[3 * i : 3 * i + 2] += lm.mass * omega**2 * m.mech.node_location(lm.node)[1] * axis
    return f


def _spinning_residual(form: str, factor: int, theta=0.4, omega=3.0) -> tuple[np.ndarray, np.ndarray]:
    """The elastic rows' inertia force of a rigid, uniformly spinning single link (``q'' = 0``, ``u = u' = 0``,
    so it is ``h_u``) plus the analytic centrifugal load, and that load's elastic rows."""
    m = ErlsModel(refine_mechanism(load_mechanism(MODELS / "single_link.toml"), factor), form=form)
    cfg = m.configuration(np.array([theta]))
    x, v = np.zeros(m.n), np.zeros(m.n)
    x[0], v[0] = theta, omega
    load = m.T.T @ _centrifugal_load(m, theta, omega)
    return m.velocity_forces(cfg, x, v)[m.nq :] + load, load


def test_eq2_elastic_rows_carry_exactly_the_centrifugal_load():
    for factor in (1, 4):
        res, load = _spinning_residual("eq2", factor)
        assert np.abs(res).max() < 1e-12 * np.abs(load).max()


def test_lagrange_form_departs_from_the_centrifugal_load_as_h_squared():
    """``"lagrange"`` adds ``T^T M_N' S q'`` (zero for eq. 2): 0.4 % of the largest nodal load at 4 elements, and
    the fitted log-log slope of its largest entry against the element length is 2."""
    n_el, err = [], []
    for factor in (1, 2, 4, 8):
        res, load = _spinning_residual("lagrange", factor)
        n_el.append(4 * factor)
        err.append(np.abs(res).max())
        if factor == 1:
            assert 1e-3 < err[-1] / np.abs(load).max() < 1e-2
    slope = np.polyfit(np.log(1.0 / np.array(n_el)), np.log(err), 1)[0]
    assert 1.9 < slope < 2.1


@pytest.fixture(scope="module")
def sixbar_state():
    mech = load_mechanism(MODELS / "sixbar.toml")
    rng = np.random.default_rng(11)
    models = {form: ErlsModel(mech, form=form) for form in FORMS}
    m = models["lagrange"]
    q = np.array(mech.q_ref) + 0.2 * rng.standard_normal(m.nq)
    x = np.r_[q, 1e-4 * rng.standard_normal(m.ne)]
    v = np.r_[rng.standard_normal(m.nq), 1e-2 * rng.standard_normal(m.ne)]
    return models, x, v


def test_coriolis_matrix_structure(sixbar_state):
    """Eq. 2's ``M_G`` annihilates rigid velocity fields (``M_G S = 0``) and is not symmetric; the damping's q rows
    hold only its mass-proportional part (``S^T K_N = 0``)."""
    models, x, v = sixbar_state
    m = models["eq2"]
    cfg = m.configuration(x[: m.nq])
    MG = m.coriolis_matrix(cfg, v[: m.nq])
    assert np.abs(MG @ cfg.pose.S).max() < 1e-12 * np.abs(MG).max()
    assert np.abs(MG - MG.T).max() > 0.1 * np.abs(MG).max()
    assert np.abs(cfg.pose.S.T @ cfg.K_N).max() < 1e-9 * np.abs(cfg.K_N).max()
    C = m.damping(cfg)
    Tud = m.T @ v[m.nq :]
    np.testing.assert_allclose(C @ v, cfg.W.T @ (m.alpha * cfg.M_N @ Tud + m.beta * cfg.K_N @ Tud), atol=1e-12)


def test_forms_agree_on_rigid_motion(sixbar_state):
    """With ``u = u' = 0`` the q rows of both forms are the rigid mechanism's Coriolis and centrifugal forces."""
    models, x, v = sixbar_state
    xr, vr = x.copy(), v.copy()
    xr[3:], vr[3:] = 0.0, 0.0
    h = [m.velocity_forces(m.configuration(xr[:3]), xr, vr)[:3] for m in models.values()]
    np.testing.assert_allclose(h[1], h[0], rtol=1e-10, atol=1e-12 * np.abs(h[0]).max())


@pytest.mark.parametrize("form", FORMS)
def test_velocity_force_jacobian_matches_finite_differences(sixbar_state, form):
    models, x, v = sixbar_state
    m = models[form]
    cfg = m.configuration(x[: m.nq])
    J = m.velocity_force_jacobian(cfg, x, v)
    fd = np.empty_like(J)
    for k in range(m.n):
        d = 1e-6 * max(1.0, abs(v[k]))
        e = np.zeros(m.n)
        e[k] = d
        fd[:, k] = (m.velocity_forces(cfg, x, v + e) - m.velocity_forces(cfg, x, v - e)) / (2 * d)
    assert np.abs(J - fd).max() < 1e-6 * np.abs(fd).max()


def test_form_errors(sixbar_state):
    models, _, _ = sixbar_state
    with pytest.raises(ValueError, match="form must be one of"):
        ErlsModel(models["eq2"].mech, form="paper")
    with pytest.raises(ValueError, match="form must be 'lagrange'"):
        ReducedModel(CraigBampton(models["eq2"]))

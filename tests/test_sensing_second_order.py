"""The links' foreshortening, the second order of the link points' positions in the elastic displacements
(:class:`exuflex.erls.sensing.SecondOrderPlan`): against the cubic deflection of a cantilever (closed form), the
geometrically exact Exudyn cantilever (static), the closure re-solved with shortened links, and differences of
its own maps entry by entry."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.kinematics import Kinematics
from exuflex.erls.model import ErlsModel
from exuflex.erls.sensing import SecondOrderPlan
from exuflex.mechanism import load_mechanism

ROOT = Path(__file__).resolve().parents[1]
LOOPS = ["models/fourbar.toml", "models/sixbar.toml", "models/slider_crank.toml", "models/fivebar.toml",
         "models/l_arm.toml", "benchmarks/models/upright_two_link.toml"]


def _points(mech):
    """Every link's end, and a station inside an element of each (a partial element's integral)."""
    return [(lk.name, lk.length) for lk in mech.links] + [(lk.name, 0.37 * lk.length) for lk in mech.links]


@pytest.fixture(scope="module", params=LOOPS)
def model(request):
    return ErlsModel(load_mechanism(ROOT / request.param))


@pytest.mark.parametrize("theta", [0.0, 0.7])
def test_cantilever_under_a_tip_load_shortens_by_the_cubic_s_slope_squared(theta):
    """The single link clamped at its hub (q held) under a static tip load P across it: the ERLS deflection is the
    cubic ``v = P x^2 (3 L - x) / (6 EI)`` (exact in Hermite elements), and ``int_0^x v'^2 / 2`` is
    ``(P / 2 EI)^2 (4 L^2 x^3 / 3 - L x^4 + x^5 / 5) / 2``: ``P^2 L^5 / (15 EI^2)`` at the tip, along the link's axis
    toward its hub; at 0.3 L (inside an element) the same formula."""
    mech = load_mechanism(ROOT / "models/single_link.toml")
    m = ErlsModel(mech)
    cfg = m.configuration(np.array([theta]))
    lk = mech.link("arm")
    L, EI, P = lk.length, lk.material.E * lk.section.I, 5.0
    t, n = np.array([math.cos(theta), math.sin(theta)]), np.array([-math.sin(theta), math.cos(theta)])
    tip = list(mech.node_ids).index(mech.node_at("arm", L))
    f = np.zeros(m.N)
    f[3 * tip : 3 * tip + 2] = P * n
    u = np.linalg.solve(m.T.T @ cfg.K_N @ m.T, m.T.T @ f)
    assert (m.point_displacement_rows(cfg, "arm", L) @ u) @ n == pytest.approx(P * L**3 / (3 * EI), rel=1e-12)
    w = SecondOrderPlan(m, [("arm", L), ("arm", 0.3 * L)]).at(cfg.pose).values(u)
    for k, x in enumerate((L, 0.3 * L)):
        want = (P / (2 * EI)) ** 2 * (4 * L**2 * x**3 / 3 - L * x**4 + x**5 / 5) / 2
        np.testing.assert_allclose(w[k, :2], -want * t, rtol=1e-10, atol=1e-12 * want)
        assert w[k, 2] == 0.0  # the link's angle is its coordinate's: held
    assert w[0, :2] @ -t == pytest.approx(P**2 * L**5 / (15 * EI**2), rel=1e-10)


def test_jacobian_entry_by_entry(model):
    """``dw/du = 2 C diag(G u) G`` against central differences of ``w``, every entry against its own scale."""
    rng = np.random.default_rng(3)
    mech = model.mech
    so = SecondOrderPlan(model, _points(mech)).at(model.kin.pose(np.array(mech.q_ref, float)))
    u = rng.normal(0, 1e-3, model.ne)
    J = so.jacobian(u)
    h = 1e-6
    fd = np.stack([(so.values(u + h * e) - so.values(u - h * e)) / (2 * h) for e in np.eye(model.ne)], axis=-1)
    # w is quadratic: central differences are exact up to rounding (of w's scale over h)
    tol = 1e-7 * np.abs(J) + 1e-10 * np.abs(J).max()
    assert np.all(np.abs(J - fd) <= tol)


def _shortened_kinematics(mech, plan: SecondOrderPlan, sigma: np.ndarray) -> Kinematics:
    """The mechanism's closure with every joint station ``s`` of a link moved back to ``s - sigma(s)``."""
    kin = Kinematics(mech)
    at = {st: i for i, st in enumerate(plan.stations)}
    kin._pos_eqs = [(a, sa - sigma[at[(a, float(sa))]], b, sb - sigma[at[(b, float(sb))]] if b >= 0 else sb, g)
                    for a, sa, b, sb, g in kin._pos_eqs]
    kin._sc_eqs = [(e[0], e[1] - sigma[at[(e[0], float(e[1]))]] if e[1] != 0.0 else e[1], *e[2:]) for e in kin._sc_eqs]
    kin._vectorise()
    return kin


def test_closure_with_the_shortened_links(model):
    """An independent route to the links' rigid motion of second order: re-solve the closure (Newton, the
    nonlinear equations) at the same q with every joint station moved back by ``eps sigma`` (``sigma`` the links'
    ``int v'^2 / 2`` up to it at a random u), and place the points at their stations shortened the same way; the
    points' motion over ``eps`` is ``w(u)`` to ``O(eps)``: with ``eps sigma`` up to 10 um, every entry within
    2e-3 of its own size, and the error halves with ``eps`` (first order: the differences', not the formula's; on
    an open chain the points' motion is linear in the stations' and the differences exact)."""
    rng = np.random.default_rng(0)
    mech = model.mech
    q = np.array(mech.q_ref, float)
    pose = model.kin.pose(q)
    pts = _points(mech)
    plan = SecondOrderPlan(model, pts)
    so = plan.at(pose)
    u = rng.normal(0, 1e-3, model.ne)
    g = so.G @ u
    sigma = plan.Sigma @ (g * g)
    w = so.values(u)
    li = {lk.name: i for i, lk in enumerate(mech.links)}
    errs = []
    eps0 = 1e-5 / np.abs(sigma).max()
    for eps in (eps0, eps0 / 2):
        kin = _shortened_kinematics(mech, plan, eps * sigma)
        z = kin.solve(q, pose.z)
        err = []
        for k, (name, x) in enumerate(pts):
            i = li[name]
            x2 = x - eps * sigma[plan._point_sid[k]]
            th, th0 = z[3 * i + 2], pose.z[3 * i + 2]
            moved = np.r_[z[3 * i : 3 * i + 2] + x2 * np.array([math.cos(th), math.sin(th)])
                          - pose.z[3 * i : 3 * i + 2] - x * np.array([math.cos(th0), math.sin(th0)]), th - th0] / eps
            scale = np.maximum(np.abs(w[k]), 1e-6 * np.abs(w[k]).max())  # (a structural zero: rounding)
            err.append(np.abs(moved - w[k]) / scale)
        errs.append(np.max(err))
    assert errs[0] < 2e-3
    assert errs[1] < 0.6 * errs[0] or errs[0] < 1e-8


def test_rates_are_time_derivatives(model):
    """``dw/dt`` (the maps' change along q' included) against central differences in time along (q', u'),
    entry by entry."""
    rng = np.random.default_rng(1)
    mech = model.mech
    q, qd = np.array(mech.q_ref, float), rng.normal(0, 1.0, model.nq)
    u, ud = rng.normal(0, 1e-3, model.ne), rng.normal(0, 1e-2, model.ne)
    plan = SecondOrderPlan(model, _points(mech))
    r = plan.at(model.kin.pose(q), qd).rates(u, ud)
    h = 1e-6
    fd = (plan.at(model.kin.pose(q + h * qd)).values(u + h * ud)
          - plan.at(model.kin.pose(q - h * qd)).values(u - h * ud)) / (2 * h)
    assert np.all(np.abs(r - fd) <= 1e-6 * np.abs(r) + 1e-9 * np.abs(r).max())


@pytest.mark.parametrize("theta, tip_mass", [(0.0, 0.3), (-0.4, 1.0)])
def test_exudyn_cantilever_tip_moves_back_by_the_shortening(theta, tip_mass):
    """The geometrically exact Exudyn cantilever (ANCF, static, under its weight and a tip mass, the hub clamped)
    against the ERLS model's linear static sag: the tip's displacement along the link is the linear stretch plus
    the second order ``w`` to 1e-3 of ``w`` (the linear map alone misses all of it), across it the linear sag."""
    pytest.importorskip("exudyn")
    from test_gravity import L, _cantilever, _clamped_static_tip

    from exuflex.erls.validity import weight_sag

    mech = _cantilever(theta, {"mass": tip_mass})
    t = np.array([math.cos(theta), math.sin(theta)])
    exact = _clamped_static_tip(mech, theta, elements_per_link=8)
    m = ErlsModel(mech)
    cfg = m.configuration(np.array([theta]))
    u, _ = weight_sag(m, cfg)
    lin = m.point_displacement_rows(cfg, "arm", L) @ u
    w = SecondOrderPlan(m, [("arm", L)]).at(cfg.pose).values(u)[0, :2]
    assert abs(w @ t) > 5e-6 and abs(w @ t) > 10 * abs(lin @ t)
    assert abs((lin + w) @ t - exact @ t) < 1e-3 * abs(w @ t)

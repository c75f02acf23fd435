"""The P-delta effect: the geometric stiffness of the links' axial loads in the ERLS elastic rows
(:meth:`exuflex.erls.model.ErlsModel.geometric_stiffness`), and what a model without it leaves out
(:mod:`exuflex.erls.validity`).

Oracles: the beam-column's first-order correction of a cantilever (a tip load across it and the axial load ``P``
along it: the root moment ``F L + P delta_tip``, ``delta_tip = F L^3 / (3 EI)``, so the root curvature grows by the
fraction ``P L^2 / (3 EI)``) and its exact solution (root curvature ``F tan(kL) / (k EI)``, ``k^2 = P / EI``;
``tanh`` in tension); the lateral stiffness of a cantilever under a fixed-direction axial load at its tip, ``P k /
(tan(kL) - kL)`` (compression; ``P k / (kL - tanh(kL))`` in tension), which sets the first frequency of a light
column carrying a tip mass, standing and hanging; the axial force of a spinning link (``rho A Omega^2 (L^2 - s^2) /
2 + m Omega^2 L``) and of a column under its weight; the work of the axial forces ``sum_e N_e int v'^2 / 2`` by
Gauss quadrature of the Hermite field, differentiated entry by entry; the ERLS coordinate rows' strain-energy
term, which equals the P-delta forces' coordinate share (the rows already hold it).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.elements import beam_geometric_stiffness
from exuflex.erls.model import ErlsModel
from exuflex.erls.validity import (
    PDELTA_DEPART_SD,
    pdelta_forces,
    weight_pdelta,
    weight_sag,
    weight_warnings,
)
from exuflex.mechanism import load_mechanism
from exuflex.mechanism.loader import parse_mechanism

ROOT = Path(__file__).resolve().parents[1]
G, E, D, L = 9.81, 69.0e9, 0.01, 0.5
EI = E * math.pi * D**4 / 64


def _column(phi: float, tip_mass: float, n_elements: int = 8, rho: float = 30.0):
    """A fresh one-link column: a light rod (30 kg/m^3: its weight some 3e-4 of the tip's) clamped at its hub, pointing up at ``phi`` rad
    from the vertical, a tip mass, a root curvature gauge (noise 1e-5)."""
    theta = math.pi / 2 - phi
    doc = {
        "model": {"name": "column", "q_ref": [theta], "gravity": [0.0, -G]},
        "materials": [{"name": "al", "E": E, "rho": rho}],
        "links": [{"name": "rod", "length": L, "material": "al", "diameter": D, "n_elements": n_elements,
                   "angle_guess": theta}],
        "joints": [{"name": "hub", "points": [{"link": "rod", "station": 0.0}], "ground": [0.0, 0.0]}],
        "coordinates": [{"name": "q1", "link": "rod", "joint": "hub"}],
        "motors": [{"name": "T1", "joint": "hub", "link": "rod", "noise_std": 0.01}],
        "payload": {"link": "rod", "station": L, "mass": tip_mass},
        "sensors": [{"name": "c_root", "kind": "curvature", "link": "rod", "station": 0.0, "noise_std": 1e-5}],
    }
    return parse_mechanism(doc, "<pdelta test>"), theta


def test_geometric_stiffness_annihilates_translation_and_gives_the_tilt_couple():
    """``K_G`` of an axial force: no force on a rigid translation; a rigid tilt ``th`` (``v = th x``) gets the couple
    ``N th L`` (lateral forces ``-N th``, ``+N th`` at the ends); symmetric."""
    N, Le, th = 3.0, 0.2, 1e-3
    K = beam_geometric_stiffness(N, Le)
    assert np.allclose(K, K.T)
    assert np.allclose(K @ np.array([0.0, 1.0, 0.0, 0.0, 1.0, 0.0]), 0.0)
    f = K @ np.array([0.0, 0.0, th, 0.0, th * Le, th])
    assert f[1] == pytest.approx(-N * th) and f[4] == pytest.approx(N * th)
    assert np.allclose(f[[0, 2, 3, 5]], 0.0, atol=1e-15)


@pytest.mark.parametrize("phi, tip_mass", [(0.1, 2.0), (0.3, 5.0), (-0.2, 3.0)])
def test_pdelta_reading_of_a_column_is_the_beam_column_correction(phi, tip_mass):
    """The column under its tip weight: the linear sag's root curvature is ``F L / EI`` (``F`` the weight across
    the rod), and the P-delta response adds the fraction ``P L^2 / (3 EI)`` (``P`` the weight along it, in
    compression): within 0.5 % on 8 elements, converging at the order 2 in the element length (the successive
    differences on 8, 16, 32 elements shrink fourfold) to within 5e-4 of it (the light rod's own weight)."""
    errs = []
    for n in (8, 16, 32):
        mech, theta = _column(phi, tip_mass, n)
        model = ErlsModel(mech, geometric=False)
        cfg = model.configuration(np.array([theta]))
        u, _ = weight_sag(model, cfg)
        F, P = tip_mass * G * math.sin(phi), tip_mass * G * math.cos(phi)
        c0 = model.curvature_row(cfg, "rod", 0.0) @ u
        assert abs(c0) == pytest.approx(abs(F) * L / EI, rel=1e-3)  # cubic elements: exact under a tip load
        (reading, channel, compression), = weight_pdelta(model, [theta]).values()
        assert channel == "c_root" and compression == pytest.approx(P, rel=1e-3)
        errs.append(reading * 1e-5 / abs(c0) / (P * L**2 / (3 * EI)) - 1)
    assert abs(errs[0]) < 0.005
    ratio = (errs[0] - errs[1]) / (errs[1] - errs[2])
    assert 3.5 < ratio < 4.5
    assert abs(errs[2] - (errs[1] - errs[2]) / 3) < 5e-4  # Richardson's extrapolation


@pytest.mark.parametrize("q", [[-0.3, 1.8], [0.1, 1.45], [0.5, 1.1]])
def test_erls_coordinate_rows_already_hold_the_pdelta_share(q):
    """At the static sag of the vertical serial arm the ERLS coordinate rows' strain-energy term (``h_q`` at rest:
    ``d/dq`` of ``u^T K(q) u / 2``, the links' rotated stiffness) equals minus the P-delta forces' coordinate
    share ``S^T f``: the coordinate rows have the effect, the elastic rows (``T^T f``) have not."""
    mech = load_mechanism(ROOT / "benchmarks" / "models" / "vertical_serial_arm.toml")
    model = ErlsModel(mech, geometric=False)
    cfg = model.configuration(np.array(q))
    u, _ = weight_sag(model, cfg)
    f, _ = pdelta_forces(model, cfg, model.T @ u, np.flatnonzero(model.el_len > 0))
    h = model.velocity_forces(cfg, np.concatenate([q, u]), np.zeros(model.n))[: model.nq]
    share = cfg.pose.S.T @ f
    # N m: the shoulder's a few tenths of the motors' torque noise; the elbow's (its relative coordinate's frame the
    # forearm's own tangent) 4e-5 to 1.3e-4, checked against its own size all the same
    assert np.abs(share).max() > 1e-3 and np.abs(share).min() > 1e-5
    assert np.allclose(h, -share, rtol=1e-3, atol=0)


def test_vertical_serial_arm_warns_naming_the_upper_arm_and_its_gauge(caplog):
    """Without the geometric stiffness, along the planned manoeuvre the upper arm (8.9 N of compression under the
    weight) reads 0.30 noise sd in its gauge: ``approaching``, from the start; the forearm (3 N of its payload's
    weight along it), whose ERLS frame is its own tangent at the elbow (its relative coordinate: the upper arm's
    elastic rotation there is no part of the forearm's elastic field, on which the geometric stiffness acts;
    docs/long_arms.md), reads below the warnings' 0.1 sd; the models without gravity (the gallery's serial arm) and
    the vertical four-bar (below 0.002 sd) give none, nor does the model with it (the default)."""
    from exuflex.manoeuvre import plan

    mech = load_mechanism(ROOT / "benchmarks" / "models" / "vertical_serial_arm.toml")
    p = plan(mech, dt=1e-2, t_end=mech.manoeuvre.duration)
    assert weight_warnings(mech, p.t, p.q) == []
    with caplog.at_level(logging.WARNING, logger="exuflex.erls.validity"):
        ws = weight_warnings(mech, p.t, p.q, geometric=False)
    assert [w.link for w in ws] == ["upper"]
    (upper,) = ws
    assert upper.level == "approaching" and upper.channel == "c_upper" and upper.time_s == 0.0
    assert 0.25 < upper.peak_reading_sd < PDELTA_DEPART_SD
    assert upper.compression_n == pytest.approx(8.9, abs=0.1)
    assert any("'upper'" in r.getMessage() and "c_upper" in r.getMessage() for r in caplog.records)
    for other in ("models/serial_arm.toml", "benchmarks/models/vertical_fourbar.toml"):
        m = load_mechanism(ROOT / other)
        p = plan(m, dt=1e-2, t_end=m.manoeuvre.duration)
        assert weight_warnings(m, p.t, p.q, geometric=False) == []


def _hermite_slope(L: float, xi: float) -> np.ndarray:
    """d v / dx of the cubic Hermite field on ``(v1, th1, v2, th2)`` at ``x = xi L`` (written out here, not the
    element's matrices)."""
    return np.array([(-6 * xi + 6 * xi**2) / L, 1 - 4 * xi + 3 * xi**2, (6 * xi - 6 * xi**2) / L,
                     -2 * xi + 3 * xi**2])


def _axial_work(model, cfg, N: np.ndarray, u: np.ndarray) -> float:
    """``sum_e N_e int_0^L v'^2 / 2 dx`` over the beam elements, ``v`` the lateral field in each element's frame,
    by 3-point Gauss quadrature (exact for the quadratic ``v'^2``)."""
    d = model.T @ u
    xg, wg = np.polynomial.legendre.leggauss(3)
    total = 0.0
    for e in np.flatnonzero(model.el_len > 0):
        L = model.el_len[e]
        dl = cfg.R[e].T @ d[model.el_dofs[e]]
        lat = dl[[1, 2, 4, 5]]
        total += N[e] * sum(w * 0.5 * (_hermite_slope(L, (x + 1) / 2) @ lat) ** 2 * L / 2 for x, w in zip(xg, wg))
    return total


@pytest.mark.parametrize("model_file, q", [("benchmarks/models/vertical_serial_arm.toml", [0.3, 1.3]),
                                           ("models/fourbar.toml", None)])
def test_geometric_forces_are_the_gradient_of_the_axial_forces_work(model_file, q):
    """``-T^T K_G(N) T u`` is minus the gradient in ``u`` of the axial forces' work across the lateral field
    (Gauss quadrature of the Hermite slopes), central differences entry by entry against each entry's own
    scale; ``K_G`` is symmetric."""
    mech = load_mechanism(ROOT / model_file)
    model = ErlsModel(mech)
    cfg = model.configuration(np.array(mech.q_ref if q is None else q, float))
    rng = np.random.default_rng(3)
    N = rng.standard_normal(model.n_el) * 10.0 * (model.el_len > 0)
    u = 1e-3 * rng.standard_normal(model.ne)
    f = model.geometric_forces(cfg, N, u)
    h = 1e-6
    fd = np.array([-(_axial_work(model, cfg, N, u + h * e) - _axial_work(model, cfg, N, u - h * e)) / (2 * h)
                   for e in np.eye(model.ne)])
    scale = np.abs(model.T.T @ np.abs(model.geometric_stiffness(cfg, np.abs(N))) @ model.T @ np.abs(u))
    assert np.all(np.abs(f - fd) <= 1e-6 * scale + 1e-12)
    KG = model.T.T @ model.geometric_stiffness(cfg, N) @ model.T
    assert np.allclose(KG, KG.T) and np.allclose(-KG @ u, f, rtol=1e-12, atol=1e-15)


def _column_frequency(model, theta: float) -> float:
    """The first frequency (rad/s) of the column's elastic rows with its coordinate held (undamped)."""
    import scipy.linalg as sla

    cfg = model.configuration(np.array([theta]))
    J = model.prescribed_jacobian(np.r_[theta, np.zeros(model.ne)], np.zeros(model.n), cfg)
    K = -J[:, : model.ne]
    return float(np.sqrt(np.min(np.real(sla.eigvals(K)))))


@pytest.mark.parametrize("phi", [0.1, -0.2, math.pi - 0.3])
def test_column_first_frequency_follows_its_axial_load(phi):
    """A light column (its rod 1e-3 of the tip mass) clamped at its hub, a 2 kg tip mass, pointing up at ``phi``
    from the vertical (standing: compression) or hanging (``pi - 0.3``: tension): the first frequency with the
    geometric stiffness against the exact lateral stiffness of a cantilever under its tip's fixed-direction axial
    load, ``w^2 / w0^2 = k(P) / (3 EI / L^3)`` (some ``1 -/+ 0.4 P L^2 / EI``; the buckling law ``1 - P / P_cr``
    to first order), within 3e-3 on 16 elements, where the model without it stays at ``w0`` (within 3e-3); and
    the static root curvature against the beam-column's exact ``F tan(kL) / (k EI)`` within 1e-3."""
    tip = 2.0
    mech, theta = _column(phi, tip, 16)
    P = tip * G * math.cos(phi)  # compression positive
    F = tip * G * math.sin(phi)
    k = math.sqrt(abs(P) / EI)
    if P > 0:
        k_lat = P * k / (math.tan(k * L) - k * L)
        c_exact = F * math.tan(k * L) / (k * EI)
    else:
        k_lat = -P * k / (k * L - math.tanh(k * L))
        c_exact = F * math.tanh(k * L) / (k * EI)
    ratio = k_lat / (3 * EI / L**3)
    assert abs(ratio - 1) > 0.03  # the effect is well above the tolerance
    w0 = _column_frequency(ErlsModel(mech, geometric=False), theta)
    w = _column_frequency(ErlsModel(mech), theta)
    assert w0**2 == pytest.approx(3 * EI / L**3 / tip, rel=3e-3)
    assert (w / w0) ** 2 == pytest.approx(ratio, rel=3e-3)
    model = ErlsModel(mech)
    cfg = model.configuration(np.array([theta]))
    u, _ = weight_sag(model, cfg)
    assert abs(model.curvature_row(cfg, "rod", 0.0) @ u) == pytest.approx(abs(c_exact), rel=1e-3)


def test_axial_forces_of_a_spinning_link_and_a_column_under_its_weight():
    """The rigid motion's axial forces (:meth:`ErlsModel.rigid_loads`, :meth:`ErlsModel.axial_forces`): a heavy
    rod (aluminium) with a tip mass spinning at ``Omega`` without gravity carries ``N(s) = rho A Omega^2 (L^2 -
    s^2) / 2 + m Omega^2 L``, and each element the mean of it over its length (linear axial elements are exact at
    the nodes under consistent loads); standing still under gravity, ``-(m + rho A (L - s)) g cos(phi)``."""
    tip, Om, phi = 2.0, 3.0, 0.2
    mech, theta = _column(phi, tip, 8, rho=2700.0)
    rhoA = 2700.0 * math.pi * D**2 / 4
    model = ErlsModel(mech)
    cfg = model.configuration(np.array([theta]))
    beams = np.flatnonzero(model.el_len > 0)
    a, b = model.el_station[beams], model.el_station[beams] + model.el_len[beams]
    g_only = model.axial_forces(cfg, model.rigid_loads(cfg))[beams]
    exact_g = -(tip + rhoA * (L - (a + b) / 2)) * G * math.cos(phi)
    np.testing.assert_allclose(g_only, exact_g, rtol=1e-9)
    np.testing.assert_allclose(cfg.N_static[beams], exact_g, rtol=1e-9)
    spin = model.axial_forces(cfg, model.rigid_loads(cfg, np.array([Om]), np.zeros(1))) - model.axial_forces(
        cfg, model.rigid_loads(cfg, None, np.zeros(1)))
    mean = rhoA * Om**2 / 2 * (L**2 - (b**3 - a**3) / (3 * (b - a))) + tip * Om**2 * L
    np.testing.assert_allclose(spin[beams], mean, rtol=1e-9)
    # held by the torques that keep the rate: the weight's and the spin's
    np.testing.assert_allclose(model.rigid_axial_forces(cfg, np.array([Om]))[beams], mean + exact_g, rtol=1e-9)


@pytest.mark.parametrize("phi", [0.1, math.pi - 0.3])
def test_reduced_model_holds_the_static_geometric_stiffness(phi):
    """The reduced model's ``K_r`` holds the static axial loads' geometric stiffness
    (:meth:`~exuflex.reduction.model.ReducedModel.geometric_stiffness`): ``K_r``'s elastic block equals ``H_u^T (K_uu
    + T^T K_G T) H_u``, the full model's elastic stiffness reduced, entry by entry; the column's reduced static sag
    (its elastic rows, ``K_r p = f_g``; one master at the tip, no interior mode) gives the beam-column's exact tip
    deflection ``F (tan(kL) - kL) / (P k)`` (``F (kL - tanh(kL)) / (|P| k)`` hanging) within 5e-4 (the rod's own
    weight, 6e-4 of the tip's, is left out of the formula), 5 % above the
    linear one standing and 3 % below it hanging, and the model without it the linear ``F L^3 / (3 EI)``. The
    root curvature is the basis's: the linear elastic link's Guyan shape, within 1.5 % of the exact (its static
    truncation, which the static corrections take up where the gauges need it)."""
    from exuflex.reduction import CraigBampton, ReducedModel

    tip = 2.0
    mech, theta = _column(phi, tip, 16)
    P, F = tip * G * math.cos(phi), tip * G * math.sin(phi)
    k = math.sqrt(abs(P) / EI)
    if P > 0:
        exact, c_exact = F * (math.tan(k * L) - k * L) / (P * k), F * math.tan(k * L) / (k * EI)
    else:
        exact, c_exact = F * (k * L - math.tanh(k * L)) / (-P * k), F * math.tanh(k * L) / (k * EI)
    linear = F * L**3 / (3 * EI)
    assert abs(exact / linear - 1) > 0.02
    normal = np.array([-math.sin(theta), math.cos(theta)])
    for geometric, want in ((True, exact), (False, linear)):
        rm = ReducedModel(CraigBampton(ErlsModel(mech, geometric=geometric)))
        nq = rm.nq
        mats = rm.matrices(np.array([theta]))
        Hu = mats.rc.H[nq:, nq:]
        K = Hu.T @ rm.model.elastic_stiffness(mats.rc.cfg) @ Hu
        assert np.all(np.abs(mats.Kr[nq:, nq:] - K) <= 1e-9 * np.sqrt(np.outer(np.diag(K), np.diag(K))))
        p = np.r_[theta, np.linalg.solve(mats.Kr[nq:, nq:], mats.fr[nq:])]
        x = mats.rc.H @ p
        cfg = mats.rc.cfg
        assert -(rm.model.point_displacement_rows(cfg, "rod", L) @ x[nq:]) @ normal == pytest.approx(want, rel=5e-4)
        if geometric:
            c0 = rm.model.curvature_row(cfg, "rod", 0.0) @ x[nq:]
            assert abs(c0) == pytest.approx(abs(c_exact), rel=0.015)

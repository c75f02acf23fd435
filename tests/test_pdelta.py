"""The weight's P-delta effect, which the ERLS model's elastic rows leave out (:mod:`exuflex.erls.validity`).

Oracles: the beam-column's first-order correction of a cantilever (a tip load across it and the axial load ``P``
along it: the root moment ``F L + P delta_tip``, ``delta_tip = F L^3 / (3 EI)``, so the root curvature grows by the
fraction ``P L^2 / (3 EI)``); the ERLS coordinate rows' strain-energy term, which must equal the P-delta forces'
coordinate share (the rows already hold it); the vertical serial arm's measured truth difference
(``docs/gravity.md``).
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


def _column(phi: float, tip_mass: float, n_elements: int = 8):
    """A fresh one-link column: a light rod (30 kg/m^3: its weight some 3e-4 of the tip's) clamped at its hub, pointing up at ``phi`` rad
    from the vertical, a tip mass, a root curvature gauge (noise 1e-5)."""
    theta = math.pi / 2 - phi
    doc = {
        "model": {"name": "column", "q_ref": [theta], "gravity": [0.0, -G]},
        "materials": [{"name": "al", "E": E, "rho": 30.0}],
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
        model = ErlsModel(mech)
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
    model = ErlsModel(mech)
    cfg = model.configuration(np.array(q))
    u, _ = weight_sag(model, cfg)
    f, _ = pdelta_forces(model, cfg, model.T @ u, np.flatnonzero(model.el_len > 0))
    h = model.velocity_forces(cfg, np.concatenate([q, u]), np.zeros(model.n))[: model.nq]
    share = cfg.pose.S.T @ f
    assert np.abs(share).min() > 1e-3  # N m: a few tenths of the motors' torque noise
    assert np.allclose(h, -share, rtol=1e-3, atol=0)


def test_vertical_serial_arm_warns_naming_the_forearm_and_its_gauge(caplog):
    """Along the planned manoeuvre the forearm (upright, 3 N of its payload's weight along it) reads 0.66-0.78
    noise sd in its gauge (``docs/gravity.md``: the Exudyn truth's c_fore differs from the ERLS truth's by 0.8-1.4
    sd): ``departed``, from the start; the models without gravity (the gallery's serial arm) and the vertical
    four-bar (below 0.002 sd) give none."""
    from exuflex.manoeuvre import plan

    mech = load_mechanism(ROOT / "benchmarks" / "models" / "vertical_serial_arm.toml")
    p = plan(mech, dt=1e-2, t_end=mech.manoeuvre.duration)
    with caplog.at_level(logging.WARNING, logger="exuflex.erls.validity"):
        ws = weight_warnings(mech, p.t, p.q)
    fore = next(w for w in ws if w.link == "fore")
    assert fore.level == "departed" and fore.channel == "c_fore" and fore.time_s == 0.0
    assert 0.6 < fore.peak_reading_sd < 0.9 and fore.peak_reading_sd >= PDELTA_DEPART_SD
    assert fore.compression_n == pytest.approx(3.0, abs=0.1)
    assert any("'fore'" in r.getMessage() and "c_fore" in r.getMessage() for r in caplog.records)
    for other in ("models/serial_arm.toml", "benchmarks/models/vertical_fourbar.toml"):
        m = load_mechanism(ROOT / other)
        p = plan(m, dt=1e-2, t_end=m.manoeuvre.duration)
        assert weight_warnings(m, p.t, p.q) == []

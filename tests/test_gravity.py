"""Gravity in the Exudyn truths (``exuflex.groundtruth``), checked against beam theory and the ERLS truth.

Static: a cantilever (the hub's slope clamped at angle ``theta``) under gravity ``g`` straight down; its tip's
deflection across the link is Euler-Bernoulli's ``q L^4 / (8 EI) + P L^3 / (3 EI) + M L^2 / (2 EI)``,
``q = rho A g_n`` the weight per length across the link, ``P = m_t g_n`` a tip mass's weight across it and
``M = m_t (a g_n - b g_t)`` its weight's moment about the tip (offset ``(a, b)`` in the link frame; ``g_t``,
``g_n`` gravity along and across the link). The ANCF cable's nodal deflections are exact for this linear problem
(cubic Hermite elements with consistent loads), so what remains is geometric nonlinearity: the beam-column effect
of the weight's axial component (relative size about half the root's axial force over the buckling load
``pi^2 EI / (4 L^2)``) and the tip mass's tilt.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("exudyn")

from exuflex.groundtruth.builder import _exu, build_truth
from exuflex.mechanism.loader import parse_mechanism

G = 9.81
E, RHO, D, L = 69.0e9, 2700.0, 0.02, 1.0


def _cantilever(theta: float, tip: dict, gravity=(0.0, -G), hub_mass: bool = True):
    """A fresh one-link mechanism (aluminium rod, hub motor) at angle ``theta`` with a tip mass ``tip``."""
    doc = {
        "model": {"name": "gravity_cantilever", "q_ref": [theta], "gravity": list(gravity)},
        "materials": [{"name": "al", "E": E, "rho": RHO}],
        "links": [{"name": "arm", "length": L, "material": "al", "diameter": D, "n_elements": 4,
                   "angle_guess": theta}],
        "joints": [{"name": "hub", "points": [{"link": "arm", "station": 0.0}], "ground": [0.0, 0.0]}],
        "coordinates": [{"name": "q1", "link": "arm", "joint": "hub"}],
        "motors": [{"name": "T1", "joint": "hub", "link": "arm"}],
        "masses": [{"link": "arm", "station": 0.0, "mass": 0.5, "inertia": 0.05}] if hub_mass else [],
        "payload": {"link": "arm", "station": L, **tip},
    }
    if not doc["masses"]:
        del doc["masses"]
    return parse_mechanism(doc, "<gravity test>")


def _clamped_static_tip(mech, theta: float, **kw) -> np.ndarray:
    """The Exudyn truth's static tip displacement (x, y; m) with the hub's slope or rotation clamped at theta."""
    exu, it = _exu()
    tm = build_truth(mech, [theta], damping=None, **kw)
    mbs = tm.mbs
    lm = tm.links["arm"]
    ground = mbs.AddNode(it.NodePointGround(referenceCoordinates=[0.0, 0.0, 0.0]))
    row = np.zeros((1, tm.node_size))
    if tm.formulation == "ancf":  # n . r' = 0, n normal to the link
        row[0, 2], row[0, 3], offset = -math.sin(theta), math.cos(theta), 0.0
    else:
        row[0, 2], offset = 1.0, -theta
    mbs.AddObject(it.ObjectConnectorCoordinateVector(
        markerNumbers=[mbs.AddMarker(it.MarkerNodeCoordinates(nodeNumber=lm.nodes[0])),
                       mbs.AddMarker(it.MarkerNodeCoordinates(nodeNumber=ground))],
        scalingMarker0=row, scalingMarker1=np.zeros((1, 0)), offset=[offset]))
    mbs.Assemble()
    ss = exu.SimulationSettings()
    ss.staticSolver.newton.relativeTolerance = 1e-8
    ss.staticSolver.newton.absoluteTolerance = 1e-6  # residual in N: the axial stiffness (2e7 N/m) limits round-off
    ss.solution.file.write = False
    ss.solution.sensors.active = False
    ss.show.statistics = False
    ss.show.computationTime = False
    ss.linearSolver.solverType = exu.LinearSolverType.EigenSparse
    assert mbs.SolveStatic(ss)
    cur = np.asarray(mbs.systemData.GetODE2Coordinates(exu.ConfigurationType.Current))
    return cur[lm.ode2[-1][:2]]


def _euler_bernoulli_tip(theta: float, m_t: float, offset=(0.0, 0.0)) -> float:
    """Linear (Euler-Bernoulli) tip deflection across the clamped link (m, along the normal (-sin, cos))."""
    A, I = math.pi * D**2 / 4, math.pi * D**4 / 64
    EI = E * I
    g_t, g_n = -G * math.sin(theta), -G * math.cos(theta)  # gravity along and across the link
    a, b = offset
    q, P = RHO * A * g_n, m_t * g_n
    M = m_t * (a * g_n - b * g_t)  # the tip mass's weight's moment about the tip
    return q * L**4 / (8 * EI) + P * L**3 / (3 * EI) + M * L**2 / (2 * EI)


def _axial_share(theta: float, m_t: float) -> float:
    """Compressive root force over the cantilever's buckling load ``pi^2 EI / (4 L^2)``: the relative size of the
    beam-column (geometric stiffness) effect that linear theory leaves out; negative in tension."""
    A, I = math.pi * D**2 / 4, math.pi * D**4 / 64
    N = (RHO * A * L + m_t) * G * math.sin(theta)
    return N / (math.pi**2 * E * I / (4 * L**2))


@pytest.mark.parametrize(
    "theta, tip, hub",
    [
        (0.0, {"mass": 0.1}, "rigid"),  # point mass: a constant mass matrix on the node
        (0.4, {"mass": 0.3, "inertia": 1e-3}, "rigid"),  # a rigid body welded to the node
        (0.0, {"mass": 0.3, "offset": [0.05, 0.02]}, "rigid"),  # offset: the weight's moment at the tip
        (-0.3, {"mass": 0.3, "offset": [0.05, 0.02]}, "slopes"),  # the legacy slopes hub: M_k t_g on the slopes
        (-0.3, {"mass": 0.3, "offset": [0.05, 0.02]}, "rigid"),
    ],
)
def test_static_tip_deflection_under_gravity_is_euler_bernoulli(theta, tip, hub):
    mech = _cantilever(theta, tip)
    u = _clamped_static_tip(mech, theta, hub=hub)
    normal = np.array([-math.sin(theta), math.cos(theta)])
    want = _euler_bernoulli_tip(theta, tip["mass"], tip.get("offset", (0.0, 0.0)))
    assert abs(want) > 1e-3
    share = _axial_share(theta, tip["mass"])
    # linear theory to 2e-4 (the tip mass's tilt, (b phi) / a); with an axial weight component, the beam-column
    # effect: compression (share > 0) deflects more, tension less, by about share / 2
    rel = (u @ normal) / want - 1.0
    assert abs(rel - 0.5 * share) <= 2e-4 + 0.25 * abs(share)
    # along the link: the axial stretch under the weight's axial component, tiny against the deflection
    assert abs(u @ np.array([math.cos(theta), math.sin(theta)])) < 0.01 * abs(want)


def test_static_tip_deflection_without_gravity_is_zero():
    mech = _cantilever(0.0, {"mass": 0.3, "offset": [0.05, 0.02]}, gravity=(0.0, 0.0))
    assert np.abs(_clamped_static_tip(mech, 0.0)).max() < 1e-12


def test_geometrically_exact_beam_converges_to_timoshenko_under_gravity():
    """The linear gebeam elements converge to the Timoshenko cantilever (Euler-Bernoulli plus the shear
    deflection ``q L^2 / (2 k G A) + P L / (k G A)``) at second order in the element length."""
    from exuflex.groundtruth.builder import POISSON, SHEAR_CORRECTION

    tip = {"mass": 0.3, "inertia": 1e-3}
    mech = _cantilever(0.0, tip)
    A = math.pi * D**2 / 4
    kGA = SHEAR_CORRECTION * E / (2 * (1 + POISSON)) * A
    want = _euler_bernoulli_tip(0.0, tip["mass"]) - G * (RHO * A * L**2 / 2 + tip["mass"] * L) / kGA
    err = [abs(_clamped_static_tip(mech, 0.0, formulation="gebeam", elements_per_link=n)[1] / want - 1)
           for n in (8, 16, 32)]
    rates = np.log2(np.array(err[:-1]) / np.array(err[1:]))
    assert err[-1] < 2e-4
    assert np.all(rates > 1.8)


VERTICAL_LINK = Path(__file__).resolve().parents[1] / "benchmarks" / "models" / "vertical_link.toml"


def _truths(mech):
    """The Exudyn (ANCF) and the ERLS full-order truths of ``mech``'s manoeuvre under its computed torque."""
    from exuflex.truth.engines import plan_drive, simulate

    drive = plan_drive(mech, mech.manoeuvre.duration, 1e-4)
    return [simulate(mech, drive, engine=e).truth for e in ("exudyn", "erls")]


def _column(sig, name: str) -> np.ndarray:
    return sig.data[:, sig.names.index(name)]


def test_vertical_link_exudyn_truth_follows_the_erls_truth_under_gravity():
    """A link lifted from hanging to horizontal against gravity (``benchmarks/models/vertical_link.toml``, the hub
    holding 6.1 N m at the end) under the computed torque, which includes gravity: the Exudyn truth's joint angle
    follows the ERLS truth's within 1e-3 rad (seen 2.6e-4; 8.5e-5 with gravity 0: the open-loop hold at the
    horizontal is neutrally stable under gravity, so differences grow there) and the tip's elastic displacement
    within 10 % of its RMS (seen 1.9 %, 1.3 %). The truth without the weight swung 4.3 rad past the plan by the end."""
    from exuflex.mechanism import load_mechanism
    from exuflex.sensors import tip_dof_names

    mech = load_mechanism(VERTICAL_LINK)
    assert mech.gravity == (0.0, -9.81)
    exu, erls = _truths(mech)
    n = min(len(exu.t), len(erls.t))
    np.testing.assert_allclose(exu.t[:n], erls.t[:n])
    q_exu, q_erls = _column(exu, "q1")[:n], _column(erls, "q1")[:n]
    assert abs(q_erls[-1]) < 2e-3  # the ERLS truth ends at the plan's horizontal
    assert np.max(np.abs(q_exu - q_erls)) < 1e-3
    for tip in tip_dof_names(mech):  # the tip's elastic displacement
        e, r = _column(exu, tip)[:n], _column(erls, tip)[:n]
        assert np.sqrt(np.mean((e - r) ** 2)) < 0.1 * np.sqrt(np.mean(r**2))


def test_prescribed_truth_held_horizontal_sags_by_euler_bernoulli():
    """The prescribed-motion truth (:func:`exuflex.groundtruth.simulate_prescribed`, built by the same builder)
    holds the vertical link's hub horizontal: released undeformed, the link vibrates about its static deflection
    under its weight and the tip mass (1 % damping at 62.8 Hz), whose mean over the last 0.1 s is Euler-Bernoulli's
    ``q L^4 / (8 EI) + P L^3 / (3 EI)`` within 3 % (seen 0.15 %: the decaying vibration's share of the mean)."""
    from exuflex.groundtruth import simulate_prescribed
    from exuflex.mechanism import load_mechanism
    from exuflex.probes import probes_for

    mech = load_mechanism(VERTICAL_LINK)
    lk = mech.links[0]
    EI, L = lk.material.E * lk.section.I, lk.length
    want = mech.gravity[1] * (lk.material.rho * lk.section.A * L**4 / (8 * EI) + mech.payload.mass * L**3 / (3 * EI))
    probe = next(p for p in probes_for(mech) if p.key == f"point:arm@{L:g}")
    rec = simulate_prescribed(mech, lambda t: np.array([0.0]), 0.6, [probe], h=1e-3, damping="rayleigh")
    tip_y = rec.values[probe.key][rec.t >= 0.5, 1]
    assert np.mean(tip_y) == pytest.approx(want, rel=0.03)


# ---------------------------------------------------------------------------------------------------------------
# the reduced model (the observer's) under gravity


def _reduced(mech, geometric: bool = True):
    from exuflex.erls.model import ErlsModel
    from exuflex.reduction import CraigBampton, ReducedModel

    return ReducedModel(CraigBampton(ErlsModel(mech, geometric=geometric)))


@pytest.mark.parametrize("theta", [0.0, -0.6, 0.9])
def test_reduced_static_sag_and_holding_torque_are_euler_bernoulli(theta):
    """The reduced model's weight ``(W J)^T M_N g`` on a cantilever clamped at the hub's angle ``theta``: the elastic
    rows' static solution ``K_r p = f_g`` gives the tip deflection across the link of Euler-Bernoulli, ``q L^4 /
    (8 EI) + P L^3 / (3 EI)`` (cubic elements with consistent loads are nodally exact; the Craig-Bampton basis
    holds the tip's static shape exactly and the interior load's response to its modes' truncation), and the
    joint row's force at that state is the weight's moment about the hub, ``g_n (rho A L^2 / 2 + m_t L)``, less
    the sag's lever (relative size the deflection over the length). Linear elasticity: the model without the
    geometric stiffness of the axial loads (with it: ``tests/test_pdelta.py``)."""
    tip = {"mass": 0.3}
    mech = _cantilever(theta, tip)
    rm = _reduced(mech, geometric=False)
    nq = rm.nq
    mats = rm.matrices(np.array([theta]))
    pe = np.linalg.solve(mats.Kr[nq:, nq:], mats.fr[nq:])
    p = np.concatenate([[theta], pe])
    x = mats.rc.H @ p
    rows = rm.model.point_displacement_rows(mats.rc.cfg, "arm", L)
    normal = np.array([-math.sin(theta), math.cos(theta)])
    want = _euler_bernoulli_tip(theta, tip["mass"])
    assert (rows @ x[nq:]) @ normal == pytest.approx(want, rel=2e-3)
    # the full-order model's static solution at the same angle: the reduced one within the basis's truncation
    cfg = rm.model.configuration(np.array([theta]))
    Kuu = rm.model.T.T @ cfg.K_N @ rm.model.T
    u_full = np.linalg.solve(Kuu, rm.model.generalized_forces(cfg, np.zeros(1))[nq:])
    assert np.abs(rows @ (x[nq:] - u_full)).max() <= 2e-3 * abs(want)
    A = math.pi * D**2 / 4
    moment = -G * math.cos(theta) * (RHO * A * L**2 / 2 + tip["mass"] * L)
    held = rm.matrices(p)
    assert (held.fr - held.Kr @ p)[0] == pytest.approx(moment, rel=5 * abs(want) / L + 1e-9)


def _held_pair(som, q0: float, d: float):
    """The cached step's held configuration at ``q0`` with its secant partner at ``q0 - d`` (the configurations
    undeformed at rest), as :meth:`ReducedObserverModel._refresh` builds them."""
    r = som.r

    def held(q):
        z = np.zeros(2 * r)
        z[0] = q
        iv = som._configuration(z, held=True)
        iv.Ca = iv.mats.Cr - som.model.beta * iv.mats.Kr
        return iv

    old, iv = held(q0 - d), held(q0)
    old.system = som._held_system(old)
    iv.old, iv.d = old, np.array([d])
    iv.dd = d * d
    iv.system = som._held_system(iv)
    return iv


def _held_errors(som, q0: float, h: float):
    """``((second, first), iv, exact)``: one interval's state error of the cached step held at ``q0`` (secant partner
    at ``q0 - h``) and evaluated at ``q0 + h``, at rest and undeformed, to second order (``s = 1``) and to first
    (``s = 0``), each over the held state's change, against the configuration evaluated exactly; and the two held
    intervals."""
    from exuflex.observer.expansion import held_step

    r, dt = som.r, 1e-3
    u, zero = np.zeros(1), np.zeros(1)
    iv, exact = _held_pair(som, q0, h), _held_pair(som, q0 + h, h)
    z = np.zeros(2 * r)
    z[0] = q0 + h
    n = som.substeps(iv, dt)
    want = held_step(z, u, zero, 0.0, dt / n, n, exact.system)[0]
    change = np.abs(want - held_step(z, u, zero, 0.0, dt / n, n, iv.system)[0]).max()
    # without the partner's curvature: the weight to first order (s = 0 drops the secant altogether)
    errs = tuple(np.abs(held_step(z, u, np.array([h]), s, dt / n, n, iv.system)[0] - want).max() / change
                 for s in (1.0, 0.0))
    return errs, iv, exact


def test_held_weight_follows_the_configuration_to_second_order():
    """The cached step's weight about a held configuration with a secant partner: ``fg + (Wg + s/2 (Wg - Wg_old))
    dl`` (:func:`exuflex.observer.expansion._held_model`), second order along the secant, so its error falls
    as the cube of the radius (the partner as far behind as ``q`` is ahead, as the refreshes place them; first
    order: the square). The vertical link at rest, 40 degrees below the horizontal, undeformed: one interval's
    state error against the configuration evaluated exactly (``K_r`` with the static axial loads' geometric
    stiffness, held with its gradient, :meth:`~exuflex.reduction.model.ReducedModel.geometric_gradient`), and the
    weight itself."""
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.reduced import ReducedObserverModel

    mech = load_mechanism(VERTICAL_LINK)
    som = ReducedObserverModel(_reduced(mech))
    q0, radii = -0.7, (0.04, 0.02, 0.01)
    step, first, weight = [], [], []
    for h in radii:
        (err, err_first), iv, exact = _held_errors(som, q0, h)
        step.append(err)
        first.append(err_first)
        fg0, fg_h = iv.forces.fg, exact.forces.fg
        W0, W_old = iv.forces.Wg[:, 0], iv.old.forces.Wg[:, 0]
        expanded = fg0 + (W0 + 0.5 * (W0 - W_old)) * h  # s = 1
        weight.append(np.abs(expanded - fg_h).max() / np.abs(fg_h - fg0).max())
    for rel, order in ((step, 2), (first, 1), (weight, 2)):  # relative errors: the order less one
        assert np.all(np.log2(np.array(rel[:-1]) / np.array(rel[1:])) > order - 0.2), (rel, order)
    assert np.all(np.array(step) < 0.1 * np.array(first))
    assert weight[0] < 1e-2

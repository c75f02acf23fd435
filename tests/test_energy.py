"""Energy consistency of the full-order ERLS model (eq. 2).

With E = v^T M(q) v / 2 + u^T K_uu(q) u / 2 the model promises dE/dt = v^T W^T B tau - u'^T C_uu u' - u'^T K_G u
(see :mod:`exuflex.erls.model`; the last the power of the geometric stiffness of the rigid motion's axial loads,
``K_G(q, q', tau)``, which no potential gives). Checked two ways:

- instantaneously, at random states of all three mechanisms (dM/dt and dK/dt by central differences
  along q'): exact up to round-off, fast;
- along an undamped, unforced motion integrated with a tight-tolerance DOP853 (the axial modes are
  stiff, so a one-element link keeps the run short).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from exuflex.erls.model import ErlsModel
from exuflex.mechanism import Damping, Material, load_mechanism

MODELS = Path(__file__).resolve().parents[1] / "models"


def _random_state(model, rng):
    n, nq = model.n, model.nq
    y = np.zeros(2 * n)
    y[:nq] = np.array(model.mech.q_ref) + 0.05 * rng.standard_normal(nq)
    y[n : n + nq] = rng.standard_normal(nq)
    y[nq:n] = 1e-3 * rng.standard_normal(model.ne)
    y[n + nq :] = 0.1 * rng.standard_normal(model.ne)
    return y


def _power_terms(model, y, tau):
    """The terms of dE/dt along the model's motion, and the power of the motors and of the damping."""
    n, nq = model.n, model.nq
    x, v = y[:n], y[n:]
    a = model.rhs(0.0, y, tau)[n:]
    cfg = model.configuration(x[:nq])
    eps = 1e-6
    cp, cm = model.configuration(x[:nq] + eps * v[:nq]), model.configuration(x[:nq] - eps * v[:nq])
    Md = (model.mass(cp) - model.mass(cm)) / (2 * eps)
    Kd = (model.stiffness(cp) - model.stiffness(cm)) / (2 * eps)
    M, K = model.mass(cfg), model.stiffness(cfg)
    dE = np.array([v @ M @ a, 0.5 * v @ Md @ v, v @ K @ x, 0.5 * x @ Kd @ x])
    p_motor = v @ model.input_matrix(cfg) @ tau
    p_damp = -v @ model.damping(cfg, x) @ v
    p_damp += v[nq:] @ model.geometric_forces(cfg, model.rigid_axial_forces(cfg, v[:nq], tau), x[nq:])
    return dE, p_motor, p_damp


@pytest.mark.parametrize("name", ["single_link", "fourbar", "sixbar"])
@pytest.mark.parametrize("damped", [False, True])
def test_power_balance(name, damped):
    mech = load_mechanism(MODELS / f"{name}.toml")
    if not damped:
        mech = mech.replace(damping=Damping(0.0, 0.0))
    model = ErlsModel(mech)
    rng = np.random.default_rng(7)
    for _ in range(3):
        y = _random_state(model, rng)
        tau = rng.standard_normal(len(mech.motors)) if damped else np.zeros(len(mech.motors))
        dE, p_motor, p_damp = _power_terms(model, y, tau)
        scale = np.abs(dE).sum() + abs(p_motor) + abs(p_damp)
        assert abs(dE.sum() - p_motor - p_damp) < 1e-9 * scale
        if not damped:
            assert p_motor == 0.0


def _one_element_link(material: Material | None = None):
    """The single-link model on one element (a coarse mesh keeps the stiff axial mode slow), undamped."""
    mech = load_mechanism(MODELS / "single_link.toml")
    lk = mech.links[0]
    lk = dataclasses.replace(lk, stations=(0.0, lk.length), node_ids=(1, 2), material=material or lk.material)
    return mech.replace(
        links=(lk,),
        masses=tuple(dataclasses.replace(m, node=1) for m in mech.masses),
        payload=dataclasses.replace(mech.payload, node=2),
        damping=Damping(0.0, 0.0),
        reduction=dataclasses.replace(mech.reduction, masters=()),
    )


def _drift(mech, t_end: float, rtol: float) -> float:
    model = ErlsModel(mech, geometric=False)  # linear elasticity: conservative (K_G's power, test_power_balance)
    n = model.n
    y0 = np.zeros(2 * n)
    y0[n] = 1.0  # hub spinning at 1 rad/s: centrifugal and Coriolis coupling at work
    y0[model.index("node2.y")] = 0.01  # 1 cm tip deflection
    y0[model.index("node2.theta")] = 0.015
    tau = np.zeros(len(mech.motors))
    sol = solve_ivp(lambda t, y: model.rhs(t, y, tau), (0.0, t_end), y0, method="DOP853", rtol=rtol,
                    atol=rtol * 1e-3)
    assert sol.success
    # the motion is far from trivial: the hub angle moved and elastic energy was exchanged
    assert abs(sol.y[0, -1]) > 0.5 * t_end
    e0, e1 = model.energy(y0), model.energy(sol.y[:, -1])
    print(f"\nenergy drift over {t_end} s (DOP853 rtol {rtol:g}, {sol.nfev} evaluations): {(e1 - e0) / e0:+.2e}")
    return (e1 - e0) / e0


def test_energy_drift_short():
    """A slender nylon link (slow axial mode) over 0.1 s: fast enough for the default suite."""
    mech = _one_element_link(Material("nylon", 2.0e9, 1150.0))
    assert abs(_drift(mech, 0.1, 1e-9)) < 1e-7


@pytest.mark.slow
def test_energy_drift_one_second():
    """The aluminium single link (one element), undamped and unforced, over 1 s: |drift| < 1e-6."""
    assert abs(_drift(_one_element_link(), 1.0, 1e-9)) < 1e-6


def test_rk4_substeps_keep_an_overdamped_mode_stable():
    """The ERLS truth splits its step where RK4 would make a physically decaying mode grow: the four-bar's
    highest mode is overdamped by the stiffness damping, lambda = -1.45e5 1/s, 14.5 times the 0.1 ms step."""
    from exuflex.erls.simulate import rk4_substeps, simulate

    lam = -1.45e5
    A = np.diag([lam, 0.0])
    A[1, 0] = 1.0  # a rigid coordinate driven by it (lambda = 0: neutral, needs no sub-step)
    n = rk4_substeps(A, 1e-4)
    assert n == 6  # |R(z)| <= 1 on the negative real axis up to |z| = 2.785: 14.5 / 6 = 2.42 (5 sub-steps: 2.9)
    f = lambda t, y, u: A @ y
    y_end = simulate(f, [1.0, 0.0], 0.01, lambda t: None, h=1e-4 / n).y[-1]
    assert abs(y_end[0]) < 1e-12
    with pytest.raises(FloatingPointError), np.errstate(over="ignore", invalid="ignore"):
        simulate(f, [1.0, 0.0], 0.01, lambda t: None, h=1e-4)
    oscillating = np.array([[0.0, 1.0], [-(2 * np.pi * 4330.0) ** 2, 0.0]])  # the six-bar's highest mode, undamped
    assert rk4_substeps(oscillating, 1e-4) == 1

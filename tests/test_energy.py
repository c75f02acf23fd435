"""Energy consistency of the full-order ERLS model (eq. 2).

With E = v^T M(q) v / 2 + u^T K_uu(q) u / 2 the model promises dE/dt = v^T W^T B tau - u'^T C_uu u'
(see :mod:`exuflex.erls.model`). Checked two ways:

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
    p_damp = -v @ model.damping(cfg) @ v
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
            assert p_motor == 0.0 and p_damp == 0.0


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
    model = ErlsModel(mech)
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

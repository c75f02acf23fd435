"""Time laws, exact inverse kinematics and rigid computed torque (exuflex.manoeuvre)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.kinematics import Kinematics
from exuflex.manoeuvre import ActuationError, computed_torque, plan, time_law
from exuflex.mechanism import Manoeuvre, load_mechanism

MODEL = Path(__file__).resolve().parents[1] / "models" / "sixbar.toml"

# Reference numbers of the six-bar reconstruction (team reference sixbar.json,
# trajectory_proposal.resulting: rigid model, upper semicircle, trapezoid ta = 0.08 s, q3 rule).
REF_Q_MIN = (0.6642, 2.5413, 4.2124)
REF_Q_MAX = (0.8372, 2.7197, 5.2124)
REF_QD_MIN = (-0.239, -0.131, 0.0)
REF_QD_MAX = (0.138, 0.252, 0.342)
REF_T1 = (-6.025, 0.481)
REF_T2 = (-14.419, 1.087)
REF_T3 = (-0.0523, 0.0523)
# Fig. 4 of the paper (axes): T1 in [-10, 5], T2 in [-20, 10], T3 about +-0.05 N m.


@pytest.fixture(scope="module")
def mech():
    return load_mechanism(MODEL)


@pytest.fixture(scope="module")
def sixbar_plan(mech):
    return plan(mech, dt=1e-3)


# ------------------------------------------------------------------------------------------ time laws
@pytest.mark.parametrize("law", ["trapezoid", "quintic", "cycloidal"])
def test_time_law_boundaries_and_rest_outside(law):
    T, ta = 3.0, 0.08
    s, sd, sdd = time_law(law, np.array([-1.0, 0.0, T, T + 1.0]), T, ta)
    np.testing.assert_allclose(s, [0, 0, 1, 1], atol=1e-15)
    np.testing.assert_allclose(sd, 0, atol=1e-12)
    np.testing.assert_allclose(sdd[[0, 3]], 0, atol=0)
    if law != "trapezoid":
        np.testing.assert_allclose(sdd, 0, atol=1e-12)


@pytest.mark.parametrize("law", ["trapezoid", "quintic", "cycloidal"])
def test_time_law_continuity_and_derivatives(law):
    T, ta = 2.0, 0.1
    t = np.linspace(0, T, 200001)
    dt = t[1] - t[0]
    s, sd, sdd = time_law(law, t, T, ta)
    # s and s' continuous: no jump larger than a step's worth of change
    assert np.max(np.abs(np.diff(s))) <= 1.01 * np.max(sd) * dt
    assert np.max(np.abs(np.diff(sd))) <= 1.01 * np.max(np.abs(sdd)) * dt
    # derivatives agree with central differences (away from the trapezoid's acceleration jumps)
    ok = np.ones(len(t) - 2, bool)
    if law == "trapezoid":
        for tj in (ta, T - ta):
            ok &= np.abs(t[1:-1] - tj) > 2 * dt
    np.testing.assert_allclose(((s[2:] - s[:-2]) / (2 * dt))[ok], sd[1:-1][ok], atol=1e-7)
    np.testing.assert_allclose(
        ((sd[2:] - sd[:-2]) / (2 * dt))[ok], sdd[1:-1][ok], atol=1e-5 * np.max(np.abs(sdd))
    )
    assert np.all(np.diff(s) >= 0)


def test_trapezoid_cruise_speed():
    T, ta = 3.0, 0.08
    _, sd, sdd = time_law("trapezoid", np.array([0.04, 1.5]), T, ta)
    assert sd[1] == pytest.approx(1 / (T - ta))
    assert sdd[0] == pytest.approx(1 / (T - ta) / ta)
    assert sdd[1] == 0


def test_trapezoid_jumps_take_the_later_phase():
    """At both acceleration jumps s'' is the later phase's (as documented): a torque table on a grid through the
    jump times switches at the grid point of the jump, at the end of the manoeuvre as at its start (the end one
    was the earlier phase's, so the six-bar's computed torque stepped 0.1 ms after a 500 Hz sample)."""
    T, ta = 3.0, 0.08
    a = 1 / (T - ta) / ta
    _, _, sdd = time_law("trapezoid", np.array([ta, T - ta, T]), T, ta)
    np.testing.assert_array_equal(sdd, [0.0, -a, -a])
    t = np.arange(30001) * 1e-4  # the plan's table grid: the jumps fall on its points 800 and 29200
    _, _, sdd = time_law("trapezoid", t, T, ta)
    assert sdd[799] == a and sdd[800] == 0.0
    assert sdd[29199] == 0.0 and sdd[29200] == -a


def test_time_law_errors():
    with pytest.raises(ValueError, match="time law must be one of"):
        time_law("linear", 0.0, 1.0)
    with pytest.raises(ValueError, match="ramp_time must be in"):
        time_law("trapezoid", 0.0, 1.0, 0.6)


# ------------------------------------------------------------------------------------------ planning
def test_ik_closes_tip_on_arc(mech, sixbar_plan):
    pl = sixbar_plan
    man = mech.manoeuvre
    kin = Kinematics(mech)
    err = 0.0
    for k in range(0, len(pl.t), 25):
        pose = kin.pose(pl.q[k])
        p, _ = kin.point(pose, man.tip.link, man.tip.station)
        phi = man.phi_start + (man.phi_end - man.phi_start) * pl.s[k]
        target = np.asarray(man.centre) + man.radius * np.array([np.cos(phi), np.sin(phi)])
        err = max(err, float(np.max(np.abs(p - target))))
    assert err < 1e-9
    # the ruled coordinate follows its linear rule
    c, a, b = man.rules[0]
    j = mech.coordinate_names.index(c)
    np.testing.assert_allclose(pl.q[:, j], a + (b - a) * pl.s, atol=1e-14)


def test_plan_ranges_match_reconstruction(sixbar_plan):
    pl = sixbar_plan
    np.testing.assert_allclose(pl.q.min(0), REF_Q_MIN, atol=2e-4)
    np.testing.assert_allclose(pl.q.max(0), REF_Q_MAX, atol=2e-4)
    np.testing.assert_allclose(pl.qd.min(0), REF_QD_MIN, atol=2e-3)
    np.testing.assert_allclose(pl.qd.max(0), REF_QD_MAX, atol=2e-3)


def test_plan_rates_match_finite_differences(mech):
    # a smooth law so that central differences are accurate; a short manoeuvre for speed
    man = dataclasses.replace(mech.manoeuvre, time_law="quintic", duration=0.5)
    pl = plan(mech, man, dt=5e-4)
    dt = pl.dt
    fd_qd = (pl.q[2:] - pl.q[:-2]) / (2 * dt)
    fd_qdd = (pl.qd[2:] - pl.qd[:-2]) / (2 * dt)
    np.testing.assert_allclose(fd_qd, pl.qd[1:-1], atol=2e-5 * np.abs(pl.qd).max())
    np.testing.assert_allclose(fd_qdd, pl.qdd[1:-1], atol=2e-4 * np.abs(pl.qdd).max())


def test_joint_manoeuvre(mech):
    q0 = np.array(mech.q_ref)
    rules = tuple((n, q0[i], q0[i] + 0.01) for i, n in enumerate(mech.coordinate_names))
    man = Manoeuvre(kind="joint", duration=0.2, time_law="cycloidal", rules=rules)
    pl = plan(mech, man, dt=0.01)
    np.testing.assert_allclose(pl.q, q0 + 0.01 * pl.s[:, None], atol=1e-15)
    np.testing.assert_allclose(pl.q[-1], q0 + 0.01)


def test_tip_arc_needs_two_free_coordinates(mech):
    man = dataclasses.replace(mech.manoeuvre, rules=())
    with pytest.raises(ValueError, match="exactly 2 coordinates without rules"):
        plan(mech, man, dt=0.1)


# ------------------------------------------------------------------------------------------ computed torque
def test_computed_torque_ranges(mech, sixbar_plan):
    tau = computed_torque(mech, sixbar_plan)
    lo, hi = tau.min(0), tau.max(0)
    for j, ref in enumerate((REF_T1, REF_T2, REF_T3)):
        assert lo[j] == pytest.approx(ref[0], rel=0.01)
        assert hi[j] == pytest.approx(ref[1], rel=0.01)
    # inside the axes of the paper's Fig. 4 (T3 within its +-0.05 axis to 5 %)
    assert -10 <= lo[0] and hi[0] <= 5
    assert -20 <= lo[1] and hi[1] <= 10
    assert np.max(np.abs(tau[:, 2])) < 0.0525
    # at rest after the manoeuvre the torque vanishes
    pl = plan(mech, dt=0.5, t_end=3.5)
    np.testing.assert_allclose(computed_torque(mech, pl)[-1], 0.0, atol=1e-10)


def test_computed_torque_power_balance(mech):
    """Rigid power: tau . (W^T B)_q^T q' = d/dt (q'^T M_qq q' / 2) (no gravity, no elasticity)."""
    from exuflex.erls.model import ErlsModel

    model = ErlsModel(mech)
    man = dataclasses.replace(mech.manoeuvre, time_law="quintic", duration=0.5)
    pl = plan(mech, man, dt=1e-3, t_end=0.2)
    tau = computed_torque(mech, pl, model=model)
    nq = model.nq
    ke, power = [], []
    for k in range(len(pl.t)):
        cfg = model.configuration(pl.q[k])
        ke.append(0.5 * pl.qd[k] @ model.mass(cfg)[:nq, :nq] @ pl.qd[k])
        power.append(tau[k] @ model.input_matrix(cfg)[:nq].T @ pl.qd[k])
    ke, power = np.array(ke), np.array(power)
    dke = (ke[2:] - ke[:-2]) / (2 * pl.dt)
    np.testing.assert_allclose(dke, power[1:-1], atol=3e-4 * np.abs(power).max())  # O(dt^2) differences


def test_computed_torque_underactuated(mech):
    weak = dataclasses.replace(mech, motors=mech.motors[:2])
    pl = plan(mech, dt=0.5, t_end=0.5)
    with pytest.raises(ActuationError, match="actuate only 2 of the 3"):
        computed_torque(weak, pl)


# ------------------------------------------------------------------------------------------ oracle
# The planner and the computed torque as they were written point by point (one Newton solve from the last
# point's prediction, then the full ERLS model's q rows at u = u' = 0 at every point): the batched planner and
# the link-by-link rigid inverse dynamics must reproduce them.
def _oracle_plan(mech, man, t):
    from scipy.linalg import lu_factor, lu_solve

    from exuflex.manoeuvre import _arc

    kin = Kinematics(mech)
    names = mech.coordinate_names
    nq, nz, ne = len(names), 3 * kin.nl, kin.n_eq
    s, sd, sdd = time_law(man.time_law, t, man.duration, man.ramp_time)
    ruled = {names.index(c): (a, b) for c, a, b in man.rules}
    idx = np.array(sorted(ruled), dtype=int)
    q, qd, qdd = (np.zeros((len(t), nq)) for _ in range(3))
    a = np.array([ruled[k][0] for k in idx])
    b = np.array([ruled[k][1] for k in idx])
    q[:, idx], qd[:, idx], qdd[:, idx] = a + np.outer(s, b - a), np.outer(sd, b - a), np.outer(sdd, b - a)
    if man.kind == "joint":
        return q, qd, qdd
    free = [k for k in range(nq) if k not in ruled]
    p, pd, pdd = _arc(man, s, sd, sdd)
    li, st = kin.link_names.index(man.tip.link), man.tip.station

    def jac(z):
        J = np.zeros((ne + 2, nz + 2))
        J[:ne, :nz] = kin.jacobian(z)
        J[:ne, nz:] = -kin._E[:, free]
        th = z[3 * li + 2]
        J[ne:, 3 * li : 3 * li + 2] = np.eye(2)
        J[ne:, 3 * li + 2] = st * np.array([-np.sin(th), np.cos(th)])
        return J

    def tip(z):
        return np.array([z[3 * li] + st * np.cos(z[3 * li + 2]), z[3 * li + 1] + st * np.sin(z[3 * li + 2])])

    qk = np.array(mech.q_ref, float)
    qk[idx] = q[0, idx]
    z = kin.pose(qk).z
    for k in range(len(t)):
        qk = qk.copy()
        qk[idx] = q[k, idx]
        if k > 0:
            h = t[k] - t[k - 1]
            qk[free] += qd[k - 1, free] * h + 0.5 * qdd[k - 1, free] * h**2
        for it in range(30):
            res = np.concatenate([kin.residual(z, qk), tip(z) - p[:, k]])
            if it > 0 and np.max(np.abs(res)) < 1e-13 * kin.newton_scale:
                break
            dx = np.linalg.solve(jac(z), -res)
            z = z + dx[:nz]
            qk[free] += dx[nz:]
        q[k] = qk
        lu = lu_factor(jac(z))
        E_r = kin._E[:, idx]
        sol = lu_solve(lu, np.concatenate([E_r @ qd[k, idx], pd[:, k]]))
        zd = sol[:nz]
        qd[k, free] = sol[nz:]
        th, thd = z[3 * li + 2], zd[3 * li + 2]
        bias = -st * thd**2 * np.array([np.cos(th), np.sin(th)])
        rhs = np.concatenate([E_r @ qdd[k, idx] - kin._jacobian_rate(z, zd) @ zd, pdd[:, k] - bias])
        qdd[k, free] = lu_solve(lu, rhs)[nz:]
    return q, qd, qdd


def _oracle_torque(mech, q, qd, qdd):
    from exuflex.erls.model import ErlsModel

    model = ErlsModel(mech)
    nq, n = model.nq, model.n
    tau = []
    for k in range(len(q)):
        x, v = np.zeros(n), np.zeros(n)
        x[:nq], v[:nq] = q[k], qd[k]
        cfg = model.configuration(q[k])
        M = model.mass(cfg)[:nq, :nq]
        h = model.velocity_forces(cfg, x, v)[:nq]
        g = model.generalized_forces(cfg, np.zeros(len(mech.motors)))[:nq]
        A = model.input_matrix(cfg)[:nq]
        tau.append(np.linalg.lstsq(A, M @ qdd[k] + h - g, rcond=None)[0])
    return np.array(tau)


def _relative(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def test_batched_plan_and_torque_equal_the_pointwise_oracle(mech, sixbar_plan):
    """The six-bar's 3 s tip arc on a 1 ms grid (batched beyond its coarse points) against the point-by-point
    planner on a 50 ms grid through the same times, and the full-model torque there."""
    pl = sixbar_plan
    every = 50
    t = pl.t[::every]
    q, qd, qdd = _oracle_plan(mech, mech.manoeuvre, t)
    assert _relative(pl.q[::every], q) < 1e-9
    assert _relative(pl.qd[::every], qd) < 1e-9
    assert _relative(pl.qdd[::every], qdd) < 1e-9
    few = slice(None, None, 6)  # the full model at 11 points
    tau = computed_torque(mech, pl)[::every][few]
    assert _relative(tau, _oracle_torque(mech, q[few], qd[few], qdd[few])) < 1e-9


def test_batched_torque_with_gravity_equals_the_oracle():
    """A joint manoeuvre of the vertical four-bar variant (gravity in the plane): the closure solved in one batch,
    the torque link by link, against the full model's q rows."""
    fb = load_mechanism(MODEL.parent / "fourbar.toml")
    fb = dataclasses.replace(fb, gravity=(0.0, -9.81))
    pl = plan(fb, dt=1e-3)
    assert len(pl.t) > 1000
    ks = np.arange(0, len(pl.t), 150)
    tau = computed_torque(fb, pl)[ks]
    q, qd, qdd = _oracle_plan(fb, fb.manoeuvre, pl.t[ks])
    np.testing.assert_array_equal(pl.q[ks], q)
    assert _relative(tau, _oracle_torque(fb, q, qd, qdd)) < 1e-9
    # a plan without the link motion (built by hand) gives the same torques
    bare = dataclasses.replace(pl, z=None, zd=None, zdd=None)
    assert _relative(computed_torque(fb, bare)[ks], tau) < 1e-12


def test_batched_plan_recovers_from_a_wrong_branch(mech, monkeypatch):
    """With only the two end points solved in sequence, the interpolated starts are poor and the batched Newton
    lands on other assembly branches: the continuity check finds those points and solves them from their
    predecessors, so the plan equals the one from close coarse points."""
    import exuflex.manoeuvre as man_mod

    ref = plan(mech, dt=5e-3)
    monkeypatch.setattr(man_mod, "_COARSE_POINTS", 2)
    rough = plan(mech, dt=5e-3)
    np.testing.assert_allclose(rough.q, ref.q, rtol=0, atol=1e-11)
    np.testing.assert_allclose(rough.qdd, ref.qdd, rtol=0, atol=1e-9 * np.abs(ref.qdd).max())

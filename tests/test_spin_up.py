"""The spin-up benchmark's pieces: the trapezoidal integrator, prescribed motion in both engines, the quick run."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.model import FORMS, ErlsModel
from exuflex.erls.simulate import simulate
from exuflex.mechanism import load_mechanism

ROOT = Path(__file__).resolve().parents[1]


def test_trapezoid_converges_at_second_order_without_damping():
    """A damped oscillator ``x'' + 2 z w x' + w^2 x = 0`` against its analytic solution: the fitted log-log slope
    of the error is 2; undamped, the trapezoidal rule keeps the amplitude exactly (A-stable, no numerical damping)."""
    w, z = 7.0, 0.05
    A = np.array([[0.0, 1.0], [-(w**2), -2 * z * w]])

    def f(t, y, u):
        return A @ y

    wd = w * np.sqrt(1 - z * z)
    exact = np.exp(-z * w * 2.0) * (np.cos(wd * 2.0) + z * w / wd * np.sin(wd * 2.0))
    hs = np.array([1e-2, 5e-3, 2.5e-3])
    err = [abs(simulate(f, [1.0, 0.0], 2.0, lambda t: None, h=h, method="trapezoid", jac=lambda t, y: A).y[-1, 0]
               - exact) for h in hs]
    assert 1.9 < np.polyfit(np.log(hs), np.log(err), 1)[0] < 2.1
    A0 = np.array([[0.0, 1.0], [-(w**2), 0.0]])
    y = simulate(lambda t, y, u: A0 @ y, [1.0, 0.0], 20.0, lambda t: None, h=0.05, method="trapezoid",
                 jac=lambda t, y: A0).y
    energy = y[:, 1] ** 2 + w**2 * y[:, 0] ** 2
    assert np.abs(energy / energy[0] - 1).max() < 1e-9
    with pytest.raises(ValueError, match="needs jac"):
        simulate(f, [1.0, 0.0], 0.1, lambda t: None, h=0.01, method="trapezoid")


@pytest.mark.parametrize("form", FORMS)
def test_prescribed_accelerations_are_the_elastic_rows_of_the_free_motion(form):
    """Prescribing ``q''`` as the free model computes it gives back the free model's ``u''``; the Jacobian of the
    prescribed accelerations equals finite differences (they are linear in ``u, u'``). The geometric stiffness's
    axial loads differ by construction: the free rows take them from the torques' rigid acceleration, the
    prescribed ones from ``q''`` (which holds the elastic coupling too); that difference is added back."""
    m = ErlsModel(load_mechanism(ROOT / "models" / "sixbar.toml"), form=form)
    rng = np.random.default_rng(5)
    x = np.r_[np.array(m.mech.q_ref) + 0.1 * rng.standard_normal(m.nq), 1e-4 * rng.standard_normal(m.ne)]
    v = np.r_[rng.standard_normal(m.nq), 1e-2 * rng.standard_normal(m.ne)]
    tau = rng.standard_normal(len(m.mech.motors))
    free = m.accelerations(x, v, tau)
    # the prescribed rows carry no motor torques: take them out of the free motion's elastic rows
    cfg = m.configuration(x[: m.nq])
    F_u = m.input_matrix(cfg)[m.nq :] @ tau
    M = m.mass(cfg)
    presc = m.prescribed_accelerations(x, v, free[: m.nq])
    dN = m.rigid_axial_forces(cfg, v[: m.nq], tau) - m.rigid_axial_forces(cfg, v[: m.nq], None, free[: m.nq])
    presc += np.linalg.solve(M[m.nq :, m.nq :], m.geometric_forces(cfg, dN, x[m.nq :]))
    np.testing.assert_allclose(presc + np.linalg.solve(M[m.nq :, m.nq :], F_u), free[m.nq :], rtol=1e-9,
                               atol=1e-9 * np.abs(free[m.nq :]).max())
    qdd = free[: m.nq]
    Jp = m.prescribed_jacobian(x, v, qdd=qdd)
    fd = np.empty_like(Jp)
    for k in range(2 * m.ne):
        e = np.zeros(2 * m.ne)
        e[k] = 1e-6
        xp, vp = x.copy(), v.copy()
        xm, vm = x.copy(), v.copy()
        (xp if k < m.ne else vp)[m.nq + k % m.ne] += e[k]
        (xm if k < m.ne else vm)[m.nq + k % m.ne] -= e[k]
        fd[:, k] = (m.prescribed_accelerations(xp, vp, qdd) - m.prescribed_accelerations(xm, vm, qdd)) / 2e-6
    assert np.abs(Jp - fd).max() < 1e-6 * np.abs(fd).max()


def _spin_up_module():
    spec = importlib.util.spec_from_file_location("spin_up", ROOT / "benchmarks" / "spin_up.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_spin_up_quick_agrees_with_exudyn_at_slow_speed(capsys):
    """``benchmarks/spin_up.py --quick`` (0.25 rad/s reached in 3 s): both ERLS forms within 2 % NRMS of Exudyn's
    ANCF beam, Exudyn's two beam formulations within 0.1 % of each other, the hub drive exact."""
    import json

    pytest.importorskip("exudyn")
    mod = _spin_up_module()
    assert mod.main(["--quick", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) >= {"slow_nrms_pct", "departure_rad_s"}
    assert out["slow_nrms_pct"] < 2.0
    assert out["ge_vs_ancf_pct"][0] < 0.1
    assert out["drive_error_rad"] < 1e-9
    assert mod.departure([1.0, 2.0, 3.0], [0.01, 0.03, 0.07]) == pytest.approx(2.5)
    assert mod.departure([1.0, 2.0], [0.01, 0.02]) is None


def test_prescribed_motion_errors():
    pytest.importorskip("exudyn")
    from exuflex.groundtruth import simulate_prescribed

    mech = load_mechanism(ROOT / "models" / "spin_up.toml")
    with pytest.raises(ValueError, match="one angle per coordinate"):
        simulate_prescribed(mech, lambda t: np.zeros(2), 0.01, [], h=1e-3)

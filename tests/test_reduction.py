"""Craig-Bampton reduction: exactness limits, Guyan statics, ranking, accuracy on the six-bar."""

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism
from exuflex.reduction import CraigBampton, ReducedModel, accuracy_indices, reduced_modes

MODELS = Path(__file__).resolve().parents[1] / "models"


@pytest.fixture(scope="module")
def sixbar():
    return ErlsModel(load_mechanism(MODELS / "sixbar.toml"))


def test_all_interior_modes_reproduce_full_eigenvalues(sixbar):
    cb = CraigBampton(sixbar, n_interior=len(sixbar.dofs.names) - 5)
    q = np.array([0.8, 2.6, 4.6])
    fr, _, _ = reduced_modes(cb, q)
    ff = modal_analysis(sixbar, q).frequencies_hz
    np.testing.assert_allclose(fr, ff, rtol=1e-8)


def test_frequencies_are_upper_bounds_and_converge_monotonically(sixbar):
    q = np.array(sixbar.mech.q_ref)
    ff = modal_analysis(sixbar, q).frequencies_hz[:6]
    cb = CraigBampton(sixbar, n_interior=0)
    prev = None
    for k in range(0, 12):
        cb.set_interior(k)
        fr = reduced_modes(cb, q)[0][:6]
        assert np.all(fr >= ff[: len(fr)] * (1 - 1e-10))  # Rayleigh-Ritz upper bounds
        if prev is not None:
            assert np.all(fr[: len(prev)] <= prev * (1 + 1e-10))  # nested subspaces: monotone
        prev = fr


def test_rotation_is_identity_at_qstar(sixbar):
    cb = CraigBampton(sixbar, n_interior=5)
    np.testing.assert_allclose(cb.rotation(cb.cfg_star), np.eye(sixbar.ne), atol=0)
    np.testing.assert_allclose(cb.rotated_modes(cb.cfg_star), cb.Phi, atol=0)


def test_guyan_reproduces_static_master_deflections(sixbar):
    cb = CraigBampton(sixbar, n_interior=0)
    q = np.array([0.9, 2.5, 4.4])
    rc = cb.at(q)
    T = sixbar.T
    Kuu = T.T @ rc.cfg.K_N @ T
    f = np.zeros(sixbar.ne)
    f[cb.im] = np.random.default_rng(0).standard_normal(len(cb.im))  # loads on masters only
    u = np.linalg.solve(Kuu, f)
    np.testing.assert_allclose(rc.B @ u[cb.im], u[cb.is_], rtol=1e-9, atol=1e-12 * np.abs(u).max())


def test_sixbar_13_dofs_meet_paper_accuracy_at_qstar(sixbar):
    cb = CraigBampton(sixbar)  # model file: paper masters, 5 interior modes, IMR
    assert cb.r == 13
    acc = accuracy_indices(cb, cb.q_star)
    assert len(acc.full_hz) == 6
    assert acc.worst_nco >= 0.99 and acc.worst_error_pct <= 2.0


def test_imr_beats_frequency_truncation_on_the_worst_mode(sixbar):
    imr = accuracy_indices(CraigBampton(sixbar, n_interior=5, ranking="imr"), sixbar.mech.q_ref)
    low = accuracy_indices(CraigBampton(sixbar, n_interior=5, ranking="frequency"), sixbar.mech.q_ref)
    assert imr.worst_error_pct < low.worst_error_pct


def test_auto_count_meets_thresholds(sixbar):
    cb = CraigBampton(sixbar, n_interior="auto")
    acc = accuracy_indices(cb, cb.q_star)
    assert acc.ok(0.99, 2.0)
    cb.set_interior(cb.n_interior - 1)
    assert not accuracy_indices(cb, cb.q_star).ok(0.99, 2.0)  # smallest such set


def test_rotation_is_what_makes_one_qstar_serve_the_manoeuvre(sixbar):
    cb = CraigBampton(sixbar, n_interior=5)
    q = np.array([0.82, 2.68, 5.1])
    good = accuracy_indices(cb, q)
    assert good.worst_nco >= 0.98 and good.worst_error_pct <= 3.0
    cb.rotate = False  # constant (unrotated) interior modes
    bad = accuracy_indices(cb, q)
    cb.rotate = True
    assert bad.worst_error_pct > 10 * good.worst_error_pct


def test_basis_builds_fast(sixbar):
    cb = CraigBampton(sixbar)
    assert cb.build_seconds < 1.0


def test_reduced_state_round_trip(sixbar):
    cb = CraigBampton(sixbar, n_interior=5)
    rm = ReducedModel(cb)
    rng = np.random.default_rng(1)
    z = rm.rest_state([0.9, 2.5, 4.4])
    z[3 : rm.r] = 1e-4 * rng.standard_normal(rm.r - 3)
    z[rm.r :] = 1e-2 * rng.standard_normal(rm.r)
    x, v = rm.full_state(z)
    np.testing.assert_allclose(rm.reduce_state(x, v), z, atol=1e-10)


def test_reduced_matrices_symmetric_positive(sixbar):
    rm = ReducedModel(CraigBampton(sixbar, n_interior=5))
    mats = rm.matrices([0.9, 2.5, 4.4])
    np.testing.assert_allclose(mats.Mr, mats.Mr.T, atol=1e-12)
    np.testing.assert_allclose(mats.Kr, mats.Kr.T, atol=1e-6 * np.abs(mats.Kr).max())
    assert np.all(np.linalg.eigvalsh(mats.Mr) > 0)


def test_along_the_manoeuvre_config_dependent_basis_keeps_accuracy(sixbar):
    """>= 20 configurations of the paper's manoeuvre, one basis built at q*: NCO >= 0.98, error <= 3 %;
    a constant basis H(q*) (B and Phi frozen) fails badly, which is what R(q, q*) and B(q) buy."""
    from exuflex.manoeuvre import plan
    from exuflex.reduction import accuracy_along

    qs = plan(sixbar.mech, dt=3.0 / 24, t_end=3.0).q  # 25 configurations
    cb = CraigBampton(sixbar)
    accs = accuracy_along(cb, qs)
    assert len(accs) >= 20
    assert min(a.worst_nco for a in accs) >= 0.98
    assert max(a.worst_error_pct for a in accs) <= 3.0
    import dataclasses

    rc_star = cb.at(cb.q_star)
    at = cb.at

    def constant(q, z0=None):  # matrices at q, basis H(q*)
        return dataclasses.replace(at(q, z0), B=rc_star.B, Psi=rc_star.Psi, H=rc_star.H)

    cb.at = constant
    try:
        frozen = [accuracy_indices(cb, q) for q in qs[::6]]
    finally:
        del cb.at
    assert max(a.worst_error_pct for a in frozen) > 100.0


def test_analytic_mass_derivative_matches_finite_differences(sixbar):
    rm = ReducedModel(CraigBampton(sixbar))
    rng = np.random.default_rng(2)
    p = np.r_[0.9, 2.5, 4.5, 1e-4 * rng.standard_normal(rm.r - 3)]
    mats = rm.matrices(p)
    dHdq = rm.cb.basis_derivative(mats.rc, np.eye(rm.r))
    analytic = rm.mass_derivative_analytic(mats, dHdq)
    fd = rm.mass_derivative(mats, p, delta=1e-7)
    assert np.abs(analytic - fd).max() < 1e-3 * np.abs(fd).max()


@pytest.mark.skipif(not __import__("exuflex.reduction._compiled").reduction._compiled.HAVE_NUMBA,
                    reason="numba is not installed")
@pytest.mark.parametrize("consistent", [True, False])
@pytest.mark.parametrize("case", ["sixbar", "fourbar_guyan_only"])
def test_compiled_configuration_evaluation_equals_numpy(sixbar, consistent, case):
    """The compiled twins of a configuration evaluation (nodal assembly, basis and Guyan shapes, basis
    derivative, reduced matrices, held force model; :mod:`exuflex.reduction._compiled`,
    :mod:`exuflex.erls._assembly`), piecewise and in one call (:func:`~exuflex.reduction._compiled.held_evaluation`),
    agree with the NumPy expressions to rounding (measured: 2e-11 relative on the
    six-bar, from the slave block's condition number 6e5) at moving, deformed states away from q*; also on the
    four-bar without interior modes."""
    model = sixbar if case == "sixbar" else ErlsModel(load_mechanism(MODELS / "fourbar.toml"))
    cb = CraigBampton(model) if case == "sixbar" else CraigBampton(model, n_interior=0)
    rm = ReducedModel(cb, consistent=consistent)
    rng = np.random.default_rng(7)
    for dq in (0.2, -0.3):
        q = np.asarray(cb.q_star) + dq * rng.standard_normal(rm.nq)
        p = np.concatenate([q, 1e-4 * rng.standard_normal(rm.r - rm.nq)])
        pd = np.concatenate([rng.standard_normal(rm.nq), 1e-2 * rng.standard_normal(rm.r - rm.nq)])
        out = []
        # NumPy (the reference), the piecewise compiled calls, held in one compiled call
        for compiled, one_call in ((False, False), (True, False), (True, True)):
            model.compiled = cb.compiled = rm.compiled = compiled
            rm.one_call = one_call
            mats, forces = rm.held(p, pd)
            out.append([mats.rc.cfg.M_N, mats.rc.cfg.K_N, mats.rc.cfg.R, mats.rc.H, mats.rc.B, mats.rc.Psi,
                        mats.rc.Kuu, mats.rc.Kss_inv, mats.J, mats.Mr, mats.Kr, mats.Cr, mats.Gr, forces.fg,
                        forces.T2, forces.V2, forces.dMr2, forces.dKr2,
                        cb.basis_derivative(mats.rc, np.column_stack([p, pd])), *forces.jacobian_tensors()]
                       + ([forces.C2] if consistent else []))
        model.compiled = cb.compiled = rm.compiled = rm.one_call = True
        for a, b, c in zip(*out):
            assert a.shape == b.shape == c.shape
            if a.size:
                np.testing.assert_allclose(b, a, rtol=0, atol=1e-9 * np.abs(a).max())
                np.testing.assert_allclose(c, a, rtol=0, atol=1e-9 * np.abs(a).max())
                # the one call and the piecewise calls do the same arithmetic
                np.testing.assert_allclose(c, b, rtol=0, atol=1e-13 * np.abs(a).max())

"""ERLS kinematics: S(q) and dS/dt agree with central differences of the closure solution."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.kinematics import Kinematics
from exuflex.mechanism import load_mechanism

MODELS = Path(__file__).resolve().parents[1] / "models"
NAMES = ("sixbar", "single_link", "fourbar", "slider_crank")
H = 1e-5  # central-difference step (rad): truncation ~H^2 = 1e-10, round-off ~1e-16 / H = 1e-11


def _configs(mech, n=3, seed=0):
    """q_ref and a few configurations near it (0.1 rad away: inside the same assembly branch)."""
    rng = np.random.default_rng(seed)
    q0 = np.array(mech.q_ref)
    return [q0] + [q0 + 0.1 * rng.standard_normal(q0.size) for _ in range(n - 1)]


def _rel(a, b, scale=0.0):
    """Largest entry error relative to the largest entry of b (or ``scale`` if larger)."""
    return np.abs(a - b).max() / max(np.abs(b).max(), scale)


@pytest.mark.parametrize("name", NAMES)
def test_closure_residual(name):
    kin = Kinematics(load_mechanism(MODELS / f"{name}.toml"))
    for q in _configs(kin.mech):
        z = kin.solve(q)
        assert np.abs(kin.residual(z, q)).max() < 1e-13


@pytest.mark.parametrize("name", NAMES)
def test_S_matches_finite_differences(name):
    kin = Kinematics(load_mechanism(MODELS / f"{name}.toml"))
    worst = 0.0
    for q in _configs(kin.mech):
        pose = kin.pose(q)
        S_fd = np.empty_like(pose.S)
        Sz_fd = np.empty_like(pose.Sz)
        for j in range(q.size):
            e = np.zeros(q.size)
            e[j] = H
            pp, pm = kin.pose(q + e), kin.pose(q - e)
            S_fd[:, j] = (pp.r - pm.r) / (2 * H)
            Sz_fd[:, j] = (pp.z - pm.z) / (2 * H)
        worst = max(worst, _rel(pose.S, S_fd), _rel(pose.Sz, Sz_fd))
    print(f"{name}: max relative |S - S_fd| = {worst:.2e}")
    assert worst < 1e-6


@pytest.mark.parametrize("name", NAMES)
def test_Sdot_matches_finite_differences(name):
    """dS/dt along q(t) = q + t qd equals (S(q + h qd) - S(q - h qd)) / 2h."""
    kin = Kinematics(load_mechanism(MODELS / f"{name}.toml"))
    rng = np.random.default_rng(1)
    worst = 0.0
    for q in _configs(kin.mech):
        qd = rng.standard_normal(q.size)
        pose = kin.pose(q)
        Szd, Sd = kin.rates(pose, qd)
        pp, pm = kin.pose(q + H * qd), kin.pose(q - H * qd)
        Sd_fd = (pp.S - pm.S) / (2 * H)
        Szd_fd = (pp.Sz - pm.Sz) / (2 * H)
        # the link-pose rates vanish for the single link (fixed origin, angle = q): scale by |S_z| |qd|
        worst = max(worst, _rel(Sd, Sd_fd), _rel(Szd, Szd_fd, np.abs(pose.Sz).max() * np.abs(qd).max()))
    print(f"{name}: max relative |dS/dt - FD| = {worst:.2e}")
    assert worst < 1e-6


def test_fourbar_closure_is_nonlinear():
    """The four-bar's coupler and rocker angles are nonlinear in the crank angle: dS/dt != 0."""
    kin = Kinematics(load_mechanism(MODELS / "fourbar.toml"))
    pose = kin.pose(kin.mech.q_ref)
    Szd, _ = kin.rates(pose, [1.0])
    coupler_rocker = Szd[[5, 8]]  # d/dt of the angle sensitivities of links 2 and 3
    assert np.abs(coupler_rocker).min() > 0.05


def test_fourbar_geometry():
    """Closed form at the crank-vertical reference: A = (0, 0.15), B from the two circles."""
    kin = Kinematics(load_mechanism(MODELS / "fourbar.toml"))
    pose = kin.pose(kin.mech.q_ref)
    A, _ = kin.point(pose, "crank", 0.15)
    B, _ = kin.point(pose, "rocker", 0.45)
    np.testing.assert_allclose(A, [0.0, 0.15], atol=1e-14)
    assert np.linalg.norm(B - A) == pytest.approx(0.5, abs=1e-13)
    assert np.linalg.norm(B - [0.6, 0.0]) == pytest.approx(0.45, abs=1e-13)
    assert B[1] > 0  # the assembly branch of the angle guesses (open configuration)


@pytest.mark.parametrize("name", NAMES)
def test_batched_coordinate_rates_equal_one_rate_per_coordinate(name):
    """``coordinate_rates`` (all unit rates at once, for the force model) equals :meth:`rates` per e_j."""
    kin = Kinematics(load_mechanism(MODELS / f"{name}.toml"))
    for q in _configs(kin.mech):
        pose = kin.pose(q)
        batched = kin.coordinate_rates(pose)
        kin.compiled = False  # the NumPy batch, the reference of the compiled one
        batched_numpy = kin.coordinate_rates(pose)
        kin.compiled = True
        for j, e in enumerate(np.eye(q.size)):
            ref = kin.rates(pose, e)[1]
            scale = np.abs(ref).max() + 1e-300
            np.testing.assert_allclose(batched[j], ref, rtol=1e-11, atol=1e-12 * scale)
            np.testing.assert_allclose(batched_numpy[j], ref, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("name", NAMES)
def test_compiled_newton_equals_numpy_newton(name):
    """The compiled closure iteration (:mod:`exuflex.erls._closure`) against its NumPy reference, from the
    initial guess and from a neighbouring solution."""
    from exuflex.erls._closure import HAVE_NUMBA

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    kin = Kinematics(load_mechanism(MODELS / f"{name}.toml"))
    rng = np.random.default_rng(3)
    for q in _configs(kin.mech):
        near = kin.solve(q + 0.03 * rng.standard_normal(q.size))
        for z0 in (kin.initial_guess(q), near):
            a = kin._newton(z0, q, 1e-12, 30)
            b = kin._newton_numpy(z0, q, 1e-12, 30)
            assert (a is None) == (b is None)
            if a is not None:
                np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


def test_compiled_solve_is_lapack_solve():
    """The closure Newton's compiled solve (LAPACK's dgesv called directly) gives exactly numba's compiled
    ``np.linalg.solve`` (the same routine on the same copies), NumPy's to rounding, and raises LinAlgError where
    they do: a singular or non-finite matrix, a non-finite right-hand side."""
    from exuflex.erls._closure import HAVE_NUMBA, _solve

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    import numba

    lapack_solve = numba.njit(lambda A, b: np.linalg.solve(A, b))
    rng = np.random.default_rng(5)
    for n in (1, 3, 12):
        A = rng.standard_normal((n, n)) + n * np.eye(n)
        b = rng.standard_normal(n)
        x = _solve(A, b)
        np.testing.assert_array_equal(x, lapack_solve(A, b))
        np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-12)
    A = np.ones((3, 3))
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        _solve(A, np.ones(3))
    B = np.eye(3)
    B[1, 2] = np.nan
    with pytest.raises(np.linalg.LinAlgError, match="infs or NaNs"):
        _solve(B, np.ones(3))
    with pytest.raises(np.linalg.LinAlgError, match="infs or NaNs"):
        _solve(np.eye(3), np.array([1.0, np.inf, 0.0]))


@pytest.mark.parametrize("name", NAMES)
def test_compiled_pose_equals_numpy_pose(name):
    """The compiled pose sensitivities (closure Jacobian, its inverse, condition, S_z, nodal r and S) against
    the NumPy path they replace."""
    from exuflex.erls._closure import HAVE_NUMBA

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    fast = Kinematics(load_mechanism(MODELS / f"{name}.toml"))
    ref = Kinematics(load_mechanism(MODELS / f"{name}.toml"))
    ref.compiled = False
    for q in _configs(fast.mech):
        a, b = fast.pose(q), ref.pose(q)
        for x, y in ((a.z, b.z), (a.Sz, b.Sz), (a.r, b.r), (a.S, b.S), (a.Jinv, b.Jinv)):
            np.testing.assert_allclose(x, y, rtol=1e-11, atol=1e-13)
        assert a.cond == pytest.approx(b.cond, rel=1e-10)


@pytest.mark.parametrize("name", NAMES)
def test_closure_functions_batch_over_leading_axes(name):
    """residual, jacobian and d(Phi_z)/dt on a stack of poses equal the single-pose values; the product
    (dPhi_z/dt) z' equals the matrix times z' and the finite difference of Phi_z along z'."""
    kin = Kinematics(load_mechanism(MODELS / f"{name}.toml"))
    rng = np.random.default_rng(3)
    qs = _configs(kin.mech)
    zs = np.array([kin.solve(q) for q in qs])
    zds = rng.standard_normal(zs.shape)
    res = kin.residual(zs, np.array(qs))
    J = kin.jacobian(zs)
    Jd = kin._jacobian_rate(zs, zds)
    prod = kin.jacobian_rate_product(zs, zds)
    for k, q in enumerate(qs):
        np.testing.assert_array_equal(res[k], kin.residual(zs[k], q))
        np.testing.assert_array_equal(J[k], kin.jacobian(zs[k]))
        np.testing.assert_array_equal(Jd[k], kin._jacobian_rate(zs[k], zds[k]))
        np.testing.assert_allclose(prod[k], Jd[k] @ zds[k], rtol=0, atol=1e-13 * np.abs(Jd[k]).max())
        fd = (kin.jacobian(zs[k] + H * zds[k]) - kin.jacobian(zs[k] - H * zds[k])) / (2 * H)
        assert _rel(fd @ zds[k], prod[k], 1.0) < 1e-8

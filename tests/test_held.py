"""The compiled arithmetic of the cached observer step equals its NumPy reference (:mod:`exuflex.observer.held`)."""

import numpy as np
import pytest

from exuflex.observer import held

pytestmark = pytest.mark.skipif(not held.HAVE_NUMBA, reason="numba is not installed")


def _system(r=13, nq=3, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(r, r))
    Mr = A @ A.T + r * np.eye(r)
    K = rng.normal(size=(r, r))
    Kr = 1e3 * K @ K.T
    Kr[:nq] = Kr[:, :nq] = 0.0  # rigid coordinates: no stiffness
    Ca = 0.1 * np.eye(r)
    Gr = rng.normal(size=(r, nq))

    def grad():
        g = 1e-2 * rng.normal(size=(nq, r, r))
        return (g + np.swapaxes(g, 1, 2)).reshape(nq, r * r)

    forces = dict(fg=rng.normal(size=r), T2=rng.normal(size=(r, r * r)), V2=rng.normal(size=(nq * r, r)),
                  C2=rng.normal(size=(r * nq, r)))
    return rng, Mr, Kr, Ca, Gr, grad, forces


@pytest.mark.parametrize("has_old", [False, True])
def test_held_step_kernel_equals_numpy_reference(has_old):
    r, nq = 13, 3
    rng, Mr, Kr, Ca, Gr, grad, fo = _system(r, nq)
    z = 0.1 * rng.normal(size=2 * r)
    u = rng.normal(size=nq)
    dl = 1e-3 * rng.normal(size=nq)
    old = _system(r, nq, seed=1)
    args = (z, u, dl, 0.4, has_old, nq, 1e-3, 1e-4, 20, Mr, Kr, Ca, Gr, grad(), grad(), fo["fg"], fo["T2"], fo["V2"],
            fo["C2"], grad(), grad(), old[3], old[4], old[6]["fg"], old[6]["T2"], old[6]["V2"], old[6]["C2"])
    ref = held.held_step_numpy(*args)
    fast = held.held_step_loops(*args)
    for a, b in zip(ref, fast):
        np.testing.assert_allclose(b, a, rtol=1e-11, atol=1e-13 * np.abs(a).max())


def test_held_step_without_velocity_coupling_term():
    """The paper's velocity transformation has no bias term (an empty C2)."""
    r, nq = 13, 3
    rng, Mr, Kr, Ca, Gr, grad, fo = _system(r, nq)
    z = 0.1 * rng.normal(size=2 * r)
    noC = np.zeros((0, r))
    g = grad()
    args = (z, np.ones(nq), np.zeros(nq), 0.0, False, nq, 0.0, 1e-4, 20, Mr, Kr, Ca, Gr, g, g, fo["fg"], fo["T2"],
            fo["V2"], noC, g, g, Ca, Gr, fo["fg"], fo["T2"], fo["V2"], noC)
    np.testing.assert_allclose(held.held_step_loops(*args)[0], held.held_step_numpy(*args)[0], rtol=1e-11)


def test_step_maps_kernel_equals_numpy_reference():
    r, nq = 13, 3
    _, Mr, Kr, Ca, Gr, _, _ = _system(r, nq)
    Cr = Ca + 1e-3 * Kr
    var = np.array([0.01, 0.04, 1e-4])
    for n in (1, 7, 20):
        ref = held.step_maps_held_numpy(Mr, Kr, Cr, Gr, 1e-4, n, var)
        fast = held.step_maps_held(Mr, Kr, Cr, Gr, 1e-4, n, var)
        for a, b in zip(ref, fast):
            np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12 * np.abs(a).max())


def test_rk4_kernel_is_n_rk4_steps_of_the_linear_system():
    """Against the step map: z_n = P^n z + SQM (G u + f) for the same held system."""
    r, nq = 13, 3
    rng, Mr, Kr, Ca, Gr, _, _ = _system(r, nq)
    Cr = Ca + 1e-3 * Kr
    z, u, f = rng.normal(size=2 * r), rng.normal(size=nq), rng.normal(size=r)
    Pn, SQM, L = held.step_maps(np.linalg.inv(Mr), Kr, Cr, Gr, 1e-4, 20)
    expected = Pn @ z + L @ u + SQM @ f
    np.testing.assert_allclose(held.rk4_held_loops(z, u, Mr, Kr, Cr, Gr, f, 1e-4, 20), expected, rtol=1e-9,
                               atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(held.rk4_held_numpy(z, u, Mr, Kr, Cr, Gr, f, 1e-4, 20), expected, rtol=1e-9,
                               atol=1e-12 * np.abs(expected).max())


def test_a_mass_matrix_that_is_not_positive_definite_gives_nan_not_garbage():
    r = 4
    Mr = -np.eye(r)
    out = held.rk4_held_loops(np.ones(2 * r), np.zeros(1), Mr, np.eye(r), np.eye(r), np.ones((r, 1)), np.zeros(r),
                              1e-4, 2)
    assert np.all(np.isnan(out))

"""The geometric stiffness of the motion's axial loads in the reduced model.

The full model's elastic rows carry ``K_G(N(q, q', tau))`` of the rigid motion's axial loads
(:meth:`exuflex.erls.model.ErlsModel.net_forces`); the reduced model holds the static part (the weight with the
holding torques) in ``K_r`` and the rest, affine in the torques and quadratic in the rates, as a linear form at
each held configuration (:meth:`exuflex.reduction.model.ReducedModel.motion_geometric`), which the cached step
contracts with each interval's torques and start rates (:func:`exuflex.observer.expansion.motion_stiffness`).
Checked entry by entry against the full model's forces, and one interval of the cached step against the RK4 step
of the reduced equations on the slider-crank with a heavy slider (where the rod's axial force is a few percent of
its buckling load).
"""

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism
from exuflex.observer.expansion import held_interval, motion_stiffness
from exuflex.observer.reduced import ReducedObserverModel
from exuflex.reduction import CraigBampton, ReducedModel
from exuflex.reduction.model import motion_coefficients

ROOT = Path(__file__).resolve().parents[1]
MODELS = [ROOT / "models" / "slider_crank.toml", ROOT / "benchmarks" / "models" / "crane_arm.toml",
          ROOT / "models" / "three_link_arm.toml"]


def _reduced(path, payload_scale=1.0):
    mech = load_mechanism(path)
    if payload_scale != 1.0:
        mech = mech.with_payload_scale(payload_scale)
    return mech, ReducedModel(CraigBampton(ErlsModel(mech)))


@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.stem)
def test_motion_form_equals_the_full_models_geometric_forces(path):
    """``-J^T [0; T^T K_G(N - N_s) T H_u p]`` of the full model's axial forces at a moving, deflected state, against
    the form contracted with ``[1, tau, q'q']`` and against :meth:`ReducedModel.motion_stiffness`, entry by entry
    (each entry against its own size)."""
    mech, rm = _reduced(path)
    model, nq, r = rm.model, rm.nq, rm.r
    rng = np.random.default_rng(1)
    q = np.asarray(mech.q_ref, float)
    p = np.concatenate([q, 1e-4 * rng.standard_normal(r - nq)])
    pd = np.concatenate([3.0 * rng.standard_normal(nq), 1e-2 * rng.standard_normal(r - nq)])
    tau = rng.standard_normal(len(mech.motors))
    mats = rm.matrices(p, pd, forces=False)
    cfg = mats.rc.cfg
    N = model.rigid_axial_forces(cfg, pd[:nq], tau)
    if cfg.N_static is not None:
        N = N - cfg.N_static
    full = mats.J[nq:].T @ model.geometric_forces(cfg, N, mats.rc.H[nq:] @ p)
    form = -np.tensordot(motion_coefficients(tau, pd[:nq]), rm.motion_geometric(mats.rc, mats.J), 1) @ p
    direct = -rm.motion_stiffness(mats.rc, mats.J, pd[:nq], tau) @ p
    scale = np.abs(full) + 1e-12 * np.abs(full).max()
    assert np.abs(full).max() > 0
    assert np.all(np.abs(form - full) <= 1e-8 * scale)
    assert np.all(np.abs(direct - full) <= 1e-8 * scale)


def test_cached_interval_carries_the_motion_stiffness_as_the_reduced_equations_do():
    """One 1 ms interval at the slider-crank's (payload x1.5) peak rate and a large torque, from the deflection the
    motion's loads cause: what the motion's geometric stiffness changes in the cached step (with and without the
    held form) against what it changes in the RK4 step of the reduced equations (every stage at its own state),
    against the change's largest entry in the positions and in the rates; the form contracted in the kernel equals
    the direct stiffness."""
    mech, rm = _reduced(ROOT / "models" / "slider_crank.toml", 1.5)
    nq, r = rm.nq, rm.r
    som = ReducedObserverModel(rm)
    z = np.zeros(2 * r)
    z[:nq], z[r : r + nq] = 2.6, 16.0
    tau = np.array([3.0])
    mats = rm.matrices(z[:r], z[r:])
    e = slice(nq, r)
    K = mats.Kr + rm.motion_stiffness(mats.rc, mats.J, z[r : r + nq], tau)
    z[e] = np.linalg.solve(K[e, e], (mats.Gr @ tau + mats.fr)[e])  # in equilibrium with the motion's stiffness
    iv = som._configuration(z, held=True)
    iv.Ca = iv.mats.Cr - som.model.beta * iv.mats.Kr
    iv.system = som._held_system(iv)
    assert iv.system.KGd.shape[0] == 3  # [1, tau, q'^2]
    dt = 1e-3
    n = som.substeps(iv, dt)
    jac = (np.zeros((0, 0, 0)), np.zeros((0, 0, 0)), np.zeros((0, 0, 0)), np.zeros((0, 0)), np.zeros((0, 0)))
    dl = np.zeros(nq)
    cached = held_interval(z, tau, np.empty(0), dl, 0.0, dt / n, n, *jac, tuple(iv.system))[0]
    cached0 = held_interval(z, tau, np.empty(0), dl, 0.0, dt / n, n, *jac, tuple(iv.system._replace(KGd=np.zeros((0, 0)))))[0]
    exact = ReducedObserverModel(rm, method="rk4").predict(z, tau, dt).x
    rm.motion_stiffness = lambda *a: np.zeros((r, r))  # the reduced equations without it
    exact0 = ReducedObserverModel(rm, method="rk4").predict(z, tau, dt).x
    d_cached, d_exact = cached - cached0, exact - exact0
    for part in (slice(0, r), slice(r, 2 * r)):
        scale = np.abs(d_exact[part]).max()
        assert scale > 0
        err = np.abs(d_cached[part] - d_exact[part]).max() / scale
        # the held force at the midpoint positions does not follow the static corrections (Ritz frequencies of
        # kHz), which move within the interval: measured 0.59 of the change in the positions and 0.73 in the rates
        # at this state (without the form the error is the whole change). The filter's figures with the held force
        # equal those with the form in the step's stiffness (docs/payload_mismatch.md's slider-crank x1.5).
        assert err <= 0.8, err
    # the form contracted in the kernel equals the direct stiffness at the interval's start
    del rm.motion_stiffness
    K = motion_stiffness(tau, z, nq, iv.system.KGd)
    K_direct = rm.motion_stiffness(iv.mats.rc, iv.mats.rc.H, z[r : r + nq], tau)
    assert np.allclose(K, K_direct, rtol=1e-10, atol=1e-10 * np.abs(K_direct).max())

"""The ERLS damping acts on the strain rate, the rate of the elastic displacements relative to the turning links.

The Lagrange form's dissipation function is ``D = v^T C(x) v / 2`` with ``C(x) = L^T (alpha P + beta K_N) L`` and
the strain-rate map ``L = [-Y(x), T]`` (:meth:`~exuflex.erls.model.ErlsModel.damping`). The oracles here are
independent of that algebra: the element-frame displacements ``e = R(theta)^T d`` of every element (and node),
differentiated in time by central differences along the motion ``x + t v``, give ``D`` from the element
stiffness matrices and the mass relative to the rigid motion (a least-squares fit of ``S a``); a bent link turned
rigidly is built by turning its nodal displacements. The free modes' ratios at rest are
``tests/test_damping.py``'s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.elements import rotation
from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"


def _model(name: str) -> ErlsModel:
    path = MODELS / f"{name}.toml"
    if not path.exists():
        path = ROOT / "benchmarks" / "models" / f"{name}.toml"
    return ErlsModel(load_mechanism(path))


def _local_rates(model: ErlsModel, x: np.ndarray, v: np.ndarray, h: float = 1e-5):
    """``(e_el', e_node')``: the element-frame rates ``d/dt (R_e^T d_e)`` of every element (n_el, 6) and of every
    node's displacement in its link's frame (N,), by central differences in t along ``x + t v``."""
    nq = model.nq

    def local(t):
        y = x + t * v
        th = model.configuration(y[:nq]).pose.link_angles
        d = model.T @ y[nq:]
        Re = rotation(th[model.el_link])
        el = np.einsum("eji,ej->ei", Re, d[model.el_dofs])
        Rn = rotation(th[model.kin.node_link])[:, :3, :3]
        nodes = np.einsum("nji,nj->ni", Rn, d.reshape(-1, 3)).ravel()
        return el, nodes, th

    (ep, np_, _), (em, nm, _) = local(h), local(-h)
    th = local(0.0)[2]
    Rn = rotation(th[model.kin.node_link])[:, :3, :3]
    s_nodes = np.einsum("nij,nj->ni", Rn, ((np_ - nm) / (2 * h)).reshape(-1, 3)).ravel()  # back to global
    return (ep - em) / (2 * h), s_nodes


def _dissipation(model: ErlsModel, x: np.ndarray, v: np.ndarray) -> float:
    """``D = beta/2 sum_e e_e'^T K_e e_e' + alpha/2 min_a |S a + s|^2_{M_N}`` from the local rates (oracle)."""
    e_rate, s = _local_rates(model, x, v)
    cfg = model.configuration(x[: model.nq])
    D = 0.5 * model.beta * np.einsum("ei,eij,ej->", e_rate, model.Kl, e_rate)
    if model.alpha:
        Lc = np.linalg.cholesky(cfg.M_N).T
        a, *_ = np.linalg.lstsq(Lc @ cfg.pose.S, -Lc @ s, rcond=None)
        b = cfg.pose.S @ a + s
        D += 0.5 * model.alpha * (b @ cfg.M_N @ b)
    return float(D)


def _state(model: ErlsModel, rng, amp: float = 2e-3):
    q = np.asarray(model.mech.q_ref) + 0.2 * rng.standard_normal(model.nq)
    return np.concatenate([q, amp * rng.standard_normal(model.ne)])


def _turned(model: ErlsModel, x: np.ndarray, qd: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """The rates ``v`` of the mechanism turning rigidly (``q' = qd``) with every link's deflection in its own frame
    held: every node's displacement turned by its link's angle change (central differences)."""
    nq = model.nq
    th0 = model.configuration(x[:nq]).pose.link_angles
    d0 = (model.T @ x[nq:]).reshape(-1, 3)

    def u_at(t):
        dth = model.configuration(x[:nq] + t * qd).pose.link_angles - th0
        Rn = rotation(dth[model.kin.node_link])[:, :3, :3]
        d = np.einsum("nij,nj->ni", Rn, d0).ravel()
        u, *_ = np.linalg.lstsq(model.T, d, rcond=None)
        assert np.abs(model.T @ u - d).max() < 1e-12  # the turned field is one of the model's
        return u

    return np.concatenate([qd, (u_at(h) - u_at(-h)) / (2 * h)])


@pytest.mark.parametrize("name", ["single_link", "l_arm", "long_link"])
def test_rigidly_turning_bent_link_dissipates_nothing(name):
    """A bent link (or welded pair) turning rigidly keeps its strain: the strain-rate law dissipates nothing, the
    global-rate law (``u'^T (alpha M_e + beta K_uu) u'``, the elastic block at ``u = 0``) did."""
    model = _model(name)
    rng = np.random.default_rng(11)
    x = _state(model, rng)
    v = _turned(model, x, np.full(model.nq, 2.0))
    cfg = model.configuration(x[: model.nq])
    old = 0.5 * v @ model.damping(cfg) @ v
    new = 0.5 * v @ model.damping(cfg, x) @ v
    assert old > 0.0
    assert abs(new) <= 1e-9 * old
    assert np.abs(model.damping_forces(cfg, x, v)).max() <= 1e-9 * np.abs(model.damping(cfg) @ v).max()


@pytest.mark.parametrize("name", ["single_link", "serial_arm", "fourbar", "sixbar", "three_link_reach"])
def test_damping_matrix_is_the_strain_rate_dissipation(name):
    """``C(x)`` entry by entry from the oracle dissipation by polarisation, ``C_ij = D(e_i + e_j) - D(e_i) -
    D(e_j)``, each entry against its own scale ``sqrt(C_ii C_jj)`` (Cauchy-Schwarz); and the damping forces
    (:meth:`damping_forces`, the gradient of ``D`` in ``v``) equal ``C v``."""
    model = _model(name)
    rng = np.random.default_rng(3)
    x = _state(model, rng)
    cfg = model.configuration(x[: model.nq])
    C = model.damping(cfg, x)
    n = model.n
    idx = list(range(model.nq)) + sorted(rng.choice(np.arange(model.nq, n), size=min(8, model.ne), replace=False))
    D1 = {i: _dissipation(model, x, np.eye(n)[i]) for i in idx}
    for i in idx:
        for j in idx:
            if j < i:
                continue
            Cij = 2 * D1[i] if i == j else _dissipation(model, x, np.eye(n)[i] + np.eye(n)[j]) - D1[i] - D1[j]
            scale = np.sqrt(max(C[i, i] * C[j, j], 0.0)) + 1e-12 * np.abs(C).max()
            assert abs(C[i, j] - Cij) <= 1e-5 * scale, (i, j, C[i, j], Cij)
    v = rng.standard_normal(n)
    f = model.damping_forces(cfg, x, v)
    np.testing.assert_allclose(f, C @ v, rtol=1e-9, atol=1e-12 * np.abs(f).max())
    # the rigid rows are not empty: the deflection's turning rate enters the strain rate through q'
    assert np.abs(C[: model.nq]).max() > 1e-6 * np.abs(C).max()


@pytest.mark.parametrize("name", ["serial_arm", "fivebar", "slider_crank", "three_link_arm"])
def test_dissipation_is_nonnegative(name):
    """``C(x)`` is symmetric positive semidefinite at random deformed states: the damping never feeds energy."""
    model = _model(name)
    rng = np.random.default_rng(5)
    for _ in range(4):
        x = _state(model, rng, amp=1e-2)
        C = model.damping(model.configuration(x[: model.nq]), x)
        scale = np.abs(C).max()
        assert np.abs(C - C.T).max() <= 1e-12 * scale
        assert np.linalg.eigvalsh(C).min() >= -1e-11 * scale
        v = rng.standard_normal(model.n)
        assert v @ C @ v >= 0.0


def test_at_rest_the_damping_is_the_elastic_block():
    """At ``u = 0`` the strain rate is ``T u'``: ``C = diag(0, alpha M_e + beta K_uu)``, the matrix whose free modes
    have the Rayleigh ratios (``tests/test_damping.py``)."""
    model = _model("sixbar")
    cfg = model.configuration(model.mech.q_ref)
    x = np.concatenate([model.mech.q_ref, np.zeros(model.ne)])
    C = model.damping(cfg, x)
    nq = model.nq
    assert np.abs(C[:nq]).max() == 0.0 and np.abs(C[:, :nq]).max() == 0.0
    Ce = model.alpha * model.elastic_mass(cfg) + model.beta * (model.T.T @ cfg.K_N @ model.T)
    np.testing.assert_allclose(C[nq:, nq:], Ce, rtol=1e-12, atol=1e-12 * np.abs(Ce).max())


@pytest.mark.parametrize("name", ["serial_arm", "sixbar"])
def test_damping_position_jacobian(name):
    """``d(C(x) v)/du`` of :meth:`damping_position_jacobian` against central differences of the damping forces,
    entry by entry against each entry's own size (the forces are bilinear in ``u`` and ``v``: exact up to round-off)."""
    model = _model(name)
    rng = np.random.default_rng(8)
    x = _state(model, rng)
    v = rng.standard_normal(model.n)
    cfg = model.configuration(x[: model.nq])
    Jd = model.damping_position_jacobian(cfg, x, v)
    eps = 1e-4
    for k in range(model.ne):
        dx = np.zeros(model.n)
        dx[model.nq + k] = eps
        fd = (model.damping_forces(cfg, x + dx, v) - model.damping_forces(cfg, x - dx, v)) / (2 * eps)
        assert np.all(np.abs(Jd[:, k] - fd) <= 1e-7 * np.abs(fd) + 1e-12 * np.abs(Jd).max()), k
    A, _ = model.state_matrix(cfg, x, v)  # the full-order observer's linearisation holds it in the u columns
    n, nq = model.n, model.nq
    Minv = np.linalg.inv(model.mass(cfg))
    K = model.stiffness(cfg)[:, nq:] + Jd
    np.testing.assert_allclose(A[n:, nq:n], -Minv @ K, rtol=1e-9, atol=1e-12 * np.abs(Minv @ K).max())


def test_reduced_turning_bent_link_dissipates_nothing():
    """In the reduced model too (``C_r = J^T C(H p) J``): the single link, deflected in its modes and turned at
    constant ``p_e`` (the basis turns with the link), meets no damping; the global-rate law's reduced damping
    (``J_u^T (alpha M_e + beta K_uu) J_u``) brakes it."""
    from exuflex.reduction import CraigBampton, ReducedModel

    model = _model("single_link")
    rm = ReducedModel(CraigBampton(model))
    rng = np.random.default_rng(2)
    nq = rm.nq
    p = np.concatenate([np.asarray(model.mech.q_ref) + 0.3, 1e-3 * rng.standard_normal(rm.r - nq)])
    pd = np.zeros(rm.r)
    pd[:nq] = 2.0
    for compiled in (False, True):
        rm.compiled = compiled
        mats = rm.matrices(p, pd, forces=False, dHdq=rm.cb.basis_derivative(rm.cb.at(p[:nq]), np.eye(rm.r)))
        cfg = mats.rc.cfg
        old = pd @ (mats.J[nq:].T @ model.damping(cfg)[nq:, nq:] @ mats.J[nq:]) @ pd
        assert old > 0.0
        assert abs(pd @ mats.Cr @ pd) <= 1e-9 * old
    rm.compiled = True

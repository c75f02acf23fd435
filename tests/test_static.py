"""Static corrections (:mod:`exuflex.reduction.static`): the Galerkin statics they make exact, the count's figure
against an independent computation through the basis ``H(q)`` and the full stiffness, and what removing one does."""

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.model import ErlsModel
from exuflex.erls.sensing import channel_matrix
from exuflex.mechanism import load_mechanism
from exuflex.reduction import CraigBampton
from exuflex.reduction.static import STATIC_MAX, _scales, load_amplitudes, load_shapes, rebase
from exuflex.reduction.truncation import PlannedInput

MODELS = Path(__file__).resolve().parents[1] / "models"


@pytest.fixture(scope="module")
def heavy():
    """The slider-crank with its slider twice as heavy: the case the corrections are for."""
    mech = load_mechanism(MODELS / "slider_crank.toml").with_payload_scale(2.0)
    return CraigBampton(ErlsModel(mech), static_max=STATIC_MAX)


def _statics(cb, q):
    """Full and reduced (Galerkin in H(q)) static elastic responses to the scaled load patterns at q, and the
    readings' rows (noise sd units, the coordinates' recoil included)."""
    model, nq = cb.model, cb.nq
    rc = cb.at(q)
    cfg = rc.cfg
    K = model.stiffness(cfg)[nq:, nq:]
    planned = PlannedInput.of(model.mech)
    a, v = load_amplitudes(model, planned, cb.path_q)
    L, names = load_shapes(model, cfg)
    F = L * _scales(a, v, L.shape[1])[None, :]
    He = rc.H[nq:, nq:]  # the q columns have no elastic rows (K has no q rows: zero Guyan columns)
    assert np.allclose(rc.H[nq:, :nq], 0.0)
    u_full = np.linalg.solve(K, F)
    u_red = He @ np.linalg.solve(He.T @ K @ He, He.T @ F)
    M = model.mass(cfg)
    C = channel_matrix(model, cfg, model.mech, planned.channels) / planned.noise[:, None]
    Y = C[:, nq:] - C[:, :nq] @ np.linalg.solve(M[:nq, :nq], M[:nq, nq:])
    return u_full, u_red, Y, names, list(planned.channels)


def _figure(cb):
    """The largest box reading of the static residual over the basis's sampled configurations."""
    worst = 0.0
    for q in cb.path_q:
        u_full, u_red, Y, _, _ = _statics(cb, q)
        worst = max(worst, float(np.abs(Y @ (u_full - u_red)).sum(axis=1).max()))
    return worst


def test_heavy_slider_keeps_corrections_and_meets_the_limit(heavy):
    st = heavy.static
    assert st is not None and st.n == heavy.n_static > 0
    assert st.figure[0] > st.limit >= st.figure[st.n]
    assert heavy.r == heavy.n_m + heavy.n_interior
    # the re-based interior modes stay M_ss-orthonormal; the kept ones K_ss-orthogonal at q* (Ritz values on the
    # diagonal: the dynamic modes are eigenvectors, the corrections a Rayleigh-Ritz basis of their span)
    cb = heavy
    nq = cb.nq
    Mw = cb.model.mass(cb.cfg_star)[nq:, nq:][np.ix_(cb.is_, cb.is_)]
    Kw = cb.model.stiffness(cb.cfg_star)[nq:, nq:][np.ix_(cb.is_, cb.is_)]
    P = cb.Phi_all
    assert np.allclose(P.T @ Mw @ P, np.eye(P.shape[1]), atol=1e-9)
    # the dynamic modes and the corrections (modes the final search adds among the re-based ones come from the
    # corrections' complement: M_ss-orthonormal to them, not K_ss-orthogonal)
    k = np.sort(cb.order[: cb.truncation["dynamic"]["n_interior"] + cb.n_static])
    KP = P[:, k].T @ Kw @ P[:, k]
    w2 = (2 * np.pi * cb.interior_frequencies_hz[k]) ** 2
    assert np.allclose(KP, np.diag(w2), atol=1e-9 * w2.max())


def test_picked_patterns_are_exact_at_their_configuration(heavy):
    """A load whose residual became a correction: the reduced static response to it equals the full model's at
    every elastic dof (to round-off) at the configuration it was taken at; a reading whose static response became
    one: that channel reads every load's reduced static response as the full model's (Galerkin orthogonality).
    The masters are exact for every load (Guyan condensation)."""
    cb = heavy
    st = cb.static
    for c, what in st.picked:
        u_full, u_red, Y, names, rows = _statics(cb, cb.path_q[c])
        scale = np.abs(u_full).max()
        assert np.abs(u_full - u_red)[cb.im].max() <= 1e-9 * scale
        if what.startswith("reading "):
            i = rows.index(what.removeprefix("reading "))
            r = Y[i] @ (u_full - u_red)
            assert np.abs(r).max() <= 1e-8 * np.abs(Y[i] @ u_full).max()
        else:
            j = names.index(what)
            assert np.abs(u_full[:, j] - u_red[:, j]).max() <= 1e-8 * np.abs(u_full[:, j]).max()


def test_figure_equals_the_basis_statics(heavy):
    """The criterion's figure against the full model's static solve and the Galerkin solve in H(q) (cb.at), on the
    dynamic modes and the corrections (the basis the figure is of; the final search may add modes after them, which
    only lower it)."""
    st = heavy.static
    n = heavy.n_interior
    heavy.set_interior(heavy.truncation["dynamic"]["n_interior"] + st.n)
    try:
        assert _figure(heavy) == pytest.approx(st.figure[st.n], rel=1e-6)
    finally:
        heavy.set_interior(n)
    assert _figure(heavy) <= st.figure[st.n] * (1 + 1e-6)


def test_removing_the_last_correction_exceeds_the_limit(heavy):
    """The basis with the first n - 1 corrections only (the same re-basing, cb.at through it) reads the static
    residual above the limit, as the criterion's figure for n - 1 says."""
    cb = heavy
    st = cb.static
    n = st.n
    dyn = [int(i) for i in cb.kept if i not in set(st.rest.tolist())]
    w2 = (2 * np.pi * cb.interior_frequencies_hz) ** 2
    saved = cb.Phi_all, cb.interior_frequencies_hz, cb.order, cb.n_interior
    try:
        Phi0, w20 = cb.Phi_all.copy(), w2.copy()
        Phi0[:, st.rest], w20[st.rest] = st.G, st.g2
        Phi1, w21 = rebase(Phi0, w20, st.rest, st.D[:, : n - 1])
        cb.Phi_all = Phi1
        cb.interior_frequencies_hz = np.sqrt(w21) / (2 * np.pi)
        cb.order = np.array(dyn + [int(i) for i in st.rest], int)
        cb.set_interior(len(dyn) + n - 1)
        fig = _figure(cb)
    finally:
        cb.Phi_all, cb.interior_frequencies_hz, cb.order = saved[:3]
        cb.set_interior(saved[3])
    assert fig == pytest.approx(st.figure[n - 1], rel=1e-6)
    assert fig > st.limit


def test_amplitudes_single_link_by_hand():
    """One revolute link about a fixed axis: no velocity force on q and a constant inertia, so the largest
    acceleration is the largest planned torque over the inertia and the kinetic energy's largest rate the plan's."""
    cb = CraigBampton(ErlsModel(load_mechanism(MODELS / "single_link.toml")))
    model = cb.model
    planned = PlannedInput.of(model.mech)
    a, v = load_amplitudes(model, planned, cb.path_q)
    cfg = model.configuration(cb.q_star)
    J = model.mass(cfg)[0, 0]
    g = model.input_matrix(cfg)[0, 0]
    assert a[0] == pytest.approx(abs(g) * np.abs(planned.u).max() / J, rel=1e-9)
    assert v[0] == pytest.approx(np.abs(planned.qd).max(), rel=1e-3)


def test_off_and_fixed_counts_add_nothing():
    mech = load_mechanism(MODELS / "slider_crank.toml").with_payload_scale(2.0)
    cb = CraigBampton(ErlsModel(mech), static_max=0)
    assert cb.static is None and cb.n_static == 0
    cb = CraigBampton(ErlsModel(mech), n_interior=3, static_max=STATIC_MAX)
    assert cb.static is None and cb.n_interior == 3


def test_modes_report_states_the_corrections():
    """``exuflex modes --reduced`` (:func:`exuflex.reduction.reduced_modes_report`): the count, its figure against
    the limit and one Ritz frequency per correction; a fixed count (the paper's six-bar) reports none."""
    from exuflex.reduction import reduced_modes_report

    mech = load_mechanism(MODELS / "slider_crank.toml").with_payload_scale(2.0)
    rep = reduced_modes_report(ErlsModel(mech), along=0)
    st = rep["static"]
    assert st["count"] >= 1 and len(st["ritz_hz"]) == len(st["picked"]) == st["count"]
    assert st["figure"] <= st["limit"] < st["figure_without"] and st["met"]
    assert rep["interior_modes"] >= st["count"]
    assert reduced_modes_report(ErlsModel(load_mechanism(MODELS / "sixbar.toml")), along=0)["static"] is None

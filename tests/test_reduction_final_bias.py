"""The reduction's requirements on the final basis (dynamic modes and static corrections, the basis the observer
uses; :mod:`exuflex.reduction.truncation`): the filter requirement's figure is :meth:`PathSamples.bias`'s quantity on
that basis, its estimated quantities are the encoders' readings, and the truncated output's quasi-static part is
what a Galerkin model on a basis that is not modal leaves out (its stiffness-weighted projection)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism
from exuflex.reduction import CraigBampton
from exuflex.reduction.truncation import FilterSample, PlannedInput, truncation_sample

MODELS = Path(__file__).resolve().parents[1] / "models"


def test_final_figure_is_the_filter_requirement_on_the_observers_basis():
    """The slider-crank (4 interior modes and 5 static corrections): ``bias`` equals the figure rebuilt from fresh
    :class:`FilterSample` objects on the final basis at the same configurations (mean over them of the mean-square
    error over the mean variance, every column of ``cb.at(q).H``); the static corrections lower the largest figure
    of the dynamic modes alone (they span quasi-static slave motion those leave out). Without static corrections the
    final search meets the requirements with dynamic modes."""
    mech = load_mechanism(MODELS / "slider_crank.toml")
    model = ErlsModel(mech)
    cb = CraigBampton(model)
    tr = cb.truncation
    assert cb.n_static > 0 and list(tr["dynamic"]["bias"]) == list(tr["bias"])
    planned = PlannedInput.of(mech)
    qs = cb.path_q[::2]  # the configurations with a truncation figure: q* and every other path sample
    ms, var = [], []
    for q in qs:
        rc = cb.at(q)
        a, b, _ = FilterSample(model, rc, planned).bias(np.arange(rc.H.shape[1]))
        ms.append(a)
        var.append(b)
    ref = np.mean(ms, axis=0) / np.mean(var, axis=0)
    np.testing.assert_allclose(list(tr["bias"].values()), ref, rtol=1e-6, atol=0)  # the Riccati doubling stops at 1e-12
    assert max(tr["bias"].values()) < max(tr["dynamic"]["bias"].values())
    assert tr["bias_met"] == (max(ref) <= cb.bias_max)
    # without static corrections the final basis' search adds dynamic modes until the requirements hold
    # (.path.PathSamples.extend_for_bias); where it adds none, the figures are the dynamic modes' own
    nc = CraigBampton(model, static_max=0)
    plain = nc.truncation
    assert nc.n_static == 0 and plain["met"] and nc.n_interior >= plain["dynamic"]["n_interior"]
    if nc.n_interior == plain["dynamic"]["n_interior"]:
        assert plain["bias"] == plain["dynamic"]["bias"] and plain["rho"] == plain["dynamic"]["rho"]


def test_estimated_quantities_are_the_readings():
    """On the serial arm (the elbow's coordinate relative to the upper arm): the filter requirement's displacement
    quantities are what the observer reports, the encoders' readings ``q + G u`` and the tip's elastic displacement
    from the rigid tip at those readings. Checked on a full state against the kinematics: the reading as the
    difference of the two links' tangent angles at the elbow and the tip from the deformed and rigid positions."""
    mech = load_mechanism(MODELS / "serial_arm.toml")
    model = ErlsModel(mech)
    cb = CraigBampton(model, n_interior=0, truncation_max=0)
    cb.set_interior(len(cb.order))
    planned = PlannedInput.of(mech)
    q = np.array([0.3, 1.1])
    rc = cb.at(q)
    fs = FilterSample(model, rc, planned)
    nq = model.nq
    G = model.coordinate_reading_rows()
    assert np.any(G)  # a relative coordinate: its reading is not q
    rng = np.random.default_rng(5)
    u = 1e-7 * rng.standard_normal(model.ne)
    z = fs.Z @ np.r_[np.zeros(nq), u]
    assert np.allclose(z[:nq], G @ u, rtol=0, atol=1e-12 * np.abs(u).max())
    # the tip's elastic displacement from the rigid tip at the readings, to first order in u (central differences)
    cfg = rc.cfg
    A = model.point_displacement_rows(cfg, *planned.tip)
    rigid = lambda qq: model.kin.point(model.configuration(qq).pose, *planned.tip)[0]
    h = 1e-6
    J = np.column_stack([(rigid(q + h * e) - rigid(q - h * e)) / (2 * h) for e in np.eye(nq)])
    ref = A @ u - J @ (G @ u)
    assert np.allclose(z[nq:], ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    assert np.abs(ref - A @ u).max() > 0.1 * np.abs(ref).max()  # the reading's part is not negligible here


def test_quasi_static_truncation_is_the_galerkin_residual():
    """With the static corrections the interior basis is Ritz vectors, not modes: its columns are not stiffness-
    orthogonal, and what a Galerkin model on some of them leaves out of a static slave deflection ``d`` is ``d - V
    (V' K_ss V)^-1 V' K_ss d``, not the columns not kept of ``d``'s coordinates. The truncation series' quasi-static
    part (:meth:`TruncationSample.channel_series`, no ringing counted) equals that residual read by the channels, on
    the three-link arm (5 dynamic modes and 4 corrections) at a configuration of its manoeuvre other than q*."""
    mech = load_mechanism(MODELS / "three_link_arm.toml")
    model = ErlsModel(mech)
    cb = CraigBampton(model)
    assert cb.n_static > 0
    kept = cb.kept.copy()
    n = cb.n_interior
    cb.set_interior(len(cb.order))
    planned = PlannedInput.of(mech)
    q = cb.path_q[5]
    rc = cb.at(q)
    ts = truncation_sample(cb, rc, modal_analysis(model, q, locked=True, hold_readings=False), planned)
    cb.set_interior(n)
    nq = model.nq
    n_i = ts.Y.shape[1]
    zeta = ts.S[:, :n_i]  # (n_t, n_int) the quasi-static interior content
    d = zeta @ rc.Psi.T  # (n_t, s) the slaves' deflection beyond the Guyan shapes
    qc, qs = cb._frame_cs(rc.cfg)
    Kw = cb._congruence(model.stiffness(rc.cfg)[nq:, nq:], qc, qs)
    Kss = Kw[np.ix_(cb.is_, cb.is_)]
    V = rc.Psi[:, kept]
    res = d - (V @ np.linalg.solve(V.T @ Kss @ V, V.T @ Kss @ d.T)).T
    # the residual's reading: the interior coordinates of the residual through the channels' rows of every mode
    ref = np.linalg.solve(rc.Psi, res.T).T @ ts.Y.T
    series = ts.channel_series(kept)
    assert np.abs(series - ref).max() <= 1e-8 * np.abs(ref).max()
    # the columns not kept of zeta (the modal rule) read something else on this basis
    plain = zeta @ (ts.Y * np.isin(np.arange(n_i), kept, invert=True)).T
    assert np.abs(plain - ref).max() > 0.5 * np.abs(ref).max()

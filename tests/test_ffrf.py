"""The FFRF truth (solid links, Hurty-Craig-Bampton modes): analytic beam frequencies, the disk cache, the
section read-outs and the probes, on coarse meshes (the ``ffrf`` extra: netgen and ngsolve)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ngsolve")

from exuflex.groundtruth import build_ffrf, ffrf_frequencies  # noqa: E402
from exuflex.groundtruth.solid import SolidSpec, solid_link  # noqa: E402
from exuflex.mechanism import load_mechanism  # noqa: E402
from exuflex.probes import Probe  # noqa: E402

MODELS = Path(__file__).resolve().parents[1] / "models"


COARSE = 2.0  # mesh size over the section's diameter: coarse, for speed (the default is 1)


@pytest.fixture(scope="module", autouse=True)
def _cache(tmp_path_factory):
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("EXUFLEX_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


def _rod(L=0.4, d=0.016, interfaces=(0.0, 0.4), stations=(0.0, 0.1, 0.4), **kw):
    base = dict(link="rod", length=L, shape="round", diameter=d, inner_diameter=None, width=None, height=d,
                E=69e9, rho=2700.0, nu=0.33, mesh_size=COARSE * d, interfaces=interfaces, stations=stations,
                band_hz=180.0)
    base.update(kw)
    return SolidSpec(**base)


@pytest.fixture(scope="module")
def single_link():
    mech = load_mechanism(MODELS / "single_link.toml")
    return mech, build_ffrf(mech, mesh_scale=COARSE)


def test_clamped_rod_matches_euler_bernoulli_and_cache_returns_the_same_link():
    """Fixed-interface modes of a rod clamped at both end faces (L/d = 25): the first bending pair at Euler-
    Bernoulli's clamped-clamped ``4.7300^2 / (2 pi L^2) sqrt(EI / rho A)`` within 1 % (shear and rotary inertia
    lower it by about 0.3 % at this slenderness); the second call reads the cache."""
    spec = _rod()
    sl = solid_link(spec)
    assert not sl.cached
    A, I = math.pi * spec.diameter**2 / 4, math.pi * spec.diameter**4 / 64
    f_eb = 4.7300**2 / (2 * math.pi * spec.length**2) * math.sqrt(spec.E * I / (spec.rho * A))
    assert sl.fixed_interface_hz[:2] == pytest.approx([f_eb, f_eb], rel=0.01)
    again = solid_link(spec)
    assert again.cached
    for k, v in sl.arrays.items():
        np.testing.assert_array_equal(again.arrays[k], v)
    np.testing.assert_array_equal(again.section(0.1), sl.section(0.1))


def test_section_read_outs_of_the_static_modes():
    """Interface rows: the six static modes of the far interface are its unit rigid motions, so the read-out
    there is exactly one unit translation in x and in y and one unit rotation about z (the frame's interface
    reads zero); the curvature at a section between the ends is linear in x for the interface's transverse
    translation (a clamped-guided beam: ``kappa = 6 (L - 2x) / L^3`` times the translation... within 5 %)."""
    spec = _rod()
    sl = solid_link(spec)
    tip, root = sl.section(0.4), sl.section(0.0)
    np.testing.assert_allclose(root[:3], 0.0, atol=1e-9)
    # one unit entry per row (a unit rigid motion); the rotation modes turn about the interface nodes' mean, which sits off the axis
    # point by a fraction of a mesh size, so they move the axis point by that offset per radian
    off = 0.1 * spec.mesh_size
    for row in tip[:3]:
        j = int(np.argmax(np.abs(row)))
        assert abs(row[j]) == pytest.approx(1.0, abs=1e-9)  # the static mode's sign is Exudyn's choice
        assert np.max(np.abs(np.delete(row, j))) < off
    # static mode 1 (unit y translation of the far end, both ends clamped in rotation): v = 3 (x/L)^2 - 2 (x/L)^3,
    # kappa = v'' = (6 - 12 x / L) / L^2
    jy = int(np.argmax(np.abs(tip[1])))
    x, L = 0.1, spec.length
    assert sl.section(0.1)[3, jy] == pytest.approx((6 - 12 * x / L) / L**2, rel=0.05)


def test_gauge_curvature_obeys_saint_venant_bending_of_the_static_modes():
    """The curvature read-out against Saint-Venant's solution of a bar bent by end loads (exact away from the ends,
    shear and the 3D section included): in the far interface's transverse-translation static mode the bending
    moment is linear and antisymmetric about mid-length (both faces clamped in rotation), so ``kappa(L/4) =
    -kappa(3L/4)`` and ``kappa(L/2) = 0``; in its rotation mode the moment is linear, so ``kappa(L/2)`` is the mean
    of ``kappa(L/4)`` and ``kappa(3L/4)``. The gauge-length read-out meets these to about 0.05 % on this coarse
    mesh; the strain of quadratic tetrahedra at one point missed them by 0.45-0.57 % (mesh noise of that size
    biases the beam observer on the FFRF truth, ``docs/ffrf_slenderness.md``)."""
    L = 0.4
    sl = solid_link(_rod(stations=(0.0, L / 4, L / 2, 3 * L / 4, L)))
    tip = sl.section(L)
    jy, jr = int(np.argmax(np.abs(tip[1]))), int(np.argmax(np.abs(tip[2])))
    k1, k2, k3 = (sl.section(x)[3] for x in (L / 4, L / 2, 3 * L / 4))
    assert abs(k1[jy] + k3[jy]) < 2e-3 * abs(k1[jy])
    assert abs(k2[jy]) < 2e-3 * abs(k1[jy])
    assert abs(k1[jr] + k3[jr] - 2 * k2[jr]) < 2e-3 * abs(k1[jr] - k3[jr])


def test_single_link_modes_match_the_analytic_beam(single_link):
    """The single-link model (hub inertia, tip mass, motor free): the FFRF bodies' first two in-plane modes
    against the analytic Euler-Bernoulli values of ``models/README.md`` (30.77, 84.12 Hz) within 1 %."""
    mech, _ = single_link
    r = ffrf_frequencies(mech, fmax=100.0, mesh_scale=COARSE)
    assert r["frequencies_hz"][:2] == pytest.approx([30.77, 84.12], rel=0.01)


def test_damping_as_stated_beta_and_alpha(single_link):
    """The damping claims of :mod:`exuflex.groundtruth.ffrf`, from Exudyn's linearised system: stiffness-
    proportional damping alone gives every in-plane mode ``beta w / 2`` (all stiffness is modal), mass-proportional
    damping alone (the rigid motions projected out) ``alpha / (2 w)``, and both their sum."""
    from exuflex.mechanism.spec import Damping

    mech, _ = single_link
    beta, alpha = 2e-5, 3.0
    for a, b in ((0.0, beta), (alpha, 0.0), (alpha, beta)):
        r = ffrf_frequencies(mech.replace(damping=Damping(a, b)), fmax=100.0, mesh_scale=COARSE, with_damping=True)
        w = 2 * np.pi * r["frequencies_hz"]
        np.testing.assert_allclose(r["damping_ratio"], a / (2 * w) + b * w / 2, rtol=1e-3)


@pytest.mark.parametrize("model", ["single_link", pytest.param("fourbar", marks=pytest.mark.slow)])
def test_alpha_damper_turns_with_the_mechanism(model):
    """The damper's ingredients away from the build configuration, against Exudyn's own at a model built there:
    the rotated mass matrix equals Exudyn's (entry by entry against the geometric mean of its row's and column's
    diagonal entries), the rigid motions satisfy Exudyn's constraint Jacobian, and the damper leaves them undamped
    (``D R = 0``). The single link's hub and tip mass turn with it; the four-bar is a closed loop."""
    import exudyn as exu

    mech = load_mechanism(MODELS / f"{model}.toml")
    fm0 = build_ffrf(mech, mesh_scale=COARSE)
    q1 = np.asarray(mech.q_ref) + 0.7
    fm1 = build_ffrf(mech, q1, mesh_scale=COARSE, damping=False)
    c1 = np.asarray(fm1.mbs.systemData.GetODE2Coordinates(exu.ConfigurationType.Reference))
    M1, _, _, CT = (np.asarray(x) for x in fm1.mbs.ComputeLinearizedSystem(returnConstraintJacobian=True))
    scale = np.sqrt(np.outer(np.abs(np.diag(M1)), np.abs(np.diag(M1)))) + 1e-300
    assert np.max(np.abs(fm0.mass_matrix(c1) - M1) / scale) < 1e-9
    R = fm0.rigid_motions(c1)
    assert R.shape[1] == len(mech.coordinates)
    assert np.max(np.abs(CT.T @ R)) < 1e-9 * np.max(np.abs(R))
    fm0.update_damper(c1)
    assert np.max(np.abs(fm0.D_alpha @ R)) < 1e-9 * mech.damping.alpha * np.max(np.abs(M1 @ R))


@pytest.mark.slow
def test_alpha_damper_spares_the_rigid_rotation_in_a_simulation(single_link):
    """The single link spun up by a torque pulse, then free (no gravity): the damper, refreshed on its schedule,
    leaves the hub's mean rotation rate after the pulse as without damping (relative 1e-4; an unprojected
    ``alpha M`` would brake it at ``alpha`` ~ 1/s), while it damps the elastic ringing about that rate."""
    from exuflex.groundtruth import simulate_ffrf

    mech, _ = single_link
    t = np.linspace(0.0, 0.45, 451)
    tau = np.where(t < 0.15, 2.0 * np.sin(np.pi * t / 0.15) ** 2, 0.0)[:, None]
    rate = {}
    for damping in (False, True):
        rec = simulate_ffrf(mech, t, tau, 0.45, h=2.5e-4, output_dt=1e-3, mesh_scale=COARSE, damping=damping,
                            probes=[Probe("slope", "arm", 0.0)])
        r = rec.rates[Probe("slope", "arm", 0.0).key][:, 0]
        rate[damping] = r[rec.t > 0.3]
    assert abs(rate[True].mean() - rate[False].mean()) < 1e-4 * rate[False].mean()
    assert rate[True].std() < 0.7 * rate[False].std()


def test_probe_values_are_the_frame_plus_the_read_outs(single_link):
    """probe_values: point = r + R(phi) (s e_x + u), slope = phi + theta, kappa; rates the exact time
    derivatives (central differences of a smooth synthetic path of the coordinates)."""
    _, fm = single_link
    b = fm.bodies["arm"]
    n = fm.mbs.systemData.ODE2Size()
    rng = np.random.default_rng(3)
    a0, a1 = rng.normal(size=n), rng.normal(size=n) * 1e-3

    def path(t):
        return a0 * 1e-3 + a1 * np.sin(3 * t) + np.where(np.arange(n) == b.frame_idx[2], t, 0.0)

    def rate(t):
        return 3 * a1 * np.cos(3 * t) + np.where(np.arange(n) == b.frame_idx[2], 1.0, 0.0)

    t, dt = 0.4, 1e-6
    c = np.stack([path(t - dt), path(t), path(t + dt)])
    cd = np.stack([rate(t - dt), rate(t), rate(t + dt)])
    for probe in (Probe("point", "arm", 1.0), Probe("slope", "arm", 0.0), Probe("curvature", "arm", 0.25)):
        v, r = fm.probe_values(probe, c, cd)
        np.testing.assert_allclose(r[1], (v[2] - v[0]) / (2 * dt), rtol=1e-6, atol=1e-9)
    v, _ = fm.probe_values(Probe("point", "arm", 1.0), c[1:2], cd[1:2])
    rows = b.solid.section(1.0)
    fr, qm = c[1, b.frame_idx], c[1, b.modal_idx]
    u = rows @ qm
    R = np.array([[math.cos(fr[2]), -math.sin(fr[2])], [math.sin(fr[2]), math.cos(fr[2])]])
    np.testing.assert_allclose(v[0], fr[:2] + R @ np.array([1.0 + u[0], u[1]]), rtol=1e-12)


def test_a_link_without_a_solid_section_is_named():
    mech = load_mechanism(MODELS / "single_link.toml")
    lk = mech.links[0]
    bare = mech.replace(links=(lk.__class__(**{**lk.__dict__, "section": lk.section.__class__(lk.section.A,
                                                                                              lk.section.I)}),))
    with pytest.raises(ValueError, match=r"links\[0\] \(arm\): the FFRF truth needs a solid section"):
        build_ffrf(bare)


@pytest.mark.slow
def test_fourbar_ffrf_truth_meets_the_observer_acceptance(tmp_path):
    """Issue 30's acceptance: the four-bar's FFRF truth (default meshes), observed with the beam observer: every
    RMS error within 1.5x its bound and the mean NIS within 10 % of its expectation."""
    from exuflex.scoring.run import observe_run
    from exuflex.runs import read_run
    from exuflex.truth import simulate_run

    model = MODELS / "fourbar.toml"
    run = read_run(simulate_run(model, tmp_path / "run", beam="ffrf", seed=1))
    out = observe_run(load_mechanism(model), run)
    ratios = out.summary["ratio_to_bound"]
    assert max(ratios.values()) < 1.5, ratios
    assert out.summary["nis_mean"] == pytest.approx(out.summary["nis_expected"], rel=0.1)

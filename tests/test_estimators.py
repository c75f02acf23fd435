"""Estimators beyond the paper's EKF: the payload- and input-augmented models (exact derivatives, the payload's
mass matrix from an independent assembly), the RTS smoother (filterpy's on a linear model) and the UKF (the
Kalman filter on a linear model). The accuracy studies on the Exudyn truth are in ``benchmarks/estimators.py``."""

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism
from exuflex.observer.augmented import AugmentedModel, nominal_mixture, payload_rows
from exuflex.observer.session import ObserverConfig, estimate, estimate_chunks, make_observer
from exuflex.runs import held_torques
from exuflex.runs import read_run

MODELS = Path(__file__).resolve().parents[1] / "models"
DATA = Path(__file__).resolve().parent / "data"


@pytest.fixture(scope="module")
def sixbar():
    return load_mechanism(MODELS / "sixbar.toml")


@pytest.fixture(scope="module")
def mid_run(sixbar):
    """An observer, a filtered state after 0.4 s of the stored ERLS log, and the torque there."""
    run = read_run(DATA / "sixbar_erls_3s")
    obs = make_observer(sixbar)
    S = run.sensors
    n = 200
    U = S.select(run.motors).data
    res = obs.ekf.run(S.t[:n], U[:n], S.select(obs.channels).data[:n])
    return obs, res.x_hat[-1].copy(), U[n - 1].copy()


def _fd(f, x, j, eps):
    xp, xm = x.copy(), x.copy()
    xp[j] += eps
    xm[j] -= eps
    return (f(xp) - f(xm)) / (2 * eps)


@pytest.mark.parametrize("theta", [1.0, 2.0])
def test_augmented_jacobian_equals_finite_differences(mid_run, theta):
    obs, z, u = mid_run
    aug = AugmentedModel(obs.model, payload_std=0.05, input_std=0.1)
    dt = obs.ekf.dt
    x = np.concatenate([z, [theta], 0.01 * np.ones(aug.nu)])
    F = aug.predict(x, u, dt).F

    def step(xx):
        return aug.predict(xx, u, dt).x

    # the extra states' columns: the scaled step's forward difference in theta; the disturbances enter through
    # the nominal map's L (exact at the nominal payload; with the payload scaled, the scaled system's response
    # differs by the payload's share of the modal masses)
    fd = _fd(step, x, aug.i_theta, 1e-4)
    assert np.max(np.abs(fd - F[:, aug.i_theta])) <= 2e-4 * np.max(np.abs(fd))
    # the disturbances' columns are the step map's L, built up to one map radius from q: their error is the
    # map's, which the map radius keeps small against the filter's uncertainty (remap_tol), not against rounding
    # (measured 3.3e-4 of the column at one state of the stored log)
    for j in list(range(aug.i_inputs.start, aug.i_inputs.stop)) if theta == 1.0 else []:
        fd = _fd(step, x, j, 1e-4)
        assert np.max(np.abs(fd - F[:, j])) <= 2e-3 * np.max(np.abs(fd))
    # the state block: at the nominal payload as close to finite differences as the nominal model's own Jacobian
    # is; with the payload doubled (its share of the tip mode's mass is about 0.47 on the six-bar) the scaled
    # system's maps take out at least 85 % of the nominal Jacobian's error
    n0 = aug.n0
    cols = [0, 2, 5, obs.model.r, obs.model.r + 2, n0 - 1]
    F0 = obs.model.predict(z, u + x[aug.i_inputs], dt).F
    for j in cols:
        eps = 1e-6 * max(1.0, abs(z[j]))
        fd_aug = _fd(step, x, j, eps)[:n0]
        fd_in = _fd(lambda zz: obs.model.predict(zz, u + x[aug.i_inputs], dt).x, z, j, eps)
        scale = np.max(np.abs(fd_aug))
        err_in = np.max(np.abs(fd_in - F0[:, j]))
        err = np.max(np.abs(fd_aug - F[:n0, j]))
        if theta == 1.0:
            assert err <= 2 * err_in + 1e-6 * scale
        else:
            assert err <= 2 * err_in + 0.15 * np.max(np.abs(fd_aug - F0[:, j])) + 1e-6 * scale


def test_nominal_payload_scale_leaves_the_prediction_unchanged(mid_run):
    obs, z, u = mid_run
    aug = AugmentedModel(obs.model, payload_std=0.05)
    dt = obs.ekf.dt
    p = aug.predict(np.concatenate([z, [1.0]]), u, dt)
    p0 = obs.model.predict(z, u, dt)
    np.testing.assert_allclose(p.x[:-1], p0.x, rtol=0, atol=1e-14)
    np.testing.assert_allclose(p.F[:-1, :-1], p0.F, rtol=0, atol=1e-14)
    assert p.x[-1] == 1.0 and p.Q[-1, -1] == pytest.approx(0.05**2 * dt)


def test_payload_mass_matrix_is_the_scaled_models_difference(sixbar, mid_run):
    """M_r(theta) - M_r(1) = (theta - 1) M_p: the nodal mass matrices of the nominal and the scaled model, assembled
    independently, differ by the payload alone; through the same basis rows W J this is the payload term."""
    obs, z, u = mid_run
    aug = AugmentedModel(obs.model, payload_std=0.05)
    aug.predict(np.concatenate([z, [1.0]]), u, obs.ekf.dt)
    iv, _ = obs.model.last_step
    Mp, Gp = aug.payload_terms(iv.mats)
    q = iv.q0
    theta = 1.7
    M1 = ErlsModel(sixbar).configuration(q).M_N
    M2 = ErlsModel(sixbar.with_payload_scale(theta)).configuration(q).M_N
    WJ = iv.mats.rc.cfg.W @ iv.mats.J
    dMr = WJ.T @ (M2 - M1) @ WJ
    np.testing.assert_allclose(dMr, (theta - 1) * Mp, rtol=1e-9, atol=1e-12 * np.abs(Mp).max())
    assert np.allclose(Mp, Mp.T) and np.linalg.eigvalsh(Mp).min() > -1e-12 * np.abs(Mp).max()
    assert np.linalg.matrix_rank(Mp, tol=1e-9 * np.abs(Mp).max()) <= 3
    np.testing.assert_array_equal(Gp, 0.0)  # the six-bar moves in a horizontal plane
    A, m = payload_rows(obs.model, iv.mats)
    assert A.shape == (3, obs.model.r) and m[0] == sixbar.payload.mass
    # the step's increment dS/dtheta from the doubled-payload twin (another assembly, the same basis): its mass
    # part is this M_p (the twin is evaluated at the held q with the current elastic coordinates: J differs by
    # their effect, far below 1e-6 relative)
    inc = aug.increment(iv, z)
    np.testing.assert_allclose(inc.Mr, Mp, rtol=0, atol=1e-6 * np.abs(Mp).max())


def test_scaled_cached_step_follows_the_scaled_reference(sixbar, mid_run):
    """With the payload doubled, the cached step of the scaled held system and the reference (RK4 of the scaled
    nonlinear reduced equations at every stage) agree as closely as the nominal cached and reference steps do,
    while the payload's effect on the step is far larger than that."""
    obs, z, u = mid_run
    dt = obs.ekf.dt
    ref = make_observer(sixbar, ObserverConfig(method="rk4"), cb=obs.model.rm.cb).model
    aug_c, aug_r = AugmentedModel(obs.model, payload_std=0.01), AugmentedModel(ref, payload_std=0.01)
    x1, x2 = np.concatenate([z, [1.0]]), np.concatenate([z, [2.0]])
    gap_nominal = np.abs(aug_c.predict(x1, u, dt).x - aug_r.predict(x1, u, dt).x).max()
    c2, r2 = aug_c.predict(x2, u, dt).x, aug_r.predict(x2, u, dt).x
    effect = np.abs(r2 - aug_r.predict(x1, u, dt).x).max()
    assert np.abs(c2 - r2).max() <= 2 * gap_nominal + 1e-3 * effect
    assert effect > 20 * gap_nominal


def test_scaled_steps_are_the_held_steps_of_the_scaled_system(mid_run):
    """The held model is linear in the held arrays: the scaled steps (the nominal and the increment's held models
    combined per scale) equal the held step of the arrays ``S + c dS`` themselves, and the interval's kernel
    (:func:`payload_interval`) returns those steps, the scaled held matrices and, from the maps it builds of them,
    the step Jacobian of :func:`step_jacobian` with the payload's velocity forms."""
    from exuflex.observer.augmented import payload_interval, scaled_steps
    from exuflex.observer.expansion import HeldSystem, held_step, step_jacobian, step_maps_noise

    obs, z, u = mid_run
    dt = obs.ekf.dt
    aug = AugmentedModel(obs.model, payload_std=0.01)
    aug.predict(np.concatenate([z, [1.0]]), u, dt)
    inner = aug.inner
    iv, sm = inner.last_step
    inc = aug.increment(iv, z)
    n = inner.substeps(iv, dt)
    dl = z[: inner.nq] - iv.q0
    s = inner.secant_factor(iv, dl)
    a = np.array([0.9, -0.4, 0.6])
    rows, Mr, Kr, Cr, Gr = scaled_steps(z, u, np.empty(0), dl, s, dt / n, n, a, tuple(iv.system), tuple(inc))
    scaled = {"Mr": "Mr", "Ca": "Ca", "dM": "dM", "fg": "fg", "T2": "T2", "C2": "C2", "old_dM": "old_dM",
              "old_Ca": "old_Ca", "old_fg": "old_fg", "old_T2": "old_T2", "old_C2": "old_C2"}
    for k, c in enumerate(a):
        hs = iv.system._replace(**{f: getattr(iv.system, f) + c * getattr(inc, g) for f, g in scaled.items()})
        ref, *mats = held_step(z, u, dl, s, dt / n, n, HeldSystem(*hs))
        np.testing.assert_allclose(rows[k], ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    for m, ref in zip((Mr, Kr, Cr, Gr), mats):
        np.testing.assert_allclose(m, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    _, dTs = aug._shares[iv.serial]
    Ts, Vs, C3 = iv.forces.jacobian_tensors()
    n0 = len(z)
    # (no scaled map yet and any scale beyond the tolerance: the scaled map is built at a[-1])
    out = payload_interval(z, (u, np.empty(0)), dl, s, dt / n, n, a, 1.6, n0 + 2, (0.2, 0.3, 1.0, 0.0),
                           (False, 0.0, sm.Pn, sm.S, sm.L, sm.Q), (sm.Pn, sm.S, sm.L, sm.Q, inner.torque_var, np.zeros(0)),
                           (Ts, dTs, Vs, C3), tuple(iv.system), tuple(inc))
    np.testing.assert_array_equal(out[0], rows)
    Pn, S, L, Q = step_maps_noise(Mr, Kr, Cr, Gr, dt / n, n, inner.torque_var)
    for got, ref in zip((*out[5][2:], *out[6:]), (Pn, S, L, Q, Mr, Kr, Cr, Gr)):
        np.testing.assert_array_equal(got, ref)
    # the augmented prediction: [z_next; theta; 0], the Jacobian with the scale's column (rows[0] - rows[-1]) / 0.2
    x, F, Qx = out[1:4]
    np.testing.assert_array_equal(x, np.concatenate([rows[-1], [1.6, 0.0]]))
    Fz = step_jacobian(z, Ts + a[-1] * dTs, Vs, C3 + a[-1] * inc.C2.reshape(C3.shape), Pn, S, np.zeros((0, 0)))
    np.testing.assert_allclose(F[:n0, :n0], Fz, rtol=0, atol=1e-13 * np.abs(Fz).max())
    np.testing.assert_array_equal(F[:n0, n0], (rows[0] - rows[-1]) / 0.2)
    np.testing.assert_array_equal(Qx[:n0, :n0], Q)
    assert F[n0, n0] == 1.0 and Qx[n0, n0] == 0.3
    assert not np.any(F[n0 + 1]) and not np.any(F[:, n0 + 1]) and not np.any(F[n0, :n0])
    assert not np.any(Qx[n0:, :n0]) and not np.any(Qx[:n0, n0:]) and Qx[n0 + 1, n0 + 1] == 0.0


def _scaled(aug, z, u, dt, a):
    """The cached step's states at the payload scales ``1 + a_k`` (:func:`scaled_steps`, one row each), from the
    held configuration of the model's last interval."""
    from exuflex.observer.augmented import scaled_steps

    inner = aug.inner
    iv, _ = inner.last_step
    n = inner.substeps(iv, dt)
    dl = z[: inner.nq] - iv.q0
    return scaled_steps(z, u, np.empty(0), dl, inner.secant_factor(iv, dl), dt / n, n, np.asarray(a, float), tuple(iv.system),
                        tuple(aug.increment(iv, z)))[0]


@pytest.mark.parametrize("theta", [1.0, 1.6])
def test_payload_scale_is_held_until_its_step_is_linear_over_its_deviation(mid_run, theta):
    """With the filter's covariance watched the scale is held until the test passes: its left-hand side is
    max |(x(theta + s) + x(theta - s)) / 2 - x(theta)| / sqrt(Q_ii) with s the scale's standard deviation, the
    releasing interval's column (x(theta + s) - x(theta - s)) / 2s, with x the interval's steps at the three scales
    (the payload increment held: the same configuration's); held, the column is zero and the process noise has
    e1 e1' more, e1 = (x(theta + s) - x(theta - s)) / 2 (the held scale's uncertainty); released, the column is
    the derivative of a model outside a filter."""
    obs, z, u = mid_run
    dt = obs.ekf.dt
    s = 0.3
    P = np.eye(len(z) + 1)
    P[-1, -1] = s**2
    x = np.concatenate([z, [theta]])
    c = theta - 1.0
    deriv = AugmentedModel(obs.model, payload_std=0.01).predict(x, u, dt).F[: len(z), -1]
    Qs = {}
    for tol, released in ((1e9, True), (1e-9, False)):
        aug = AugmentedModel(obs.model, payload_std=0.01, linearity_tol=tol)
        aug.watch_covariance(lambda: P)
        p = aug.predict(x, u, dt)
        xp, xm, x0 = _scaled(aug, z, u, dt, [c + s, c - s, c])
        e2 = 0.5 * (xp + xm) - x0
        col = p.F[: aug.n0, aug.i_theta]
        Qs[released] = p.Q[: aug.n0, : aug.n0]
        e1 = 0.5 * (xp - xm)
        q = np.sqrt(np.diagonal(p.Q)[: aug.n0] - (0.0 if released else e1**2))
        assert aug.last_linearity == pytest.approx(np.max(np.abs(e2) / q), rel=1e-9)
        np.testing.assert_allclose(p.x[:-1], x0, rtol=0, atol=1e-12 * np.abs(x0).max())
        assert aug.released == released and aug.n_held == (0 if released else 1)
        if released:
            ref = (xp - xm) / (2 * s)
            np.testing.assert_allclose(col, ref, rtol=0, atol=1e-9 * np.abs(ref).max())
            # the next interval: the derivative, whatever the test would say
            aug.linearity_tol = 1e-9
            np.testing.assert_allclose(aug.predict(x, u, dt).F[: aug.n0, aug.i_theta], deriv, rtol=0,
                                       atol=1e-6 * np.abs(deriv).max())
            released_model = aug
        else:
            assert not np.any(col)
            np.testing.assert_allclose(Qs[False] - Qs[True], np.outer(e1, e1), rtol=0,
                                       atol=1e-9 * np.abs(e1).max() ** 2)
        # the second-order term is not zero (the step is not linear in the payload: M_r^-1), and it is the
        # curvature: it scales as s^2 (the halved deviation's term a quarter, up to the next order)
        hp, hm = _scaled(aug, z, u, dt, [c + s / 2, c - s / 2])
        e2h = 0.5 * (hp + hm) - x0
        assert np.abs(e2).max() > 1e-6 * np.abs(xp - xm).max()
        assert np.max(np.abs(4 * e2h - e2)) <= 0.1 * np.abs(e2).max()
    released_model.reset()
    assert not released_model.released and released_model.n_held == 0


def test_payload_estimator_reports_its_posterior_mixed_with_the_nominal_hypothesis(sixbar):
    """``estimate`` with the payload estimator: the filter's record mixed by :func:`nominal_mixture` (the scale's
    prior variance grown by its walk since the start), the same in chunks; with ``payload_nominal_p`` 0 the
    filter's posterior itself. On the nominal payload's log the nominal hypothesis gains probability over the run,
    and the report is closer to the plain EKF than the filter's posterior is."""
    run = read_run(DATA / "sixbar_erls_3s")
    S = run.sensors
    obs = make_observer(sixbar, ObserverConfig(estimator="ekf-payload"))
    U, Y = held_torques(S.select(run.motors).data), S.select(obs.channels).data
    e = estimate(obs, S.t, U, Y)
    raw = obs.ekf.run(S.t, U, Y)
    it = obs.ekf.model.i_theta
    prior_var = obs.ekf.P0[it, it] + obs.config.payload_std**2 * (S.t - S.t[0])
    x, P, w = nominal_mixture(raw.x_hat, raw.P, raw.P_theta, it, prior_var, obs.config.payload_nominal_p)
    np.testing.assert_array_equal(e.result.x_hat, x)
    np.testing.assert_array_equal(e.result.P, P)
    np.testing.assert_array_equal(e.result.nominal_p, w)
    chunks = list(estimate_chunks(obs, S.t, U, Y, rows=400))
    np.testing.assert_array_equal(np.vstack([c.result.x_hat for c in chunks]), x)
    assert w[0] == pytest.approx(obs.config.payload_nominal_p) and w[-1] > 0.8
    plain = make_observer(sixbar)
    xp = plain.ekf.run(S.t, U, S.select(plain.channels).data).x_hat
    late = S.t >= S.t[0] + 0.3
    n0 = obs.ekf.model.n0
    assert np.abs(x[late, :n0] - xp[late]).mean() < np.abs(raw.x_hat[late, :n0] - xp[late]).mean()
    with pytest.raises(ValueError, match=r"payload_nominal_p must be a probability in \[0, 1\], got 1.5"):
        make_observer(sixbar, ObserverConfig(estimator="ekf-payload", payload_nominal_p=1.5))
    off = make_observer(sixbar, ObserverConfig(estimator="ekf-payload", payload_nominal_p=0.0))
    e0 = estimate(off, S.t, U, Y)
    np.testing.assert_array_equal(e0.result.x_hat, raw.x_hat)
    assert e0.result.nominal_p is None


def test_gauss_markov_disturbance_decays_with_its_stationary_variance(mid_run):
    obs, z, u = mid_run
    tau, sd, dt = 0.1, 0.2, obs.ekf.dt
    aug = AugmentedModel(obs.model, input_std=sd, input_tau=tau)
    d = np.array([0.3, -0.1, 0.05])
    p = aug.predict(np.concatenate([z, d]), u, dt)
    phi = np.exp(-dt / tau)
    np.testing.assert_allclose(p.x[aug.i_inputs], phi * d)
    # stationary: phi^2 sd^2 + q = sd^2
    np.testing.assert_allclose(np.diag(p.Q[aug.i_inputs, aug.i_inputs]), sd**2 * (1 - phi**2))


def test_estimator_choice_errors(sixbar):
    with pytest.raises(ValueError, match="estimator must be one of"):
        make_observer(sixbar, ObserverConfig(estimator="kf"))
    with pytest.raises(ValueError, match="payload_std or input_std"):
        AugmentedModel(make_observer(sixbar).model)
    with pytest.raises(ValueError, match="linearity_tol must be positive"):
        AugmentedModel(make_observer(sixbar).model, payload_std=0.01, linearity_tol=0.0)


# ------------------------------------------------------------------------------------------ RTS smoother
def _linear_system(seed=3, n=200):
    """A damped oscillator pair observed through one position, with its simulated record."""
    from exuflex.observer.base import LinearDiscreteModel

    rng = np.random.default_rng(seed)
    dt = 0.01
    A = np.eye(4)
    A[0, 2] = A[1, 3] = dt
    A[2, 0], A[3, 1], A[2, 2], A[3, 3] = -40 * dt, -90 * dt, 1 - 0.2 * dt, 1 - 0.1 * dt
    A[2, 1] = 5 * dt
    Q = np.diag([1e-8, 1e-8, 1e-4, 2e-4])
    C = {"y1": np.array([1.0, 0, 0, 0]), "y2": np.array([0.5, 1.0, 0, 0])}
    R_std = {"y1": 0.01, "y2": 0.02}
    x = np.array([0.1, -0.05, 0.0, 0.3])
    Y = np.empty((n, 2))
    for k in range(n):
        if k:
            x = A @ x + rng.multivariate_normal(np.zeros(4), Q)
        Y[k] = [C["y1"] @ x + 0.01 * rng.standard_normal(), C["y2"] @ x + 0.02 * rng.standard_normal()]
    Y[50:60, 1] = np.nan  # a blank channel: partial updates
    return LinearDiscreteModel(A, None, C, Q), R_std, np.arange(n) * dt, Y, dt


def test_rts_smoother_equals_filterpy_on_a_linear_model():
    from filterpy.kalman import KalmanFilter

    from exuflex.observer.ekf import MultirateEKF
    from exuflex.observer.smoother import rts_smooth

    model, R_std, t, Y, dt = _linear_system()
    x0, P0 = np.zeros(4), np.array([0.1, 0.1, 1.0, 1.0])
    ekf = MultirateEKF(model, ("y1", "y2"), R_std, x0, P0, dt=dt)
    sm = rts_smooth(ekf, t, None, Y)
    # the forward pass is the filter's own run
    res = ekf.run(t, None, Y, reset=True)
    np.testing.assert_allclose(sm.x_filt, res.x_hat, rtol=0, atol=1e-14)
    # filterpy's backward pass on the same forward estimates
    kf = KalmanFilter(dim_x=4, dim_z=2)
    xs, Ps, _, _ = kf.rts_smoother(sm.x_filt.copy(), sm.P_filt.copy(), Fs=[model.A] * len(t), Qs=[model.Q] * len(t))
    np.testing.assert_allclose(sm.x_hat, xs, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sm.P, Ps, rtol=1e-7, atol=1e-14)
    # smoothing never increases the variance, and the last sample is the filter's
    assert np.all(sm.P_diag <= np.diagonal(sm.P_filt, axis1=1, axis2=2) * (1 + 1e-9))
    np.testing.assert_array_equal(sm.x_hat[-1], sm.x_filt[-1])


def test_rts_smoother_stays_finite_with_an_undriven_damped_mode():
    """A mode that decays by 0.9 a sample with no process noise: its filtered variance falls below the filter's
    variance floor within the record. The smoother's forward pass leaves the floor out, so the backward pass does
    not amplify it (by 1/0.81 a sample: 1e18 over the last 200 samples, as the five-bar's smoothed estimates
    overflowed): the smoothed covariances are filterpy's on the same forward pass and never above the filtered."""
    from filterpy.kalman import KalmanFilter

    from exuflex.observer.base import LinearDiscreteModel
    from exuflex.observer.ekf import MultirateEKF
    from exuflex.observer.smoother import rts_smooth

    A = np.array([[1.0, 0.0], [0.0, 0.9]])
    Q = np.diag([1e-4, 0.0])
    model = LinearDiscreteModel(A, None, {"y": np.array([1.0, 1.0])}, Q)
    n = 600
    rng = np.random.default_rng(2)
    t, Y = np.arange(n) * 0.01, rng.standard_normal((n, 1)) * 0.01
    ekf = MultirateEKF(model, ("y",), {"y": 0.01}, np.zeros(2), np.array([1.0, 1.0]), dt=0.01)
    sm = rts_smooth(ekf, t, None, Y)
    assert np.diagonal(sm.P_filt, axis1=1, axis2=2)[-1, 1] < 1e-18  # below the filter's floor
    kf = KalmanFilter(dim_x=2, dim_z=1)
    xs, Ps, _, _ = kf.rts_smoother(sm.x_filt.copy(), sm.P_filt.copy(), Fs=[A] * n, Qs=[Q] * n)
    np.testing.assert_allclose(sm.x_hat, xs, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sm.P, Ps, rtol=1e-7, atol=1e-14)
    assert np.all(sm.P_diag <= np.diagonal(sm.P_filt, axis1=1, axis2=2) * (1 + 1e-9) + 1e-30)
    assert ekf._floor[1] == 1e-18  # the filter's own floor is back


# ------------------------------------------------------------------------------------------ UKF
def test_ukf_equals_the_kalman_filter_on_a_linear_model():
    from exuflex.observer.ekf import MultirateEKF
    from exuflex.observer.ukf import UnscentedKF

    model, R_std, t, Y, dt = _linear_system(seed=5)
    x0, P0 = np.zeros(4), np.array([0.1, 0.1, 1.0, 1.0])
    kf = MultirateEKF(model, ("y1", "y2"), R_std, x0, P0, dt=dt, store_P="full").run(t, None, Y)
    for alpha in (1e-2, 0.5):
        ukf = UnscentedKF(model, ("y1", "y2"), R_std, x0, P0, dt=dt, alpha=alpha, store_P="full").run(t, None, Y)
        np.testing.assert_allclose(ukf.x_hat, kf.x_hat, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(ukf.P, kf.P, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(ukf.nis, kf.nis, rtol=1e-6, equal_nan=True)


def test_ukf_has_the_ekfs_gate_fault_monitors_and_divergence():
    """On a linear model the UKF is the Kalman filter, so with the EKF's monitors (:class:`Monitoring`: the gate,
    the sensor-fault windows) it must gate the same spike, find the same offset fault and report the same NIS flag
    as the EKF, with "diverged" meaning a non-finite state for both (the NIS flag is ``nis_flagged``)."""
    from exuflex.observer.ekf import Monitoring, MultirateEKF
    from exuflex.observer.ukf import UnscentedKF

    from exuflex.observer.base import LinearDiscreteModel

    model, R_std, t, Y2, dt = _linear_system(seed=5, n=400)
    c3 = np.array([1.0, -1.0, 0, 0])  # a third channel: the gate leaves out a minority of the channels only
    model = LinearDiscreteModel(model.A, None, {**model.C, "y3": c3}, model.Q)
    x = np.array([0.1, -0.05, 0.0, 0.3])
    rng = np.random.default_rng(9)
    y3 = np.empty(len(t))
    for k in range(len(t)):  # (y3 of the noise-free motion from the same start: the filters see the same record)
        x = model.A @ x if k else x
        y3[k] = c3 @ x + 0.01 * rng.standard_normal()
    R_std = {**R_std, "y3": 0.05}
    Y = np.column_stack([Y2, y3])
    Y[120, 0] += 40 * R_std["y1"]  # a spike in one channel: gated
    Y[250:, 1] += 8 * R_std["y2"]  # an offset from sample 250: a fault, and the NIS test flags
    chans = ("y1", "y2", "y3")
    x0, P0 = np.zeros(4), np.array([0.1, 0.1, 1.0, 1.0])
    mon = Monitoring(nis_window=50, gate_p=1e-6, fault_window=40)
    kf = MultirateEKF(model, chans, R_std, x0, P0, dt=dt, monitoring=mon).run(t, None, Y)
    ukf = UnscentedKF(model, chans, R_std, x0, P0, dt=dt, monitoring=mon).run(t, None, Y)
    assert kf.n_rejected["y1"] >= 1 and kf.channel_faults and kf.nis_flagged
    assert ukf.n_rejected == kf.n_rejected
    assert [(f["channel"], f["kind"], f["start"]) for f in ukf.channel_faults] == \
        [(f["channel"], f["kind"], f["start"]) for f in kf.channel_faults]
    assert ukf.flagged_intervals == kf.flagged_intervals and ukf.nis_flagged_at == kf.nis_flagged_at
    assert not ukf.diverged and not kf.diverged
    np.testing.assert_allclose(ukf.x_hat, kf.x_hat, rtol=1e-7, atol=1e-9)


# ------------------------------------------------------------------------------------------ command line
def test_cli_observe_with_the_input_estimator_and_the_smoother(tmp_path, capsys):
    """``--estimator ekf-input --smooth --json``: disturbance estimates per motor with their std (on an ERLS log
    without disturbances: consistent with zero), smoothed errors below the filter's on the joint angles."""
    import json

    from exuflex.cli import main

    rc = main(["observe", str(MODELS / "sixbar.toml"), str(DATA / "sixbar_erls_3s"), "--estimator", "ekf-input",
               "--smooth", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["estimator"] == "ekf-input" and out["smoothed"]
    assert set(out["inputs"]) == {"T1", "T2", "T3"}
    for v in out["inputs"].values():
        assert v["std"] > 0 and abs(v["value"]) < 4 * v["std"]
    for q in ("q1", "q2", "q3"):
        assert out["rms_error"][q] < out["filtered_rms_error"][q]
    rc = main(["observe", str(MODELS / "sixbar.toml"), str(DATA / "sixbar_erls_3s"), "--estimator", "ukf",
               "--smooth"])
    assert rc == 2 and "needs an EKF estimator" in capsys.readouterr().err


def test_cli_observe_refuses_a_smoother_record_beyond_the_memory_limit(tmp_path, capsys, monkeypatch):
    """``--smooth`` keeps about three n x n matrices per sample: past the memory limit a one-line refusal naming
    --smooth and the need, before the filter runs (nothing written)."""
    import exuflex.validate as validate
    from exuflex.cli import main

    n_samples, nx = 1501, 26  # the six-bar log: 3 s at 500 Hz; need about 8 nx^2 x 3 per sample (24 MB)
    monkeypatch.setattr(validate, "memory_limit_bytes", lambda: 8 * nx**2 * 3 * n_samples // 10)
    rc = main(["observe", str(MODELS / "sixbar.toml"), str(DATA / "sixbar_erls_3s"), "--smooth",
               "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert rc == 2 and "--smooth:" in err and "samples of a" in err and "more than the" in err, err
    assert not (tmp_path / "out" / "estimates.csv").exists()


# ------------------------------------------------------------------------------------------ sensor design
def test_gauge_ranking_bounds_are_the_observers_bounds_and_monotone(sixbar):
    """The ranking's bounds are :func:`steady_bound`'s for an observer built on the model with those channels
    (independently built here); a gauge never raises the bound; the greedy set beats its first station alone."""
    import dataclasses
    import math

    from exuflex.scoring.design import rank_gauges
    from exuflex.observer.session import physical_names
    from exuflex.scoring.bound import steady_bound

    res = rank_gauges(sixbar, n_candidates=2)
    assert len(res.single) == 2 * len(sixbar.links)
    b = [d["tip_bound"] for d in res.single]
    assert b == sorted(b) and all(x <= res.encoders_bound * (1 + 1e-9) for x in b)
    assert res.greedy_set_bound <= b[0] and res.greedy_set[0] == res.single[0]["name"]
    # the file's own set with the common noise, through an observer of its own
    sensors = tuple(dataclasses.replace(s, noise_std=res.gauge_noise) if s.kind == "curvature" else s
                    for s in sixbar.sensors)
    mech = dataclasses.replace(sixbar, sensors=sensors)
    bnd = steady_bound(make_observer(mech))
    nq = len(mech.coordinate_names)
    x, y = physical_names(mech)[2 * nq : 2 * nq + 2]
    assert res.model_set_bound == pytest.approx(math.hypot(bnd[x], bnd[y]), rel=1e-6)
    assert [g["name"] for g in res.model_gauges] == ["c1", "c2", "c4"]


def test_cli_design_ranks_the_stations(capsys):
    import json

    from exuflex.cli import main

    assert main(["design", str(MODELS / "sixbar.toml"), "--candidates", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["single"]) == 5 and {g["name"] for g in out["model_gauges"]} == {"c1", "c2", "c4"}
    assert all(1 <= g["rank"] <= 6 for g in out["model_gauges"])
    assert main(["design", str(MODELS / "sixbar.toml"), "--candidates", "0"]) == 2


def test_ukf_retakes_a_failed_sigma_point_step_after_a_model_reset():
    """A caching model whose step fails away from its cache (NaN) is reset and stepped again: the run equals the
    one on the model that never fails."""
    from exuflex.observer.ukf import UnscentedKF

    model, R_std, t, Y, dt = _linear_system(seed=7, n=60)

    class Fragile:
        nx = model.nx

        def __init__(self):
            self.calls = 0
            self.fresh = True

        def reset(self):
            self.fresh = True

        def predict(self, x, u, dt, u_next=None):
            self.calls += 1
            p = model.predict(x, u, dt, u_next)
            if self.calls % 7 == 0 and not self.fresh:  # a stale cache: no finite step
                return p._replace(x=np.full(self.nx, np.nan))
            self.fresh = False
            return p

        def measure(self, x, channels):
            return model.measure(x, channels)

    x0, P0 = np.zeros(4), np.array([0.1, 0.1, 1.0, 1.0])
    ref = UnscentedKF(model, ("y1", "y2"), R_std, x0, P0, dt=dt).run(t, None, Y)
    ukf = UnscentedKF(Fragile(), ("y1", "y2"), R_std, x0, P0, dt=dt)
    res = ukf.run(t, None, Y)
    assert ukf.n_model_resets > 0 and not res.nonfinite
    np.testing.assert_allclose(res.x_hat, ref.x_hat, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("persistent", [False, True])
def test_ukf_breakdown_of_a_sigma_point_step(persistent):
    """A finite but absurd step from a sigma point (an unstable held expansion far from its centre) is retaken
    after a model reset; if it breaks down again, the point follows the mean's linearisation. On a linear model
    both give the Kalman filter's result exactly (the linearisation is exact there)."""
    from exuflex.observer.ukf import UnscentedKF

    model, R_std, t, Y, dt = _linear_system(seed=11, n=60)

    class Unstable:
        nx = model.nx

        def __init__(self):
            self.calls = 0
            self.bad = None  # the point whose step broke down

        def reset(self):
            if not persistent:
                self.bad = None

        def predict(self, x, u, dt, u_next=None):
            self.calls += 1
            p = model.predict(x, u, dt, u_next)
            if self.calls % 5 == 0 and not np.array_equal(x, self.ukf._x):  # a sigma point, not the mean
                self.bad = x.copy()
            if self.bad is not None and np.array_equal(x, self.bad):
                return p._replace(x=p.x * 1e30)
            return p

        def measure(self, x, channels):
            return model.measure(x, channels)

    x0, P0 = np.zeros(4), np.array([0.1, 0.1, 1.0, 1.0])
    ref = UnscentedKF(model, ("y1", "y2"), R_std, x0, P0, dt=dt).run(t, None, Y)
    unstable = Unstable()
    ukf = unstable.ukf = UnscentedKF(unstable, ("y1", "y2"), R_std, x0, P0, dt=dt)
    res = ukf.run(t, None, Y)
    assert ukf.n_model_resets > 0 and not res.nonfinite
    assert (ukf.n_linearised > 0) == persistent
    np.testing.assert_allclose(res.x_hat, ref.x_hat, rtol=1e-9, atol=1e-12)


@pytest.fixture(scope="module")
def serial_arm_payload():
    """The serial arm's cached observer model and its payload-augmented model, and a state with both joints
    turning (the bias force ``J^T M a_b`` is bilinear in the joint rates and the elastic rates) and the torques.
    One interior mode (the band's count): the order fit over dt below assumes the steps' difference smooth in dt,
    which an interior mode at 372 Hz (``omega dt`` 1.9 at the largest dt, kept by the automatic count's filter
    requirement) breaks."""
    mech = load_mechanism(MODELS / "serial_arm.toml")
    obs = make_observer(mech, ObserverConfig(n_interior=1))
    m = obs.model
    r, nq = m.r, m.nq
    rng = np.random.default_rng(1)
    z = m.initial_state(mech.q_ref, qd=np.array([1.5, -2.0]))
    z[nq:r] = 1e-4 * rng.normal(size=r - nq)
    z[r + nq :] = 1e-2 * rng.normal(size=r - nq)
    return mech, m, AugmentedModel(m, payload_std=0.01), z, np.array([1.0, -0.5])


def _fresh_increment(m, aug, z, u, dt):
    """The held configuration evaluated at ``z`` (no secant partner) and its payload increment."""
    m.reset()
    aug.reset()
    aug.predict(np.concatenate([z, [1.0]]), u, dt)
    iv, _ = m.last_step
    return iv, aug.increment(iv, z)


def test_payload_increment_is_the_derivative_of_the_full_forces_in_the_payload_mass(serial_arm_payload):
    """The increment's forces (weight, velocity forms and the bias force ``J^T M a_b`` with the bias
    acceleration's curvature ``d^2(H p)/dq^2 [q', q']``) at the held state equal the central difference in the
    payload scale of the reduced model's forces evaluated directly (``fr`` of :meth:`ReducedModel.matrices`, the
    full model's forces through ``J``) on models with the payload scaled by ``1 +- 0.5``: entry by entry within
    1e-9 of the entry, or 1e-13 of the largest where an entry is at round-off (the forces are linear in the payload mass, so the difference is exact up to rounding; the
    curvature is a forward difference in ``fr`` and a central one in the increment, some 1e-6 of the curvature's
    share apart). Measured: 7e-11 of the entry at most. The bias term and its curvature are each a visible share
    of every entry (so that a test without them would fail): measured the curvature 1.1e-5 to 6.6e-4 of the entry."""
    from exuflex.observer.augmented import payload_twin

    _, m, aug, z, u = serial_arm_payload
    r, nq = m.r, m.nq
    iv, inc = _fresh_increment(m, aug, z, u, 1e-3)
    p, pd = z[:r].copy(), z[r:]
    p[:nq] = iv.q0
    f_vel = inc.fg - 0.5 * ((pd @ inc.T2).reshape(r, r) @ pd)
    f_bias = -np.outer(pd, pd[:nq]).ravel() @ inc.C2
    eps = 0.5
    fd = (payload_twin(m.rm, 1 + eps).matrices(p, pd).fr - payload_twin(m.rm, 1 - eps).matrices(p, pd).fr) / (2 * eps)
    floor = 1e-13 * np.abs(fd).max()  # (an entry at round-off: the relative frames' elastic row is one)
    np.testing.assert_allclose(f_vel + f_bias, fd, rtol=1e-9, atol=floor)
    big = np.abs(fd) > 1e3 * floor
    # the bias form without the curvature: the two models' forms at the state as the held evaluation gives them
    flat = payload_twin(m.rm, 2.0).held(p, pd)[1].C2 - payload_twin(m.rm, 1.0).held(p, pd)[1].C2
    f_curv = f_bias + np.outer(pd, pd[:nq]).ravel() @ flat
    # the bias term against the check's 1e-9 of the entry: measured 2.0e-4 of the entry at least (the elbow's
    # transverse master, whose Guyan shape holds the upper arm's elastic rotation there, a master too)
    assert np.all(np.abs(f_bias[big]) > 1e-5 * np.abs(fd[big]))
    assert np.all(np.abs(f_curv[big]) > 1e3 * 1e-9 * np.abs(fd[big])), np.abs(f_curv[big] / fd[big]).min()


@pytest.mark.xfail(strict=True, reason=(
    "with the upper arm's elastic rotation at the elbow a master (exuflex.reduction.masters.reading_masters) the "
    "cached and the reference payload steps differ at first order in dt by 4e-7 to 7e-7 in every rate entry (the "
    "same with dt from 0.1 down to 0.0125 ms and from 0.05 down to 0.00625 ms, so not the fit), 9e-4 of the largest "
    "entries' bias rate but 1-20 times that of the four entries whose bias rate is 3e-8 to 6e-7 (over 0.4-0.05 ms, "
    "where the master's 408 Hz clamped mode reaches omega dt 1.0, the fit gives 4e-6): not found"))
def test_cached_and_reference_payload_steps_agree_to_the_held_configurations_order(serial_arm_payload):
    """The payload's effect on the step, ``x(theta = 2) - x(theta = 1)``, of the cached step (the held
    configuration's scaled system, :func:`scaled_steps`) against the reference (RK4 of the scaled nonlinear
    reduced equations at every stage, ``_scaled_rk4``). The cached step holds the configuration at the interval's
    start, so the two differ in the rates by ``O(dt^2)`` (a configuration error ``q' t`` integrated over the
    interval); a force the cached step leaves out adds its rate times ``dt``: the payload's bias force ``J^T M a_b``
    with its rate ``g = M_r(2)^-1 f_bias`` would add ``-g dt``, the bias acceleration's curvature alone 0.3-1 % of
    ``g`` (measured here). Per rate entry the difference over dt = 0.4, 0.2, 0.1, 0.05 ms is fitted by ``b dt + a
    dt^2 + c dt^3 + d dt^4``: the first-order coefficient ``b_i`` must be within 1e-3 of ``|g_i|``. Measured:
    ``|b_i / g_i|`` at most 6e-5 (without the curvature 0.3-1.4 %). The reference carries the nominal model's
    geometric stiffness of the motion, as the cached step does; the payload's share of it, which both leave out,
    is bounded against the payload's whole effect on the accelerations."""
    from exuflex.observer.augmented import scaled_steps

    mech, m, aug, z, u = serial_arm_payload
    r, nq = m.r, m.nq
    ref = make_observer(mech, ObserverConfig(method="rk4"), cb=m.rm.cb).model
    aug_r = AugmentedModel(ref, payload_std=0.01)
    a = np.array([1.0, 0.0])
    dts = np.array([4e-4, 2e-4, 1e-4, 5e-5])
    E = []
    for dt in dts:
        iv, inc = _fresh_increment(m, aug, z, u, dt)
        n = m.substeps(iv, dt)
        dl = z[:nq] - iv.q0
        assert not np.any(dl)
        c = scaled_steps(z, u, np.empty(0), dl, 0.0, dt / n, n, a, tuple(iv.system), tuple(inc))[0]
        ref.reset()
        aug_r.reset()
        aug_r.predict(np.concatenate([z, [1.0]]), u, dt)
        rr = aug_r._scaled_rk4(z, u, dt, a)
        E.append(((c[0] - c[1]) - (rr[0] - rr[1]))[r:])
    b = np.linalg.solve(np.vstack([dts, dts**2, dts**3, dts**4]).T, np.array(E))[0]
    pd = z[r:]
    f_bias = -np.outer(pd, pd[:nq]).ravel() @ inc.C2
    g = np.linalg.solve(iv.mats.Mr + inc.Mr, f_bias)
    assert np.all(np.abs(b) <= 1e-3 * np.abs(g)), np.abs(b / g).max()
    # what both leave out: the payload's share of the motion's geometric stiffness (the axial loads of its inertia),
    # against the payload's whole effect on the accelerations at the state (measured 0.2-4.0 % per entry)
    p = z[:r]

    def accelerations(model):
        mt = model.matrices(p, pd)
        K = model.motion_stiffness(mt.rc, mt.J, pd[:nq], u)
        return mt, K, np.linalg.solve(mt.Mr, mt.Gr @ u + mt.fr - mt.Cr @ pd - (mt.Kr + K) @ p)

    m1, K1, a1 = accelerations(m.rm)
    m2, K2, a2 = accelerations(aug.twin)
    share = np.linalg.solve(m2.Mr, (K2 - K1) @ p)
    assert np.all(np.abs(share) <= 0.1 * np.abs(a2 - a1)), np.abs(share / (a2 - a1)).max()

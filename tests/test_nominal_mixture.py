"""The payload estimator's report (:func:`exuflex.observer.augmented.nominal_mixture`): on a linear-Gaussian
model with a constant unknown parameter it is the exact Bayesian model average of "the parameter is nominal" and
"the parameter is unknown", checked against two filterpy Kalman filters (one per hypothesis) and their marginal
likelihoods."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy.stats import norm

from exuflex.observer.augmented import nominal_mixture


def _linear_case(theta_true: float, seed: int, steps: int = 40):
    """A damped oscillator driven by a constant force scaled by an unknown parameter theta (prior N(1, 0.5^2)),
    its position measured: the joint filter (theta a state), the nominal one (theta = 1 known), and the log
    marginal likelihood of the measurements under each."""
    rng = np.random.default_rng(seed)
    dt, s0, r = 0.05, 0.5, 0.02**2
    A = np.array([[1.0, dt], [-4.0 * dt, 1.0 - 0.4 * dt]])
    b = np.array([0.0, 0.3 * dt])  # theta's force
    Q = np.diag([1e-6, 1e-4])
    H = np.array([[1.0, 0.0]])
    # the truth
    z = np.zeros(2)
    ys = []
    for _ in range(steps):
        z = A @ z + b * theta_true + rng.multivariate_normal(np.zeros(2), Q)
        ys.append(H @ z + rng.normal(0.0, np.sqrt(r), 1))
    joint = KalmanFilter(dim_x=3, dim_z=1)
    joint.F = np.block([[A, b[:, None]], [np.zeros((1, 2)), np.ones((1, 1))]])
    joint.Q = np.zeros((3, 3))
    joint.Q[:2, :2] = Q
    joint.H = np.hstack([H, [[0.0]]])
    joint.R = np.array([[r]])
    joint.x = np.array([0.0, 0.0, 1.0])
    joint.P = np.diag([1e-8, 1e-8, s0**2])
    nominal = KalmanFilter(dim_x=2, dim_z=1)
    nominal.F, nominal.Q, nominal.H, nominal.R = A, Q, H, np.array([[r]])
    nominal.x = np.zeros(2)
    nominal.P = np.diag([1e-8, 1e-8])
    nominal.B = b[:, None]
    ll_joint = ll_nom = 0.0
    for y in ys:
        joint.predict()
        joint.update(y)
        ll_joint += joint.log_likelihood
        nominal.predict(u=np.array([1.0]))
        nominal.update(y)
        ll_nom += nominal.log_likelihood
    return joint, nominal, ll_joint, ll_nom, s0**2


@pytest.mark.parametrize(("theta_true", "p"), [(1.0, 0.5), (1.3, 0.5), (2.0, 0.9), (1.0, 0.99)])
def test_mixture_is_the_bayesian_model_average_of_a_linear_gaussian_model(theta_true, p):
    joint, nominal, ll_joint, ll_nom, prior_var = _linear_case(theta_true, seed=3)
    x, P = joint.x, joint.P
    xr, Pr, w = nominal_mixture(x, P, P[:, 2], 2, prior_var, p)
    # the nominal hypothesis' posterior probability from the two marginal likelihoods (Savage-Dickey is exact here)
    w_ref = p / (p + (1.0 - p) * np.exp(ll_joint - ll_nom))
    assert w[0] == pytest.approx(w_ref, rel=1e-9, abs=1e-12)
    # the conditional on theta = 1 is the nominal filter's posterior; the report the two hypotheses' mixture
    x_nom = np.append(nominal.x, 1.0)
    P_nom = np.zeros((3, 3))
    P_nom[:2, :2] = nominal.P
    mean = w_ref * x_nom + (1.0 - w_ref) * x
    cov = (w_ref * (P_nom + np.outer(x_nom - mean, x_nom - mean))
           + (1.0 - w_ref) * (P + np.outer(x - mean, x - mean)))
    np.testing.assert_allclose(xr, mean, rtol=0, atol=1e-9 * np.abs(mean).max())
    np.testing.assert_allclose(Pr, cov, rtol=0, atol=1e-9 * np.abs(cov).max())
    # with variances only: the mixture's diagonal
    _, Pd, _ = nominal_mixture(x[None], np.diag(P)[None], P[:, 2][None], 2, prior_var, p)
    np.testing.assert_allclose(Pd[0], np.diag(cov), rtol=0, atol=1e-9 * np.abs(cov).max())


def test_mixture_follows_the_evidence_for_and_against_the_nominal_payload():
    """Savage-Dickey by hand (the scale's posterior density at 1 over its prior density there), and the limits:
    no nominal prior leaves the posterior, a certain one gives the conditional; a sample without a scale
    variance is left as it is."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(4, 4))
    P = A @ A.T
    x = rng.normal(size=4)
    x[1] = 1.4
    bf = norm.pdf(1.0, x[1], np.sqrt(P[1, 1])) / norm.pdf(1.0, 1.0, 0.5)
    _, _, w = nominal_mixture(x, P, P[:, 1], 1, 0.25, 0.3)
    assert w[0] == pytest.approx(0.3 * bf / (0.3 * bf + 0.7), rel=1e-12)
    bf = norm.pdf(1.0, x[1], np.sqrt(P[1, 1])) / norm.pdf(1.0, 1.2, 0.5)  # a prior centred elsewhere
    _, _, w = nominal_mixture(x, P, P[:, 1], 1, 0.25, 0.3, prior_mean=1.2)
    assert w[0] == pytest.approx(0.3 * bf / (0.3 * bf + 0.7), rel=1e-12)
    xr, Pr, w = nominal_mixture(x, P, P[:, 1], 1, 0.25, 0.0)
    assert w[0] == 0.0 and np.array_equal(xr, x) and np.allclose(Pr, P, rtol=0, atol=1e-15)
    xr, Pr, w = nominal_mixture(x, P, P[:, 1], 1, 0.25, 1.0)
    g = P[:, 1] / P[1, 1]  # the Gaussian conditional on x[1] = 1
    np.testing.assert_allclose(xr, x + g * (1.0 - x[1]), rtol=1e-12)
    np.testing.assert_allclose(Pr, P - np.outer(P[:, 1], P[:, 1]) / P[1, 1], rtol=0, atol=1e-12)
    assert xr[1] == pytest.approx(1.0) and abs(Pr[1, 1]) < 1e-12
    X = np.vstack([x, x])
    C = np.vstack([P[:, 1], np.full(4, np.nan)])
    xr, _, w = nominal_mixture(X, None, C, 1, 0.25, 0.5)
    assert w[1] == 0.0 and np.array_equal(xr[1], x)

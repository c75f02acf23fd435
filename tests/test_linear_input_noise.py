"""The process noise of a step with the torques linear between two samples (``input_hold = "linear"``).

With a linear hold the step reads two noisy torque samples, the interval's start ``u_k`` and its end ``u_k+1``:
the measured torques' noise ``n`` moves the state at the interval's end by ``A n_k + B n_k+1`` (``A``, ``B`` the
step's derivatives in the two samples, ``S`` the torques' noise covariance), and each sample's noise enters two
intervals: the process noise is correlated from one interval to the next. The filter's process noise is the held
torque's, white, ``L S L^T`` with ``L = A + B``. That describes the noise where ``A`` and ``B`` are small against
``L`` (slow modes: ``A ~ B ~ L / 2``, and the two intervals' parts add up to ``L``). For a mode whose half period
is near the sample interval they are not: a torque held over half a period leaves the mode's rate near zero, the
ramp between two samples does not, and the two parts cancel in the open loop but not where an update has
corrected the first between them.

On ``benchmarks/models/scara_pick.toml`` (a relative elbow motor; the reduced model has a mode near 520 Hz, sampled
at 1 kHz) ``A`` and ``B`` of the elbow rate per N m of the elbow torque are about 8 times ``L``, and the filter on
its logs (declared linear) has an elbow-rate error ringing at 480-500 Hz some 7 times its own standard deviation;
the same log declared held, or its torques smoothed before the filter, is within the bound.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer.session import make_observer

ROOT = Path(__file__).resolve().parents[1]


LINEAR_XFAIL = pytest.mark.xfail(strict=True, reason="the linear hold's process noise is the held torque's, white "
                                 "L S L^T: on scara_pick the accumulated standard deviations of the elastic "
                                 "coordinates are up to 2.5 times the two samples' (module docstring)")


@pytest.mark.parametrize("hold", ["zoh", pytest.param("linear", marks=LINEAR_XFAIL)])
def test_step_noise_is_the_torque_samples(hold):
    """The filter's covariance of the noise accumulated over 20 intervals (the step's Jacobian and process noise
    frozen at one state), entry by entry on the diagonal, against the covariance of the state's response to
    independent noise in the torque samples (the step's central differences in its two samples, each sample's
    noise entering the interval it ends and the one it starts), wherever that variance is above 1e-6 of its
    largest of the kind (positions, rates). The first sample's noise enters through the first interval only (the
    held input's ``L`` has both parts): a relative margin of 0.1 holds that one interval's share of twenty. With a
    held input (``B = 0``, ``A = L``) the two agree."""
    mech = load_mechanism(ROOT / "benchmarks/models/scara_pick.toml")
    som = make_observer(mech).model
    som.input_hold, som.input_delay = hold, 0.0
    x = som.initial_state(np.asarray(mech.q_ref, float), np.array([0.5, -1.0]))
    u = np.array([0.5, 0.2])
    dt = 1.0 / mech.sample_rate_hz
    pred = som.predict(x, u, dt, u)
    nu = len(u)
    A = np.empty((len(x), nu))
    B = np.empty((len(x), nu))
    for j in range(nu):
        e = np.zeros(nu)
        e[j] = 1e-3
        A[:, j] = (som.predict(x, u + e, dt, u).x - som.predict(x, u - e, dt, u).x) / 2e-3
        B[:, j] = (som.predict(x, u, dt, u + e).x - som.predict(x, u, dt, u - e).x) / 2e-3
    S = np.diag(som.torque_var)
    F = pred.F
    # n intervals frozen at this step: the torque sample j moves the state at the end by G_j n_j, G_j = F^(n-1-j) A
    # + F^(n-j) B (it ends interval j-1 and starts interval j); the filter's, sum_j F^(n-1-j) Q F^(n-1-j)^T; the
    # last sample's noise (it starts the next interval) is in neither
    n = 20
    Fp = [np.eye(len(x))]
    for _ in range(n):
        Fp.append(F @ Fp[-1])
    want = np.zeros_like(pred.Q)
    got = np.zeros_like(pred.Q)
    for j in range(n):
        G = Fp[n - 1 - j] @ A + (Fp[n - j] @ B if j > 0 else 0.0)
        want += G @ S @ G.T
        got += Fp[n - 1 - j] @ pred.Q @ Fp[n - 1 - j].T
    want, got = np.diag(want), np.diag(got)
    r = som.r
    for part in (slice(0, r), slice(r, 2 * r)):
        w, g = want[part], got[part]
        keep = w > 1e-6 * w.max()
        rel = np.abs(g[keep] - w[keep]) / w[keep]
        assert rel.max() < 0.1, (rel, g[keep], w[keep])

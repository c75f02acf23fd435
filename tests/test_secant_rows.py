"""The cached observer's measurement rows away from the held configuration (:meth:`ReducedObserverModel.measure`):
the q-dependence to second order along the secant, with its exact Jacobian.

The slider-crank's slider position ``x_B = r cos q + sqrt(l^2 - r^2 sin^2 q)`` is the gallery's most curved
rigid channel: to first order about the held ``q0`` its error is ``1/2 x_B'' dl^2``, of the order of the
channel's noise at the measurement radius. With the second-order term the error is of third order in the
distance (partner and state at the same distance either side of ``q0``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, make_observer

ROOT = Path(__file__).resolve().parents[1]
CHANNELS = ("q1", "xB", "c_rod_quarter", "c_rod_mid")


@pytest.fixture(scope="module")
def slider_model():
    mech = load_mechanism(ROOT / "models" / "slider_crank.toml")
    return make_observer(mech, ObserverConfig(channels=CHANNELS)).model


def _hold_with_partner(m, q0: float, h: float):
    """Hold the undeformed configuration at q0 with its secant partner at q0 - h (what a refresh does)."""
    old = m._configuration(m.initial_state([q0 - h]), held=True)
    iv = m._configuration(m.initial_state([q0]), held=True)
    d = iv.q0 - old.q0
    iv.old, iv.d, iv.dd, iv.rad = old, d, float(d @ d), 0.05
    m._last = iv
    return iv


def _exact(m, x):
    """The channels at x from the rows of x's own configuration (exact for an undeformed state)."""
    c0, Hm = m._affine(m._configuration(x), CHANNELS)
    return c0 + Hm @ x


@pytest.mark.parametrize("q0", [1.2, 2.5, 4.0])
def test_slider_channel_is_third_order_along_the_secant(slider_model, q0):
    """Partner at q0 - h, state at q0 + h: the slider channel's error falls as h^3 (fitted log-log slope within
    0.1 of 3), where the first-order rows of the held configuration alone err as h^2 (slope within 0.1 of 2);
    at the smallest distance the second-order error is below a tenth of the first-order one."""
    m = slider_model
    hs = np.array([0.005, 0.01, 0.02, 0.04])
    err2, err1 = [], []
    for h in hs:
        iv = _hold_with_partner(m, q0, h)
        x = m.initial_state([q0 + h])
        exact = _exact(m, x)[1]
        err2.append(abs(m.measure(x, CHANNELS).y[1] - exact))
        c0, Hm = m._affine(iv, CHANNELS)
        err1.append(abs((c0 + Hm @ x)[1] - exact))
    assert np.polyfit(np.log(hs), np.log(err2), 1)[0] == pytest.approx(3.0, abs=0.1)
    assert np.polyfit(np.log(hs), np.log(err1), 1)[0] == pytest.approx(2.0, abs=0.1)
    assert err2[0] < 0.1 * err1[0]


def test_measurement_jacobian_is_the_derivative_of_the_second_order_rows(slider_model):
    """The q-column of H is the derivative of the channels the model returns (central differences, 1e-8
    relative), also where the second-order term is active (away from q0 along the secant)."""
    m = slider_model
    iv = _hold_with_partner(m, 2.0, 0.02)
    x = m.initial_state([2.03])
    meas = m.measure(x, CHANNELS)
    eps = 1e-6
    xp, xm = x.copy(), x.copy()
    xp[0] += eps
    xm[0] -= eps
    fd = (m.measure(xp, CHANNELS).y - m.measure(xm, CHANNELS).y) / (2 * eps)
    assert m._last is iv  # no configuration evaluated anew: the held rows were used
    np.testing.assert_allclose(meas.H[:, 0], fd, rtol=0, atol=1e-8 * np.abs(meas.H[:, 0]).max())

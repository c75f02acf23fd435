"""The cached observer's measurement rows away from the held configuration (:meth:`ReducedObserverModel.measure`):
the rows' exact first-order change with q in every direction, and the rigid parts' second order.

The reference is the exact measurement: the rows of the state's own configuration, evaluated anew
(:meth:`ReducedObserverModel._affine` at ``_configuration(x)``, exact in p), and the q-columns of its Jacobian by
central differences of that measurement in q. About a held ``q0`` the expansion's error is of second order in
``dl = q - q0`` (of third for the rigid part of an undeformed state): halving ``dl`` must divide every entry's
error by about four, in directions of every coordinate and two more, entry by entry. The three mechanisms cover the
channel kinds: a serial arm's relative encoders, gauges on three links turning with each other and its tip
position; the six-bar's closed loop (dependent link angles, a relative encoder, the tip); the slider-crank's
slider position.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, make_observer

ROOT = Path(__file__).resolve().parents[1]
MODELS = ("three_link_arm", "sixbar", "slider_crank")
SLIDER = ("q1", "xB", "c_rod_quarter", "c_rod_mid")


@pytest.fixture(scope="module", params=MODELS)
def case(request):
    """The model's observer model with every sensor channel, a held undeformed configuration away from q* and
    elastic coordinates of a deflected state."""
    mech = load_mechanism(ROOT / "models" / f"{request.param}.toml")
    channels = tuple(s.name for s in mech.sensors)
    m = make_observer(mech, ObserverConfig()).model  # its rows serve any of the mechanism's channels
    q0 = np.asarray(m.rm.cb.q_star, float) + 0.05
    iv = m._configuration(m.initial_state(q0), held=True)
    pe = 2e-4 * np.random.default_rng(3).standard_normal(m.r - m.nq)
    return m, iv, channels, pe


def _directions(nq: int) -> list:
    rng = np.random.default_rng(7)
    return list(np.eye(nq)) + [v / np.linalg.norm(v) for v in rng.standard_normal((2, nq))]


def _exact(m, x, channels, eps=1e-6):
    """The channels at x from x's own configuration and their Jacobian: the elastic columns are the rows of that
    configuration, the q-columns central differences of the exact channels."""
    def y(x):
        c0, Hm = m._affine(m._configuration(x), channels)
        return c0 + Hm @ x, Hm

    y0, H = y(x)
    H = H.copy()
    for j in range(m.nq):
        xp, xm = x.copy(), x.copy()
        xp[j] += eps
        xm[j] -= eps
        H[:, j] = (y(xp)[0] - y(xm)[0]) / (2 * eps)
    return y0, H


def _errors(m, iv, channels, x):
    """``(|y - y_exact|, |H - H_exact|, first-order errors of both)``: the held rows with their change against the
    exact measurement, and the held configuration's rows alone (``c0 + Hm x``) against it."""
    centre = m.rows_about(iv, 0.15)
    meas = m.measure(x, channels)
    assert m._centre is centre  # iv's rows served: none rebuilt
    y, H = _exact(m, x, channels)
    c0, Hm = m._affine(iv, channels)
    return np.abs(meas.y - y), np.abs(meas.H - H), np.abs(c0 + Hm @ x - y), np.abs(Hm - H)


def _second_order(e1, e2, scale, what):
    """Entry by entry: the expansion's error ``e1`` at ``dl`` and ``e2`` at ``dl / 2``, at most 0.35 of it (second
    order: a quarter), above a rounding floor of each entry's own scale."""
    floor = 1e-9 * scale + 1e-15
    bad = e2 > 0.35 * e1 + floor
    assert not np.any(bad), f"{what}: not second order at {np.argwhere(bad).tolist()}: {e1[bad]} -> {e2[bad]}"


def test_rows_follow_the_configuration_to_second_order(case):
    """y and H of :meth:`measure` against the exact measurement at ``q0 + h u`` and ``q0 + h u / 2`` (h = 0.01
    rad, where the third-order terms are small against the second-order ones on every model) for u along every coordinate and two other directions: on a deflected state, y and H's elastic columns
    to second order in h; on the undeformed state, H's q-columns too (on a deflected state they leave out the
    elastic rows' q-derivative, :meth:`ReducedObserverModel.measure`)."""
    m, iv, channels, pe = case
    nq, r = m.nq, m.r
    h = 0.01
    seen = []  # the first-order rows' error ratios at dl / 2 and dl, where that error is above rounding
    for u in _directions(nq):
        for deflected in (True, False):
            res = []
            for step in (h, h / 2):
                x = m.initial_state(iv.q0 + step * u)
                if deflected:
                    x[nq:r] = pe
                res.append(_errors(m, iv, channels, x))
            (ey1, eH1, oy1, oH1), (ey2, eH2, oy2, oH2) = res
            c0, Hm = m._affine(iv, channels)
            y_scale = np.abs(c0) + np.abs(Hm).max(axis=1)
            H_scale = np.abs(Hm[:, :r]).max(axis=1, keepdims=True)
            cols = slice(0, r) if not deflected else slice(nq, r)
            _second_order(ey1, ey2, y_scale, f"y along {u} (deflected {deflected})")
            _second_order(eH1[:, cols], eH2[:, cols], H_scale, f"H along {u} (deflected {deflected})")
            assert np.all(eH1[:, r:] == 0)  # no velocity columns
            # the rows at q0 alone: their error ratio where it is above rounding
            o1 = np.concatenate([oy1, oH1[:, cols].ravel()])
            o2 = np.concatenate([oy2, oH2[:, cols].ravel()])
            big = o1 > 1e-6 * np.concatenate([y_scale, np.broadcast_to(H_scale, oH1.shape)[:, cols].ravel()])
            seen.append(o2[big] / o1[big])
    # the rows at q0 alone are first order (the error halves with dl): the test sees the change it checks
    assert np.max(np.concatenate(seen)) > 0.45


def test_measurement_jacobian_is_the_derivative_of_the_returned_channels(case):
    """H of :meth:`measure` is the derivative of the y it returns (central differences in every state entry,
    1e-6 of each entry's own size), off the held configuration in a direction of all coordinates at once, on a
    deflected state, once the elastic rows' q-derivative ``D_j x`` it leaves out of the q-columns is added
    (:meth:`ReducedObserverModel.measure`)."""
    m, iv, channels, pe = case
    nq, r = m.nq, m.r
    x = m.initial_state(iv.q0 + 0.05 * _directions(nq)[-1])
    x[nq:r] = pe
    centre = m.rows_about(iv, 0.15)
    H = m.measure(x, channels).H
    D = m._rows(iv, channels)[2]
    H[:, :nq] += np.einsum("jic,c->ij", D, x[:r])  # the left-out term
    eps = 1e-6
    fd = np.empty_like(H)
    for j in range(m.nx):
        xp, xm = x.copy(), x.copy()
        xp[j] += eps
        xm[j] -= eps
        fd[:, j] = (m.measure(xp, channels).y - m.measure(xm, channels).y) / (2 * eps)
    assert m._centre is centre
    np.testing.assert_allclose(H, fd, rtol=1e-6, atol=1e-9 * np.abs(H).max())


@pytest.fixture(scope="module")
def slider_model():
    mech = load_mechanism(ROOT / "models" / "slider_crank.toml")
    return make_observer(mech, ObserverConfig(channels=SLIDER)).model


@pytest.mark.parametrize("q0", [1.2, 2.5, 4.0])
def test_slider_channel_is_third_order(slider_model, q0):
    """The slider-crank's slider position ``x_B = r cos q + sqrt(l^2 - r^2 sin^2 q)``, the gallery's most curved
    rigid channel: about the held ``q0`` the rows alone err as ``1/2 x_B'' dl^2`` (fitted log-log slope within
    0.1 of 2), with the second-order term as ``dl^3`` (slope within 0.1 of 3, below a tenth of the first-order
    error at the smallest distance), either side of q0."""
    m = slider_model
    iv = m._configuration(m.initial_state([q0]), held=True)
    hs = np.array([0.005, 0.01, 0.02, 0.04])
    for sign in (1.0, -1.0):
        err2, err1 = [], []
        for h in hs:
            x = m.initial_state([q0 + sign * h])
            m.rows_about(iv, 0.05)
            exact = _exact(m, x, SLIDER)[0][1]
            err2.append(abs(m.measure(x, SLIDER).y[1] - exact))
            c0, Hm = m._affine(iv, SLIDER)
            err1.append(abs((c0 + Hm @ x)[1] - exact))
        assert np.polyfit(np.log(hs), np.log(err2), 1)[0] == pytest.approx(3.0, abs=0.1)
        assert np.polyfit(np.log(hs), np.log(err1), 1)[0] == pytest.approx(2.0, abs=0.1)
        assert err2[0] < 0.1 * err1[0]

"""The measurement rows' own radius (:meth:`ReducedObserverModel._recentre`): the replaced rows' error measured at
each rebuild, and the radius that keeps the rows' error near ``rows_tol`` channel noises.

- An analytic case: the slider-crank's slider position ``x_B(q) = r cos q + sqrt(l^2 - r^2 sin^2 q)`` (a rigid
  channel): the error the rebuild measures is the remainder of its second-order Taylor expansion about the old
  centre, in units of the channel's noise.
- The radius rule: an error growing as ``dist^2`` is brought to ``0.81 rows_tol`` at the new radius.
- Along a path: the measured channels of a deflected arm moving through its workspace, from the rows with their
  adaptive radius against the exact measurement at every step, stay within ``rows_tol`` noises, on a gallery arm
  and on the fresh long arm (benchmarks/models/three_link_reach.toml), while rows held over the largest radius
  exceed it (the test would see the error grow).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, make_observer

ROOT = Path(__file__).resolve().parents[1]
SLIDER = ("q1", "xB")


def _exact_y(m, x, channels):
    """The channels at ``x`` from x's own configuration (exact in q and p)."""
    c0, Hm = m._affine(m._configuration(x), channels)
    return c0 + Hm @ x


@pytest.mark.parametrize("q_old", [1.2, 2.5, 4.0])
def test_rebuild_measures_the_slider_taylor_remainder(q_old):
    """The error :meth:`_rows_error` measures for rows about ``q_old`` replaced by rows about ``q_old + d`` on the
    undeformed slider-crank (no filter covariance: against the noise): ``|x_B(q_new) - x_B - x_B' d - x_B'' d^2 / 2|
    / sigma`` with the derivatives of the closed form at ``q_old``, within 1 % (the encoder's row is exact)."""
    mech = load_mechanism(ROOT / "models" / "slider_crank.toml")
    m = make_observer(mech, ObserverConfig(channels=SLIDER)).model
    r, l = (lk.length for lk in mech.links)
    sig = m.sensors["xB"].noise_std
    s, c = math.sin(q_old), math.cos(q_old)
    g = l * l - r * r * s * s
    g1, g2 = -r * r * math.sin(2 * q_old), -2 * r * r * math.cos(2 * q_old)
    f1 = -r * s + g1 / (2 * math.sqrt(g))
    f2 = -r * c + g2 / (2 * math.sqrt(g)) - g1 * g1 / (4 * g**1.5)

    def xb(q):
        return r * math.cos(q) + math.sqrt(l * l - (r * math.sin(q)) ** 2)

    for d in (0.02, 0.04, -0.04):
        old = m.rows_about(m._rows_at(np.array([q_old])), 0.05)
        new = m.rows_about(m._rows_at(np.array([q_old + d])), 0.05)
        x = m.initial_state([q_old + d])
        expected = abs(xb(q_old + d) - xb(q_old) - f1 * d - 0.5 * f2 * d * d) / sig
        assert m._rows_error(old, new, x, SLIDER) == pytest.approx(expected, rel=1e-2)


def test_radius_rule_brings_a_quadratic_error_to_the_tolerance():
    """:meth:`_rows_radius`: for an error ``e(d) = k d^2`` measured at ``dist`` the new radius ``R`` has ``e(R) =
    0.81 rows_tol`` (the 0.9 margin squared), within the radius limits and at most twice the last radius."""
    mech = load_mechanism(ROOT / "models" / "single_link.toml")
    m = make_observer(mech, ObserverConfig()).model
    k, dist = 40.0, 0.03
    R = m._rows_radius(0.04, dist, k * dist**2)
    assert k * R**2 == pytest.approx(0.81 * m.rows_tol)
    assert m._rows_radius(0.004, dist, k * dist**2) == pytest.approx(0.008)  # at most twice the last radius
    assert m._rows_radius(0.04, dist, 0.0) == min(0.08, m.rows_max)  # no error: grows
    assert m._rows_radius(0.04, dist, 1e9) == m.rows_min


def _path_errors(m, channels, pe, u, n=200, step=2e-3):
    """The largest error of :meth:`measure` against the exact channels, in channel noises, along ``q* + s u`` (s
    from 0 to ``n step``, moving at 1 rad/s along ``u``) with the elastic coordinates ``pe``; and the number of
    rebuilds."""
    noise = m._noise(channels)
    q0 = np.asarray(m.rm.cb.q_star, float)
    worst, n0 = 0.0, m.n_rows
    for i in range(n + 1):
        x = m.initial_state(q0 + i * step * u, u)
        x[m.nq : m.r] = pe
        y = m.measure(x, channels).y
        worst = max(worst, float(np.max(np.abs(y - _exact_y(m, x, channels)) / noise)))
    return worst, m.n_rows - n0


@pytest.mark.parametrize("path", ["models/three_link_arm.toml", "benchmarks/models/three_link_reach.toml"])
def test_rows_error_along_a_path_stays_within_tolerance(path):
    """Along 0.4 rad of a path in a direction of all three joints, on a state whose gauges read a tenth of their
    full scale: with the rows held over the largest radius (``rows_min = rows_max``) the error reaches ``e``
    noises; with ``rows_tol = e / 10`` the adaptive radius keeps every channel's error within it: the rows'
    error grows with the distance, and the radius (rebuilding more often) is what keeps it."""
    mech = load_mechanism(ROOT / path)
    obs = make_observer(mech, ObserverConfig())
    m, channels = obs.model, tuple(obs.channels)
    nq, r = m.nq, m.r
    u = np.array([1.0, -0.8, 0.6])[:nq]
    iv = m._rows_at(np.asarray(m.rm.cb.q_star, float))
    Hm = m._affine(iv, channels)[1]
    scale = np.array([m.sensors[c].full_scale or np.inf for c in channels])
    pe = np.random.default_rng(5).standard_normal(r - nq)
    pe *= 0.1 / np.max(np.abs(Hm[:, nq:r] @ pe) / scale)
    rows = (m.rows_min, m.rows_rad, m.rows_max)
    m.rows_min = m.rows_rad = m.rows_max
    worst_held, held = _path_errors(m, channels, pe, u)
    m.reset()
    m.rows_min, m.rows_rad, m.rows_max = rows
    m.rows_tol = worst_held / 10
    worst, rebuilds = _path_errors(m, channels, pe, u)
    assert worst <= m.rows_tol, (worst, worst_held, rebuilds)
    assert rebuilds > 2 * held

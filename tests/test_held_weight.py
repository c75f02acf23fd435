"""The cached step's weight where q leaves its secant's line (more than one rigid coordinate).

The held model takes the weight ``fg(q)`` about the held configuration ``q0`` by its gradient ``Wg`` and, with a
secant partner at ``q0 - d``, by half the gradient's change along the secant, ``fg + (Wg + s/2 (Wg - Wg_old)) dl``
(``s = dl . d / d . d``; :func:`exuflex.observer.expansion._held_model`), as it takes ``M_r`` and ``K_r``. With
``dl = s d + w`` the error is ``1/2 D2(w, dl)`` (``D2`` the weight's second derivative): third order on the line
(``w = 0``) and second order off it. A weight extrapolated along the secant from the two weights alone, ``fg + (1 +
s) Wg dl - s^2 (fg - fg_old)``, is the same on the line but has the first-order error ``s Wg w`` off it (on the
crane arm, ``benchmarks/models/crane_arm.toml``, a bias of the filter on its own model: ``benchmarks/held_step.py``).
Measured here on that arm, entry by entry, each entry against its own change: the weight itself and one interval
of the held step from rest against the interval of the configuration evaluated exactly.
"""

import math
from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer.expansion import held_step, step_maps
from exuflex.observer.reduced import ReducedObserverModel, _secant_factor
from exuflex.reduction import CraigBampton, ReducedModel

ROOT = Path(__file__).resolve().parents[1]
CRANE = ROOT / "benchmarks" / "models" / "crane_arm.toml"
RADII = (0.02, 0.01, 0.005)


@pytest.fixture(scope="module")
def som():
    from exuflex.erls.model import ErlsModel

    mech = load_mechanism(CRANE)
    return ReducedObserverModel(ReducedModel(CraigBampton(ErlsModel(mech))))


def _at_rest(som, q):
    z = np.zeros(som.nx)
    z[: som.nq] = q
    return z


def _held(som, q, old=None):
    """The configuration ``q`` held undeformed at rest, with ``old`` as its secant partner (as ``_refresh`` does)."""
    iv = som._configuration(_at_rest(som, q), held=True)
    iv.Ca = iv.mats.Cr - som.model.beta * iv.mats.Kr
    if old is not None:
        iv.old, iv.d = old, iv.q0 - old.q0
        iv.dd = float(iv.d @ iv.d)
    iv.system = som._held_system(iv)
    return iv


def _interval(som, iv, q, follow=True):
    """One interval of 1 ms of the held step from rest at ``q``, and the generalised force it held over it
    (from the step's maps: ``z1 = P^n z + S f``, no torque); ``follow`` False: the held model at its centre, not
    following q."""
    dl = q - iv.q0 if follow else np.zeros(som.nq)
    s = _secant_factor(iv, dl)
    n = som.substeps(iv, 1e-3)
    z = _at_rest(som, q)
    u = np.zeros(len(som.mech.motors))
    z1, M, K, C, G = held_step(z, u, dl, s, 1e-3 / n, n, iv.system)
    Pn, S, _ = step_maps(np.linalg.inv(M), K, C, G, 1e-3 / n, n)
    return s, z1, np.linalg.lstsq(S, z1 - Pn @ z, rcond=None)[0]


def _orders(err, floor=1e-7):
    """log2 of the error's fall per halving of the radius, per entry (rows: the radii), of the entries whose error
    at the largest radius is above ``floor`` (relative): below it the next orders' terms, of either sign, decide."""
    err = np.asarray(err)
    keep = err[0] > floor
    return np.log2(err[:-1, keep] / err[1:, keep])


@pytest.mark.parametrize("angle", [
    pytest.param(0.0, marks=pytest.mark.xfail(strict=True, reason=(
        "with the relative elbow's ERLS frame on the forearm's own tangent (docs/long_arms.md) the held step's "
        "interval on the secant's line has four state entries (the 149 Hz interior mode's and the 1.3 kHz "
        "correction's positions and rates) falling as t^2.5-2.7 per halving at t = 0.02-0.005 rad, not t^3; the "
        "weight itself still falls as t^3 in every entry (measured to t = 0.0025): not found"))),
    pytest.param(40.0, marks=pytest.mark.xfail(strict=True, reason=(
        "with the relative elbow's ERLS frame on the forearm's own tangent two weight entries fall as t^1.2-1.3 "
        "then t^1.7 off the line from t = 0.02 (their second order emerges below t = 0.01: with radii 0.01, "
        "0.005, 0.0025 every entry passes); not changed here"))),
])
def test_held_weight_error_is_second_order_off_the_secant_and_third_on_it(som, angle):
    """Held at ``q0`` (mid-manoeuvre) with its partner ``t`` back along ``d``, q at ``q0 + t (cos a d + sin a n)``
    for ``t`` = 0.02, 0.01, 0.005 rad: the held weight against the weight evaluated at q, per entry and against the
    entry's own change, falls as ``t^3`` on the line (``a`` = 0) and as ``t^2`` 40 degrees off it (the secant still in
    use: cosine 0.77 > 0.7); one interval of the held step from rest against the configuration's own interval
    falls the same way, each state entry against the change the held model follows (the interval's change from the
    held model not following q to the configuration's own). The weight from the secant's
    two weights alone (``fg + (1 + s) Wg dl - s^2 (fg - fg_old)``) is as good on the line, but off it its error
    does not fall against the change (first order): what the test would see."""
    q0 = np.array([1.55, -1.45])
    dhat = np.array([0.4, -0.9]) / math.hypot(0.4, -0.9)
    nhat = np.array([-dhat[1], dhat[0]])
    a = math.radians(angle)
    weight, state, two = [], [], []
    for t in RADII:
        old = _held(som, q0 - t * dhat)
        iv = _held(som, q0, old)
        q = q0 + t * (math.cos(a) * dhat + math.sin(a) * nhat)
        s, z1, f = _interval(som, iv, q)
        assert s == pytest.approx(math.cos(a), rel=1e-9)  # the secant in use
        exact = _held(som, q)
        _, z1_exact, f_exact = _interval(som, exact, q)
        fg, fg_exact = iv.forces.fg, exact.forces.fg
        np.testing.assert_allclose(f_exact, fg_exact, rtol=1e-8, atol=1e-10 * np.abs(fg_exact).max())
        change = np.abs(fg_exact - fg)
        weight.append(np.abs(f - fg_exact) / change)
        dl = q - q0
        secant_only = fg + (1.0 + s) * (iv.forces.Wg[:, : som.nq] @ dl) - s * s * (fg - old.forces.fg)
        two.append(np.abs(secant_only - fg_exact) / change)
        # the state's error against the change the held model follows (its interval not following q)
        state.append(np.abs(z1 - z1_exact) / np.abs(z1_exact - _interval(som, iv, q, follow=False)[1]))
    order = 3.0 if angle == 0.0 else 2.0
    # relative to its own change (first order in t), each entry's error falls at the order less one
    for rel in (weight, state):
        o = _orders(rel)
        # the last halving within a quarter of the order, the first within a half (the next order's term)
        assert o.size and np.all(o[-1] > order - 1.0 - 0.25) and np.all(o > order - 1.0 - 0.5), (angle, o)
    if angle == 0.0:
        assert np.max(weight[0]) < 2e-3, weight[0]
    else:
        assert np.max(_orders(two)) < 0.5, _orders(two)
        assert np.max(two[-1]) > 10.0 * np.max(weight[-1])

"""The cached step's velocity forces at a deformed state: their first order in the elastic coordinates.

The held configuration is undeformed, and its velocity forms (``T``, the bias form ``C2``) are those of the velocity
map ``J_0`` there; at a deformed state ``J = J_0 + sum_m p_m A_m`` (``A_m = [d(H e_m)/dq, 0]``), and the forms are
polynomials in ``J``. The held system carries their derivatives in each elastic coordinate (``pT``, ``pC2``:
:meth:`exuflex.observer.reduced.ReducedObserverModel._velocity_forms`) and the step adds them
(:func:`exuflex.observer.expansion._velocity_terms`). Here, at the held configuration with the links turning and
bent, the force the held step holds over an interval (from its maps) against the reduced model's own forces there
(:meth:`exuflex.reduction.ReducedModel.matrices`), entry by entry against the entry's own change with the elastic
coordinates: with the terms what remains is of second order in them, without them the error is of first order
(of the change's own size in the rows they act on).
"""

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism
from exuflex.observer.expansion import held_step, step_maps
from exuflex.observer.reduced import ReducedObserverModel
from exuflex.reduction import CraigBampton, ReducedModel

ROOT = Path(__file__).resolve().parents[1]
MODELS = ("benchmarks/models/vertical_link.toml", "benchmarks/models/crane_arm.toml", "models/sixbar.toml")


def _held_force(som, hs, z):
    """The generalised force the held step holds over 1 ms from ``z`` at the held configuration (``z1 = P^n z + L
    u + S f`` with no torque, from the interval's own matrices)."""
    n = 10
    u = np.zeros(len(som.mech.motors))
    z1, M, K, C, G = held_step(z, u, np.zeros(som.nq), 0.0, 1e-4, n, hs)
    Pn, S, _ = step_maps(np.linalg.inv(M), K, C, G, 1e-4, n)
    return np.linalg.lstsq(S, z1 - Pn @ z, rcond=None)[0]


@pytest.mark.parametrize("name", MODELS)
def test_held_velocity_forces_follow_the_elastic_coordinates_to_first_order(name):
    """Joint rates of 2 rad/s, elastic coordinates and rates of a manoeuvre's size: per entry of the generalised
    force, the held step's against the model's (the bias acceleration's curvature term included), over that entry's
    change from the undeformed state at the same rates. With the first-order terms what remains is of second order
    in the elastic coordinates: halving them divides each entry's error by about 4 (at most 0.3 here, above the
    force extraction's round-off, 1e-7 of the largest force), and it is within 3e-4 of the change (the six-bar's joint rows 1.3e-4: the curvature's force taken with
    the held velocity map, ``(J - J_0)^T M a_b``); without them a first-order error of more than a tenth of the
    change in some entry."""
    som = ReducedObserverModel(ReducedModel(CraigBampton(ErlsModel(load_mechanism(ROOT / name)))))
    rm, nq, r = som.rm, som.nq, som.r
    z0 = np.zeros(2 * r)
    z0[:nq] = rm.cb.q_star
    iv = som._configuration(z0, held=True)
    iv.Ca = iv.mats.Cr - som.model.beta * iv.mats.Kr
    iv.system = som._held_system(iv)
    hs = iv.system._replace(KGd=np.zeros((0, 0)))  # the velocity forces alone (the motion's geometric forces:
    # tests/test_motion_geometric.py)
    assert hs.pT.shape == (r - nq, r**3) and hs.pC2.shape == (r - nq, r * nq * r)
    without = hs._replace(pT=np.zeros((0, 0)), pC2=np.zeros((0, 0)))
    rng = np.random.default_rng(1)
    e = 1e-3 * rng.normal(size=r - nq)
    rates = np.concatenate([2.0 * np.sign(rng.normal(size=nq)), 5e-2 * rng.normal(size=r - nq)])
    errs = []
    for scale in (1.0, 0.5):
        z = z0.copy()
        z[nq:r] = scale * e
        z[r:] = rates
        exact = rm.matrices(z[:r], z[r:]).fr
        change = np.abs(exact - rm.matrices(z0[:r], z[r:]).fr)
        floor = 1e-9 * np.abs(exact).max()
        err = np.abs(_held_force(som, hs, z) - exact)
        assert np.all(err <= 3e-4 * change + floor), err / (change + floor)
        errs.append((err, floor))
        if scale == 1.0:
            err_without = np.abs(_held_force(som, without, z) - exact)
            assert np.max(err_without / (change + floor)) > 0.1, err_without / (change + floor)
    (e1, f1), (e2, f2) = errs
    assert np.all(e2 <= 0.3 * e1 + 100 * f2), e2 / (e1 + 100 * f2)  # above the force extraction's round-off

"""The truth engines' records depend on the torques before their instant alone (docs/ringing.md).

Under a bounded force a mechanism's positions and rates are continuous, so its state at a sample instant does not
depend on the torque held from that instant on; the observer's sampled model has it so (the torque sampled at
``t_k`` is held over the interval after ``t_k``). Generalized-alpha balances forces at step ends: the step-end
forces (:meth:`exuflex.erls.implicit.HeldTable.step_ends`) keep the hold's impulse and take nothing after a
recorded instant into its record."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.implicit import HeldTable, erls_implicit
from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism

MODELS = Path(__file__).resolve().parents[1] / "models"


def test_step_end_forces_keep_the_impulse_and_take_nothing_after_a_record():
    """A random staircase switching at the records (every 7 steps of h = 1e-3 / 7) and at odd instants between.
    The window sums ``h (f_0 + ... + f_j)`` are the hold's integral up to ``t_j + h/2`` at every step end but the
    records (the windows tile the time axis); the impulse up to a record, ``h (f_0 + ... + f_j-1) + h f_j / 2``, is
    the hold's integral up to it (exact, by the table's cumulative sum); changing the table from a record on changes
    no force at or before it."""
    rng = np.random.default_rng(3)
    h, every, n = 1e-3 / 7, 7, 70
    t_tab = np.sort(np.concatenate([np.arange(0, 10) * 1e-3, rng.uniform(0, 1e-2, 13)]))
    vals = rng.normal(size=len(t_tab))
    tab = HeldTable(t_tab, vals)
    f = tab.step_ends(h, n, every)[:, 0]
    t = np.arange(n + 1) * h
    start = tab.integral(-h / 2)[0]
    rec = np.arange(every, n, every)
    windows = np.cumsum(h * f) - (tab.integral(t + h / 2)[:, 0] - start)
    others = np.setdiff1d(np.arange(n + 1), rec)
    np.testing.assert_allclose(windows[others], 0.0, rtol=0, atol=1e-14)
    upto = np.concatenate([[0.0], np.cumsum(h * f)[:-1]]) + 0.5 * h * f - (tab.integral(t)[:, 0] - start)
    np.testing.assert_allclose(upto[rec], 0.0, rtol=0, atol=1e-14)
    # causality: the table changed from a record on leaves every force up to it as it was
    for j in rec:
        v2 = np.where(t_tab >= t[j] - 1e-15, vals + 5.0, vals)
        f2 = HeldTable(t_tab, v2).step_ends(h, n, every)[:, 0]
        np.testing.assert_array_equal(f2[: j + 1], f[: j + 1])
        assert np.all(np.abs(f2[j + 1 :] - f[j + 1 :]) > 1.0)  # and acts from the next step on
    # a clean switch F0 -> F1 at a record: f_j = F0, f_j+1 = (3 F1 - F0) / 2
    g = HeldTable([0.0, 1e-3], [[1.0], [3.0]]).step_ends(h, 14, every)[:, 0]
    assert g[7] == pytest.approx(1.0) and g[8] == pytest.approx(4.0) and g[9] == pytest.approx(3.0)
    # no records: the symmetric means, as before
    np.testing.assert_allclose(tab.step_ends(h, n)[:, 0], tab.mean(t - h / 2, t + h / 2)[:, 0], rtol=0, atol=1e-15)


def test_held_table_on_an_uneven_grid_is_the_exact_integral():
    tab = HeldTable([0.0, 0.1, 0.3, 0.35], [[1.0], [2.0], [4.0], [8.0]])
    assert tab.integral(0.2)[0] == pytest.approx(0.1 + 0.2)
    assert tab.integral(0.4)[0] == pytest.approx(0.1 + 0.4 + 0.2 + 0.4)
    assert tab.integral(-0.1)[0] == pytest.approx(-0.1)
    with pytest.raises(ValueError, match="strictly increasing"):
        HeldTable([0.0, 0.0, 1.0], [1.0, 2.0, 3.0])


def test_erls_record_at_a_torque_step_is_the_state_before_it():
    """The slider-crank (a stiff axial rod under a 0.3 kg slider) from rest, a torque step at the record t = 2 ms:
    the record there is the one without the step (to round-off), and one step of the truth's size later the rod's
    midspan moves. With the symmetric mean the record at the step carried a velocity of the stiff modes' response
    (docs/ringing.md)."""
    mech = load_mechanism(MODELS / "slider_crank.toml")
    model = ErlsModel(mech)
    n = model.n
    y0 = np.zeros(2 * n)
    y0[: model.nq] = mech.q_ref
    h = 1e-3 / 115
    t_tab = np.arange(0, 31) * 1e-4
    base = np.full((len(t_tab), 1), 0.02)
    step = base.copy()
    step[t_tab >= 2e-3 - 1e-12] += 0.1
    a = erls_implicit(model, t_tab, base, y0, 3e-3, h, output_every=115)
    b = erls_implicit(model, t_tab, step, y0, 3e-3, h, output_every=115)
    np.testing.assert_allclose(a.t, [0.0, 1e-3, 2e-3, 3e-3], atol=1e-12)
    np.testing.assert_allclose(b.y[:3], a.y[:3], rtol=0, atol=1e-12 * np.abs(a.y).max())
    assert np.max(np.abs(b.y[3, n:] - a.y[3, n:])) > 1e-4  # the step acts after its instant


def test_exudyn_record_at_a_torque_step_is_the_state_before_it():
    """The same on the Exudyn truth (ANCF beams, its own generalized-alpha): the probes' values and rates at the
    record of the torque step are those without it."""
    pytest.importorskip("exudyn")
    from exuflex.groundtruth import simulate_truth

    mech = load_mechanism(MODELS / "slider_crank.toml")
    t_tab = np.arange(0, 31) * 1e-4
    base = np.full((len(t_tab), 1), 0.02)
    step = base.copy()
    step[t_tab >= 2e-3 - 1e-12] += 0.1
    kw = {"h": 1e-3 / 115, "output_dt": 1e-3, "q0": mech.q_ref}
    a = simulate_truth(mech, t_tab, base, 3e-3, **kw)
    b = simulate_truth(mech, t_tab, step, 3e-3, **kw)
    moved = 0.0
    for k in a.values:
        for x, y in ((a.values[k], b.values[k]), (a.rates[k], b.rates[k])):
            np.testing.assert_allclose(y[:3], x[:3], rtol=0, atol=1e-10 * max(np.abs(x).max(), 1e-12))
        moved = max(moved, float(np.max(np.abs(b.rates[k][3] - a.rates[k][3]))))
    assert moved > 1e-4  # the step acts after its instant

"""The reduced truth (:func:`exuflex.truth.reduced_truth`) is the reduced model's own continuous dynamics.

The consistent reference of the acceptance must be exact to its own model: its states against a fine RK4 of the
same reduced equations (four times the sub-steps), entry by entry against each true state's own range over the
run; and the step map frozen at each interval's start (the linear system with the matrices and forces of the
interval's start, :meth:`~exuflex.observer.reduced.ReducedObserverModel.frozen_interval`, what the reduced truth
was stepped with before) against the same reference, to show what the comparison can see.
"""

from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer.reduced import ReducedObserverModel
from exuflex.observer.session import make_observer
from exuflex.sensors import erls_probe_record, true_states
from exuflex.truth.engines import plan_drive, reduced_truth

ROOT = Path(__file__).resolve().parents[1]


def _frozen(mech, drive, duration, h):
    """The truth stepped by the frozen step map of each interval's start (the departure measured here)."""
    rm = make_observer(mech).model.rm
    som = ReducedObserverModel(rm, h=h, method="rk4")
    dt = 1.0 / mech.sample_rate_hz
    n = int(round(duration / dt)) + 1
    t = np.arange(n) * dt
    tau = drive.tau[np.minimum(np.round(t / (drive.t[1] - drive.t[0])).astype(int), len(drive.tau) - 1)]
    z = som.initial_state(drive.q0, drive.qd0)
    Y = np.empty((n, 2 * rm.model.n))
    for k in range(n):
        Y[k, : rm.model.n], Y[k, rm.model.n :] = rm.full_state(z)
        if k < n - 1:
            z = som.frozen_interval(z, tau[k], dt)[0].x
    return true_states(mech, erls_probe_record(rm.model, t, Y))


@pytest.mark.slow
def test_reduced_truth_is_its_model_s_continuous_dynamics():
    """The vertical link (gravity, a bent link turning: every term of the reduced equations), its manoeuvre's first
    0.15 s: the truth within 1e-5 of each state's range of the fine RK4 (measured 1e-9 in the angle, 1e-6 in the
    rates over the whole manoeuvre); the frozen map more than 100 times further off."""
    mech = load_mechanism(ROOT / "benchmarks/models/vertical_link.toml")
    duration = 0.15
    drive = plan_drive(mech, duration, 1e-3)
    truth = reduced_truth(mech, drive, duration, 1e-4).truth
    fine = reduced_truth(mech, drive, duration, 2.5e-5).truth
    frozen = _frozen(mech, drive, duration, 1e-4)
    scale = np.ptp(fine.data, axis=0)
    err = np.abs(truth.data - fine.data).max(axis=0)
    assert np.all(err <= 1e-5 * scale), dict(zip(fine.names, err / scale, strict=True))
    err_frozen = np.abs(frozen.data - fine.data).max(axis=0)
    assert np.max(err_frozen / scale) > 100 * np.max(err / scale), (err_frozen / scale, err / scale)

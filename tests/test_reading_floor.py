"""The filter's steady bias from a repeated error (:meth:`ReducedObserverModel._persistent_bias`), which the
measurement rows' and the held model's radii keep within their tolerances, and what it keeps off the estimates
(docs/reading_floor.md).

- The closed form ``b = (I - A)^-1 c`` against the filter's own error recursion iterated (the Kalman gain and the
  step map applied interval by interval until the error settles), entry by entry in the coordinates' estimates,
  for a channel bias and for a state error, on an arm with relative encoders (the readings' rows).
- Slow: the noiseless floor on the observer's own reduced model as the truth (``exuflex.truth.engines.
  reduced_truth``: the observer's approximations alone make it): every coordinate's RMS error within 0.3 of the
  bound on the three-link arm (0.43 for the wrist's reading when the radii were judged per channel and per
  interval).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, make_observer

ROOT = Path(__file__).resolve().parents[1]


def _held_model(path: str):
    """The observer's model of ``path`` after a few intervals from rest (a held configuration and step map), the
    filter's channels and a steady covariance of them (the Riccati recursion of the held map iterated)."""
    mech = load_mechanism(ROOT / path)
    obs = make_observer(mech, ObserverConfig())
    m, channels = obs.model, tuple(obs.channels)
    x = m.initial_state(np.asarray(m.rm.cb.q_star, float), np.full(m.nq, 0.3))
    u = np.zeros(len(mech.motors))
    P = np.eye(m.nx) * 1e-6
    m.watch_covariance(lambda: P)
    for _ in range(3):
        x = m.predict(x, u, 1e-3).x
    Hm = m.measure(x, channels).H
    F, Q = m._last.map.Pn, m._last.map.Q
    R = np.diag(m._noise(channels) ** 2)
    for _ in range(4000):  # the steady prior covariance of the held map
        K = P @ Hm.T @ np.linalg.inv(Hm @ P @ Hm.T + R)
        P = F @ ((np.eye(m.nx) - K @ Hm) @ P) @ F.T + Q
        P = 0.5 * (P + P.T)
    return m, channels, Hm, P


def _iterated(m, Hm, noise, P, dy, dz, n=20000):
    """The posterior error after ``n`` intervals of the filter with the gain of ``P`` and the held map, a channel
    bias ``dy`` at every update and a state error ``dz`` at every prediction (from zero)."""
    K = P @ Hm.T @ np.linalg.inv(Hm @ P @ Hm.T + np.diag(noise**2))
    F = m._last.map.Pn
    e = np.zeros(m.nx)
    for _ in range(n):
        e_prior = F @ e + dz
        e = e_prior - K @ (Hm @ e_prior + dy)
    return e, (np.eye(m.nx) - K @ Hm) @ P


@pytest.mark.parametrize("kind", ["channel", "state"])
def test_persistent_bias_is_the_filter_error_recursion(kind):
    """``_persistent_bias`` equals the filter's error recursion run to its end, in units of the filter's standard
    deviation of each coordinate's reading and rate (the wrist's and elbow's relative readings include the other
    link's elastic rotation), within 1e-6 of the largest."""
    m, channels, Hm, P = _held_model("models/three_link_arm.toml")
    noise = m._noise(channels)
    rng = np.random.default_rng(3)
    dy = (rng.standard_normal(len(channels)) * noise * 0.1) if kind == "channel" else np.zeros(len(channels))
    dz = (rng.standard_normal(m.nx) * np.sqrt(np.diag(P)) * 1e-3) if kind == "state" else np.zeros(m.nx)
    rc = m._last.rc
    got = m._persistent_bias(P, Hm, noise, rc, dy=dy if kind == "channel" else None,
                             dz=dz if kind == "state" else None)
    e, Pp = _iterated(m, Hm, noise, P, dy, dz)
    nq, r = m.nq, m.r
    R = m.reading_G @ rc.H[nq:]
    T = np.zeros((2 * nq, m.nx))
    T[:nq, :nq] = T[nq:, r : r + nq] = np.eye(nq)
    T[:nq, :r] += R
    T[nq:, r:] += R
    ratio = np.abs(T @ e) / np.sqrt(np.einsum("ij,jk,ik->i", T, Pp, T))
    assert np.any(R != 0)
    assert got == pytest.approx(float(ratio.max()), rel=1e-6)


@pytest.mark.slow
def test_noiseless_floor_on_the_observers_own_model(tmp_path):
    """The observer on a noiseless log of its own reduced model (the truth integrates the reduced equations
    finely: what remains is the observer's held model, step map and measurement rows): every coordinate's RMS
    error within 0.3 of the bound on three_link_arm (its wrist reading's was 0.43 with the radii judged per
    channel and per interval)."""
    from exuflex.measure import measure
    from exuflex.runs import read_run, write_run
    from exuflex.scoring.run import observe_run
    from exuflex.truth.engines import plan_drive, reduced_truth

    mech = load_mechanism(ROOT / "models" / "three_link_arm.toml")
    d = mech.manoeuvre.duration
    rec = reduced_truth(mech, plan_drive(mech, d, 1e-4, None), d, 1e-4)
    meas = measure(mech, rec.clean, rec.torque_t, rec.torques, seed=1, noise=False, quantisation=False, t_end=d)
    write_run(tmp_path, meas.signals, rec.truth, {"engine": "reduced", "mechanism": mech.name, "seed": 1},
              motors=mech.motor_names)
    o = observe_run(mech, read_run(tmp_path), ObserverConfig.for_model(mech), keep="summary")
    ratios = {k: v for k, v in o.summary["ratio_to_bound"].items() if k.startswith(("q", "dq"))}
    assert max(ratios.values()) <= 0.3, ratios

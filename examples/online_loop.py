"""
An online loop: one sample at a time
====================================

An online loop: feed the observer one sample at a time, as a real-time controller would.

    python examples/online_loop.py

The samples come from the shipped test run here; on a rig they come from the data acquisition. Each call to
``ekf.step(t, u, y)`` predicts to ``t`` with the torques held since the previous sample and updates with the
channels ``y`` (NaN: not sampled at ``t``); it returns the reduced state, which ``obs.physical`` maps to the
physical quantities (joint angles and rates, tip elastic displacement and velocity).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import exuflex as xf

ROOT = Path(__file__).resolve().parents[1]


def main(n_samples: int = 500) -> np.ndarray:
    mech = xf.load_mechanism(ROOT / "models" / "sixbar.toml")
    obs = xf.make_observer(mech)  # the paper's channels: q1 q2 q3 c1 c2 c4
    run = xf.read_run(ROOT / "tests" / "data" / "sixbar_erls_3s")
    U = run.sensors.select(mech.motor_names).data
    Y = run.sensors.select(obs.channels).data
    t = run.sensors.t
    obs.ekf.reset()
    states = np.empty((n_samples, obs.ekf.nx))
    for k in range(n_samples):  # the real-time loop
        states[k] = obs.ekf.step(t[k], U[k], Y[k])
    phys = obs.physical(t[:n_samples], states)
    err = phys["q1"] - np.interp(phys.t, run.truth.t, run.truth["q1"])
    print(f"{n_samples} samples online; q1 error after 0.3 s: RMS {np.sqrt(np.mean(err[t[:n_samples] > 0.3] ** 2)):.2e} rad")
    return phys.data


if __name__ == "__main__":
    main()

"""A lab-style log of the six-bar from a full-order ERLS truth: samples at irregular instants (uniform time-stamp
jitter and a clock running fast by ``drift_ppm``), renamed columns and a time column in milliseconds, as a rig's
data logger would write it. Each sample is the clean channel at its own instant (the truth is recorded every
integration step, 0.1 ms, and interpolated linearly, an error below 1e-3 of the noise) plus white noise of the
model's ``noise_std``; the torque is the table value in force at that instant plus its noise. The truth CSV holds
the true states at the same instants, so errors compare like with like.

    python tests/_lablog.py OUT_DIR [--jitter-ms 0.2] [--drift-ppm 500] [--duration 3] [--seed 1]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RENAME = {"T1": "motor1_Nm", "T2": "motor2_Nm", "T3": "motor3_Nm", "q1": "enc1_rad", "q2": "enc2_rad",
          "q3": "enc3_rad", "c1": "gauge1", "c2": "gauge2", "c4": "gauge4"}
TIME = "Time_ms"


def lab_log(out: Path, *, jitter_s: float = 0.2e-3, drift_ppm: float = 500.0, duration: float = 3.0,
            seed: int = 1, h: float = 1e-4) -> dict:
    """Write ``lab.csv`` and ``truth.csv`` into ``out``; returns the ``--map`` and settings."""
    from exuflex.cli.simulate import _erls_truth
    from exuflex.manoeuvre import computed_torque, plan
    from exuflex.mechanism import load_mechanism
    from exuflex.sensors import monotonic_record, sensor_channels, true_states

    mech = load_mechanism(ROOT / "models" / "sixbar.toml")
    pl = plan(mech, dt=h, t_end=duration)
    tau = computed_torque(mech, pl)
    rec = monotonic_record(_erls_truth(mech, pl.t, tau, duration, h, h, pl.q[0], pl.qd[0], None))
    clean, truth = sensor_channels(mech, rec), true_states(mech, rec)
    dt = 1.0 / mech.sample_rate_hz
    rng = np.random.Generator(np.random.PCG64(seed))
    n = int(np.floor((duration - 2 * jitter_s) / (dt * (1 + drift_ppm * 1e-6)))) + 1
    t = np.arange(n) * dt * (1 + drift_ppm * 1e-6) + jitter_s + rng.uniform(-jitter_s, jitter_s, n)
    cols, names = [], []
    i_hold = np.clip(np.searchsorted(pl.t, t, side="right") - 1, 0, len(pl.t) - 1)
    for j, m in enumerate(mech.motors):
        cols.append(tau[i_hold, j] + m.noise_std * rng.standard_normal(n))
        names.append(RENAME[m.name])
    sensors = {s.name: s for s in mech.sensors}
    for c in ("q1", "q2", "q3", "c1", "c2", "c4"):
        cols.append(np.interp(t, clean.t, clean[c]) + sensors[c].noise_std * rng.standard_normal(n))
        names.append(RENAME[c])
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "lab.csv", "w") as f:
        f.write(",".join([TIME, *names]) + "\n")
        for k in range(n):
            f.write(",".join([f"{t[k] * 1e3:.6f}", *(repr(float(c[k])) for c in cols)]) + "\n")
    with open(out / "truth.csv", "w") as f:
        f.write(",".join(["time", *truth.names]) + "\n")
        for k in range(n):
            f.write(",".join([repr(float(t[k])), *(repr(float(np.interp(t[k], truth.t, truth[c])))
                                                   for c in truth.names)]) + "\n")
    return {"map": ",".join(f"{k}={v}" for k, v in RENAME.items()), "n": n, "seed": seed,
            "jitter_s": jitter_s, "drift_ppm": drift_ppm}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out")
    ap.add_argument("--jitter-ms", type=float, default=0.2)
    ap.add_argument("--drift-ppm", type=float, default=500.0)
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    info = lab_log(Path(a.out), jitter_s=a.jitter_ms * 1e-3, drift_ppm=a.drift_ppm, duration=a.duration,
                   seed=a.seed)
    print(f"wrote {a.out}/lab.csv, truth.csv ({info['n']} rows); --map {info['map']}")

"""A lab-style log of the six-bar from a full-order ERLS truth: samples at irregular instants (uniform time-stamp
jitter and a clock running fast by ``drift_ppm``), renamed columns and a time column in milliseconds, as a rig's
data logger would write it. Each sample is the clean channel at its own instant (the truth is recorded every
integration step, 0.1 ms, and interpolated linearly, an error below 1e-3 of the noise) plus white noise of the
model's ``noise_std``; the torque is the table value in force at that instant plus its noise. The truth CSV holds
the true states at the same instants, so errors compare like with like.

The ERLS truth (:func:`lab_truth`, a few minutes) does not depend on the seed: compute it once and pass it to
:func:`lab_log` / :func:`lab_signals` for every seed.

    python tests/_lablog.py OUT_DIR [--jitter-ms 0.2] [--drift-ppm 500] [--duration 3] [--seed 1]
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "sixbar.toml"
RENAME = {"T1": "motor1_Nm", "T2": "motor2_Nm", "T3": "motor3_Nm", "q1": "enc1_rad", "q2": "enc2_rad",
          "q3": "enc3_rad", "c1": "gauge1", "c2": "gauge2", "c4": "gauge4"}
CHANNELS = ("q1", "q2", "q3", "c1", "c2", "c4")
TIME = "Time_ms"


@dataclass(frozen=True)
class LabTruth:
    """The seed-independent part of a lab log: the manoeuvre's torque table and the ERLS truth's clean channels and
    true states, recorded every step ``h``."""

    duration: float
    h: float
    torque_t: np.ndarray  # (n_table,) the table's times
    torques: np.ndarray  # (n_table, n_motors)
    clean: object  # exuflex.sensors.Signals
    truth: object  # exuflex.sensors.Signals


def lab_truth(duration: float = 3.0, h: float = 1e-4) -> LabTruth:
    """The six-bar's manoeuvre planned at ``h``, its rigid computed torque, and the full-order ERLS truth under it."""
    from exuflex.manoeuvre import computed_torque, plan
    from exuflex.mechanism import load_mechanism
    from exuflex.sensors import monotonic_record, sensor_channels, true_states
    from exuflex.truth import erls_truth

    mech = load_mechanism(MODEL)
    pl = plan(mech, dt=h, t_end=duration)
    tau = computed_torque(mech, pl)
    rec = monotonic_record(erls_truth(mech, pl.t, tau, duration, h, h, pl.q[0], pl.qd[0], None))
    return LabTruth(duration, h, np.asarray(pl.t), np.asarray(tau), sensor_channels(mech, rec), true_states(mech, rec))


def lab_signals(lt: LabTruth, *, jitter_s: float = 0.2e-3, drift_ppm: float = 500.0, seed: int = 1):
    """One seeded log of ``lt`` in memory: ``(log, truth)``, both :class:`~exuflex.sensors.Signals` at the samples'
    instants, the log's channels under the model's names (torques, then :data:`CHANNELS`)."""
    from exuflex.mechanism import load_mechanism
    from exuflex.sensors import Signals

    mech = load_mechanism(MODEL)
    dt = 1.0 / mech.sample_rate_hz
    rng = np.random.Generator(np.random.PCG64(seed))
    n = int(np.floor((lt.duration - 2 * jitter_s) / (dt * (1 + drift_ppm * 1e-6)))) + 1
    t = np.arange(n) * dt * (1 + drift_ppm * 1e-6) + jitter_s + rng.uniform(-jitter_s, jitter_s, n)
    cols, names = [], []
    i_hold = np.clip(np.searchsorted(lt.torque_t, t, side="right") - 1, 0, len(lt.torque_t) - 1)
    for j, m in enumerate(mech.motors):
        cols.append(lt.torques[i_hold, j] + m.noise_std * rng.standard_normal(n))
        names.append(m.name)
    sensors = {s.name: s for s in mech.sensors}
    for c in CHANNELS:
        cols.append(np.interp(t, lt.clean.t, lt.clean[c]) + sensors[c].noise_std * rng.standard_normal(n))
        names.append(c)
    truth = Signals(t, lt.truth.names, np.column_stack([np.interp(t, lt.truth.t, lt.truth[c]) for c in lt.truth.names]))
    return Signals(t, tuple(names), np.column_stack(cols)), truth


def lab_log(out: Path, *, jitter_s: float = 0.2e-3, drift_ppm: float = 500.0, duration: float = 3.0,
            seed: int = 1, h: float = 1e-4, truth: LabTruth | None = None) -> dict:
    """Write ``lab.csv`` and ``truth.csv`` into ``out`` (``truth``: a :func:`lab_truth` of this ``duration`` and
    ``h``, computed if None); returns the ``--map`` and settings."""
    lt = lab_truth(duration, h) if truth is None else truth
    if abs(lt.duration - duration) > 1e-12 or abs(lt.h - h) > 1e-15:
        raise ValueError(f"the lab truth is for {lt.duration} s at h = {lt.h} s, not {duration} s at {h} s")
    sig, tr = lab_signals(lt, jitter_s=jitter_s, drift_ppm=drift_ppm, seed=seed)
    t, n = sig.t, len(sig.t)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "lab.csv", "w") as f:
        f.write(",".join([TIME, *(RENAME[c] for c in sig.names)]) + "\n")
        for k in range(n):
            f.write(",".join([f"{t[k] * 1e3:.6f}", *(repr(float(v)) for v in sig.data[k])]) + "\n")
    with open(out / "truth.csv", "w") as f:
        f.write(",".join(["time", *tr.names]) + "\n")
        for k in range(n):
            f.write(",".join([repr(float(t[k])), *(repr(float(v)) for v in tr.data[k])]) + "\n")
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

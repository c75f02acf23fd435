"""
Your own mechanism, from scratch to observed
============================================

Your own mechanism: a model file written from scratch (a flexible single link on a hub motor, a strain gauge
and an encoder), its modes, a simulated run and the observer on it.

    python examples/own_mechanism.py [--out DIR]

Write the model file for your rig the same way (schema: ``models/README.md``; every field is checked on
loading and a mistake is reported in one line naming the field). The same from the command line:

    exuflex modes my_arm.toml
    exuflex simulate my_arm.toml --out runs/my_arm --engine erls --seed 1
    exuflex observe my_arm.toml runs/my_arm
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import exuflex as xf

MODEL = """
[model]
name = "my_arm"
description = "A 0.8 m aluminium arm on a hub motor, tip mass, one encoder and one strain gauge"
sample_rate_hz = 500.0
q_ref = [0.0]
gravity = [0.0, 0.0]

[[materials]]
name = "aluminium"
E = 69.0e9
rho = 2700.0

[[links]]
name = "arm"
length = 0.8
material = "aluminium"
diameter = 0.02
n_elements = 4
angle_guess = 0.0

[[joints]]
name = "hub"
points = [{ link = "arm", station = 0.0 }]
ground = [0.0, 0.0]

[[coordinates]]
name = "q1"
link = "arm"
joint = "hub"

[[motors]]
name = "T1"
joint = "hub"
link = "arm"
noise_std = 0.01
full_scale = 10.0

[[masses]]
link = "arm"
station = 0.0
mass = 0.5
inertia = 0.05
label = "hub"

[payload]
link = "arm"
station = 0.8
mass = 0.1
label = "tip mass"

[damping]
alpha = 2.0
beta = 2.0e-5

[[sensors]]
name = "q1"
kind = "encoder"
link = "arm"
joint = "hub"
noise_std = 1.0e-3
full_scale = 8.0

[[sensors]]
name = "c_root"
kind = "curvature"
link = "arm"
station = 0.2
noise_std = 1.0e-4
full_scale = 0.1

[manoeuvre]
kind = "joint"
duration = 1.0
time_law = "trapezoid"
ramp_time = 0.1
rules = [{ coordinate = "q1", start = 0.0, end = 0.8 }]

[reduction]
masters = ["node5.y", "node5.theta"]
q_star = [0.4]
n_interior = "auto"
"""


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.strip().split("\n")[3])
    ap.add_argument("--out", default=None, help="folder for the model file and the run (default: a temporary one)")
    ap.add_argument("--duration", type=float, default=None, help="simulated time (s; default the manoeuvre's)")
    a = ap.parse_args(argv)
    tmp = None if a.out else tempfile.TemporaryDirectory()
    out = Path(a.out or tmp.name)
    out.mkdir(parents=True, exist_ok=True)
    model = out / "my_arm.toml"
    model.write_text(MODEL)

    from exuflex.cli.modes import modes_report
    from exuflex.truth import simulate_run

    rep = modes_report(str(model), fmax=200.0)
    print("modes (Hz):", [round(f, 2) for f in rep["full"]["frequencies_hz"]])
    run_dir = simulate_run(model, out / "run", engine="erls", seed=1, duration=a.duration)
    mech = xf.load_mechanism(model)
    res = xf.observe_run(mech, xf.read_run(run_dir), report=print)
    print({k: round(v, 2) for k, v in res.summary.get("ratio_to_bound", {}).items()})
    if tmp is not None:
        tmp.cleanup()
    return res.summary


if __name__ == "__main__":
    main()

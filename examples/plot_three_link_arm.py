"""
Three-link arm: shoulder, elbow and wrist motors
================================================

``models/three_link_arm.toml``: an open chain of three flexible links in the horizontal plane: a shoulder
motor drives the upper arm from the ground, an elbow motor on the upper arm's end drives the forearm and a
wrist motor on the forearm's end drives the hand, both relative to the link before; their reaction torques
act on that link. Three closely spaced low modes couple through the joints.

The whole chain on one second of its manoeuvre: the full-order modes, an Exudyn truth that writes the sensor
log, the observer with its default settings on that log, and its errors against its own bound. The same from
the command line::

    exuflex modes models/three_link_arm.toml
    exuflex simulate models/three_link_arm.toml --out runs/three_link_arm --seed 1 --duration 1
    exuflex observe models/three_link_arm.toml runs/three_link_arm --out obs/three_link_arm

The acceptance over three seeds and the whole manoeuvre, for every mechanism: :doc:`/gallery`.
"""

import tempfile
from pathlib import Path

import exuflex as xf
from exuflex.erls.modal import modal_analysis
from exuflex.plots import modes_figure, observer_figures
from exuflex.truth import simulate_run

# the model files, from the repository's root or from examples/
MODELS = Path("models") if Path("models").is_dir() else Path("../models")
MODEL = MODELS / "three_link_arm.toml"
OUT = Path(tempfile.mkdtemp(prefix="exuflex_three_link_arm_"))

# %%
# The full-order model's modes at the reference configuration, motors free (``exuflex modes``).
mech = xf.load_mechanism(MODEL)
modal = modal_analysis(xf.ErlsModel(mech), mech.q_ref)
FIGURES = [modes_figure(mech, modal, OUT / "modes.png")]

# %%
# One second of the manoeuvre simulated by Exudyn (ANCF cable elements), the sensors' noise drawn with seed
# 1; then the reduced-order EKF on the log, scored against the truth from the start-up on.
run = xf.read_run(simulate_run(MODEL, OUT / "run", engine="exudyn", seed=1, duration=1.0))
out = xf.observe_run(mech, run)
print({k: round(v, 2) for k, v in out.summary["ratio_to_bound"].items()})  # RMS error / bound

SHOWN = ("fig_trajectory.png", "fig_joint_errors.png", "fig_tip_errors.png")
FIGURES = [p for p in observer_figures(OUT, mech, run, out) if p.name in SHOWN]

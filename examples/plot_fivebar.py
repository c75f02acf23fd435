"""
Five-bar: two motors, a closed chain
====================================

``models/fivebar.toml``: a closed chain with two degrees of freedom: two grounded motors drive the proximal
links; the distal links meet at the end-effector joint, and one carries on to a tool tip with a payload. The
closure couples the two motors nonlinearly.

The whole chain on one second of its manoeuvre: the full-order modes, an Exudyn truth that writes the sensor
log, the observer with its default settings on that log, and its errors against its own bound. The same from
the command line::

    exuflex modes models/fivebar.toml
    exuflex simulate models/fivebar.toml --out runs/fivebar --seed 1 --duration 1
    exuflex observe models/fivebar.toml runs/fivebar --out obs/fivebar

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
MODEL = MODELS / "fivebar.toml"
OUT = Path(tempfile.mkdtemp(prefix="exuflex_fivebar_"))

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

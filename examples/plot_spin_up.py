"""
Spin-up beam: where the ERLS stops being valid
==============================================

``models/spin_up.toml``: Kane, Ryan and Banerjee's 10 m beam clamped to a hub, driven from rest to a steady
angular speed. The classic test of geometric stiffening: the ERLS has linear elasticity in the rotating frame,
so it departs from a geometrically exact beam as the speed approaches the first clamped-free frequency. This
model has no sensors: it is a validity benchmark, not an observer case. Its modes with the hub held (the
clamped-free beam) are drawn here; the spin-up against Exudyn's ANCF and geometrically exact beams is
``python benchmarks/spin_up.py`` (minutes), on :doc:`/validity`.
"""

import tempfile
from pathlib import Path

import exuflex as xf
from exuflex.erls.modal import modal_analysis
from exuflex.plots import modes_figure

# the model files, from the repository's root or from examples/
MODELS = Path("models") if Path("models").is_dir() else Path("../models")
OUT = Path(tempfile.mkdtemp(prefix="exuflex_spin_up_"))

mech = xf.load_mechanism(MODELS / "spin_up.toml")
modal = modal_analysis(xf.ErlsModel(mech), mech.q_ref, locked=True)  # the hub held: clamped-free
print("clamped-free frequencies (rad/s):", [round(2 * 3.141592653589793 * f, 3) for f in modal.frequencies_hz[:3]])
FIGURES = [modes_figure(mech, modal, OUT / "modes.png")]

"""
Slider-crank: a flexible connecting rod
=======================================

``models/slider_crank.toml``: a stiff crank driven by a motor, a slender flexible connecting rod and a slider
block on a prismatic joint. The rod's first bending mode is near 100 Hz; the slider's position ``xB`` is
measured. ERLS against Exudyn on this mechanism: :doc:`/slider_crank`.

The whole chain on one second of its manoeuvre: the full-order modes, an Exudyn truth that writes the sensor
log, the observer with its default settings on that log, and its errors against its own bound. The same from
the command line::

    exuflex modes models/slider_crank.toml
    exuflex simulate models/slider_crank.toml --out runs/slider_crank --seed 1 --duration 1
    exuflex observe models/slider_crank.toml runs/slider_crank --out obs/slider_crank

The chain is the same on every mechanism's page: ``examples/_whole_chain.py``, shown on :doc:`plot_sixbar`.
The acceptance over ten seeds and three truths, for every mechanism: :doc:`/acceptance`.
"""

from _whole_chain import modes, observed

# %%
# The full-order model's modes at the reference configuration, motors free (``exuflex modes``).
FIGURES = modes("slider_crank")

# %%
# One second of the manoeuvre: the Exudyn truth, the observer on its log, its RMS error over its bound.
FIGURES, ratio_to_bound = observed("slider_crank")
print(ratio_to_bound)

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

The chain is the same on every mechanism's page: ``examples/_whole_chain.py``, shown on :doc:`plot_sixbar`.
The acceptance over ten seeds and three truths, for every mechanism: :doc:`/acceptance`.
"""

from _whole_chain import modes, observed

# %%
# The full-order model's modes at the reference configuration, motors free (``exuflex modes``).
FIGURES = modes("fivebar")

# %%
# One second of the manoeuvre: the Exudyn truth, the observer on its log, its RMS error over its bound.
FIGURES, ratio_to_bound = observed("fivebar")
print(ratio_to_bound)

"""
Four-bar: a flexible crank-rocker
=================================

``models/fourbar.toml``: the smallest closed chain whose ERLS closure is nonlinear in q (the coupler and
rocker angles are transcendental functions of the crank angle). One motor drives the crank; the coupler
carries an overhang to a tip payload.

The whole chain on one second of its manoeuvre: the full-order modes, an Exudyn truth that writes the sensor
log, the observer with its default settings on that log, and its errors against its own bound. The same from
the command line::

    exuflex modes models/fourbar.toml
    exuflex simulate models/fourbar.toml --out runs/fourbar --seed 1 --duration 1
    exuflex observe models/fourbar.toml runs/fourbar --out obs/fourbar

The chain is the same on every mechanism's page: ``examples/_whole_chain.py``, shown on :doc:`plot_sixbar`.
The acceptance over ten seeds and three truths, for every mechanism: :doc:`/acceptance`.
"""

from _whole_chain import modes, observed

# %%
# The full-order model's modes at the reference configuration, motors free (``exuflex modes``).
FIGURES = modes("fourbar")

# %%
# One second of the manoeuvre: the Exudyn truth, the observer on its log, its RMS error over its bound.
FIGURES, ratio_to_bound = observed("fourbar")
print(ratio_to_bound)

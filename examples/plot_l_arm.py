"""
L-shaped arm: two tubes welded at a right angle
===============================================

``models/l_arm.toml``: a motor on a ground hub turns an aluminium tube (the boom), and a thinner tube is
welded across the boom's end at 90 degrees, with a payload at its tip. One coordinate, one motor; the weld
couples the two tubes' bending: the cross tube's axial direction is the boom's transverse one. Its
masters are chosen automatically (``exuflex.reduction.masters``).

The whole chain on one second of its manoeuvre: the full-order modes, an Exudyn truth that writes the sensor
log, the observer with its default settings on that log, and its errors against its own bound. The same from
the command line::

    exuflex modes models/l_arm.toml
    exuflex simulate models/l_arm.toml --out runs/l_arm --seed 1 --duration 1
    exuflex observe models/l_arm.toml runs/l_arm --out obs/l_arm

The chain is the same on every mechanism's page: ``examples/_whole_chain.py``, shown on :doc:`plot_sixbar`.
The acceptance over ten seeds and three truths, for every mechanism: :doc:`/acceptance`.
"""

from _whole_chain import modes, observed

# %%
# The full-order model's modes at the reference configuration, motors free (``exuflex modes``).
FIGURES = modes("l_arm")

# %%
# One second of the manoeuvre: the Exudyn truth, the observer on its log, its RMS error over its bound.
FIGURES, ratio_to_bound = observed("l_arm")
print(ratio_to_bound)

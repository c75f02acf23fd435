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

The chain is the same on every mechanism's page: ``examples/_whole_chain.py``, shown on :doc:`plot_sixbar`.
The acceptance over ten seeds and three truths, for every mechanism: :doc:`/acceptance`.
"""

from _whole_chain import modes, observed

# %%
# The full-order model's modes at the reference configuration, motors free (``exuflex modes``).
FIGURES = modes("three_link_arm")

# %%
# One second of the manoeuvre: the Exudyn truth, the observer on its log, its RMS error over its bound.
FIGURES, ratio_to_bound = observed("three_link_arm")
print(ratio_to_bound)

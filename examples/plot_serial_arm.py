"""
Serial arm: shoulder and elbow motors
=====================================

``models/serial_arm.toml``: a two-link serial arm (SCARA-like): the shoulder motor drives the upper arm from
the ground, the elbow motor sits on the upper arm's end and drives the forearm relative to it. An open
chain whose links' elastic motion couples through the elbow.

The whole chain on one second of its manoeuvre: the full-order modes, an Exudyn truth that writes the sensor
log, the observer with its default settings on that log, and its errors against its own bound. The same from
the command line::

    exuflex modes models/serial_arm.toml
    exuflex simulate models/serial_arm.toml --out runs/serial_arm --seed 1 --duration 1
    exuflex observe models/serial_arm.toml runs/serial_arm --out obs/serial_arm

The chain is the same on every mechanism's page: ``examples/_whole_chain.py``, shown on :doc:`plot_sixbar`.
The acceptance over ten seeds and three truths, for every mechanism: :doc:`/acceptance`.
"""

from _whole_chain import modes, observed

# %%
# The full-order model's modes at the reference configuration, motors free (``exuflex modes``).
FIGURES = modes("serial_arm")

# %%
# One second of the manoeuvre: the Exudyn truth, the observer on its log, its RMS error over its bound.
FIGURES, ratio_to_bound = observed("serial_arm")
print(ratio_to_bound)

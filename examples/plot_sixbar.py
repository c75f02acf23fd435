"""
Six-bar: the paper's test case
==============================

``models/sixbar.toml``: the six-bar planar mechanism of Palomba, Richiedei and Trevisani (2018), Section 4.1,
Fig. 2, Tables 1-3, three motors, the encoders and strain gauges of the paper (every assumption marked in the
file). The paper's own choices (masters, interior modes, noise) stay in the file.

The whole chain on one second of its manoeuvre: the full-order modes, an Exudyn truth that writes the sensor
log, the observer with its default settings on that log, and its errors against its own bound. The same from
the command line::

    exuflex modes models/sixbar.toml
    exuflex simulate models/sixbar.toml --out runs/sixbar --seed 1 --duration 1
    exuflex observe models/sixbar.toml runs/sixbar --out obs/sixbar

The chain is the same on every mechanism's page: ``examples/_whole_chain.py`` (below). The acceptance over
ten seeds and three truths, for every mechanism: :doc:`/acceptance`.

.. literalinclude:: ../../examples/_whole_chain.py
   :pyobject: observed
"""

from _whole_chain import modes, observed

# %%
# The full-order model's modes at the reference configuration, motors free (``exuflex modes``).
FIGURES = modes("sixbar")

# %%
# One second of the manoeuvre: the Exudyn truth, the observer on its log, its RMS error over its bound.
FIGURES, ratio_to_bound = observed("sixbar")
print(ratio_to_bound)

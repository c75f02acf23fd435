"""
Single link: a flexible arm on a hub motor
==========================================

``models/single_link.toml``: one flexible aluminium link driven by a hub motor, with a tip mass: the classic
flexible-arm benchmark, and exuflex's analytic check of the ERLS model (its Euler-Bernoulli frequency
equations are solved in ``tests/test_modal.py``).

The whole chain on one second of its manoeuvre: the full-order modes, an Exudyn truth that writes the sensor
log, the observer with its default settings on that log, and its errors against its own bound. The same from
the command line::

    exuflex modes models/single_link.toml
    exuflex simulate models/single_link.toml --out runs/single_link --seed 1 --duration 1
    exuflex observe models/single_link.toml runs/single_link --out obs/single_link

The chain is the same on every mechanism's page: ``examples/_whole_chain.py``, shown on :doc:`plot_sixbar`.
The acceptance over ten seeds and three truths, for every mechanism: :doc:`/acceptance`.
"""

from _whole_chain import modes, observed

# %%
# The full-order model's modes at the reference configuration, motors free (``exuflex modes``).
FIGURES = modes("single_link")

# %%
# One second of the manoeuvre: the Exudyn truth, the observer on its log, its RMS error over its bound.
FIGURES, ratio_to_bound = observed("single_link")
print(ratio_to_bound)

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

from _whole_chain import modes

FIGURES = modes("spin_up", locked=True)  # the hub held: the clamped-free beam

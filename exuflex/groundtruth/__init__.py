"""Exudyn ground truth: an independent flexible-multibody model of a mechanism (the "real mechanism").

This subpackage is the only place in exuflex that imports :mod:`exudyn`. It builds the mechanism from
planar flexible beams (:func:`build_truth`), computes its eigenfrequencies and modal damping
(:func:`exudyn_frequencies`, :func:`modal_damping`) and simulates it under motor torques, recording
the probes of :mod:`exuflex.probes` (:func:`simulate_truth`), or under a prescribed motion of its
coordinates (:func:`simulate_prescribed`). A third formulation, floating-frame bodies reduced from solid meshes
(:mod:`.ffrf`, :mod:`.solid`; netgen and ngsolve, the ``ffrf`` extra), is built by :func:`build_ffrf`.
"""

from .builder import DAMPINGS, FORMULATIONS, LinkMesh, TruthModel, build_truth, link_mesh_stations
from .eigen import exudyn_frequencies, modal_damping
from .ffrf import FfrfModel, build_ffrf, ffrf_frequencies, simulate_ffrf
from .prescribed import simulate_prescribed
from .simulate import simulate_truth, smooth_torque_table, time_truth

__all__ = [
    "DAMPINGS",
    "FfrfModel",
    "FORMULATIONS",
    "LinkMesh",
    "TruthModel",
    "build_ffrf",
    "build_truth",
    "exudyn_frequencies",
    "ffrf_frequencies",
    "link_mesh_stations",
    "modal_damping",
    "simulate_ffrf",
    "simulate_prescribed",
    "simulate_truth",
    "smooth_torque_table",
    "time_truth",
]

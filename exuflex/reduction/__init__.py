"""Configuration-dependent Craig-Bampton reduction of ERLS models (paper Sec. 2.2 and 4.1)."""

from .accuracy import AccuracyResult, accuracy_along, accuracy_indices, match_modes, reduced_modes
from .basis import CraigBampton, ReducedConfiguration, interior_mode_scores
from .masters import automatic_masters
from .model import ReducedModel
from .path import PathSamples, manoeuvre_configurations
from .report import reduced_modes_report

__all__ = [
    "AccuracyResult",
    "accuracy_along",
    "accuracy_indices",
    "match_modes",
    "reduced_modes",
    "automatic_masters",
    "PathSamples",
    "manoeuvre_configurations",
    "CraigBampton",
    "ReducedConfiguration",
    "interior_mode_scores",
    "ReducedModel",
    "reduced_modes_report",
]

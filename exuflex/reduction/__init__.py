"""Configuration-dependent Craig-Bampton reduction of ERLS models (paper Sec. 2.2 and 4.1)."""

from .accuracy import AccuracyResult, accuracy_along, accuracy_indices, reduced_modes
from .basis import CraigBampton, ReducedConfiguration, interior_mode_scores
from .model import ReducedModel
from .report import reduced_modes_report

__all__ = [
    "AccuracyResult",
    "accuracy_along",
    "accuracy_indices",
    "reduced_modes",
    "CraigBampton",
    "ReducedConfiguration",
    "interior_mode_scores",
    "ReducedModel",
    "reduced_modes_report",
]

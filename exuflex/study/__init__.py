"""Model-mismatch studies (truth with changed parameters, nominal observer) and their aggregation."""

from .overrides import OverrideError, apply_overrides, parse_set, parse_value
from .runner import (
    FORMAT,
    Level,
    StudyResult,
    StudySpec,
    estimator_figure_rows,
    figure_rows,
    make_executor,
    payload_levels,
    run_estimator_studies,
    run_study,
    slenderness_levels,
    sweep_levels,
)

__all__ = [
    "FORMAT",
    "Level",
    "OverrideError",
    "StudyResult",
    "StudySpec",
    "apply_overrides",
    "estimator_figure_rows",
    "figure_rows",
    "make_executor",
    "parse_set",
    "parse_value",
    "payload_levels",
    "run_estimator_studies",
    "run_study",
    "slenderness_levels",
    "sweep_levels",
]

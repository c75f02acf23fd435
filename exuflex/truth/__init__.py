"""The truth: the "real mechanism" simulated under the manoeuvre's torque, its run folders, and the
engines' cross-validation.

One entry point per use: :func:`simulate` (a mechanism under a :class:`Drive`, engine ``"exudyn"``, ``"erls"``
or ``"reduced"``, see :mod:`.engines`) and :func:`simulate_run` (a model file to a run folder, the library form
of ``exuflex simulate``). :mod:`.crossval` compares the Exudyn and ERLS engines on a manoeuvre. Exudyn itself is
imported only in :mod:`exuflex.groundtruth`, by the ``"exudyn"`` engine.
"""

from .crossval import TruthComparison, compare_truths, manoeuvre_table, truth_vs_erls
from .engines import (
    BEAMS,
    ENGINES,
    EXUDYN_ELEMENTS_PER_LINK,
    INTEGRATORS,
    Drive,
    TruthRecord,
    erls_truth,
    exudyn_mesh,
    gen_alpha_step,
    plan_drive,
    reduced_truth,
    simulate,
)
from .run import simulate_run, simulate_runs

__all__ = [
    "BEAMS",
    "ENGINES",
    "EXUDYN_ELEMENTS_PER_LINK",
    "INTEGRATORS",
    "Drive",
    "TruthComparison",
    "TruthRecord",
    "compare_truths",
    "erls_truth",
    "exudyn_mesh",
    "gen_alpha_step",
    "manoeuvre_table",
    "plan_drive",
    "reduced_truth",
    "simulate",
    "simulate_run",
    "simulate_runs",
    "truth_vs_erls",
]

"""The whole chain on one mechanism, as the gallery's mechanism pages run it (``examples/plot_<model>.py``).

Each step is one call of the library, the same as one command::

    exuflex modes models/NAME.toml                                  # modes()
    exuflex simulate models/NAME.toml --out RUN --seed 1 --duration 1
    exuflex observe models/NAME.toml RUN --out OUT                  # observed()

The figures are the files :mod:`exuflex.plots` writes (what ``exuflex observe --out`` writes); the gallery
shows the paths a script leaves in its ``FIGURES``.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import exuflex as xf
from exuflex.erls.modal import modal_analysis
from exuflex.plots import modes_figure, observer_figures
from exuflex.truth import simulate_run

# the model files, from the repository's root or from examples/
MODELS = Path("models") if Path("models").is_dir() else Path("../models")
SHOWN = ("fig_trajectory.png", "fig_joint_errors.png", "fig_tip_errors.png")


def modes(name: str, out: Path | None = None, *, locked: bool = False) -> list[Path]:
    """The full-order model's mode shapes at the model file's reference configuration (motors free, or
    ``locked``), drawn on its links; returns the figure's path."""
    out = Path(out or tempfile.mkdtemp(prefix=f"exuflex_{name}_"))
    mech = xf.load_mechanism(MODELS / f"{name}.toml")
    modal = modal_analysis(xf.ErlsModel(mech), mech.q_ref, locked=locked)
    return [modes_figure(mech, modal, out / "modes.png")]


def observed(name: str, out: Path | None = None, *, duration: float = 1.0, seed: int = 1,
             shown=SHOWN) -> tuple[list[Path], dict[str, float]]:
    """``duration`` seconds of the model file's manoeuvre simulated by Exudyn (ANCF cable elements, the
    sensors' noise drawn with ``seed``), the reduced-order EKF with its default settings on that log, scored
    against the truth from the start-up on. Returns the figures named in ``shown`` and the RMS error over the
    bound per quantity."""
    out = Path(out or tempfile.mkdtemp(prefix=f"exuflex_{name}_"))
    model = MODELS / f"{name}.toml"
    mech = xf.load_mechanism(model)
    run = xf.read_run(simulate_run(model, out / "run", engine="exudyn", seed=seed, duration=duration))
    outcome = xf.observe_run(mech, run)
    figures = [p for p in observer_figures(out, mech, run, outcome) if p.name in shown]
    return figures, {k: round(v, 2) for k, v in outcome.summary["ratio_to_bound"].items()}

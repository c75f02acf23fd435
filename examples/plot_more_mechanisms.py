"""
Every other model file
======================

Each model file in ``models/`` has its page in this gallery; a model file added without a script of its own
(``examples/plot_<name>.py``) is drawn here, so that the gallery always shows every mechanism: its
full-order modes at the reference configuration and, where the file has sensors and a manoeuvre, the
observer's estimates and errors on half a second of an Exudyn truth.
"""

import tempfile
from pathlib import Path

import exuflex as xf
from exuflex.erls.modal import modal_analysis
from exuflex.plots import modes_figure, observer_figures
from exuflex.truth import simulate_run

# the model files, from the repository's root or from examples/
MODELS = Path("models") if Path("models").is_dir() else Path("../models")
EXAMPLES = MODELS.parent / "examples"
OUT = Path(tempfile.mkdtemp(prefix="exuflex_more_"))


def without_page() -> list[Path]:
    """The model files that have no gallery script of their own."""
    return [m for m in sorted(MODELS.glob("*.toml")) if not (EXAMPLES / f"plot_{m.stem}.py").exists()]


print("model files without a page of their own:", [m.name for m in without_page()] or "none")

# %%
# Each of them: the modes, then the observer on a short truth where the file has sensors and a manoeuvre.
FIGURES = []
for model in without_page():
    mech = xf.load_mechanism(model)
    modal = modal_analysis(xf.ErlsModel(mech), mech.q_ref)
    FIGURES.append(modes_figure(mech, modal, OUT / f"{model.stem}_modes.png"))
    if mech.sensors and mech.manoeuvre is not None:
        run = xf.read_run(simulate_run(model, OUT / model.stem, engine="exudyn", seed=1, duration=0.5))
        out = xf.observe_run(mech, run)
        print(model.stem, {k: round(v, 2) for k, v in out.summary["ratio_to_bound"].items()})
        FIGURES += [p for p in observer_figures(OUT / model.stem, mech, run, out) if p.name == "fig_joint_errors.png"]

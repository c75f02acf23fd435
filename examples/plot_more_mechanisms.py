"""
Every other model file
======================

Each model file in ``models/`` has its page in this gallery; a model file added without a script of its own
(``examples/plot_<name>.py``) is drawn here, so that the gallery always shows every mechanism: its
full-order modes at the reference configuration and, where the file has sensors and a manoeuvre, the
observer's estimates and errors on half a second of an Exudyn truth.
"""

from pathlib import Path

from _whole_chain import MODELS, modes, observed

import exuflex as xf

EXAMPLES = MODELS.parent / "examples"


def without_page() -> list[Path]:
    """The model files that have no gallery script of their own."""
    return [m for m in sorted(MODELS.glob("*.toml")) if not (EXAMPLES / f"plot_{m.stem}.py").exists()]


print("model files without a page of their own:", [m.name for m in without_page()] or "none")

# %%
# Each of them: the modes, then the observer on a short truth where the file has sensors and a manoeuvre.
FIGURES = []
for model in without_page():
    FIGURES += modes(model.stem)
    mech = xf.load_mechanism(model)
    if mech.sensors and mech.manoeuvre is not None:
        figures, ratio_to_bound = observed(model.stem, duration=0.5, shown=("fig_joint_errors.png",))
        print(model.stem, ratio_to_bound)
        FIGURES += figures

"""A truth-parameter sweep (any model-file field), e.g. the Rayleigh damping the paper does not state.

    python studies/sweep.py OUT [--quick]

Equivalent to ``exuflex study sweep models/sixbar.toml --set damping.alpha=...``.
"""

from __future__ import annotations

from pathlib import Path

from exuflex.study import StudySpec, run_study, sweep_levels

MODEL = Path(__file__).resolve().parents[1] / "models" / "sixbar.toml"
FULL = {"sets": [("damping.alpha", [0.77, 1.540443708541752, 3.08])], "runs": 20, "duration": None}
QUICK = {"sets": [("damping.alpha", [0.77, 3.08])], "runs": 2, "duration": 0.1}


def compute(out, config: dict = FULL, *, workers: int = 1, **kw):
    spec = StudySpec(model=str(MODEL), levels=sweep_levels(config["sets"]), runs=config["runs"],
                     duration=config["duration"], kind="sweep")
    return run_study(spec, out, workers=workers, **kw)


def plot(summary: dict, path):
    from exuflex.plots import sweep_figure

    return sweep_figure(summary, path)


if __name__ == "__main__":
    import argparse

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("out")
    p.add_argument("--quick", action="store_true")
    a = p.parse_args()
    print(plot(compute(a.out, QUICK if a.quick else FULL).summary, Path(a.out) / "fig_sweep.png"))

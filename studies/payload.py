"""The paper's payload-mismatch study (Sec. 4.3, eq. 21, Fig. 11).

    python studies/payload.py OUT [--quick] [--workers N]

``compute`` runs (or resumes) the study, ``plot`` draws Fig. 11 from its summary; ``QUICK`` is the
seconds-long configuration the tests use. Equivalent to ``exuflex study payload models/sixbar.toml``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from exuflex.study import StudySpec, payload_levels, run_study
from exuflex.study.runner import figure_rows

MODEL = Path(__file__).resolve().parents[1] / "models" / "sixbar.toml"
FULL = {"levels": (0, 25, 50, 75, 100), "runs": 100, "duration": None, "engine": "exudyn"}
QUICK = {"levels": (0, 100), "runs": 2, "duration": 0.1, "engine": "exudyn"}


def spec(config: dict = FULL, model=MODEL, seed: int = 0) -> StudySpec:
    return StudySpec(model=str(model), levels=payload_levels(config["levels"]), runs=config["runs"],
                     base_seed=seed, engine=config["engine"], duration=config["duration"], kind="payload")


def compute(out, config: dict = FULL, *, workers: int = 1, scheduler=None, progress: bool = False, **kw):
    """Run (or resume) the study into ``out``; returns the :class:`exuflex.study.StudyResult`."""
    return run_study(spec(config), out, workers=workers, scheduler=scheduler, progress=progress, **kw)


def plot(summary: dict, path):
    """Fig. 11 from a study summary (every estimated quantity, mu +- sigma per payload level)."""
    from exuflex.plots import payload_study_figure

    return payload_study_figure(figure_rows(summary), path)


if __name__ == "__main__":
    import argparse

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("out")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--workers", type=int, default=1)
    a = p.parse_args()
    res = compute(a.out, QUICK if a.quick else FULL, workers=a.workers, progress=sys.stderr.isatty())
    print(plot(res.summary, Path(a.out) / "fig_payload.png"))

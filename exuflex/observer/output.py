"""Writing an observer outcome: estimates and result summary (with provenance); the command line adds the
figures (:func:`exuflex.plots.observer_figures`)."""

from __future__ import annotations

import json
from pathlib import Path

from ..runs import atomic_write_text, package_versions, write_signals_csv

__all__ = ["write_outcome"]


def write_outcome(out_dir, mech, run, outcome) -> Path:
    """Write ``estimates.csv`` (physical estimates) and ``result.json`` (metrics, settings, versions) into
    ``out_dir``; every file is written atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_signals_csv(out / "estimates.csv", outcome.estimate.physical)
    summary = dict(outcome.summary)
    summary["versions"] = package_versions()
    summary["run_meta"] = {k: run.meta.get(k) for k in ("engine", "seed", "model", "settings") if k in run.meta}
    atomic_write_text(out / "result.json", json.dumps(summary, indent=1, default=float))
    return out

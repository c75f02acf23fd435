"""Writing an observer outcome: estimates, result summary (with provenance) and figures."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from ..runs import atomic_write_text, package_versions, write_signals_csv

__all__ = ["write_outcome"]

log = logging.getLogger(__name__)


def write_outcome(out_dir, mech, run, outcome, plots: bool = True) -> Path:
    """Write ``estimates.csv`` (physical estimates), ``result.json`` (metrics, settings, versions) and the
    figures (``fig_*.png``) into ``out_dir``; every file is written atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_signals_csv(out / "estimates.csv", outcome.estimate.physical)
    summary = dict(outcome.summary)
    summary["versions"] = package_versions()
    summary["run_meta"] = {k: run.meta.get(k) for k in ("engine", "seed", "model", "settings") if k in run.meta}
    atomic_write_text(out / "result.json", json.dumps(summary, indent=1, default=float))
    if plots:
        from ..plots import observer_figures

        for f in observer_figures(out, mech, run, outcome):
            log.info("wrote %s", os.fspath(f))
    return out

"""Writing an observer outcome: estimates, result summary (with provenance) and figures."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from ..runs import atomic_write_text, package_versions, write_signals_csv

__all__ = ["summary_table", "write_outcome"]

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


_UNITS = {"rad": "rad", "rad/s": "rad/s", "m": "m", "m/s": "m/s"}


def summary_table(mech, outcome, bound: bool = True) -> str:
    """The result as text: a header (samples, model, channels, NIS), then one row per physical quantity with its
    unit, RMS and max error against the truth (if any), the bound for this log and their ratio."""
    s = outcome.summary
    res = outcome.estimate.result
    phys = outcome.estimate.physical
    lines = [f"{mech.name}: {len(res.t)} samples, reduced model {s['reduced_ndof']} dofs, channels "
             f"{' '.join(s.get('channels_used') or s['channels'])}",
             f"wall {s['wall_s']:.2f} s, real-time factor {s['real_time_factor']:.2f}, mean NIS {s['nis_mean']:.2f} "
             f"(expected {s['nis_expected']:.1f})"]
    if s.get("diverged"):
        lines.append(f"DIVERGED: the estimates became non-finite at t = {s['diverged_at']} s")
    elif s.get("nis_inconsistent"):
        lines.append(f"NIS inconsistent from t = {s['nis_flagged_at']} s (the innovations exceed what the filter's "
                     "covariance explains: model mismatch or noise settings; the estimates stay finite)")
    units = dict(zip(phys.names, phys.units or ("",) * len(phys.names), strict=True))
    met = outcome.metrics
    bnd = outcome.bound or {}
    if met:
        lines.append(f"{'quantity':10s} {'unit':>6s} {'RMS error':>11s} {'max error':>11s} {'bound':>11s} "
                     f"{'ratio':>6s}")
        for k, v in met["rms_error"].items():
            b = bnd.get(k)
            ratio = f"{v / b:6.2f}" if b else "     -"
            bs = f"{b:11.3g}" if b else "          -"
            lines.append(f"{k:10s} {units.get(k, ''):>6s} {v:11.3g} {met['max_error'][k]:11.3g} {bs} {ratio}")
    elif bound and bnd:
        lines.append(f"{'quantity':10s} {'unit':>6s} {'bound':>11s}")
        for k, b in bnd.items():
            lines.append(f"{k:10s} {units.get(k, ''):>6s} {b:11.3g}")
    return "\n".join(lines)

"""Figures of a sweep study (a payload study uses :func:`exuflex.plots.payload_study_figure`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["sweep_figure"]


def sweep_figure(summary: dict, path, quantities=None) -> Path:
    """eq. 21 mu (markers) +- sigma (bars) of each quantity per sweep level (levels on the x axis).

    Default quantities: the tip ones, elastic (``x25 y26 dx25 dy26``) beside absolute (``tip_x tip_y dtip_x
    dtip_y``), else every quantity of the summary.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from .runner import ABS_TIP_QUANTITIES, TIP_QUANTITIES, ordered_quantities, quantity_title

    tips = [q for q in TIP_QUANTITIES + ABS_TIP_QUANTITIES if q in summary["quantities"]]
    qs = ordered_quantities(summary, quantities or tips or summary["quantities"])
    levels = summary["levels"]
    numeric = all(isinstance(lv["value"], (int, float)) and not isinstance(lv["value"], bool) for lv in levels)
    x = np.array([lv["value"] for lv in levels], float) if numeric else np.arange(len(levels), dtype=float)
    ncols = 2 if len(qs) > 1 else 1
    nrows = int(np.ceil(len(qs) / ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.0 * ncols, 2.8 * nrows + 0.9), squeeze=False)
    for k, q in enumerate(qs):
        ax = axes[k // ncols, k % ncols]
        mu = np.array([lv["eq21"][q]["mu"] for lv in levels])
        sg = np.array([lv["eq21"][q]["sigma"] for lv in levels])
        ax.errorbar(x, mu, yerr=sg, fmt="o", capsize=4, ecolor="k")
        ax.set_title(quantity_title(q, summary), fontsize=10)
        ax.set_ylabel(f"|{q} error|")
        ax.grid(True, lw=0.3)
        ax.set_xticks(x)
        ax.set_xticklabels([str(lv["value"]) if numeric else lv["label"] for lv in levels],
                           rotation=0 if numeric else 30, fontsize=7)
        ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 2))
    for k in range(len(qs), nrows * ncols):
        axes[k // ncols, k % ncols].set_visible(False)
    fields = sorted({o[0] for lv in levels for o in lv["overrides"]})
    fig.suptitle(f"Truth-model mismatch sweep: {', '.join(fields)} (eq. 21 mu +- sigma)")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

"""One-command reproduction of the paper (Table 2, Figs 3-11, report.md).

    python studies/reproduce.py OUT [--quick] [--workers N]

Equivalent to ``exuflex reproduce --out OUT``; ``compute`` is what the tests call with ``QUICK``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from exuflex.cli.reproduce import FULL, QUICK, reproduce

MODEL = Path(__file__).resolve().parents[1] / "models" / "sixbar.toml"

__all__ = ["FULL", "QUICK", "compute"]


def compute(out, quick: bool = False, *, workers: int = 1, **kw) -> Path:
    """Regenerate everything into ``out``; returns the report's path."""
    return reproduce(MODEL, out, quick=quick, workers=workers, **kw)


if __name__ == "__main__":
    import argparse

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("out")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--workers", type=int, default=1)
    a = p.parse_args()
    print(compute(a.out, a.quick, workers=a.workers, progress=sys.stderr.isatty()))

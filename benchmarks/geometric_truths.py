"""The ERLS truth with and without the geometric stiffness, against the independent Exudyn truth. Writes a block of
``docs/validity.md``.

For each model: the full-order ERLS truths of the same torque table with the geometric stiffness of the rigid
motion's axial loads (``exuflex.erls.model``, "Geometric stiffness", the default) and without it (linear elasticity,
``geometric=False``), each against the geometrically exact Exudyn truth: per elastic true quantity (the tip's
elastic displacement and its rate) the RMS difference after the observer's start-up over the observer's bound
(a run's ``bound_rms``), seed 1 (the truth does not depend on the seed). The truths are those of
``benchmarks/gallery.py --acceptance --truth-dir DIR`` (``DIR/<engine>/<model>/s1``), one directory per ERLS
variant; the bounds and start-up from that run's JSON.

Usage: python benchmarks/geometric_truths.py --with DIR/erls --without DIR0/erls --exudyn DIR0/exudyn
       --bounds DIR0/acceptance.json [--docs docs/validity.md]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

BEGIN, END = "<!-- geometric_truths.py: begin -->", "<!-- geometric_truths.py: end -->"


def load(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path) as f:
        rows = csv.reader(f)
        head = next(rows)
        return head, np.array([[float(x) for x in row] for row in rows])


def compare(with_dir: Path, without_dir: Path, exudyn_dir: Path, runs: dict) -> list[dict]:
    """Per model (those with all three truths and a seed-1 ERLS run in ``runs``): per elastic quantity the RMS
    difference to Exudyn over the bound, without and with the geometric stiffness."""
    out = []
    for model in sorted(p.name for p in with_dir.iterdir()):
        run = runs.get((model, "erls", 1))
        files = [d / model / "s1" / "truth.csv" for d in (without_dir, with_dir, exudyn_dir)]
        if run is None or not all(f.exists() for f in files):
            continue
        (h0, a0), (h1, a1), (he, ae) = (load(f) for f in files)
        n = min(len(a0), len(a1), len(ae))
        keep = a0[:n, 0] >= run["metrics_from_s"]
        row = {"model": model, "quantities": {}}
        for k, b in run["bound_rms"].items():
            if k in h0 and k in h1 and k in he and b > 0 and not k.lstrip("d").startswith("q"):
                e = ae[:n, he.index(k)][keep]
                row["quantities"][k] = [float(np.sqrt(np.mean((e - a[:n, h.index(k)][keep]) ** 2)) / b)
                                        for h, a in ((h0, a0), (h1, a1))]
        out.append(row)
    return out


def block(rows: list[dict], command: str) -> str:
    lines = [BEGIN, f"Measured by `{command}` (seed 1; the acceptance's truths under the truth step rule).", "",
             "| model | Exudyn - ERLS truth, RMS / bound: without -> with the geometric stiffness |", "|---|---|"]
    for r in rows:
        lines.append(f"| {r['model']} | " + ", ".join(f"{k} {a:.2f} -> {b:.2f}" for k, (a, b) in r["quantities"].items())
                     + " |")
    lines.append(END)
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--with", dest="with_dir", required=True, help="ERLS truths with the geometric stiffness")
    ap.add_argument("--without", required=True, help="ERLS truths without it")
    ap.add_argument("--exudyn", required=True, help="Exudyn truths of the same torque tables")
    ap.add_argument("--bounds", required=True, help="the gallery run's JSON (bounds, start-up)")
    ap.add_argument("--docs", default="", help="page whose geometric_truths.py block is rewritten")
    a = ap.parse_args(argv)
    data = json.loads(Path(a.bounds).read_text())
    runs = {(r["model"], r["engine"], r["seed"]): r for r in data["runs"]}
    rows = compare(Path(a.with_dir), Path(a.without), Path(a.exudyn), runs)
    command = "python benchmarks/geometric_truths.py " + " ".join(sys.argv[1:] if argv is None else argv)
    text = block(rows, command)
    print(text)
    if a.docs:
        page = Path(a.docs).read_text()
        if BEGIN in page and END in page:
            page = page[: page.index(BEGIN)] + text + page[page.index(END) + len(END):]
        else:
            page = page.rstrip("\n") + "\n\n" + text + "\n"
        Path(a.docs).write_text(page)
    return 0


if __name__ == "__main__":
    sys.exit(main())

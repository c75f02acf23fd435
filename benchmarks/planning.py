"""Planning and computed torque against the Exudyn solve, per model. Writes ``docs/planning.md``.

For every model with a manoeuvre, ``exuflex simulate MODEL`` (Exudyn truth, the whole manoeuvre, the torque table
on the integration grid ``--h``) in this process, one after the other; from its ``meta.json``: the planner's and the
computed torque's wall times (``timings.plan_s``, ``timings.torque_s``), their wall and CPU total
(``plan_and_torque_s``, ``plan_and_torque_cpu_s``) and the truth's (``truth_s``, ``truth_cpu_s``: build, solve and
probes), and the ratios of the two within the run.

Usage: python benchmarks/planning.py [--models models/sixbar.toml,...] [--h 1e-4] [--out docs/planning.md]
"""

from __future__ import annotations  # noqa: I001  (exuflex first: single-threaded BLAS before NumPy loads it)

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import exuflex  # noqa: F401

from exuflex.cli.simulate import simulate_run
from exuflex.mechanism import load_mechanism

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = [*sorted((ROOT / "models").glob("*.toml")), ROOT / "tests" / "data" / "fivebar_tip.toml"]


def measure(model: Path, h: float) -> dict | None:
    mech = load_mechanism(model)
    if mech.manoeuvre is None:
        return None
    with tempfile.TemporaryDirectory() as d:
        out = simulate_run(model, Path(d) / "run", seed=0, h=h)
        t = json.loads((out / "meta.json").read_text())["settings"]["timings"]
    return {"model": str(model.relative_to(ROOT)) if model.is_relative_to(ROOT) else str(model),
            "kind": mech.manoeuvre.kind, "points": round(mech.manoeuvre.duration / h) + 1,
            **{k: t[k] for k in ("plan_s", "torque_s", "plan_and_torque_s", "plan_and_torque_cpu_s", "truth_s",
                                 "truth_cpu_s")},
            "wall_ratio": t["plan_and_torque_s"] / t["truth_s"],
            "cpu_ratio": t["plan_and_torque_cpu_s"] / t["truth_cpu_s"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default=None, help="comma-separated model files (default: models/*.toml and the "
                    "test five-bar)")
    ap.add_argument("--h", type=float, default=1e-4)
    ap.add_argument("--out", default=str(ROOT / "docs" / "planning.md"))
    args = ap.parse_args(argv)
    models = [Path(m).resolve() for m in args.models.split(",")] if args.models else DEFAULT
    rows = [r for r in (measure(m, args.h) for m in models) if r is not None]
    cmd = "python benchmarks/planning.py" + ("" if args.h == 1e-4 else f" --h {args.h:g}")
    lines = [
        "# Planning and computed torque against the Exudyn solve",
        "",
        f"Written by `{cmd}` (one process, the runs one after the other, {os.cpu_count()} CPUs shared with other",
        "work: the ratios within a run are the figures to compare; times in s). Each row is one",
        "`exuflex simulate MODEL` of the whole manoeuvre with the torque table on the integration grid; the columns",
        "are its `meta.json` timings: the planner (`plan_s`: exact inverse kinematics with rates, batched over the",
        "grid), the rigid computed torque (`torque_s`), their wall and CPU total, and the Exudyn truth's (build,",
        "solve, probes).",
        "",
        "| model | manoeuvre | grid points | plan | torque | plan + torque (CPU) | truth (CPU) | ratio wall | ratio CPU |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| `{r['model']}` | {r['kind']} | {r['points']} | {r['plan_s']:.2f} | {r['torque_s']:.2f} | "
                     f"{r['plan_and_torque_s']:.2f} ({r['plan_and_torque_cpu_s']:.2f}) | {r['truth_s']:.2f} "
                     f"({r['truth_cpu_s']:.2f}) | {r['wall_ratio']:.2f} | {r['cpu_ratio']:.2f} |")
    Path(args.out).write_text("\n".join(lines) + "\n", encoding="utf-8")
    for r in rows:
        print(json.dumps(r), file=sys.stdout)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

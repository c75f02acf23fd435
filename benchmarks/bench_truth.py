"""Wall time of the 3 s six-bar ground truth (Exudyn, ANCF 4 elements per link, h = 1e-4 s).

Target: no slower than real time (<= 3 s wall). Drives the truth with the paper's computed torques
(rigid inverse dynamics along the planned manoeuvre) when the model has a manoeuvre.

Usage: python benchmarks/bench_truth.py [model.toml] [--smooth] [--repeat N]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from exuflex.groundtruth import time_truth
from exuflex.mechanism import load_mechanism
from exuflex.runs import package_versions

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", nargs="?", default=str(ROOT / "models" / "sixbar.toml"))
    ap.add_argument("--smooth", action="store_true", help="smooth torque pulses instead of the manoeuvre")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--h", type=float, default=1e-4)
    args = ap.parse_args()
    mech = load_mechanism(args.model)
    duration = mech.manoeuvre.duration if mech.manoeuvre is not None else 3.0

    def load() -> float:
        return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")

    walls, cpus, stats = [], [], []
    load_before = load()
    for _ in range(args.repeat):
        st: dict = {}
        c0 = time.process_time()
        walls.append(
            time_truth(mech, duration, h=args.h, torques="smooth" if args.smooth else "auto", stats=st)
        )
        cpus.append(time.process_time() - c0)
        stats.append(st)
    print(
        f"model {mech.name}: {duration:g} s simulated, h = {args.h:g} s, torques: {'smooth' if args.smooth else 'manoeuvre'}"
        f", Exudyn {package_versions()['exudyn']}"
    )
    print(f"wall time  best {min(walls):.2f} s  (all: {', '.join(f'{w:.2f}' for w in walls)})")

    def joined(key: str) -> str:
        return ", ".join(f"{st[key]:.2f}" for st in stats)

    print(
        f"solve      wall {joined('wall_s')} s, cpu {joined('cpu_s')} s (of which pre-step "
        f"{joined('pre_step_s')} s); Newton {stats[0]['newton_per_step']:.2f} iterations/step"
    )
    print(f"cpu  time  all {', '.join(f'{c:.2f}' for c in cpus)} s  (includes planning the manoeuvre)")
    print(
        f"real-time factor {min(walls) / duration:.2f}  (target <= 1); load average {load_before:.1f} before, "
        f"{load():.1f} after, on {os.cpu_count()} cores"
    )


if __name__ == "__main__":
    main()

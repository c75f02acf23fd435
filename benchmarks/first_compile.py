"""CPU time of the first use with an empty numba cache: import, building the six-bar's observer, a short log.

    python benchmarks/first_compile.py [--repeats 2] [--model models/sixbar.toml] [--run tests/data/sixbar_short]

Each repeat runs a fresh Python process with ``NUMBA_CACHE_DIR`` set to an empty temporary folder (so every kernel
the observer uses is compiled, none loaded) and reports the process's CPU seconds per stage (``time.process_time``:
on a shared machine wall time measures the other jobs). The median over the repeats is printed; the same code
scatters by several seconds between runs, so compare versions in alternating runs.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
t0 = time.process_time()
from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, _hold, estimate, make_observer
from exuflex.runs import read_run
t1 = time.process_time()
mech = load_mechanism(sys.argv[1]); run = read_run(sys.argv[2])
obs = make_observer(mech, ObserverConfig.for_model(mech))
t2 = time.process_time()
S = run.sensors
estimate(obs, S.t, _hold(S.select(mech.motor_names).data), S.select(obs.channels).data)
t3 = time.process_time()
print(json.dumps({"import_s": t1 - t0, "make_observer_s": t2 - t1, "first_run_s": t3 - t2, "total_s": t3 - t0}))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--model", default=str(ROOT / "models" / "sixbar.toml"))
    ap.add_argument("--run", default=str(ROOT / "tests" / "data" / "sixbar_short"))
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    runs = []
    for i in range(args.repeats):
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, NUMBA_CACHE_DIR=cache)
            print(f"repeat {i + 1}/{args.repeats}: compiling with an empty cache ...", file=sys.stderr, flush=True)
            out = subprocess.run([sys.executable, "-c", CHILD, args.model, args.run], env=env, check=True,
                                 capture_output=True, text=True)
            runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    if args.json:
        print(json.dumps({"median": med, "runs": runs}, indent=1))
        return 0
    print(f"CPU seconds with an empty numba cache (median of {len(runs)}): "
          + ", ".join(f"{k.removesuffix('_s')} {v:.1f}" for k, v in med.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Peak memory of reading and observing a large log; writes ``docs/log_memory.md``.

The log: the six-bar's 3 s ERLS run (``tests/data/sixbar_erls_3s``) followed by the mechanism at rest (torques and
curvatures zero, angles and tip at their last values, each with its channel's noise from the model file, seeded)
until ``sensors.csv`` reaches ``--mb`` megabytes; no truth. Each measurement runs in a fresh process:

- ``read``: :func:`exuflex.runs.read_run` alone, peak traced allocations (``tracemalloc``) and the process's peak
  resident set (``ru_maxrss``) against its resident set before reading;
- ``observe``: ``exuflex observe models/sixbar.toml RUN --json`` and ``... --out DIR --no-plots --json`` (the
  estimates streamed to ``estimates.csv``) under ``/usr/bin/time -v`` (maximum resident set size, wall time),
  with ``--observe``; the same on the 3 s log, the process's size without a long log;
- what ``observe`` holds per log row (the log, what :func:`exuflex.scoring.run.observe_run` keeps of the
  filtered record) and per chunk of :data:`~exuflex.observer.session.CHUNK_ROWS` rows, counted from the arrays
  of a run on the 3 s log, beside the filter's whole record (``keep="all"``, the library's default).

Usage: ``python benchmarks/log_memory.py [--mb 200] [--observe] [--keep DIR]``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SOURCE_RUN = ROOT / "tests" / "data" / "sixbar_erls_3s"
MODEL = ROOT / "models" / "sixbar.toml"


def make_log(out: Path, megabytes: float, seed: int = 0) -> dict:
    """Write the run folder ``out`` (see the module docstring); returns its size and row count."""
    from exuflex.mechanism import load_mechanism
    from exuflex.runs import read_run

    mech = load_mechanism(MODEL)
    run = read_run(SOURCE_RUN)
    sig = run.sensors
    noise = {m.name: m.noise_std for m in mech.motors} | {s.name: s.noise_std for s in mech.sensors}
    last = sig.data[-1].copy()
    rest = np.array([0.0 if (n in noise and n.startswith("T")) or n.startswith("c") else v
                     for n, v in zip(sig.names, last, strict=True)])
    std = np.array([noise.get(n, 0.0) for n in sig.names])
    dt = float(sig.t[1] - sig.t[0])
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    target = megabytes * 1e6
    n_rows = len(sig.t)
    with open(out / "sensors.csv", "w", encoding="utf-8") as fh:
        fh.write(",".join(("time",) + sig.names) + "\n")
        for k in range(len(sig.t)):
            fh.write(",".join([repr(float(sig.t[k]))] + [repr(float(v)) for v in sig.data[k]]) + "\n")
        k0 = len(sig.t)
        t_last = float(sig.t[-1])
        while fh.tell() < target:
            block = rest + std * rng.standard_normal((5000, len(rest)))
            lines = []
            for j, row in enumerate(block):
                t = round(t_last + (k0 - len(sig.t) + j + 1) * dt, 9)
                lines.append(",".join([repr(t)] + [repr(float(v)) for v in row]))
            fh.write("\n".join(lines) + "\n")
            k0 += len(block)
        n_rows = k0
    meta = dict(run.meta)
    meta["truth"] = []
    meta["units"] = {"sensors.csv": meta.get("units", {}).get("sensors.csv", {})}
    meta["benchmark"] = {"log": "benchmarks/log_memory.py", "seed": seed, "rest_after_s": t_last}
    (out / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
    return {"bytes": (out / "sensors.csv").stat().st_size, "rows": n_rows}


READ_PROBE = textwrap.dedent("""
    import json, resource, sys, tracemalloc
    import numpy as np
    from exuflex.runs import read_run
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    tracemalloc.start()
    run = read_run(sys.argv[1])
    cur, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    arrays = run.sensors.data.nbytes + run.sensors.t.nbytes
    print(json.dumps({"traced_peak_bytes": peak, "traced_held_bytes": cur, "maxrss_before_kb": before,
                      "maxrss_after_kb": after, "rows": len(run.sensors.t), "array_bytes": arrays}))
""")


def measure_read(run_dir: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", READ_PROBE, str(run_dir)], capture_output=True, text=True, env=env,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def measure_observe(run_dir: Path, out: Path | None = None) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "exuflex", "observe", str(MODEL), str(run_dir), "--json"]
    if out is not None:
        cmd += ["--out", str(out), "--no-plots"]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr)
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([0-9:.]+)", p.stderr)
    secs = sum(float(x) * 60**i for i, x in enumerate(reversed(wall.group(1).split(":")))) if wall else None
    tail = [ln for ln in p.stderr.splitlines() if ln.startswith("exuflex")][-3:]
    return {"exit": p.returncode, "maxrss_kb": int(rss.group(1)) if rss else None, "wall_s": secs,
            "stderr_tail": tail}


def record_bytes_per_sample() -> tuple[dict, dict]:
    """Bytes per log row of what ``observe`` holds besides the process itself, counted from the arrays of runs of
    the observer on the 3 s log (they grow linearly with the rows): the log, what the command line keeps of the
    filtered record, and the filter's whole record (``keep="all"``); and the bytes of one chunk of the streamed
    path (a constant)."""
    from exuflex.mechanism import load_mechanism
    from exuflex.scoring.output import EstimatesTable
    from exuflex.observer.session import CHUNK_ROWS, ObserverConfig, estimate_chunks, make_observer
    from exuflex.scoring.run import observe_run
    from exuflex.runs import read_run

    mech = load_mechanism(MODEL)
    run = read_run(SOURCE_RUN)
    n = len(run.sensors.t)
    obs = make_observer(mech, ObserverConfig())
    obs.ekf.store_P = "none"
    lean = observe_run(mech, run, ObserverConfig(), observer=obs, keep="summary", with_bound=False).estimate
    parts = {"log (sensors.csv as float64)": run.sensors.data.nbytes + run.sensors.t.nbytes,
             "kept: NIS and its degrees of freedom": lean.result.nis.nbytes + lean.result.nis_dof.nbytes}
    phys = lean.physical  # the 3 s log has a truth: kept for its errors
    parts[f"kept with a truth or figures: physical estimates ({len(phys.names)} columns)"] = phys.data.nbytes
    obs.ekf.store_P = "diag"
    full = observe_run(mech, run, ObserverConfig(), observer=obs, keep="all", with_bound=False).estimate.result
    whole = sum(getattr(full, a).nbytes for a in ("x_hat", "P", "innovations", "S", "nis", "nis_dof"))
    parts["not kept: the filter's whole record, keep='all' (estimates, P diagonal, innovations, S, NIS)"] = whole
    per_row = {k: v / n for k, v in parts.items()}
    obs.ekf.store_P = "full"  # --out: the full covariance of a chunk, for the tip's standard deviations
    S = run.sensors
    ch = next(estimate_chunks(obs, S.t, S.select(run.motors).data, S.select(obs.channels).data, innovations=False))
    table = EstimatesTable(mech, obs).rows(ch.physical, ch.result.x_hat, ch.result.P)
    rec = ch.result
    one = sum(a.nbytes for a in (rec.x_hat, rec.P, rec.nis, rec.nis_dof, ch.physical.data, table.data)) / len(rec.t)
    return per_row, {"rows": CHUNK_ROWS, "bytes_per_row": one, "bytes": one * CHUNK_ROWS}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mb", type=float, default=200.0, help="size of sensors.csv (MB, default 200)")
    ap.add_argument("--observe", action="store_true", help="also run exuflex observe on it (long)")
    ap.add_argument("--keep", help="write the log here and keep it (default: a temporary folder)")
    ap.add_argument("--doc", default=str(ROOT / "docs" / "log_memory.md"))
    args = ap.parse_args(argv)
    tmp = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="exuflex_log_"))
    try:
        made = make_log(tmp, args.mb)
        rd = measure_read(tmp)
        obs = small = None
        if args.observe:
            small = {"json": measure_observe(SOURCE_RUN),
                     "out": measure_observe(SOURCE_RUN, Path(tempfile.mkdtemp(prefix="exuflex_est_")) / "o")}
            obs = {"json": measure_observe(tmp), "out": measure_observe(tmp, tmp / "estimates_out")}
        per_row, chunk = record_bytes_per_sample()
    finally:
        if not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)
    mb = made["bytes"] / 1e6
    lines = [
        "# Memory of reading and observing a large log",
        "",
        "Written by `python benchmarks/log_memory.py --mb {:g}{}` (see its docstring for the log).".format(
            args.mb, " --observe" if args.observe else ""),
        "",
        f"Log: `sensors.csv` of {mb:.1f} MB, {made['rows']} rows of 13 columns (six-bar, 500 Hz).",
        "",
        "| measurement | figure |",
        "|---|---|",
        f"| `read_run`: the arrays it returns | {rd['array_bytes'] / 1e6:.1f} MB "
        f"({rd['array_bytes'] / made['bytes']:.2f} x the file) |",
        f"| `read_run`: peak traced allocations (tracemalloc) | {rd['traced_peak_bytes'] / 1e6:.1f} MB "
        f"({rd['traced_peak_bytes'] / made['bytes']:.2f} x the file) |",
        f"| `read_run`: peak resident set of the process, before -> after reading | "
        f"{rd['maxrss_before_kb'] / 1e3:.0f} MB -> {rd['maxrss_after_kb'] / 1e3:.0f} MB (+"
        f"{(rd['maxrss_after_kb'] - rd['maxrss_before_kb']) / 1e3:.0f} MB, "
        f"{(rd['maxrss_after_kb'] - rd['maxrss_before_kb']) * 1e3 / made['bytes']:.2f} x the file) |",
    ]
    if obs is not None:
        for key, what in (("json", "`exuflex observe MODEL RUN --json`"),
                          ("out", "`exuflex observe MODEL RUN --json --out DIR --no-plots` (estimates.csv streamed)")):
            o, s0 = obs[key], small[key]
            lines.append(f"| {what}: maximum resident set size, wall time (exit {o['exit']}) | "
                         f"{o['maxrss_kb'] / 1e3:.0f} MB (**{o['maxrss_kb'] * 1e3 / made['bytes']:.2f} x the file**), "
                         f"{o['wall_s']:.0f} s; on the 3 s log {s0['maxrss_kb'] / 1e3:.0f} MB |")
    row_bytes = made["bytes"] / made["rows"]
    lines += ["", f"What `observe` holds per log row besides the process itself (the text is {row_bytes:.0f} bytes a "
              "row), counted from the arrays of runs on the 3 s log; the log is filtered "
              f"{chunk['rows']} rows at a time and only the rows marked kept grow with it:", "",
              "| array | bytes per row | x the text |", "|---|---|---|"]
    for k, v in per_row.items():
        lines.append(f"| {k} | {v:.0f} | {v / row_bytes:.2f} |")
    lines += ["", f"One chunk of {chunk['rows']} rows with `--out` (its record with the full covariance, physical "
              f"estimates and table): {chunk['bytes_per_row']:.0f} bytes a row, {chunk['bytes'] / 1e6:.1f} MB, "
              "whatever the log's length.",
              "", "Figures of one run on a shared machine; memory figures do not depend on its load.", ""]
    Path(args.doc).write_text("\n".join(lines))
    print("\n".join(lines))
    for o in (obs or {}).values():
        if o["exit"] != 0:
            print("observe stderr:", *o["stderr_tail"], sep="\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

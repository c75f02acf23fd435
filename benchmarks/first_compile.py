"""Wall and CPU time of the first use with an empty numba cache: import, the kernels' compilation, building the
six-bar's observer, a short log.

    python benchmarks/first_compile.py [--repeats 3] [--jobs 1,2] [--groups] [--kernels] [--md docs/first_compile.md]
                                       [--model models/sixbar.toml] [--run tests/data/sixbar_short] [--json]

Each repeat runs a fresh Python process with ``NUMBA_CACHE_DIR`` set to an empty temporary folder (so every kernel
the observer uses is compiled, none loaded) and ``EXUFLEX_COMPILE_JOBS`` set to one of ``--jobs``; the process
calls :func:`exuflex._compile.prepare` (the kernels compiled in that many processes) before ``make_observer``.
Reported per repeat: the wall seconds (what the user waits) and the CPU seconds of the process and of the
compiling subprocesses it started (``resource.getrusage(RUSAGE_CHILDREN)``), per stage where they are the
process's own. After each such process, ``python -m exuflex observe MODEL RUN`` with another empty cache and the
same job count: the first use as a user meets it (:func:`exuflex._compile.start` begins the compilation before the
command's checks, which compile the kinematics group in the command's process). The job counts alternate within each repeat (1, 2, 1, 2, ...), so that a change in the machine's
load hits both alike; the load average is recorded before and after. A last process with the cache left warm
measures what the first use costs once compiled (``warm``).

``--groups``: each kernel group of :mod:`exuflex._compile` compiled alone in a fresh process with an empty cache
(``python -m exuflex._compile GROUP``; a group that calls other groups' kernels with those cached first), and a
process that imports them and sets numba's compiler up (a trivial kernel): the CPU seconds that
:attr:`exuflex._compile.KernelGroup.cost`
and :data:`exuflex._compile.START_COST` hold (the plan's weights).

``--kernels``: ``exuflex observe`` twice more in one process with an empty cache under a listener on numba's
compile events (:data:`KERNELS_CHILD`): each compilation's CPU seconds without those nested in it, per kernel; numba's
own implementations; the same signature compiled twice; and, with the groups' warm-ups switched off, what the
command itself calls (the rest is what the warm-ups compile that it does not need).

``--md``: the figures as a markdown page ('' for none).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, resource, sys, time
w0, t0 = time.perf_counter(), time.process_time()
from exuflex import _compile
from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, estimate, make_observer
from exuflex.runs import held_torques, read_run
w1, t1 = time.perf_counter(), time.process_time()
_compile.prepare()
w2, t2 = time.perf_counter(), time.process_time()
mech = load_mechanism(sys.argv[1]); run = read_run(sys.argv[2])
obs = make_observer(mech, ObserverConfig.for_model(mech))
w3, t3 = time.perf_counter(), time.process_time()
S = run.sensors
estimate(obs, S.t, held_torques(S.select(mech.motor_names).data), S.select(obs.channels).data)
w4, t4 = time.perf_counter(), time.process_time()
ch = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"wall": {"import": w1 - w0, "compile": w2 - w1, "make_observer": w3 - w2, "first_run": w4 - w3,
                           "total": w4 - w0},
                  "cpu": {"import": t1 - t0, "compile": t2 - t1, "make_observer": t3 - t2, "first_run": t4 - t3,
                          "total": t4 - t0},
                  "cpu_subprocesses": ch.ru_utime + ch.ru_stime}))
"""

# ``exuflex observe`` in this process under a listener on numba's compile events: per compilation the dispatcher, its
# signature and its CPU seconds less those of the compilations nested in it (a kernel compiles the kernels it calls
# that are not compiled yet inside its own event); argv[3] "lazy": exuflex._compile's warm-ups switched off, so that
# only what the command calls compiles
KERNELS_CHILD = r"""
import contextlib, io, json, sys, time
from numba.core import event
rows, stack = [], []

def name(d):
    try:
        return f"{d.py_func.__module__}.{d.py_func.__qualname__}"
    except Exception:
        return repr(d)[:80]

class Listener(event.Listener):
    def on_start(self, ev):
        stack.append([time.process_time(), 0.0])

    def on_end(self, ev):
        c0, nested = stack.pop()
        total = time.process_time() - c0
        if stack:
            stack[-1][1] += total
        rows.append({"kernel": name(ev.data.get("dispatcher")), "args": str(ev.data.get("args")), "self_s": total - nested})

event.register("numba:compile", Listener())
from exuflex import _compile
if sys.argv[3] == "lazy":
    _compile.start = lambda *a, **k: None
    _compile.prepare = lambda *a, **k: 0.0
from exuflex.cli import main
c0 = time.process_time()
with contextlib.redirect_stdout(io.StringIO()):
    rc = main(["observe", sys.argv[1], sys.argv[2]])
print(json.dumps({"rc": rc, "cpu_s": time.process_time() - c0, "rows": rows}))
"""

# the groups imported and numba's compiler set up (a trivial kernel compiled): what every compiling process pays once
IMPORT_ONLY = "import numba; from exuflex import _compile; _compile.groups(); numba.njit(lambda x: x + 1)(1)"


def _children_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _run(cmd: list[str], env: dict) -> tuple[float, float, str]:
    """Wall seconds, CPU seconds (the process and everything it waited for) and stdout of ``cmd``."""
    c0, w0 = _children_cpu(), time.perf_counter()
    out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True)
    return time.perf_counter() - w0, _children_cpu() - c0, out.stdout


def _first_use(args, jobs: int, cache: str) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache, EXUFLEX_COMPILE_JOBS=str(jobs), PYTHONPATH=str(ROOT))
    wall, cpu, out = _run([sys.executable, "-c", CHILD, args.model, args.run], env)
    rec = json.loads(out.strip().splitlines()[-1])
    rec.update(jobs=jobs, process_wall_s=wall, process_cpu_s=cpu)
    return rec


def _first_observe(args, jobs: int, cache: str) -> dict:
    """``python -m exuflex observe MODEL RUN`` with the empty cache ``cache``: what the user runs first (the bound,
    the checks and the report included: the compilation starts before the checks)."""
    import re

    env = dict(os.environ, NUMBA_CACHE_DIR=cache, EXUFLEX_COMPILE_JOBS=str(jobs), PYTHONPATH=str(ROOT))
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    c0, w0 = _children_cpu(), time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "exuflex", "observe", args.model, args.run], env=env, cwd=ROOT,
                         check=True, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - w0, _children_cpu() - c0
    m = re.search(r"numba kernels compiled in ([0-9.]+) s", res.stderr)
    return {"jobs": jobs, "wall_s": wall, "cpu_s": cpu, "compile_s": float(m.group(1)) if m else None}


def _groups(repeats: int) -> dict:
    """CPU seconds per group alone (median over ``repeats``), and of a process that compiles nothing."""
    from exuflex import _compile

    needs = {g.name: list(g.needs) for g in _compile.groups()}
    cpu = {n: [] for n in ["(start, nothing compiled)", *needs]}
    for _ in range(repeats):
        for name, runs in cpu.items():
            with tempfile.TemporaryDirectory() as cache:
                env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=str(ROOT))
                if needs.get(name):  # the kernels it calls cached first (its cost is what it adds to them)
                    _run([sys.executable, "-m", "exuflex._compile", *needs[name]], env)
                cmd = ([sys.executable, "-c", IMPORT_ONLY] if name.startswith("(") else
                       [sys.executable, "-m", "exuflex._compile", name])
                runs.append(_run(cmd, env)[1])
    start = statistics.median(cpu.pop("(start, nothing compiled)"))
    return {"start_cpu_s": start, "group_cpu_s": {n: statistics.median(v) - start for n, v in cpu.items()},
            "runs": cpu}


def _kernels(args) -> dict:
    """What compiles in ``exuflex observe`` with an empty cache, in one process (:data:`KERNELS_CHILD`): with the
    kernel groups' warm-ups (what a first use compiles) and without them (what the command calls)."""
    out = {}
    for kind in ("groups", "lazy"):
        print(f"kernels: exuflex observe with an empty cache ({kind}) ...", file=sys.stderr, flush=True)
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, NUMBA_CACHE_DIR=cache, EXUFLEX_COMPILE_JOBS="1", PYTHONPATH=str(ROOT))
            res = subprocess.run([sys.executable, "-c", KERNELS_CHILD, args.model, args.run, kind], env=env,
                                 cwd=ROOT, check=True, capture_output=True, text=True)
        out[kind] = json.loads(res.stdout.strip().splitlines()[-1])
    return out


def _kernels_section(k: dict) -> str:
    """Per kernel, what compiles (:func:`_kernels`), as markdown."""
    import collections

    def per_kernel(rows):
        agg = collections.defaultdict(lambda: {"s": 0.0, "n": 0, "sigs": set()})
        for r in rows:
            a = agg[r["kernel"]]
            a["s"] += r["self_s"]
            a["n"] += 1
            a["sigs"].add(r["args"])
        return agg

    rows = k["groups"]["rows"]
    agg = per_kernel(rows)
    total = sum(r["self_s"] for r in rows)
    own = sum(r["self_s"] for r in rows if r["kernel"].startswith("numba."))
    twice = collections.Counter((r["kernel"], r["args"]) for r in rows)
    again = sum(r["self_s"] for r in rows if twice[(r["kernel"], r["args"])] > 1) * 0.5  # (two of a kind: one spare)
    again_names = sorted({r["kernel"].rsplit(".", 1)[-1] if not r["kernel"].startswith("numba.") else r["kernel"]
                          for r in rows if twice[(r["kernel"], r["args"])] > 1 and r["self_s"] > 0.2})
    lazy = per_kernel(k["lazy"]["rows"])
    lazy_total = sum(r["self_s"] for r in k["lazy"]["rows"])
    unused = {n: a["s"] for n, a in agg.items() if n not in lazy and not n.startswith("numba.")}
    top = sorted(((n, a) for n, a in agg.items() if not n.startswith("numba.")), key=lambda kv: -kv[1]["s"])[:20]
    table = "\n".join(f"| `{n.replace('exuflex.', '')}` | {a['s']:.2f} | {a['n']} | {len(a['sigs'])} |" for n, a in top)
    return (
        "## What compiles, kernel by kernel\n\n"
        "`exuflex observe MODEL RUN` in one process (`EXUFLEX_COMPILE_JOBS=1`) with an empty cache, under a listener "
        "on numba's compile events (`numba.core.event`, `numba:compile`): per compilation its CPU seconds less those "
        "of the compilations nested in it (a kernel compiles the not yet compiled kernels it calls, and numba's own "
        "implementations of the NumPy functions it uses, inside its own event). The command took "
        f"{k['groups']['cpu_s']:.1f} s CPU, of which {total:.1f} s compiling ({len(rows)} compilations). The 20 "
        "largest of the package's kernels (seconds summed over their compilations; a helper compiled into several "
        "kernels, `inline='always'` or `register_jitable`, is typed and lowered in each):\n\n"
        "| kernel | CPU s | compilations | signatures |\n|---|---|---|---|\n" + table + "\n\n"
        f"numba's own implementations (`np.linalg`'s, array constructors, ...): {own:.1f} s over "
        f"{sum(1 for r in rows if r['kernel'].startswith('numba.'))} compilations: they are not cached on their own "
        "(their code is cached inside each kernel that uses them), so every process that compiles such a kernel "
        "compiles them again. The same kernel with the same signature compiled more than once: "
        f"{again:.1f} s spare ({', '.join(again_names) or 'none above 0.2 s'}). "
        f"With the groups' warm-ups switched off (only what the command calls compiles, at its first call): "
        f"{k['lazy']['cpu_s']:.1f} s CPU, {lazy_total:.1f} s compiling; compiled by the warm-ups but not called "
        "by the command: " + (", ".join(f"`{n.replace('exuflex.', '')}` {v:.2f} s" for n, v in
                                        sorted(unused.items(), key=lambda kv: -kv[1]) if v > 0.05) or "nothing")
        + ".\n\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--jobs", default="1,2", help="compiling processes to compare, alternating (e.g. 1,2)")
    ap.add_argument("--groups", action="store_true", help="also the CPU cost of each kernel group alone")
    ap.add_argument("--kernels", action="store_true", help="also what compiles, kernel by kernel (numba's events)")
    ap.add_argument("--group-repeats", type=int, default=None, help="repeats of --groups (default: --repeats)")
    ap.add_argument("--model", default=str(ROOT / "models" / "sixbar.toml"))
    ap.add_argument("--run", default=str(ROOT / "tests" / "data" / "sixbar_short"))
    ap.add_argument("--md", default=str(ROOT / "docs" / "first_compile.md"), help="markdown page ('' for none)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    try:
        jobs = [int(j) for j in args.jobs.split(",")]
        assert jobs and min(jobs) >= 1
    except (ValueError, AssertionError):
        ap.error(f"--jobs: expected process counts >= 1 separated by commas (e.g. 1,2), got {args.jobs!r}")
    out: dict = {"load_before": os.getloadavg(), "started": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                 "runs": []}
    for i in range(args.repeats):
        for j in jobs:
            print(f"repeat {i + 1}/{args.repeats}, {j} process(es): compiling with an empty cache ...",
                  file=sys.stderr, flush=True)
            with tempfile.TemporaryDirectory() as cache:
                out["runs"].append(_first_use(args, j, cache))
                if i == args.repeats - 1 and j == jobs[-1]:
                    out["warm"] = _first_use(args, j, cache)
            print(f"repeat {i + 1}/{args.repeats}, {j} process(es): exuflex observe with an empty cache ...",
                  file=sys.stderr, flush=True)
            with tempfile.TemporaryDirectory() as cache:
                out.setdefault("observe", []).append(_first_observe(args, j, cache))
    if args.groups:
        print("kernel groups alone ...", file=sys.stderr, flush=True)
        out["groups"] = _groups(args.group_repeats or args.repeats)
    if args.kernels:
        out["kernels"] = _kernels(args)
    out["load_after"] = os.getloadavg()
    out["median"] = {j: {"wall_s": statistics.median(r["process_wall_s"] for r in out["runs"] if r["jobs"] == j),
                         "cpu_s": statistics.median(r["process_cpu_s"] for r in out["runs"] if r["jobs"] == j),
                         "observe_wall_s": statistics.median(r["wall_s"] for r in out["observe"] if r["jobs"] == j),
                         "observe_cpu_s": statistics.median(r["cpu_s"] for r in out["observe"] if r["jobs"] == j)}
                     for j in jobs}
    if args.md:
        Path(args.md).write_text(_page(out, argv if argv is not None else sys.argv[1:]))
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    for j, m in out["median"].items():
        print(f"{j} process(es): wall {m['wall_s']:.1f} s, CPU {m['cpu_s']:.1f} s (median of {args.repeats}, "
              f"empty numba cache); exuflex observe: wall {m['observe_wall_s']:.1f} s, CPU {m['observe_cpu_s']:.1f} s")
    print(f"warm cache: wall {out['warm']['process_wall_s']:.1f} s, CPU {out['warm']['process_cpu_s']:.1f} s")
    if "groups" in out:
        g = out["groups"]
        print(f"start without compiling: {g['start_cpu_s']:.1f} s CPU; groups alone: "
              + ", ".join(f"{k} {v:.1f}" for k, v in g["group_cpu_s"].items()))
    print(f"load average (1, 5, 15 min) before {_load(out['load_before'])}, after {_load(out['load_after'])}")
    return 0


def _load(la) -> str:
    return " ".join(f"{x:.2f}" for x in la)


def _page(out: dict, argv: list) -> str:
    """The figures as a markdown page (the machine's load before and after included: the absolute seconds hold
    for that machine at that moment; the ratio between job counts measured in alternation is what carries over)."""
    import numba

    from exuflex.runs import package_versions

    rows = "\n".join(
        f"| {k + 1} | {r['jobs']} | {r['process_wall_s']:.1f} | {r['process_cpu_s']:.1f} | {r['cpu']['total']:.1f} | "
        f"{r['cpu_subprocesses']:.1f} | {r['wall']['compile']:.1f} | {r['wall']['make_observer']:.1f} | "
        f"{r['wall']['first_run']:.1f} |"
        for k, r in enumerate(out["runs"]))
    med = "\n".join(f"| {j} | {m['observe_wall_s']:.1f} | {m['observe_cpu_s']:.1f} | {m['wall_s']:.1f} | "
                    f"{m['cpu_s']:.1f} |" for j, m in out["median"].items())
    obs = "; ".join(f"{r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU ({r['jobs']} processes"
                    + (f", compiling {r['compile_s']:.0f} s" if r["compile_s"] is not None else "") + ")"
                    for r in out["observe"])
    w = out["warm"]
    versions = ", ".join(f"{k} {v}" for k, v in {**package_versions(), "numba": numba.__version__,
                                                  "python": platform.python_version()}.items())
    page = (
        "# The first use with an empty compile cache\n\n"
        f"Written by `{' '.join(['python benchmarks/first_compile.py', *argv])}` (see its docstring), started "
        f"{out['started']} on a machine with {os.cpu_count()} cores. Load average (1, 5, 15 min) before: "
        f"{_load(out['load_before'])}, after: {_load(out['load_after'])} (other jobs share the cores: a load above "
        "the benchmark's own processes slows the parallel runs more).\n\n"
        "The first use as a user meets it: `python -m exuflex observe MODEL RUN` in a fresh process with an empty "
        "`NUMBA_CACHE_DIR` (the kernels compiled in the number of processes given by `EXUFLEX_COMPILE_JOBS`, begun "
        "by `exuflex._compile.start` before the command's checks, which compile the kinematics group in the "
        "command's process, and finished by `exuflex._compile.prepare`; issue 29's aim: at most 30 s on 2 cores). "
        "Beside it the library's part alone: a fresh "
        "process with an empty cache imports exuflex, compiles the kernels "
        "(`exuflex._compile.prepare`, in the number of processes given by `EXUFLEX_COMPILE_JOBS`), builds the "
        "six-bar's observer and filters a short log. Wall: what the user waits; CPU: the process and the "
        "compiling subprocesses it started. The same work takes the same CPU seconds on a steady machine: a run "
        "with markedly more ran while the machine was slowed (other jobs, clock drift), and its wall time with "
        "it.\n\n"
        "| processes | `exuflex observe`: median wall s | median CPU s | library part: median wall s | "
        "median CPU s |\n|---|---|---|---|---|\n" + med + "\n\n"
        f"`exuflex observe` runs: {obs}.\n\n"
        "The library part's runs:\n\n"
        "| run | processes | wall s | CPU s | of which main | of which subprocesses | compile wall s | "
        "make_observer wall s | first run wall s |\n|---|---|---|---|---|---|---|---|---|\n" + rows + "\n\n"
        f"The same with the cache left warm (kernels loaded, none compiled): wall {w['process_wall_s']:.1f} s, "
        f"CPU {w['process_cpu_s']:.1f} s, of which `prepare` (the cache check; no process started) "
        f"{w['wall']['compile']:.3f} s wall.\n\n"
    )
    if "groups" in out:
        g = out["groups"]
        page += (
            "Kernel groups compiled alone (`python -m exuflex._compile GROUP`, empty cache but for the groups it "
            "calls), CPU seconds beyond a process that imports them and compiles a trivial kernel "
            f"({g['start_cpu_s']:.1f} s; `START_COST`): "
            + ", ".join(f"{k} {v:.1f}" for k, v in g["group_cpu_s"].items())
            + " (the weights `exuflex._compile.plan` shares the groups out by).\n\n"
        )
    if "kernels" in out:
        page += _kernels_section(out["kernels"])
    return page + f"Versions: {versions}.\n"


if __name__ == "__main__":
    raise SystemExit(main())

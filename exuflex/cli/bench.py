"""``exuflex bench [MODEL] [--json] [--quick]``: observer speed (reduced vs full order), basis build, truth.

Measures in one run on one core (see :mod:`exuflex.bench`): the reduced and the full-order observer on
the paper's manoeuvre at the paper's rates (RK4 0.1 ms, updates at 500 Hz) as wall time, real-time
factor (simulated time / wall; the reduced observer's over the whole log as ``exuflex observe`` runs it,
and ``online``, sample by sample as a real-time loop calls it) and per-update latency p50/p99; the
reduction basis build time; the Exudyn ground-truth time. ``--quick``: a 0.2 s manoeuvre. With ``--json`` one JSON object is printed::

    {"reduced": {"wall_s", "real_time_factor", "p50_update_ms", "p99_update_ms", "online": {...}, ...},
     "full": {"wall_s", "real_time_factor", ...}, "speedup_reduced_vs_full": float,
     "basis_s": float, "truth_s": float, ...}
"""

from __future__ import annotations

import argparse
import sys

from ..runs import dump_json
from .args import positive_float, positive_int
from .args import seed as seed_type

__all__ = ["add_parser", "run"]


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "bench",
        help="time the reduced and full-order observers, the basis build and the ground truth",
        description=__doc__.split("\n")[0],
    )
    p.add_argument("model", nargs="?", default=None, help="model file (default: models/sixbar.toml)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.add_argument("--quick", action="store_true", help="a 0.2 s manoeuvre (seconds instead of minutes)")
    p.add_argument("--duration", type=positive_float, default=None, help="simulated time (s); overrides --quick")
    p.add_argument("--no-full", action="store_true", help="skip the (slow) full-order observer")
    p.add_argument("--no-reference", action="store_true",
                   help="skip the comparison with the reduced observer's exact reference (method rk4)")
    p.add_argument("--seed", type=seed_type, default=1, help="measurement noise seed (default 1)")
    p.add_argument("--repeat", type=positive_int, default=5,
                   help="times the reduced observer filters the log; the median run is reported (default 5)")
    p.set_defaults(func=run)
    return p


def _fmt(r: dict) -> str:
    lines = [
        (
            f"exuflex bench: {r['model']}, {r['duration_s']:g} s manoeuvre, RK4 {r['h_s'] * 1e3:g} ms, "
            f"updates every {r['dt_s'] * 1e3:g} ms, CPU {r['machine']['cpu_pinned']} "
            f"(load {r['machine']['load_average_1min']:.1f} on {r['machine']['cpus']} cores)"
        ),
    ]
    for name in ("reduced", "full"):
        o = r.get(name)
        if not o:
            continue
        lines.append(
            f"  {name:8s} observer ({o['n_states']} states): wall {o['wall_s']:8.2f} s  "
            f"real-time x{o['real_time_factor']:7.2f}  update p50 {o['p50_update_ms']:7.3f} ms  "
            f"p99 {o['p99_update_ms']:7.3f} ms  q RMS error {o['q_rms_error_rad']:.2e} rad"
            + (f"  FAILED: {o['failed']}" if o.get("failed") else "")
        )
        if o.get("repeats", 1) > 1:
            walls = ", ".join(f"{w:.3f}" for w in o["wall_s_runs"])
            lines.append(f"  {'':8s} median of {o['repeats']} runs; walls {walls} s "
                         f"(best: real-time x{o['real_time_factor_best']:.2f})")
        on = o.get("online")
        if on:
            walls = ", ".join(f"{w:.3f}" for w in on["wall_s_runs"])
            lines.append(f"  {'':8s} online (ekf.step per sample, the latencies above): wall {on['wall_s']:.3f} s  "
                         f"real-time x{on['real_time_factor']:.2f}; walls {walls} s")
    ref = r.get("reference")
    if ref:
        w = ref["worst"]
        lines.append(
            f"  reduced vs its reference path ({ref['method']}): RMS difference / RMS estimation error at most "
            f"{ref['worst_ratio']:.3f} ({w}: {ref['rms_difference'][w]:.2e} vs {ref['rms_error'][w]:.2e})"
        )
    if r.get("speedup_reduced_vs_full"):
        lines.append(f"  speed-up reduced vs full: {r['speedup_reduced_vs_full']:.1f}x")
    lines.append(f"  reduction basis: {r['basis_s']:.3f} s")
    lines.append(f"  Exudyn truth:    {r['truth_s']:.2f} s  (real-time x{r['truth_real_time_factor']:.2f})")
    return "\n".join(lines)


def run(args) -> int:
    from ..bench import DEFAULT_MODEL, run_bench

    res = run_bench(
        args.model or DEFAULT_MODEL,
        quick=args.quick,
        duration=args.duration,
        seed=args.seed,
        full=not args.no_full,
        reference=not args.no_reference,
        repeat=args.repeat,
        progress=None
        if args.json or not sys.stderr.isatty()
        else lambda m: print(f"... {m}", file=sys.stderr),
    )
    print(dump_json(res, indent=2) if args.json else _fmt(res))
    return 0

"""Where the observer's time goes: the real-time factor and its split per sample, measured in one run.

    python benchmarks/observer_speed.py [--model models/sixbar.toml] [--run tests/data/sixbar_erls_3s] [--repeats 7]
                                        [--json] [--md docs/observer_speed.md]

Filters the run's log with default settings ``--repeats`` times and reports the median real-time factor, then
filters it once more with timers around the parts of a sample (each timer costs a fraction of a microsecond):

- the compiled sample loop (:func:`exuflex.observer.expansion.cached_samples`): per sample the model's interval
  (held step and step Jacobian), the measurement rows, the Kalman algebra and the sensor-fault windows;
- configuration evaluations (the held model's refreshes, with their spectrum and error estimates);
- step-map rebuilds (the maps and the replaced map's error);
- the rest: the Python around those calls (renewing the loop's arrays, the NIS test and bookkeeping after each
  stretch of samples, the few samples that go through ``MultirateEKF.step``, recording).

The split says what a faster sample would have to remove: the real-time factor with the rest taken away is
printed as the ceiling of the present arithmetic. Figures are ratios and fractions of one run (the machine's
speed drifts); the absolute factor holds for this machine at this moment only. The figures go to the markdown page
``--md`` with the machine's load average at the end of the run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


class _Timer:
    """Wraps ``owner.name`` (a function or method) and accumulates its wall time and calls."""

    def __init__(self, owner, name: str):
        self.owner, self.name, self.f = owner, name, getattr(owner, name)
        self.total, self.calls = 0.0, 0
        f, me = self.f, self

        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                me.total += time.perf_counter() - t0
                me.calls += 1

        setattr(owner, name, timed)

    def restore(self) -> None:
        setattr(self.owner, self.name, self.f)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "sixbar.toml"))
    ap.add_argument("--run", default=str(ROOT / "tests" / "data" / "sixbar_erls_3s"), help="a run folder")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--md", default=str(ROOT / "docs" / "observer_speed.md"), help="markdown page ('' for none)")
    args = ap.parse_args(argv)

    from exuflex.mechanism import load_mechanism
    from exuflex.observer import reduced
    from exuflex.observer.session import ObserverConfig, _hold, estimate, make_observer
    from exuflex.runs import read_run

    mech = load_mechanism(args.model)
    run = read_run(args.run)
    obs = make_observer(mech, ObserverConfig.for_model(mech))
    S = run.sensors
    U = _hold(S.select(mech.motor_names).data)
    Y = S.select(obs.channels).data
    estimate(obs, S.t, U, Y)  # compile and warm
    rtf = [estimate(obs, S.t, U, Y).real_time_factor for _ in range(args.repeats)]
    n = len(S.t)
    span = float(S.t[-1] - S.t[0])

    timers = {
        "compiled sample loop": _Timer(obs.ekf, "_loop"),
        "configuration evaluations": _Timer(reduced.ReducedObserverModel, "_refresh"),
        "step maps": _Timer(reduced.ReducedObserverModel, "_maps"),
        "step-map errors": _Timer(reduced.ReducedObserverModel, "_map_error"),
    }
    t0 = time.perf_counter()
    obs.ekf.run(S.t, U, Y)
    wall = time.perf_counter() - t0
    for t in timers.values():
        t.restore()
    parts = {k: t.total for k, t in timers.items()}
    parts["step-map rebuilds"] = parts.pop("step maps") + parts.pop("step-map errors")
    timers["step-map rebuilds"] = timers.pop("step maps")
    parts["the rest (Python between the calls)"] = wall - sum(parts.values())
    us = {k: 1e6 * v / n for k, v in parts.items()}
    ceiling = span / (wall - parts["the rest (Python between the calls)"])
    out = {"model": mech.name, "samples": n, "span_s": span, "median_real_time_factor": statistics.median(rtf),
           "real_time_factors": rtf, "timed_run_us_per_sample": 1e6 * wall / n, "us_per_sample": us,
           "fraction": {k: v / wall for k, v in parts.items()},
           "calls": {k: t.calls for k, t in timers.items()},
           "real_time_factor_without_the_rest": ceiling}
    out["load_average_1min"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    if args.md:
        Path(args.md).write_text(_page(out, argv if argv is not None else sys.argv[1:], args.repeats))
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    print(f"{mech.name}: {n} samples over {span:.3g} s; median real-time factor {out['median_real_time_factor']:.1f} "
          f"({args.repeats} runs: {', '.join(f'{r:.1f}' for r in rtf)})")
    print(f"timed run: {out['timed_run_us_per_sample']:.1f} us per sample")
    for k, v in us.items():
        c = out["calls"].get(k)
        print(f"  {k:40s} {v:7.1f} us  {100 * out['fraction'][k]:5.1f} %" + (f"  ({c} calls)" if c is not None else ""))
    print(f"real-time factor with the rest removed: {ceiling:.1f}")
    return 0


def _page(out: dict, argv: list, repeats: int) -> str:
    """The measured figures as a markdown page (the machine's load at the end of the run included: the absolute
    factor holds for that machine at that moment only; the split into parts is what carries over)."""
    from exuflex.runs import package_versions

    rows = "\n".join(f"| {k} | {v:.1f} | {100 * out['fraction'][k]:.1f} % | {out['calls'].get(k, '')} |"
                      for k, v in out["us_per_sample"].items())
    load = out["load_average_1min"]
    versions = ", ".join(f"{k} {v}" for k, v in {**package_versions(), "python": platform.python_version()}.items())
    return (
        "# Where the observer's time goes\n\n"
        f"Written by `{' '.join(['python benchmarks/observer_speed.py', *argv])}` (see its docstring).\n\n"
        f"Model {out['model']}, {out['samples']} samples over {out['span_s']:.3g} s, default settings: median real-time "
        f"factor **{out['median_real_time_factor']:.1f}** over {repeats} runs "
        f"({', '.join(f'{r:.1f}' for r in out['real_time_factors'])}); the configuration evaluated "
        f"{out['calls']['configuration evaluations']} times and the step map rebuilt "
        f"{out['calls']['step-map rebuilds']} times per run. "
        + (f"Load average over the last minute at the end: {load:.2f} (2 cores).\n\n" if load is not None else "\n\n")
        + f"One more run with timers around the parts of a sample: {out['timed_run_us_per_sample']:.1f} us per sample.\n\n"
        "| part | us per sample | share | calls |\n|---|---|---|---|\n" + rows + "\n\n"
        f"Real-time factor with the rest taken away (the ceiling of the present arithmetic): "
        f"{out['real_time_factor_without_the_rest']:.1f}.\n\n"
        f"Versions: {versions}.\n"
    )


if __name__ == "__main__":
    raise SystemExit(main())

"""A sensor fault present from the first sample, against the same fault appearing mid-run; writes
``docs/offset_from_start.md``.

The log: the six-bar's 3 s ERLS run with truth (``tests/data/sixbar_erls_3s``, seed 1). A fault is added to one
encoder channel's measured values, either from ``t = 0`` or from ``t = 1 s``: an offset (``y + b``) or a gain
error (``(1 + g) y``). The default observer (``ObserverConfig()``: per-channel gating and fault reports on, fault
isolation off) runs on each log (and, in the last two cases, the same observer with the relative encoder
``q3rel`` added: on the six-bar's parallelogram ``q3rel = q3 - q1 - pi``, a second reading of ``q1``; and with a
bias state on ``q1``, :mod:`exuflex.observer.bias`, prior standard deviation 0.1 rad); reported are the fault reports of ``ChannelMonitor`` (channel, kind, time
found), the NIS flag, and the RMS error of every joint angle over the scored interval as a multiple of its
estimation bound.

Usage: ``python benchmarks/offset_from_start.py [--doc docs/offset_from_start.md]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
from _pages import publish  # (a script: its folder is on the path)

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "tests" / "data" / "sixbar_erls_3s"
MODEL = ROOT / "models" / "sixbar.toml"

REDUNDANT = ("q1", "q2", "q3", "q3rel", "c1", "c2", "c4")  # q3rel = q3 - q1 - pi on the parallelogram: q1 twice

CASES = [  # (label, channel, from time, fault, observer channels (None: the default set), options)
    ("clean", None, 0.0, None, None, {}),
    ("q1 offset 0.06 rad from 1 s", "q1", 1.0, ("offset", 0.06), None, {}),
    ("q1 offset 0.06 rad from 0 s", "q1", 0.0, ("offset", 0.06), None, {}),
    ("q1 offset 0.2 rad from 0 s", "q1", 0.0, ("offset", 0.2), None, {}),
    ("q2 offset 0.06 rad from 0 s", "q2", 0.0, ("offset", 0.06), None, {}),
    ("q1 gain +5 % from 1 s", "q1", 1.0, ("gain", 0.05), None, {}),
    ("q1 gain +5 % from 0 s", "q1", 0.0, ("gain", 0.05), None, {}),
    ("clean, channels + q3rel", None, 0.0, None, REDUNDANT, {}),
    ("q1 offset 0.06 rad from 0 s, channels + q3rel", "q1", 0.0, ("offset", 0.06), REDUNDANT, {}),
    ("q1 offset 0.06 rad from 0 s, channels + q3rel, --isolate-faults", "q1", 0.0, ("offset", 0.06), REDUNDANT,
     {"isolate": True}),
    ("q1 offset 0.06 rad from 0 s, bias state on q1", "q1", 0.0, ("offset", 0.06), None, {"bias": "q1"}),
    ("clean, channels + q3rel, bias state on q1", None, 0.0, None, REDUNDANT, {"bias": "q1"}),
    ("q1 offset 0.06 rad from 0 s, channels + q3rel, bias state on q1", "q1", 0.0, ("offset", 0.06), REDUNDANT,
     {"bias": "q1"}),
]
BIAS0_STD = 0.1  # rad: the bias state's prior standard deviation


def faulty(run, channel: str | None, t0: float, fault) -> object:
    """``run`` with ``fault`` (``("offset", b)`` or ``("gain", g)``) on ``channel`` from time ``t0``."""
    if channel is None:
        return run
    s = run.sensors
    data = s.data.copy()
    j = s.names.index(channel)
    on = s.t >= t0
    kind, v = fault
    data[on, j] = data[on, j] + v if kind == "offset" else data[on, j] * (1.0 + v)
    return dataclasses.replace(run, sensors=dataclasses.replace(s, data=data))


def main(argv=None) -> int:
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.bias import with_bias_states
    from exuflex.observer.session import ObserverConfig, make_observer
    from exuflex.scoring.run import observe_run
    from exuflex.runs import read_run

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--doc", default=str(ROOT / "docs" / "offset_from_start.md"))
    args = ap.parse_args(argv)
    mech = load_mechanism(MODEL)
    run = read_run(RUN)
    rows = []
    for label, ch, t0, fault, channels, opt in CASES:
        cfg = ObserverConfig(channels=channels, fault_isolation=opt.get("isolate", False))
        obs = make_observer(mech, cfg)
        if "bias" in opt:
            obs = with_bias_states(obs, [opt["bias"]], BIAS0_STD)
        out = observe_run(mech, faulty(run, ch, t0, fault), cfg, observer=obs)
        res = out.estimate.result
        s = out.summary
        found = [f for f in s["channel_faults"]]
        ratio = s["ratio_to_bound"]
        mean_err = {q: float(np.mean(out.estimate.physical[q][out.estimate.physical.t >= s["metrics_from_s"]]
                                 - np.interp(out.estimate.physical.t[out.estimate.physical.t >= s["metrics_from_s"]],
                                             run.truth.t, run.truth[q])))
                for q in ("q1", "q2", "q3")}
        bias = None
        if "bias" in opt:
            i = obs.ekf.model.i_bias[opt["bias"]]
            bias = (float(res.x_hat[-1, i]), float(np.sqrt(res.P_diag[-1, i])))
        rows.append({"case": label, "faults": found, "nis_flagged_at": s["nis_flagged_at"], "bias_end": bias,
                     "flagged_intervals": s["flagged_intervals"], "ratio": {q: ratio[q] for q in ("q1", "q2", "q3")},
                     "mean_error": mean_err, "nis_mean": s["nis_mean"], "n_rejected": s["n_rejected"]})
        print(json.dumps(rows[-1], default=float))

    def fmt_faults(fs):
        if not fs:
            return "none"
        return "; ".join(f"{f['channel']} {f['kind']} at {f['start']:.3f} s" + (
            f" (cleared {f['end']:.3f} s)" if f["end"] is not None else "") for f in fs[:4]) + (
            f"; {len(fs) - 4} more" if len(fs) > 4 else "")

    lines = [
        "# A sensor fault present from the first sample",
        "",
        "Written by `python benchmarks/offset_from_start.py` (see its docstring): the six-bar's 3 s ERLS run with "
        "truth, a fault added to one encoder from 0 s or from 1 s, the default observer.",
        "",
        "| case | faults reported (channel, kind, time found) | NIS flagged intervals (s) | q1 / q2 / q3 RMS error "
        "/ bound | mean error q1 / q2 / q3 (rad) | bias state at 3 s (rad) |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        iv = ", ".join(f"{a:.2f}-{b:.2f}" if b is not None else f"{a:.2f}-" for a, b in r["flagged_intervals"]) \
            or "none"
        lines.append(f"| {r['case']} | {fmt_faults(r['faults'])} | {iv} | "
                     + " / ".join(f"{r['ratio'][q]:.1f}" for q in ("q1", "q2", "q3")) + " | "
                     + " / ".join(f"{r['mean_error'][q]:+.4f}" for q in ("q1", "q2", "q3")) + " | "
                     + (f"{r['bias_end'][0]:+.5f} +- {r['bias_end'][1]:.5f}" if r["bias_end"] else "-") + " |")
    lines += ["", ""]
    publish("\n".join(lines), args.doc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

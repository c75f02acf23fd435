"""The interior modes' filter requirement checked against the observer: predicted and measured on noiseless logs,
and what the modes it adds cost. Writes docs/filter_requirement.md.

    python benchmarks/filter_requirement.py [--models steel_arm,serial_arm,...] [--truth-dir DIR] [--repeats 5]
        [--out docs/filter_requirement.md] [--json F]

For every model (the gallery's files with a manoeuvre and the fresh mechanisms in benchmarks/models/ written for
the criterion) the automatic interior modes without the filter requirement (``bias_max=0``: the band's thresholds
and the channels' truncated output) and with it (the default), and the requirement's figure for each
(:mod:`exuflex.reduction.truncation`, "What the filter makes of it"). Where the two choices differ:

- the full-order ERLS model simulated without noise (the truth's input, no noise in the log, no quantisation);
  the observer, with each choice, filtering that log: its RMS error over the bound is the part of the ratio the
  reduction makes (a noisy log adds the bound's own variance: RMS/bound about sqrt(1 + this^2));
- the filter's CPU time on that log with each choice (no bound), in pairs alternating, the median of the
  ratios.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
from _pages import publish  # (a script: its folder is on the path)

from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism
from exuflex.reduction import CraigBampton, PathSamples
from exuflex.reduction.truncation import BIAS_MAX, PlannedInput

ROOT = Path(__file__).resolve().parents[1]
FRESH = ["benchmarks/models/steel_arm.toml", "benchmarks/models/single_link_16.toml"]
# a relative-coordinate arm whose innovations the channels' rho does not see (the innovations' requirement)
EVIDENCE = ["benchmarks/models/long_two_link.toml"]


def _path(name: str) -> Path:
    p = Path(name)
    if p.suffix == ".toml":
        return p if p.is_absolute() else ROOT / p
    return ROOT / "models" / f"{name}.toml"


def models() -> list[str]:
    out = [p.stem for p in sorted((ROOT / "models").glob("*.toml")) if load_mechanism(p).manoeuvre is not None]
    return out + FRESH + EVIDENCE


def noiseless_truth(path: Path, out: Path) -> Path:
    """The full-order ERLS model's run of the file's manoeuvre, its log without noise or quantisation (kept)."""
    from exuflex.measure import measure
    from exuflex.runs import write_run
    from exuflex.truth.engines import plan_drive, simulate

    if (out / "sensors.csv").is_file():
        return out
    mech = load_mechanism(path)
    d = mech.manoeuvre.duration
    drive = plan_drive(mech, d, 1e-4, None)
    rec = simulate(mech, drive, "erls", d, 1e-4, erls_step="auto")  # the truth step rule, as `exuflex simulate`
    meas = measure(mech, rec.clean, rec.torque_t, rec.torques, seed=1, noise=False, quantisation=False, t_end=d)
    write_run(out, meas.signals, rec.truth, {"engine": "erls", "mechanism": mech.name, "seed": 1,
                                             "settings": {"duration_s": d, "noise": False}}, motors=mech.motor_names)
    return out


def figures(path: Path) -> dict:
    """Both choices and the requirement's figure (per estimated quantity, sqrt: in units of the bound) for each."""
    mech = load_mechanism(path)
    model = ErlsModel(mech)
    old = CraigBampton(model, bias_max=0)
    new = CraigBampton(model)
    every = CraigBampton(model, n_interior=0, truncation_max=0)
    every.set_interior(len(every.order))
    planned = PlannedInput.of(mech)
    ps = PathSamples(every, new.path_q, planned)
    out = {"model": mech.name, "file": str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path),
           "bias_max": BIAS_MAX, "choices": {}}
    for label, cb in (("without", old), ("with", new)):
        # the dynamic modes the choice keeps (indices of the model's interior modes, ascending frequency); the
        # static corrections that follow them re-base modes not kept (their columns are not those modes)
        dyn = np.sort(cb.order[: (cb.truncation.get("dynamic") or {}).get("n_interior", cb.n_interior - cb.n_static)])
        b = ps.bias(dyn)
        final = ps.bias_of_basis(lambda q, cb=cb: cb.at(q).H)
        # the innovations' figure of the final basis: whitened mean square summed over the channels, over the samples
        nu = float(np.mean([fs.bias_of(cb.at(t.q).H)[2].sum() for t, fs in zip(ps.truncation, ps.filters)]))
        out["choices"][label] = {"n_interior": int(len(dyn)), "n_static": int(cb.n_static),
                                 "kept_hz": [float(f) for f in every.interior_frequencies_hz[dyn]],
                                 "kept": [int(i) for i in dyn],
                                 "predicted": {k: float(np.sqrt(v)) for k, v in zip(planned.quantities, b)},
                                 "met": bool(b.max() <= BIAS_MAX), "n_total": int(cb.n_interior),
                                 "final": {k: float(np.sqrt(v)) for k, v in zip(planned.quantities, final)},
                                 "final_met": bool(final.max() <= BIAS_MAX), "innovation": nu,
                                 "n_channels": len(planned.channels)}
    out["_cbs"] = (old, new)
    return out


def observe(path: Path, run_dir: Path, cbs, repeats: int) -> dict:
    """The observer with each basis on the noiseless log: RMS error over the bound, the NIS per channel (without
    noise: the innovations the reduction leaves, the prediction's figure over the channel count), and the filter's
    CPU time (where the bases differ)."""
    from exuflex.observer.session import ObserverConfig, make_observer
    from exuflex.runs import read_run
    from exuflex.scoring.run import observe_run

    mech = load_mechanism(path)
    run = read_run(run_dir)
    config = ObserverConfig.for_model(mech)
    res = {}
    for label, cb in zip(("without", "with"), cbs):
        if cbs[0] is cbs[1] and label == "without":
            continue
        o = observe_run(mech, run, config, observer=make_observer(mech, config, cb=cb), keep="summary")
        res[label] = {k: float(v) for k, v in o.summary["ratio_to_bound"].items()}
        res[label + "_nis"] = float(o.summary["nis_mean"] / o.summary["nis_expected"])
    ratios = []
    for _ in range(repeats if cbs[0] is not cbs[1] else 0):
        t = []
        for cb in cbs:
            obs = make_observer(mech, config, cb=cb)
            c0 = time.process_time()
            observe_run(mech, run, config, observer=obs, with_bound=False, keep="summary")
            t.append(time.process_time() - c0)
        ratios.append(t[1] / t[0])
    if ratios:
        res["cpu_ratio"] = float(np.median(ratios))
        res["cpu_ratios"] = [float(r) for r in ratios]
    return res


def page(rows: list[dict], args: str) -> str:
    qs = lambda d: ", ".join(f"{k} {v:.2f}" for k, v in d.items())
    lines = [
        "# The interior modes' filter requirement, checked",
        "",
        f"Written by `python benchmarks/filter_requirement.py{args}` (the command regenerates this page). The",
        "derivation is in `docs/reduction.md` (\"What the filter makes of it\", the docstring of",
        "`exuflex/reduction/truncation.py`).",
        "",
        "For every model: the automatic interior modes without the filter requirement (the band's thresholds and the",
        "channels' truncated output, `CraigBampton(..., bias_max=0)`) and with it (the default), and the",
        "requirement's figure for each: per estimated quantity the steady filter's RMS error on the linearised full",
        ("model under the manoeuvre, in units of its bound (the square root of the figure limited to "
        f"{BIAS_MAX:g}, i.e. {np.sqrt(BIAS_MAX):.2f}), with the choice's dynamic modes alone (what the criterion "
         "ranks) and with the final basis the observer uses: those modes and the static corrections that follow "
         "them ({doc}`/theory/reduction`; `CraigBampton.truncation['bias']`, on which the count is judged)."),
        "Innovations: the steady filter's whitened innovations on the same linearised run, their mean square",
        "per channel (the figure summed over the channels is limited to 0.1: `INNOVATION_MAX`), what a noiseless",
        "log adds to the NIS per channel.",
        "Where the choices differ (and for the models named by `--observe`), the observer filters the full-order",
        "ERLS model's log without noise (no quantisation): its RMS error over the bound (this run's bound, along its",
        "truth) is the part of the acceptance ratio the reduction makes; with noise the ratio is about sqrt(1 +",
        "this^2); its NIS per channel is the innovations' part (with noise about 1 + this). CPU: the filter's time on",
        "that log with the default choice over the other (no bound), median of the pairs' ratios.",
        "",
        ("| model | choice | interior (Hz at q*) + static corrections | predicted, dynamic modes: RMS / bound | "
         "predicted, final basis | innovations per channel, predicted | measured without noise: RMS / bound | "
         "NIS per channel, measured without noise | CPU |"),
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        for label in ("without", "with"):
            c = r["choices"][label]
            obs = r.get("observed", {})
            meas = qs(obs[label]) if label in obs else "-"
            nis = f"{obs[label + '_nis']:.3f}" if label + "_nis" in obs else "-"
            nu = f"{c['innovation'] / c['n_channels']:.3f}"
            cpu = (f"{obs['cpu_ratio']:.2f}x ({', '.join(f'{x:.2f}' for x in obs['cpu_ratios'])})"
                   if label == "with" and "cpu_ratio" in obs else "-")
            hz = ", ".join(f"{f:.0f}" for f in c["kept_hz"]) or "-"
            lines.append(f"| {r['model']} | {label} | {c['n_interior']} ({hz}) + {c['n_static']} | "
                         f"{qs(c['predicted'])}{'' if c['met'] else ' (above the limit)'} | {qs(c['final'])}"
                         f"{'' if c['final_met'] else ' (above the limit)'} | {nu} | {meas} | {nis} | {cpu} |")
    above = []
    for r in rows:
        c, obs = r["choices"]["with"], r.get("observed", {}).get("with", {})
        for k, v in obs.items():
            if k in c["final"] and v > c["final"][k] + 0.2:
                above.append(f"{r['model']} {k} {v:.2f} (predicted {c['final'][k]:.2f})")
    if above:
        lines += ["", "Measured on the noiseless log more than 0.2 above the final basis' prediction (default choice): "
                  + "; ".join(above) + ". The prediction is the linearised model's (at rest at each configuration, "
                  "the velocity forces left out). Where the observer with every interior mode "
                  "(`CraigBampton(model, n_interior=N)`, N the slave count) leaves the same figure, it is not the "
                  "truncation."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default=None, help="comma-separated model names or files (default: the gallery with "
                    "a manoeuvre and " + ", ".join(FRESH) + ")")
    ap.add_argument("--truth-dir", default=None, help="keep the noiseless truths here (reused when there)")
    ap.add_argument("--repeats", type=int, default=5, help="CPU-time pairs per model (default 5)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "filter_requirement.md"))
    ap.add_argument("--json", default="", help="JSON output ('' for none)")
    ap.add_argument("--observe", default="", help="comma-separated models (file stems) observed on their noiseless "
                    "log even where both choices are the same")
    a = ap.parse_args(argv)
    observe_also = {Path(m).stem for m in a.observe.split(",") if m}
    import tempfile

    keep = tempfile.TemporaryDirectory() if a.truth_dir is None else None
    tdir = Path(a.truth_dir or keep.name)
    rows = []
    for name in (a.models.split(",") if a.models else models()):
        path = _path(name)
        r = figures(path)
        old, new = r.pop("_cbs")
        c0, c1 = r["choices"]["without"], r["choices"]["with"]
        differ = (c0["kept"], c0["n_total"]) != (c1["kept"], c1["n_total"])
        if differ or path.stem in observe_also:
            run_dir = noiseless_truth(path, tdir / "erls_noiseless" / path.stem)
            r["observed"] = observe(path, run_dir, (old, new) if differ else (new, new), a.repeats)
        rows.append(r)
        print(json.dumps(r), flush=True)
    args = ((f" --models {a.models}" if a.models else "") + (f" --repeats {a.repeats}" if a.repeats != 5 else "")
            + (f" --observe {a.observe}" if a.observe else ""))
    publish(page(rows, args) + "\n", a.out)
    if a.json:
        from exuflex.runs import package_versions

        Path(a.json).write_text(json.dumps({"rows": rows, "versions": {**package_versions(),
                                            "python": platform.python_version()}}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

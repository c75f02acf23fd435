"""The whole chain on every mechanism of the gallery: truth, measured log, observer, errors against its bound.

    python benchmarks/gallery.py [--models serial_arm,fivebar] [--seeds 1,2,3] [--engine exudyn]
                                 [--no-reference] [--json docs/gallery.json] [--md docs/gallery.md]
    python benchmarks/gallery.py --acceptance --truth-dir DIR [--seeds 1-10] [--method rk4] [--json J]
                                 [--md docs/acceptance.md]

For each model file in ``models/`` with a manoeuvre and each seed:

1. the run folder of ``exuflex simulate MODEL --seed S`` (its library entry point,
   :func:`exuflex.truth.simulate_run`; Exudyn truth by default), written to a temporary folder;
2. the observer with default settings on that log (:func:`exuflex.scoring.run.observe_run`, what
   ``exuflex observe MODEL RUN`` runs): RMS error of every physical estimate after the start-up, divided by the
   observer's own bound (``bound_rms``: the posterior Cramer-Rao bound along the truth, its standard deviations'
   RMS over the scored samples, from the start-up to the log's end, :func:`exuflex.scoring.bound.bound_track`); the time-averaged NIS against the mean number of channels per update (its expectation);
   the filter's flags (NIS divergence test, non-finite state);
3. the same log through the exact reference step map (:data:`REFERENCE`: the reduced model integrated by RK4
   over every interval, no held matrices): the default path's RMS error divided by the reference's, per quantity.

The acceptance of issue 15 (:func:`acceptance`): every RMS error within 1.5x its bound, the NIS within 10 % of
the channel count, no flag, and the default path within 10 % of the reference. The script prints a table and
writes the measured figures as JSON and as the markdown page ``docs/gallery.md``.

``--acceptance``: issue 28's acceptance (:data:`ACCEPTANCE`) on both truths, the full-order ERLS engine and
Exudyn, beside the consistent reference (:data:`CONSISTENT`: the observer's own reduced model generating the data),
without the reference path, written to ``docs/acceptance.md``:

- per run: every RMS error within 1.25x the bound on the ERLS truth and 1.5x on the Exudyn truth, the NIS within
  10 % of the channel count, no flag;
- over the seeds (:func:`seed_statistics`): each quantity's RMS / bound and the NIS / channels as the mean and the
  90th percentile over the seeds, beside the consistent truth's, and the paired excess over it (per seed the
  difference of the two runs' ratios, which share that seed's noise): a model error shows as an excess above its
  standard error, a consistent filter's scatter as a spread the consistent truth has too. A per-run worst over
  about ten quantities scatters for a consistent filter; its mean over many seeds does not.

Each model's truth is simulated once per engine and measured with every seed (:func:`truth_runs`: its motion does
not depend on the seed). ``--truth-dir DIR`` keeps the truth runs (``DIR/<engine>/<model>/s<seed>``) and reuses
those already there, so that observer variants are scored on the same truths; ``--method rk4`` scores the
observer with the exact step map.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import tempfile
import time
import tomllib
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
SEEDS = (1, 2, 3)

REFERENCE = {"method": "rk4"}
"""The exact reference path's observer settings (ObserverConfig fields): the step map by RK4 every interval."""

RATIO_MAX = 1.5  # RMS error after the start-up / the observer's bound
ACCEPTANCE = {"erls": 1.25, "exudyn": 1.5}
"""Issue 28's largest RMS error / bound per truth engine (``--acceptance``)."""
CONSISTENT = "reduced"
"""The consistent reference truth of ``--acceptance``: the observer's own reduced model generating the data, so the
spread of its figures over the seeds is a consistent filter's scatter (:func:`exuflex.truth.reduced_truth`)."""
PERCENTILE = 90  # the upper percentile over the seeds reported beside the mean
NIS_TOL = 0.10  # |time-averaged NIS / channels - 1|
PATH_TOL = 0.10  # |RMS default / RMS reference - 1|


def gallery() -> list[str]:
    """The gallery's model names: the files in ``models/`` with a manoeuvre."""
    return sorted(p.stem for p in MODELS.glob("*.toml") if "manoeuvre" in tomllib.loads(p.read_text()))


def model_path(model: str) -> Path:
    """A gallery model's file (``models/<model>.toml``), or ``model`` itself when it names a model file (a
    mechanism of one's own, scored the same way)."""
    return Path(model) if model.endswith(".toml") else MODELS / f"{model}.toml"


def truth_runs(model: str, seeds, *, engine: str = "exudyn", truth_dir: Path) -> tuple[dict[int, Path], float]:
    """The truth runs of ``model`` for ``seeds`` in ``truth_dir/<engine>/<model>/s<seed>``: those already there are
    reused, the others written by one truth simulation measured with each missing seed
    (:func:`exuflex.truth.simulate_runs`: the truth's motion does not depend on the seed). Returns the folders by
    seed and the seconds the simulation took (0 when every run was there)."""
    from exuflex.truth import simulate_runs

    base = Path(truth_dir) / engine / Path(model).stem
    runs = {s: base / f"s{s}" for s in seeds}
    missing = {s: p for s, p in runs.items() if not (p / "meta.json").exists()}
    t0 = time.perf_counter()
    if missing:
        base.mkdir(parents=True, exist_ok=True)
        simulate_runs(model_path(model), missing, engine=engine)
    return runs, (time.perf_counter() - t0 if missing else 0.0)


def run_chain(model: str, seed: int, *, engine: str = "exudyn", reference: bool = True,
              work: Path | None = None, truth_dir: Path | None = None, observer: dict | None = None) -> dict:
    """Truth, log and observer (default and, if ``reference``, the exact reference path) for one model and seed;
    the measured figures as a JSON-ready dict. ``truth_dir``: keep the truth run in
    ``truth_dir/<engine>/<model>/s<seed>`` and reuse it when it is there (:func:`truth_runs`); ``observer``:
    ObserverConfig fields replacing the defaults (e.g. ``{"method": "rk4"}``)."""
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.session import ObserverConfig, physical_names
    from exuflex.runs import read_run

    mech = load_mechanism(model_path(model))
    model = Path(model).stem
    with tempfile.TemporaryDirectory(dir=work) as tmp:
        runs, truth_s = truth_runs(model, [seed], engine=engine, truth_dir=Path(truth_dir or tmp))
        run = read_run(runs[seed])
        config = replace(ObserverConfig(), **(observer or {}))
        out = _observe(mech, run, config)
        ref = _observe(mech, run, replace(config, **REFERENCE)) if reference else None
    if isinstance(out, str):  # the filter raised: a non-finite state
        names = physical_names(mech)
        nan = {k: float("nan") for k in names}
        row = {"model": model, "seed": seed, "engine": engine, "duration_s": float(run.sensors.t[-1] - run.sensors.t[0]),
               "channels": [], "reduced_ndof": None, "metrics_from_s": config.start_up, "rms_error": nan,
               "bound_rms": nan, "ratio_to_bound": nan, "nis_mean": float("nan"), "nis_expected": float("nan"),
               "diverged": True, "diverged_at": None, "nonfinite": True, "error": out, "truth_wall_s": truth_s,
               "observer_wall_s": float("nan"), "real_time_factor": float("nan")}
        row["acceptance"] = acceptance(row)
        return row
    s = out.summary
    res = out.estimate.result
    row = {
        "model": model,
        "seed": seed,
        "engine": engine,
        "duration_s": float(run.sensors.t[-1] - run.sensors.t[0]),
        "channels": list(s["channels"]),
        "reduced_ndof": s["reduced_ndof"],
        "metrics_from_s": s["metrics_from_s"],
        "rms_error": s["rms_error"],
        "bound_rms": s["bound_rms"],
        "ratio_to_bound": s["ratio_to_bound"],
        "nis_mean": s["nis_mean"],
        "nis_expected": s["nis_expected"],
        "diverged": bool(s["diverged"]),
        "diverged_at": s["diverged_at"],
        "nonfinite": bool(res.nonfinite),
        "truth_wall_s": truth_s,
        "observer_wall_s": s["wall_s"],
        "real_time_factor": s["real_time_factor"],
    }
    if isinstance(ref, str):
        row["reference"] = {"settings": dict(REFERENCE), "error": ref}
        row["default_over_reference"] = {k: float("nan") for k in s["rms_error"]}
    elif ref is not None:
        rr = ref.summary
        row["reference"] = {
            "settings": dict(REFERENCE),
            "rms_error": rr["rms_error"],
            "ratio_to_bound": rr["ratio_to_bound"],
            "nis_mean": rr["nis_mean"],
            "diverged": bool(rr["diverged"]),
            "observer_wall_s": rr["wall_s"],
        }
        row["default_over_reference"] = {k: _ratio(v, rr["rms_error"].get(k)) for k, v in s["rms_error"].items()}
    row["acceptance"] = acceptance(row)
    return row


def _observe(mech, run, config):
    """The observer's outcome on a run, or the message of the :class:`FilterDivergedError` it raised (a non-finite
    state or covariance)."""
    from exuflex.observer import FilterDivergedError
    from exuflex.scoring.run import observe_run

    try:
        return observe_run(mech, run, config)
    except FilterDivergedError as exc:
        return str(exc)


def _ratio(a, b) -> float:
    return a / b if b and math.isfinite(b) and b > 0 and math.isfinite(a) else float("nan")


def acceptance(row: dict) -> dict:
    """Issue 15's acceptance for one run: which criteria hold, and the worst figure of each."""
    ratios = row["ratio_to_bound"]
    worst_q = max(ratios, key=lambda k: ratios[k] if math.isfinite(ratios[k]) else math.inf)
    nis_rel = row["nis_mean"] / row["nis_expected"] - 1.0 if row["nis_expected"] else float("nan")
    out = {
        "worst_ratio": ratios[worst_q],
        "worst_quantity": worst_q,
        "errors_within_bound": all(math.isfinite(v) and v <= RATIO_MAX for v in ratios.values()),
        "nis_rel": nis_rel,
        "nis_consistent": math.isfinite(nis_rel) and abs(nis_rel) <= NIS_TOL,
        "no_flag": not (row["diverged"] or row["nonfinite"]),
    }
    d = row.get("default_over_reference")
    if d is not None:
        dev = {k: abs(v - 1.0) if math.isfinite(v) else math.inf for k, v in d.items()}
        wq = max(dev, key=dev.get)
        out.update(path_worst_quantity=wq, path_worst=d[wq], path_within=dev[wq] <= PATH_TOL)
    out["passed"] = all(v for k, v in out.items() if k in ("errors_within_bound", "nis_consistent", "no_flag",
                                                            "path_within"))
    return out


def _fmt(v, nd=2) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{nd}f}"


def summary_table(rows: list[dict]) -> list[str]:
    head = ("| model | seed | worst RMS / bound | NIS / channels | flags | worst default / reference | passes |",
            "|---|---|---|---|---|---|---|")
    out = list(head)
    for r in rows:
        a = r["acceptance"]
        flags = ", ".join(f for f, on in (("NIS test at %.3g s" % (r["diverged_at"] or 0), r["diverged"]
                                           and r["diverged_at"] is not None),
                                          (r.get("error") or "non-finite", r["nonfinite"])) if on) or "none"
        path = (f"{_fmt(a['path_worst'], 3)} ({a['path_worst_quantity']})" if "path_worst" in a else "-")
        out.append(f"| {r['model']} | {r['seed']} | {_fmt(a['worst_ratio'])} ({a['worst_quantity']}) | "
                   f"{_fmt(r['nis_mean'])} / {_fmt(r['nis_expected'], 1)} | {flags} | {path} | "
                   f"{'yes' if a['passed'] else 'no'} |")
    return out


def quantity_tables(rows: list[dict]) -> list[str]:
    out = []
    for model in dict.fromkeys(r["model"] for r in rows):
        rs = [r for r in rows if r["model"] == model]
        qs = list(rs[0]["ratio_to_bound"])
        about = (f"{len(rs[0]['channels'])} channels ({', '.join(rs[0]['channels'])}), reduced model "
                 f"{rs[0]['reduced_ndof']} dofs, errors from {rs[0]['metrics_from_s']:g} s of {rs[0]['duration_s']:g} s.")
        out += ["", f"### {model}", "", about, "",
                "| seed | figure | " + " | ".join(qs) + " |", "|---|---|" + "---|" * len(qs)]
        for r in rs:
            out.append(f"| {r['seed']} | RMS / bound | " + " | ".join(_fmt(r["ratio_to_bound"][q]) for q in qs) + " |")
            if "default_over_reference" in r:
                out.append(f"| {r['seed']} | default / reference | "
                           + " | ".join(_fmt(r["default_over_reference"][q], 3) for q in qs) + " |")
        out.append("| | bound | " + " | ".join(f"{rs[0]['bound_rms'][q]:.3g}" for q in qs) + " |")
    return out


def markdown(rows: list[dict], settings: dict) -> str:
    cmd = "python benchmarks/gallery.py" + settings["command_args"]
    n_pass = sum(r["acceptance"]["passed"] for r in rows)
    lines = [
        "# The mechanism gallery: the whole chain on every model",
        "",
        (f"Generated by `{cmd}` (do not edit: rerun the script). Truth engine: {settings['engine']}; seeds "
         f"{', '.join(map(str, settings['seeds']))}; the observer with default settings; the exact reference path "
         f"is the observer with {', '.join(f'{k}={v!r}' for k, v in REFERENCE.items())}."),
        "",
        (f"Acceptance of issue 15 per run: every RMS error after the start-up within {RATIO_MAX}x the observer's "
         f"own bound (`bound_rms`: the posterior Cramer-Rao bound along the truth, its standard deviations' RMS "
         f"over the scored samples, from the start-up to the log's end; docs/bound.md), time-averaged NIS "
         f"within {NIS_TOL:.0%} of the channel count, no flag (NIS divergence test, non-finite state), and the "
         f"default path's RMS errors within {PATH_TOL:.0%} of the reference's. Runs passing: {n_pass} of "
         f"{len(rows)}."),
        "",
        *summary_table(rows),
        "",
        "## Per quantity",
        *quantity_tables(rows),
        "",
        "## Speed (this run, shared 2-core machine)",
        "",
        "| model | seed | truth (s) | observer (s) | real-time factor | reference observer (s) |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        ref = r.get("reference") or {}
        lines.append(f"| {r['model']} | {r['seed']} | {r['truth_wall_s']:.1f} | {r['observer_wall_s']:.2f} | "
                     f"{r['real_time_factor']:.1f} | {_fmt(ref.get('observer_wall_s'), 1)} |")
    lines += ["", f"Versions: {', '.join(f'{k} {v}' for k, v in settings['versions'].items())}.", ""]
    return "\n".join(lines)


def acceptance_28(row: dict) -> dict:
    """Issue 28's acceptance for one run (:data:`ACCEPTANCE`): the worst RMS error / bound within the engine's limit,
    the NIS within 10 % of the channel count, no flag."""
    a = acceptance(row)
    limit = ACCEPTANCE.get(row["engine"], ACCEPTANCE["erls"])
    ok = math.isfinite(a["worst_ratio"]) and a["worst_ratio"] <= limit
    return {"limit": limit, "worst_ratio": a["worst_ratio"], "worst_quantity": a["worst_quantity"],
            "nis_rel": a["nis_rel"], "passed": ok and a["nis_consistent"] and a["no_flag"],
            "flags": not a["no_flag"]}


def _nis_ratio(r: dict) -> float:
    return r["nis_mean"] / r["nis_expected"] if r["nis_expected"] else float("nan")


def seed_statistics(rows: list[dict], percentile: float = PERCENTILE) -> dict:
    """Per engine and model, over the seeds: each quantity's RMS / bound and the NIS / channels as the mean and the
    ``percentile``-th percentile, and, where the :data:`CONSISTENT` truth has the same seeds, the paired excess over
    it: per seed the engine's ratio minus the consistent truth's (the same seed draws the same noise, so the two
    runs' errors share their noise-driven part), its mean and the standard error of that mean. A model error shows
    as a paired excess several standard errors above zero; a consistent filter's scatter as a spread the
    consistent truth shares."""
    import numpy as np

    out: dict = {}
    by = {}
    for r in rows:
        by.setdefault((r["engine"], r["model"]), []).append(r)
    for (engine, model), rs in by.items():
        ref = {r["seed"]: r for r in by.get((CONSISTENT, model), [])} if engine != CONSISTENT else {}
        qs = {}
        for q in rs[0]["ratio_to_bound"]:
            v = np.array([r["ratio_to_bound"][q] for r in rs], float)
            st = {"mean": float(np.mean(v)), "p": float(np.percentile(v, percentile))}
            pairs = [(r["ratio_to_bound"][q], ref[r["seed"]]["ratio_to_bound"].get(q, np.nan)) for r in rs
                     if r["seed"] in ref]
            if len(pairs) >= 2:
                d = np.array([a - b for a, b in pairs], float)
                st.update(excess=float(np.mean(d)), excess_se=float(np.std(d, ddof=1) / np.sqrt(len(d))))
            qs[q] = st
        nis = np.array([_nis_ratio(r) for r in rs], float)
        worst = max(qs, key=lambda q: qs[q]["mean"] if math.isfinite(qs[q]["mean"]) else math.inf)
        limit = ACCEPTANCE.get(engine, ACCEPTANCE["erls"])
        nis_mean = float(np.mean(nis))
        flags = int(sum(r["diverged"] or r["nonfinite"] for r in rs))
        out[(engine, model)] = {
            "engine": engine, "model": model, "n": len(rs), "seeds": [r["seed"] for r in rs], "quantities": qs,
            "worst": worst, "nis_mean": nis_mean, "nis_p": float(np.percentile(nis, percentile)),
            "nis_low": float(np.percentile(nis, 100 - percentile)), "flags": flags, "limit": limit,
            "passed": bool(all(math.isfinite(s["mean"]) and s["mean"] <= limit for s in qs.values())
                           and abs(nis_mean - 1.0) <= NIS_TOL and not flags),
        }
    return out


def _excess(s: dict) -> str:
    if "excess" not in s or not math.isfinite(s["excess"]):
        return "-"
    return f"{s['excess']:+.2f} ± {2 * s['excess_se']:.2f}"


def acceptance_page(rows: list[dict], settings: dict) -> str:
    """The markdown page of ``--acceptance``: over the seeds, per engine and model, each quantity's RMS / bound and
    the NIS (mean and percentile, :func:`seed_statistics`) beside the consistent truth's; then per run the worst
    RMS / bound and the NIS, and every run."""
    cmd = "python benchmarks/gallery.py" + settings["command_args"]
    seeds = settings["seeds"]
    pc = settings.get("percentile", PERCENTILE)
    obs = settings.get("observer") or {}
    lines = ["# Issue 28's acceptance on the gallery", "",
             f"Generated by `{cmd}` (do not edit: rerun the script); the code at commit {settings.get('commit', '?')}.",
             "", (f"The observer with default settings{' except ' + ', '.join(f'{k}={v!r}' for k, v in obs.items()) if obs else ''}, "
                  f"no per-file tuning; seeds {_seed_span(seeds)} (N = {len(seeds)}); each model's truth is simulated "
                  "once per engine and measured with every seed's noise (the truth's motion does not depend on the "
                  "seed). Truths: "
                  + ", ".join(f"{k} (limit {v}x)" for k, v in ACCEPTANCE.items())
                  + (f", and the consistent reference `{CONSISTENT}` (the observer's own reduced model generating "
                     "the data: what a consistent filter's figures and their scatter look like; RK4 of the reduced "
                     "equations with every stage at its own state, `exuflex.truth.reduced_truth`, so the paired "
                     "excess over it is the filter's own step's departure from its continuous model)."
                     if any(r["engine"] == CONSISTENT for r in rows) else
                     f"; the consistent reference `{CONSISTENT}` was not run in this rerun (`--engine` without it), "
                     "so its columns are blank.")), ""]
    stats = seed_statistics(rows, pc)
    engines = list(dict.fromkeys(r["engine"] for r in rows))
    models = list(dict.fromkeys(r["model"] for r in rows))
    lines += ["## Over the seeds", "",
              ("A per-run figure (a run's worst RMS / bound over its quantities) scatters for a consistent filter: "
               "an RMS over a short log scatters by about 1/sqrt(2 x the number of correlation times in it), and the "
               "worst of about ten such ratios is above 1 more often than not. So each quantity's RMS / bound is "
               f"stated over the N seeds: its mean and {pc}th percentile; beside them the consistent truth's, and the "
               "paired excess over it (per seed the difference of the two runs' ratios, which share the seed's noise; "
               "mean ± 2 standard errors): model error where the excess is clearly above zero, scatter where the "
               "consistent truth shows the same spread. Acceptance over the seeds: every quantity's mean RMS / bound "
               f"within the engine's limit, the mean NIS / channels within {NIS_TOL:.0%} of 1, no flag."), ""]
    head = ["| model | engine | N | worst quantity | mean RMS / bound | "
            f"p{pc} | {CONSISTENT}: mean, p{pc} | paired excess | NIS / channels: mean | "
            f"p{100 - pc}-p{pc} | flags | passes |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += head
    for model in models:
        for engine in engines:
            s = stats.get((engine, model))
            if s is None:
                continue
            w = s["worst"]
            q = s["quantities"][w]
            ref = stats.get((CONSISTENT, model), {}).get("quantities", {}).get(w)
            refs = f"{_fmt(ref['mean'])}, {_fmt(ref['p'])}" if ref and engine != CONSISTENT else "-"
            verdict = ("yes" if s["passed"] else "no") + (" (reference)" if engine == CONSISTENT else "")
            lines.append(f"| {model} | {engine} | {s['n']} | {w} | {_fmt(q['mean'])} | {_fmt(q['p'])} | {refs} | "
                         f"{_excess(q)} | {_fmt(s['nis_mean'], 3)} | {_fmt(s['nis_low'], 3)}-{_fmt(s['nis_p'], 3)} | "
                         f"{s['flags']} | {verdict} |")
    n_ok = sum(s["passed"] for (e, _), s in stats.items() if e in ACCEPTANCE)
    n_all = sum(1 for (e, _) in stats if e in ACCEPTANCE)
    lines += ["", f"Models and truths passing over the seeds: {n_ok} of {n_all}.", "", "### Per quantity", "",
              (f"Each model's quantities: mean (p{pc}) of RMS / bound over the seeds per truth, and the paired excess "
               f"over the `{CONSISTENT}` truth (mean ± 2 standard errors); last row the NIS / channels.")]
    for model in models:
        es = [e for e in engines if (e, model) in stats]
        if not es:
            continue
        others = [e for e in es if e != CONSISTENT]
        qs = list(stats[(es[0], model)]["quantities"])
        lines += ["", f"#### {model}", "",
                  "| quantity | " + " | ".join(f"{e}: mean (p{pc})" for e in es)
                  + "".join(f" | {e} - {CONSISTENT}" for e in others if CONSISTENT in es) + " |",
                  "|---|" + "---|" * (len(es) + (len(others) if CONSISTENT in es else 0))]
        for q in qs:
            cells = [f"{_fmt(stats[(e, model)]['quantities'][q]['mean'])} ({_fmt(stats[(e, model)]['quantities'][q]['p'])})"
                     for e in es]
            if CONSISTENT in es:
                cells += [_excess(stats[(e, model)]["quantities"][q]) for e in others]
            lines.append(f"| {q} | " + " | ".join(cells) + " |")
        cells = [f"{_fmt(stats[(e, model)]['nis_mean'], 3)} ({_fmt(stats[(e, model)]['nis_p'], 3)})" for e in es]
        if CONSISTENT in es:
            cells += ["-" for _ in others]
        lines.append("| NIS / channels | " + " | ".join(cells) + " |")
    lines += ["", "## Per run", "",
              (f"Issue 28's per-run criterion: every RMS error after the start-up within the engine's limit times the "
               f"observer's own bound (`bound_rms`), the time-averaged NIS within {NIS_TOL:.0%} of the channel count, "
               "no flag (NIS divergence test, non-finite state). 'worst RMS / bound' is a run's largest ratio over "
               "its quantities; mean and worst are over the seeds.")]
    n_pass = sum(r["acc28"]["passed"] for r in rows if r["engine"] in ACCEPTANCE)
    lines += ["", f"Runs passing: {n_pass} of {sum(r['engine'] in ACCEPTANCE for r in rows)}.", ""]
    for engine in engines:
        rs = [r for r in rows if r["engine"] == engine]
        limit = ACCEPTANCE.get(engine, ACCEPTANCE["erls"])
        lines += [f"### {engine} truth (limit {limit}x{', the consistent reference' if engine == CONSISTENT else ''})",
                  "", "| model | worst RMS / bound: mean | worst (quantity, seed) | NIS / channels: mean | worst | flags "
                  "| passing |", "|---|---|---|---|---|---|---|"]
        for model in dict.fromkeys(r["model"] for r in rs):
            m = [r for r in rs if r["model"] == model]
            w = [r["acc28"]["worst_ratio"] for r in m]
            k = int(max(range(len(m)), key=lambda i: w[i] if math.isfinite(w[i]) else math.inf))
            nis = [_nis_ratio(r) for r in m]
            kn = int(max(range(len(m)), key=lambda i: abs(nis[i] - 1) if math.isfinite(nis[i]) else math.inf))
            lines.append(f"| {model} | {_fmt(sum(w) / len(w))} | {_fmt(w[k])} ({m[k]['acc28']['worst_quantity']}, "
                         f"{m[k]['seed']}) | {_fmt(sum(nis) / len(nis), 3)} | {_fmt(nis[kn], 3)} | "
                         f"{sum(r['acc28']['flags'] for r in m)} | {sum(r['acc28']['passed'] for r in m)} of {len(m)} |")
        lines.append("")
    lines += ["### Every run", "", "| engine | model | seed | reduced dofs | worst RMS / bound | NIS / channels | passes |",
              "|---|---|---|---|---|---|---|"]
    for r in rows:
        a = r["acc28"]
        lines.append(f"| {r['engine']} | {r['model']} | {r['seed']} | {r['reduced_ndof']} | {_fmt(a['worst_ratio'])} "
                     f"({a['worst_quantity']}) | {_fmt(r['nis_mean'])} / {_fmt(r['nis_expected'], 1)} | "
                     f"{'yes' if a['passed'] else 'no'} |")
    lines += ["", f"Versions: {', '.join(f'{k} {v}' for k, v in settings['versions'].items())}.", ""]
    return "\n".join(lines)


def _seed_span(seeds) -> str:
    s = list(seeds)
    return f"{s[0]}-{s[-1]}" if len(s) > 2 and s == list(range(s[0], s[-1] + 1)) else ", ".join(map(str, s))


def _seeds(text: str) -> list[int]:
    """``1,2,3`` or ``1-10`` (or a mix) as a list of seeds."""
    out = []
    for part in (p for p in text.split(",") if p):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def _commit() -> str:
    import subprocess

    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except Exception:  # noqa: BLE001 - not a git checkout
        return "?"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default=None,
                    help="comma-separated model names or model files (default: every file in models/)")
    ap.add_argument("--seeds", default=",".join(map(str, SEEDS)),
                    help="noise seeds, comma-separated or a range such as 1-10 (default 1,2,3)")
    ap.add_argument("--engine", default=None,
                    help="truth engine(s), comma-separated: exudyn, erls, reduced (default exudyn; --acceptance: "
                         "erls,exudyn,reduced)")
    ap.add_argument("--acceptance", action="store_true",
                    help="issue 28's acceptance on the ERLS and Exudyn truths beside the consistent reduced truth, per "
                         "run and over the seeds (no reference path); writes --md")
    ap.add_argument("--method", default=None, choices=("cached", "rk4"),
                    help="the observer's step map (default: the observer's default)")
    ap.add_argument("--truth-dir", default=None, help="keep the truth runs here and reuse those already there")
    ap.add_argument("--no-reference", action="store_true", help="skip the exact reference path")
    ap.add_argument("--json", default=str(ROOT / "docs" / "gallery.json"), help="JSON output ('' for none)")
    ap.add_argument("--md", default=str(ROOT / "docs" / "gallery.md"), help="markdown page ('' for none)")
    ap.add_argument("--markdown-from", default=None, help="rewrite --md from this JSON of an earlier run (no runs)")
    a = ap.parse_args(argv)
    engines = (a.engine or ("erls,exudyn," + CONSISTENT if a.acceptance else "exudyn")).split(",")
    bad = [e for e in engines if e not in ("exudyn", "erls", "reduced")]
    if bad:
        ap.error(f"--engine: expected exudyn, erls or reduced, got {bad[0]!r}")
    if a.acceptance:
        a.no_reference = True
        if a.md == str(ROOT / "docs" / "gallery.md"):
            a.md = str(ROOT / "docs" / "acceptance.md")
        if a.json == str(ROOT / "docs" / "gallery.json"):
            a.json = ""
    if a.markdown_from:
        data = json.loads(Path(a.markdown_from).read_text())
        page = acceptance_page if data["settings"].get("acceptance_28") else markdown
        Path(a.md).write_text(page(data["runs"], data["settings"]))
        print(f"wrote {a.md}")
        return 0
    models = a.models.split(",") if a.models else gallery()
    unknown = sorted(m for m in models if m not in gallery() and not (m.endswith(".toml") and Path(m).is_file()))
    if unknown:
        ap.error(f"--models: no models/{unknown[0]}.toml and no such model file; the gallery has "
                 f"{', '.join(gallery())}")
    try:
        seeds = _seeds(a.seeds)
    except ValueError:
        ap.error(f"--seeds: expected integers separated by commas or a range such as 1-10, got {a.seeds!r}")
    from exuflex.runs import package_versions

    observer = {"method": a.method} if a.method else {}
    rows = []
    keep = tempfile.TemporaryDirectory() if a.truth_dir is None else None
    truth_dir = Path(a.truth_dir) if a.truth_dir else Path(keep.name)
    sim_s = {}
    for engine, m in ((e, m) for e in engines for m in models):  # one truth per engine and model, every seed
        sim_s[(engine, m)] = truth_runs(m, seeds, engine=engine, truth_dir=truth_dir)[1]
    for engine, m, s in ((e, m, s) for e in engines for m in models for s in seeds):
        r = run_chain(m, s, engine=engine, reference=not a.no_reference, truth_dir=truth_dir, observer=observer)
        r["truth_wall_s"] = sim_s[(engine, m)]
        if a.acceptance:
            r["acc28"] = acceptance_28(r)
        rows.append(r)
        ac = r["acceptance"]
        print(f"{engine:6s} {Path(m).stem:14s} seed {s}: worst RMS/bound {ac['worst_ratio']:.2f} ({ac['worst_quantity']}), NIS "
              f"{r['nis_mean']:.2f} / {r['nis_expected']:.1f}, diverged {r['diverged']}, "
              + (f"default/reference {ac['path_worst']:.3f} ({ac['path_worst_quantity']}), " if "path_worst" in ac
                 else "") + (f"issue 28 ({r['acc28']['limit']}x): {'PASS' if r['acc28']['passed'] else 'FAIL'}"
                             if a.acceptance else f"{'PASS' if ac['passed'] else 'FAIL'}"), flush=True)
    args = ((" --acceptance --truth-dir DIR" if a.acceptance else "") + (f" --models {a.models}" if a.models else "")
            + (f" --seeds {a.seeds}" if seeds != list(SEEDS) else "")
            + (f" --engine {a.engine}" if a.engine else "") + (f" --method {a.method}" if a.method else "")
            + (" --no-reference" if a.no_reference and not a.acceptance else ""))
    settings = {"engine": ",".join(engines), "seeds": seeds, "models": models, "reference": None if a.no_reference else
                REFERENCE, "acceptance": {"ratio_max": RATIO_MAX, "nis_tol": NIS_TOL, "path_tol": PATH_TOL},
                "acceptance_28": ACCEPTANCE if a.acceptance else None, "commit": _commit(), "observer": observer,
                "percentile": PERCENTILE, "truth_s": {f"{e}/{m}": v for (e, m), v in sim_s.items()},
                "command_args": args, "versions": {**package_versions(), "python": platform.python_version()}}
    if a.acceptance:
        if a.json:
            Path(a.json).write_text(json.dumps({"settings": settings, "runs": rows}, indent=1, default=float) + "\n")
            print(f"wrote {a.json}")
        page = acceptance_page(rows, settings)
        print(page)
        if a.md:
            Path(a.md).write_text(page)
            print(f"wrote {a.md}")
        return 0
    print("\n".join(summary_table(rows)))
    if a.json:
        Path(a.json).write_text(json.dumps({"settings": settings, "runs": rows}, indent=1, default=float) + "\n")
        print(f"wrote {a.json}")
    if a.md:
        Path(a.md).write_text(markdown(rows, settings))
        print(f"wrote {a.md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

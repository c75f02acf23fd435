"""``exuflex study payload|sweep|slenderness MODEL --out DIR``: model-mismatch studies (truth changed, observer
nominal; or, for slenderness, beam theory against solid truths).

``payload``: the paper's Fig. 11 study, the truth's tip payload raised by each of ``--levels`` percent;
``--estimators ekf,ekf-payload,ukf`` runs it once per estimator (``OUT/<estimator>``, on the same truths) and
draws them side by side.
``sweep``: any model-file field(s) of the truth, ``--set links.L1.diameter=0.030,0.031`` (several ``--set``
form a grid).
``slenderness``: the beam-theory study, ``--link NAME --levels 50,20,10,5,3``: the link's L/d set by its diameter,
the truth that geometry as solid FFRF bodies (``--beam``), the observer the level's own (beam) model, each run
scored against its bound (``ratio_to_bound``). Each writes ``results.csv`` (one row per run), ``summary.json`` (eq. 21 mu and sigma per level
and quantity, settings, model and sha256, seeds, versions, wall time) and a figure. A study restarted with
the same arguments skips its finished runs and cached truths.
"""

from __future__ import annotations

import argparse
import sys
import time

from .args import add_overwrite, nonneg_float, out_path, positive_float, positive_int
from .args import seed as seed_type

__all__ = ["QUICK", "add_parser", "build_spec", "run"]

QUICK = {"duration": 0.4, "runs": 3, "levels": "0,50,100"}
DEFAULT_LEVELS = "0,25,50,75,100"
SLENDERNESS = {"levels": "50,20,10,7,5.5", "runs": 5, "quick_levels": "50,10,5.5", "quick_runs": 2}


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", help="model file (TOML), e.g. models/sixbar.toml")
    p.add_argument("--out", required=True, type=out_path, help="study folder (created; an existing study there is resumed)")
    add_overwrite(p)
    p.add_argument("--runs", type=positive_int, default=None, help="noise realisations per level (default 100)")
    p.add_argument("--workers", type=positive_int, default=1, help="local worker processes (default 1: in-process)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786): run there")
    p.add_argument("--quick", action="store_true",
                   help=f"short check: {QUICK['duration']} s, {QUICK['runs']} runs per level")
    p.add_argument("--engine", choices=("exudyn", "erls", "reduced"), default="exudyn",
                   help="truth engine (default exudyn; reduced: the observer's own model, a consistency check)")
    p.add_argument("--duration", type=positive_float, default=None, help="simulated time (s); default: the manoeuvre's")
    p.add_argument("--seed", type=seed_type, default=0, help="base seed; run j uses seed + j (default 0)")
    p.add_argument("--start-up", type=nonneg_float, default=None,
                   help="seconds left out of the error statistics (default min(0.3, duration / 4))")
    p.add_argument("--h", type=positive_float, default=1e-4, help="truth integration step (s)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (shown only on a terminal)")


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("study", help="model-mismatch studies: payload (Fig. 11) or a parameter sweep",
                       description=__doc__.split("\n")[0])
    ss = p.add_subparsers(dest="study_kind", required=True)
    pp = ss.add_parser("payload", help="truth payload raised by --levels percent (the paper's Fig. 11)")
    _common(pp)
    pp.add_argument("--levels", default=None, help=f"payload increases in %% (default {DEFAULT_LEVELS})")
    pp.add_argument("--estimators", default=None, metavar="E1,E2,...",
                    help="run the study once per estimator (ekf, ukf, ekf-payload, ekf-input, imm) into OUT/<estimator> "
                         "on the same truths and draw Fig. 11 with them side by side (OUT/fig_payload_estimators.png)"
                         "; default: the paper's EKF alone in OUT")
    sp = ss.add_parser("sweep", help="truth parameter sweep: --set FIELD=V1,V2,...")
    _common(sp)
    sp.add_argument("--set", dest="sets", action="append", required=True, metavar="FIELD=V1,V2,...",
                    help="a model-file field of the truth and its values, e.g. links.L1.diameter=0.03,0.031; "
                         "repeat for a grid")
    sl = ss.add_parser("slenderness", help="beam theory's limits: the beam observer on solid (FFRF) truths as "
                                           "--link grows stubby (--levels L/d)")
    _common(sl)
    sl.add_argument("--link", required=True, help="the link whose slenderness is swept (a round section)")
    sl.add_argument("--levels", default=None,
                    help=f"slenderness ratios L/d (default {SLENDERNESS['levels']}; --quick {SLENDERNESS['quick_levels']})")
    sl.add_argument("--beam", default="ffrf", help="the truth's bodies (default ffrf: solid meshes; ancf, ge: beams)")
    sl.add_argument("--keep", default="dynamics", help="dynamics (default: the link's EI and rho A kept, E and rho "
                    "scaled with the diameter: only the solid's shape changes) or material (E and rho kept)")
    sl.add_argument("--mesh-scale", type=positive_float, default=None,
                    help="the truth's solid mesh size on the link as a multiple of its diameter (default: the "
                         "truth's default; 2 is a coarse, quick mesh)")
    p.set_defaults(func=run)
    return p


def build_spec(args):
    """The :class:`~exuflex.study.StudySpec` of parsed arguments (``--quick`` fills unset options)."""
    from ..errors import UsageError
    from ..study import StudySpec, parse_set, payload_levels, sweep_levels

    runs = args.runs if args.runs is not None else (QUICK["runs"] if args.quick else 100)
    duration = args.duration if args.duration is not None else (QUICK["duration"] if args.quick else None)
    if args.study_kind == "slenderness":
        from ..mechanism import load_mechanism
        from ..study import slenderness_levels
        from ..truth import BEAMS

        if args.beam not in BEAMS:
            raise UsageError(f"--beam {args.beam!r}: expected one of {', '.join(BEAMS)}")
        text = args.levels if args.levels is not None else \
            SLENDERNESS["quick_levels" if args.quick else "levels"]
        cells = [x.strip() for x in text.split(",")]
        if not text.strip() or not all(cells):
            raise UsageError(f"--levels {text!r}: expected comma-separated slenderness ratios L/d, e.g. 50,20,10,5,3")
        levels = slenderness_levels(load_mechanism(args.model), args.link, cells, args.mesh_scale, args.keep)
        if args.runs is None:
            runs = SLENDERNESS["quick_runs" if args.quick else "runs"]
        return StudySpec(model=args.model, levels=levels, runs=runs, base_seed=args.seed, engine=args.engine,
                         duration=duration, h=args.h, start_up=args.start_up, kind="slenderness", beam=args.beam,
                         observer_model="level", with_bound=True)
    if args.study_kind == "payload":
        text = args.levels if args.levels is not None else (QUICK["levels"] if args.quick else DEFAULT_LEVELS)
        cells = [x.strip() for x in text.split(",")]
        try:
            if not text.strip() or not all(cells):
                raise ValueError(text)
            pct = [float(x) for x in cells]
        except ValueError:
            raise UsageError(f"--levels {text!r}: expected comma-separated percentages, none empty, e.g. 0,25,50"
                             ) from None
        levels = payload_levels(pct)
    else:
        levels = sweep_levels([parse_set(s) for s in args.sets])
    return StudySpec(model=args.model, levels=levels, runs=runs, base_seed=args.seed, engine=args.engine,
                     duration=duration, h=args.h, start_up=args.start_up, kind=args.study_kind)


def _print_table(summary: dict, qs, stream) -> None:
    print(f"{'level':>24s} {'runs':>4s} {'div':>3s} {'nis':>3s} {'max|dq|':>8s} "
          + " ".join(f"{'mu ' + q:>10s} {'sigma':>9s}" for q in qs), file=stream)
    for lv in summary["levels"]:
        cells = " ".join(f"{lv['eq21'][q]['mu']:10.3g} {lv['eq21'][q]['sigma']:9.3g}" for q in qs)
        print(f"{lv['label'][:24]:>24s} {lv['n_runs']:4d} {lv['n_diverged']:3d} {lv.get('n_nis_flagged', 0):3d} "
              f"{lv.get('max_q_error_rad', float('nan')):8.2g} {cells}", file=stream)


def print_summary(summary: dict, stream=None) -> None:
    """eq. 21 mu and sigma per level: the tip elastic quantities, then (if present) the absolute tip ones."""
    from ..study.runner import ABS_TIP_QUANTITIES, TIP_QUANTITIES

    stream = stream or sys.stdout
    elastic = list((summary.get("tip_quantities") or {}).get("elastic") or
                   [q for q in TIP_QUANTITIES if q in summary["quantities"]])
    qs = elastic or summary["quantities"][:4]
    absolute = [q for q in ABS_TIP_QUANTITIES if q in summary["quantities"]]
    if absolute and elastic:
        print("tip elastic displacement and velocity (m, m/s):", file=stream)
    _print_table(summary, qs, stream)
    if absolute:
        print("absolute tip position and velocity, rigid + elastic (m, m/s):", file=stream)
        _print_table(summary, absolute, stream)
    if any(lv.get("worst_ratio") for lv in summary["levels"]):
        print("RMS error / bound (posterior Cramer-Rao bound along the truth): the worst quantity per run, mean "
              "(min - max) over the runs", file=stream)
        for lv in summary["levels"]:
            w = lv.get("worst_ratio") or {}
            worst = max(set(w.get("quantity", [])), key=w.get("quantity", []).count, default="-")
            print(f"{lv['label'][:24]:>24s} {w.get('mean', float('nan')):6.2f} ({w.get('min', float('nan')):.2f} - "
                  f"{w.get('max', float('nan')):.2f})  mostly {worst}", file=stream)
    print("div: diverged runs (non-finite, or a joint-angle error above the track-loss limit); nis: runs the "
          "NIS window test flags (inconsistency, expected under mismatch)", file=stream)


def run(args) -> int:
    from ..study import OverrideError, run_study

    from ..mechanism import load_mechanism
    from ..validate import check_simulation_settings

    mech = load_mechanism(args.model)
    duration = args.duration if args.duration is not None else (QUICK["duration"] if args.quick else None)
    if mech.manoeuvre is not None:
        check_simulation_settings(mech, duration if duration is not None else mech.manoeuvre.duration, args.h)
    try:
        spec = build_spec(args)
        t0 = time.perf_counter()
        if getattr(args, "estimators", None) is not None:
            return _run_estimators(spec, args, t0)
        res = run_study(spec, args.out, workers=args.workers, scheduler=args.scheduler,
                        progress=not args.no_progress, overwrite=args.overwrite)
    except (OverrideError, ValueError, RuntimeError) as exc:
        print(f"exuflex study: error: {exc}", file=sys.stderr)
        return 2
    figure = _figure(res)
    print_summary(res.summary)
    print(f"{res.n_computed} run(s) computed, {res.n_reused} reused, {time.perf_counter() - t0:.1f} s; "
          f"wrote {res.out}/results.csv, summary.json" + (f", {figure.name}" if figure else ""))
    return 0


def _run_estimators(spec, args, t0: float) -> int:
    """``--estimators``: one study per estimator on shared truths, each summary printed, one figure of them all."""
    from ..study import estimator_figure_rows, run_estimator_studies

    names = [e.strip() for e in args.estimators.split(",") if e.strip()]
    results = run_estimator_studies(spec, args.out, names, workers=args.workers, scheduler=args.scheduler,
                                    progress=not args.no_progress, overwrite=args.overwrite)
    for e, res in results.items():
        print(f"estimator {e} ({res.out}):")
        print_summary(res.summary)
    figure = _estimators_figure({e: r.summary for e, r in results.items()}, args.out)
    n_new = sum(r.n_computed for r in results.values())
    n_old = sum(r.n_reused for r in results.values())
    print(f"{n_new} run(s) computed, {n_old} reused, {time.perf_counter() - t0:.1f} s; wrote "
          + ", ".join(f"{r.out}/summary.json" for r in results.values()) + (f", {figure}" if figure else ""))
    return 0


def _estimators_figure(summaries: dict, out):
    """Fig. 11 with the estimators side by side (the paper's four tip panels where the study has them, else every
    quantity), or None with a warning if drawing fails."""
    from pathlib import Path

    from ..plots import payload_study_figure, paper_payload_quantities
    from ..study import estimator_figure_rows

    try:
        rows = estimator_figure_rows(summaries)
        four = paper_payload_quantities([r["quantity"] for r in rows])
        if four:
            rows = [r for r in rows if r["quantity"] in four]
        return payload_study_figure(rows, Path(out) / "fig_payload_estimators.png")
    except Exception as exc:  # noqa: BLE001 - a figure failure must not lose the studies' numbers
        print(f"exuflex study: warning: estimators figure failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        return None


def _figure(res):
    """The study's figure in its folder, or None (with a warning) if drawing fails: the numbers are written."""
    from ..plots import study_figure

    try:
        return study_figure(res.summary, res.out)
    except Exception as exc:  # noqa: BLE001 - a figure failure must not lose the study's numbers
        print(f"exuflex study: warning: study figure failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        return None

"""Estimators beyond the paper on the payload-mismatch truths: plain EKF, payload EKF, input EKF, UKF, RTS smoother.

Reads the cached level truths of a payload study (``exuflex study payload MODEL --levels 0,100 --out DIR``
writes ``DIR/truth/<level>/truth.npz`` with the Exudyn truth) and, for each level and seed, draws the Table-3
noise exactly as the study does (:func:`exuflex.measure.measure`, ``seed``), runs each estimator and reports the
RMS errors after the start-up, the payload estimate after ``--settle`` s and its normalised error.

    python benchmarks/estimators.py models/sixbar.toml DIR --seeds 20 --estimators ekf,ekf-payload
    python benchmarks/estimators.py models/sixbar.toml DIR --speed 5 --estimators ekf,ekf-payload,ekf-input,ukf
    python benchmarks/estimators.py models/single_link.toml DIR --seeds 10 --estimators ekf@truth  # the reference

    python benchmarks/estimators.py models/M.toml DIR --from-json A.json,B.json --walk-table docs/tuning.md

The last writes the payload random walk's table (``ekf-payload`` rows at two ``payload_std`` values per model, from
runs with ``--payload-std``) into the page between its ``estimators.py walk`` markers.

``DIR`` may also be the folder of ``exuflex study payload MODEL --estimators ...`` (its shared ``truth``). With
``--speed N`` the estimators are timed in turn on one log instead (ratios within one run).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import numpy as np

from exuflex.measure import measure
from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, estimate, make_observer
from exuflex.scoring.run import metrics
from exuflex.study.runner import _load_truth

LEGEND = """Columns: mean over the seeds of the per-run RMS error after the start-up (rad, rad/s, m); the speed is
measured apart, the estimators timed in turn on one log (section "Speed"; the JSON rows keep each accuracy run's
real-time factor, taken while other runs shared the machine). Smoothed / filtered: the
RTS smoother's RMS error over the filter's on the same log. "After the settle time": mean RMS errors over the
samples after `--settle` s only (the payload estimate learned). NIS: the mean normalised innovation squared over all
runs' updates after the start-up and the two-sided 95 % chi-square band of a consistent filter (updates taken as
independent). Payload scale: the estimate at the last sample (mean over runs) and its std; "within 10 % after
settle": the estimate stays within 10 % of the truth at every sample after the settle time; "|err|/std <= 3":
at the last sample. The payload estimator's rows are its report (`payload_nominal_p`, default 0.5: the filter's
posterior mixed with its conditional on the nominal payload, `exuflex.observer.augmented.nominal_mixture`); with
`payload_nominal_p=0` the filter's posterior itself. `n`: runs in the means; `div`: runs whose estimate went non-finite (left out). `ekf@truth`: the
paper's EKF on a model built with the truth's payload (its own reduced model and basis), what an estimator of the
payload on the nominal model's basis can at best reach.
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model")
    ap.add_argument("study_dir")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--estimators", default="ekf,ekf-payload")
    ap.add_argument("--settle", type=float, default=1.5)
    ap.add_argument("--smooth", action="store_true", help="also the RTS smoother of each estimator")
    ap.add_argument("--payload-std", type=float, default=None, help="random-walk std of the payload scale per sqrt(s)")
    ap.add_argument("--config", action="append", default=[], metavar="FIELD=VALUE",
                    help="an ObserverConfig field (float), e.g. payload0_std=0.3")
    ap.add_argument("--scales", default=None, help="only these payload scales, e.g. 1.0")
    ap.add_argument("--from-json", default=None, help="comma-separated --json files of earlier runs: tables only")
    ap.add_argument("--measured-by", action="append", default=[], help="commands that wrote the --from-json files "
                    "(listed in the --doc page)")
    ap.add_argument("--doc", default=None, help="write the tables to this markdown page")
    ap.add_argument("--json", default=None, help="write the per-run rows here")
    ap.add_argument("--walk-table", default=None, metavar="PAGE",
                    help="with --from-json: the payload random walk's table (ekf-payload rows at two payload_std "
                         "values per model) into PAGE between its estimators.py walk markers")
    ap.add_argument("--speed", type=int, default=0, metavar="N",
                    help="instead: time each estimator N times on the nominal level's seed-0 log, in rotation "
                         "(ratios within one run), and the RTS smoother's passes")
    args = ap.parse_args(argv)
    mech = load_mechanism(args.model)
    rows = []
    if args.speed:
        rows = _speed(mech, args)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
        return 0
    if args.from_json:  # tables of earlier runs of this script (no filtering)
        for f in args.from_json.split(","):
            rows += [dict({"model": mech.name}, **r) for r in json.loads(Path(f).read_text())]
    for lvdir in [] if args.from_json else sorted(Path(args.study_dir, "truth").glob("L*")):
        level = json.loads((lvdir / "level.json").read_text())
        scale = float(level.get("level", level).get("payload_scale", 1.0)) if isinstance(level, dict) else 1.0
        if args.scales and scale not in [float(x) for x in args.scales.split(",")]:
            continue
        lt = _load_truth(lvdir / "truth.npz", {})
        truth_mech = mech.with_payload_scale(scale) if scale != 1.0 else mech
        duration = float(lt.clean.t[-1])
        for est_name in args.estimators.split(","):
            kw = {} if args.payload_std is None else {"payload_std": args.payload_std}
            kw.update({c.split("=")[0]: float(c.split("=")[1]) for c in args.config})
            # "ekf@truth": the paper's EKF on the truth's own payload (its reduced model and basis built with it)
            obs = (make_observer(truth_mech, ObserverConfig(estimator="ekf", **kw)) if est_name == "ekf@truth"
                   else make_observer(mech, ObserverConfig(estimator=est_name, **kw)))
            obs.ekf.nonfinite_action = "flag"
            for seed in range(args.seeds):
                meas = measure(truth_mech, lt.clean, lt.torque_t, lt.torques, seed=seed, t_end=duration)
                S = meas.signals
                U = S.select(mech.motor_names).data
                Y = S.select(obs.channels).data
                t0 = time.perf_counter()
                smooth = args.smooth and est_name != "ukf"
                e = estimate(obs, S.t, U, Y, smooth=smooth)
                wall = time.perf_counter() - t0
                m = metrics(e.filtered_physical if smooth else e.physical, lt.truth, 0.3)["rms_error"]
                late = metrics(e.filtered_physical if smooth else e.physical, lt.truth, args.settle)["rms_error"]
                m.update({f"late_{k}": v for k, v in late.items()})
                if smooth:
                    ms = metrics(e.physical, lt.truth, 0.3)["rms_error"]
                    m.update({f"smoothed_{k}": v for k, v in ms.items()})
                    m["smoother_backward_s"] = e.smoothed.backward_s
                    m["smoother_wall_s"] = e.smoothed.wall_s
                mean_nis, exp_nis = e.result.mean_nis(burn_in=int(0.3 * 500))
                label = est_name + (f" ({', '.join(args.config)})" if args.config else "")
                row = {"model": mech.name, "scale": scale, "estimator": label, "seed": seed,
                       "payload_std": ObserverConfig(estimator=est_name if est_name != "ekf@truth" else "ekf",
                                                     **kw).payload_std,
                       "rtf": e.real_time_factor,
                       "wall_s": wall, "diverged": bool(e.result.diverged), "nis_mean": mean_nis,
                       "nis_expected": exp_nis, "n_nis": int(np.isfinite(e.result.nis[150:]).sum()),
                       **{k: m[k] for k in m}}
                it = getattr(obs.ekf.model, "i_theta", None)
                if it is not None:
                    k = int(np.searchsorted(S.t, S.t[0] + args.settle))
                    th = e.result.x_hat[k:, it]
                    sd = np.sqrt(e.result.P_diag[k:, it])
                    row["theta_at_settle"] = float(th[0])
                    row["theta_end"] = float(th[-1])
                    row["theta_max_relerr_after_settle"] = float(np.max(np.abs(th - scale)) / scale)
                    row["theta_std_end"] = float(sd[-1])
                    row["theta_nerr_max"] = float(np.max(np.abs(th - scale) / sd))
                    row["theta_nerr_end"] = float(abs(th[-1] - scale) / sd[-1])
                    if e.result.nominal_p is not None:  # the report's weight of the nominal payload
                        row["nominal_p_at_settle"] = float(e.result.nominal_p[k])
                        row["nominal_p_end"] = float(e.result.nominal_p[-1])
                rows.append(row)
                print(json.dumps({k: (round(v, 6) if isinstance(v, float) else v) for k, v in row.items()
                                  if k in ("scale", "estimator", "seed", "q1", "q3", "dq1", "dq3", "theta_end",
                                           "theta_std_end", "theta_nerr_end", "rtf", "nis_mean")}), flush=True)
    if args.walk_table:
        if not args.from_json:
            ap.error("--walk-table: the table is made from --from-json files")
        from _pages import rewrite_block

        files = ",".join(Path(f).name for f in args.from_json.split(","))
        cmd = f"python benchmarks/estimators.py {args.model} DIR --from-json {files} --walk-table {args.walk_table}"
        rewrite_block(args.walk_table, *WALK, "\n".join(_walk_table(rows, cmd, args.measured_by)))
        return 0
    lines = _table(rows)
    speed = _speed_table(rows)
    if args.doc:
        if args.from_json:  # the tables' command: the files by name, the commands that wrote them listed above
            files = ",".join(Path(f).name for f in args.from_json.split(","))
            cmd = f"python benchmarks/estimators.py {args.model} DIR --from-json {files} --doc {args.doc}"
        else:
            cmd = "python benchmarks/estimators.py " + " ".join(argv if argv is not None else sys.argv[1:])
        Path(args.doc).write_text(
            "# Estimators beyond the paper: measured on the payload-mismatch truths\n\n"
            "Written by `benchmarks/estimators.py` (RMS errors after the 0.3 s start-up, averaged over the seeds; "
            "the noise of seed `s` is the payload study's run `s`; the truths are Exudyn's, cached by "
            "`exuflex study payload MODEL --levels 0,100 --out DIR`). Regenerate with:\n\n"
            + "".join(f"    {c}\n" for c in args.measured_by) + f"    {cmd}\n\n```\n" + "\n".join(lines)
            + "\n```\n\n" + LEGEND
            + ("\n## Speed\n\nMedian wall time of each estimator over the nominal level's seed-0 log "
               "(`estimate`: the filter, its report and the physical estimates), the estimators timed in turn "
               "within one run (`--speed N`); `wall / ekf` is the ratio to the plain EKF's median in that run "
               "(the machine is shared: the ratios, not the absolute times, carry over).\n\n```\n"
               + "\n".join(speed) + "\n```\n" if speed else ""))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


def _speed(mech, args) -> list[dict]:
    """Wall time of each estimator over the same log, the estimators timed in turn ``args.speed`` times (the UKF
    once per three turns: it is two orders slower); the RTS smoother's forward and backward passes with the EKF.
    Medians and the ratio of each median to the EKF's, all from this one run."""
    lvdir = next(d for d in sorted(Path(args.study_dir, "truth").glob("L*"))
                 if float(json.loads((d / "level.json").read_text())["level"].get("payload_scale", 1.0)) == 1.0)
    lt = _load_truth(lvdir / "truth.npz", {})
    meas = measure(mech, lt.clean, lt.torque_t, lt.torques, seed=0, t_end=float(lt.clean.t[-1]))
    S = meas.signals
    span = float(S.t[-1] - S.t[0])
    names = [e for e in args.estimators.split(",")]
    obs = {e: make_observer(mech, ObserverConfig(estimator=e)) for e in names}
    walls: dict[str, list[float]] = {e: [] for e in names}
    walls["smoother (ekf forward + backward)"] = []
    for e in names:  # a first run of each, untimed: kernels loaded, solvers warm
        estimate(obs[e], S.t, S.select(mech.motor_names).data, S.select(obs[e].channels).data)
    for k in range(args.speed):
        for e in names:
            if e == "ukf" and k % 3:
                continue
            U = S.select(mech.motor_names).data
            Y = S.select(obs[e].channels).data
            t0 = time.perf_counter()
            estimate(obs[e], S.t, U, Y)
            walls[e].append(time.perf_counter() - t0)
            if e == "ekf":
                walls["smoother (ekf forward + backward)"].append(estimate(obs[e], S.t, U, Y, smooth=True).smoothed.wall_s)
    ref = float(np.median(walls["ekf"])) if walls.get("ekf") else float("nan")
    rows = [{"speed": e, "repeats": len(w), "median_wall_s": float(np.median(w)), "real_time_factor":
             span / float(np.median(w)), "wall_over_ekf": float(np.median(w)) / ref, "log_s": span}
            for e, w in walls.items() if w]
    for r in rows:
        print(json.dumps(r), flush=True)
    return rows


def _speed_table(rows) -> list[str]:
    rows = [r for r in rows if "speed" in r]
    if not rows:
        return []
    out = [f"{'estimator':>34s} {'repeats':>7s} {'wall (s)':>9s} {'x real time':>11s} {'wall / ekf':>10s}"]
    for r in rows:
        out.append(f"{r['speed']:>34s} {r['repeats']:7d} {r['median_wall_s']:9.3f} {r['real_time_factor']:11.1f} "
                   f"{r['wall_over_ekf']:10.2f}")
    return out


def _table(rows) -> list[str]:
    lines: list[str] = []

    def out(text: str) -> None:
        print(text)
        lines.append(text)

    rows = [r for r in rows if "scale" in r]
    models = list(dict.fromkeys(r.get("model", "") for r in rows))
    for model in models:
        if len(models) > 1:
            out(f"{model}:")
        _model_table([r for r in rows if r.get("model", "") == model], out)
    return lines


WALK = ("<!-- estimators.py walk: begin -->", "<!-- estimators.py walk: end -->")


def _walk_table(rows, cmd: str, measured_by: list[str]) -> list[str]:
    """The payload scale's random walk (``payload_std``) at its two values per model: the spread of ``z``, the
    scale's error over its standard deviation at the last sample, over the seeds; the runs with ``|z| > 3``; and
    the states' RMS errors at the larger walk over those at the smaller (the range over the quantities), at the
    nominal payload and with it doubled. Rows: ``ekf-payload`` without ``--config`` (the report, default
    ``payload_nominal_p``); a row without ``payload_std`` ran with the default."""
    from exuflex.observer.session import ObserverConfig

    default = ObserverConfig().payload_std
    rows = [dict(r, payload_std=r.get("payload_std", default)) for r in rows if r.get("estimator") == "ekf-payload"]
    lines = [WALK[0], "Measured on the payload study's level truths (the nominal payload and the payload doubled) by",
             "", *(f"    {c}" for c in measured_by), f"    {cmd}", "",
             "`z`: the payload scale's error over its standard deviation at the last sample; its mean (sd) and "
             "the runs with abs(z) > 3 over the seeds, at the smaller walk -> the larger; state RMS: the mean RMS "
             "error at the larger walk over the mean at the smaller, smallest-largest over the joint angles, rates "
             "and tip displacements.", "",
             "| mechanism | seeds | `z` mean (sd): nominal | +100 % | runs with abs(z) > 3: nominal | +100 % "
             "| state RMS, larger walk over smaller: nominal | +100 % |",
             "|---|---|---|---|---|---|---|---|"]
    for model in dict.fromkeys(r["model"] for r in rows):
        mine = [r for r in rows if r["model"] == model]
        walks = sorted({r["payload_std"] for r in mine})
        if len(walks) != 2:
            raise SystemExit(f"--walk-table: {model}: expected ekf-payload rows at two payload_std values, got "
                             f"{walks}")
        cols = [c for c in mine[0] if re.fullmatch(r"(d?q|x|y)\d+", c)]
        z, big, ratio, n = {}, {}, {}, set()
        for scale in (1.0, 2.0):
            at = {w: [r for r in mine if r["payload_std"] == w and r["scale"] == scale
                      and np.isfinite(r["theta_end"])] for w in walks}
            n |= {len(v) for v in at.values()}
            zs = {w: np.array([(r["theta_end"] - scale) / r["theta_std_end"] for r in v]) for w, v in at.items()}
            z[scale] = " -> ".join(f"{np.mean(zs[w]):+.2f} ({np.std(zs[w], ddof=1):.2f})" for w in walks)
            big[scale] = " -> ".join(f"{int(np.sum(np.abs(zs[w]) > 3))} of {len(zs[w])}" for w in walks)
            rr = [np.mean([r[c] for r in at[walks[1]]]) / np.mean([r[c] for r in at[walks[0]]]) for c in cols]
            ratio[scale] = f"{min(rr):.3f}-{max(rr):.3f}"
        lines.append(f"| {model} ({walks[0]:g} -> {walks[1]:g}) | {'/'.join(map(str, sorted(n)))} | {z[1.0]} | "
                     f"{z[2.0]} | {big[1.0]} | {big[2.0]} | {ratio[1.0]} | {ratio[2.0]} |")
    return [*lines, WALK[1]]


def _model_table(rows, out) -> None:
    keys = sorted({(r["scale"], r["estimator"]) for r in rows})
    # the joint angles and rates, and the tip's elastic displacements (named by their master dofs)
    names = [c for c in rows[0] if re.fullmatch(r"(d?q|x|y)\d+", c)]
    cols = [c for c in names if c.startswith("q")] + [c for c in names if c.startswith("dq")] + \
        [c for c in names if c[0] in "xy"]
    late = [c for c in cols if "late_" + c in rows[0]]
    w = max(12, *(len(r["estimator"]) for r in rows))
    out(f"{'scale':>5s} {'estimator':>{w}s} {'n':>3s} {'div':>3s} " + " ".join(f"{c:>9s}" for c in cols))
    for sc, en in keys:
        every = [r for r in rows if r["scale"] == sc and r["estimator"] == en]
        # a run whose estimate went non-finite is counted (div) and left out of the means
        rr = [r for r in every if all(np.isfinite(r[c]) for c in cols)]
        cells = " ".join(f"{np.mean([r[c] for r in rr]):9.3g}" for c in cols)
        out(f"{sc:5.2f} {en:>{w}s} {len(rr):3d} {len(every) - len(rr):3d} {cells}")
        if late:
            out("      after the settle time: " + ", ".join(
                f"{c} {np.mean([r['late_' + c] for r in rr]):.3g}" for c in late))
        if "smoothed_q1" in rr[0]:
            cs = [c for c in cols if "smoothed_" + c in rr[0]]
            out("      smoothed / filtered RMS (mean of per-run ratios; worst run): " + ", ".join(
                f"{c} {np.mean([r['smoothed_' + c] / r[c] for r in rr]):.2f} "
                f"({np.max([r['smoothed_' + c] / r[c] for r in rr]):.2f})" for c in cs))
            out(f"      smoother: forward + backward {np.median([r['smoother_wall_s'] for r in rr]):.2f} s, backward "
                  f"{np.median([r['smoother_backward_s'] for r in rr]):.2f} s per run (median)")
        if "nis_mean" in rr[0]:
            nis = np.array([r["nis_mean"] for r in rr])
            nn = np.array([r["n_nis"] for r in rr])
            ex = rr[0]["nis_expected"]
            # the mean NIS over all runs' updates is chi-square(sum dof) / sum n for a consistent filter
            from scipy.stats import chi2

            tot = float(np.sum(nis * nn) / nn.sum())
            dof = ex * nn.sum()
            lo, hi = chi2.ppf(0.025, dof) / nn.sum(), chi2.ppf(0.975, dof) / nn.sum()
            out(f"      NIS: mean {tot:.3f} over {nn.sum()} updates (expected {ex:g}; 95 % band of a consistent "
                  f"filter {lo:.3f}..{hi:.3f}); per-run means {nis.min():.2f}..{nis.max():.2f}")
        if "theta_end" in rr[0]:
            within = np.mean([r["theta_max_relerr_after_settle"] <= 0.10 for r in rr])
            cons = np.mean([r["theta_nerr_end"] <= 3 for r in rr])
            out(f"      payload scale: end mean {np.mean([r['theta_end'] for r in rr]):.3f}, std "
                  f"{np.mean([r['theta_std_end'] for r in rr]):.3f}; within 10 % after settle in {within:.0%} of "
                  f"runs; |err|/std <= 3 at the end in {cons:.0%}")
        if "nominal_p_end" in rr[0]:
            out(f"      nominal payload's probability (the report's weight): at the settle time "
                f"{np.mean([r['nominal_p_at_settle'] for r in rr]):.3f}, at the end "
                f"{np.mean([r['nominal_p_end'] for r in rr]):.3f} (mean over runs; min "
                f"{np.min([r['nominal_p_end'] for r in rr]):.3f}, max {np.max([r['nominal_p_end'] for r in rr]):.3f})")



if __name__ == "__main__":
    sys.exit(main())

"""The IMM payload estimator against issue 29's bars, beside the payload EKF (the frontier it is measured against).

For each model and its payload study's two level truths (the model file's payload and the payload doubled,
``exuflex study payload MODEL --levels 0,100 --runs 1 --out ROOT/<model stem>``), every seed's sensor log (the
noise of the study's run ``s``, :func:`exuflex.measure.measure`) is filtered by the plain EKF, the payload EKF
(``ekf-payload``, its report the model average against the nominal payload) and the IMM (``imm``), all with the
observer's default settings, and scored over the samples after ``--start-up`` s, all seeds together:

- nominal cost: each coordinate's RMS error at the nominal payload over the plain EKF's (bar: <= 1.05 for the
  six-bar's q3 and dq3; every joint coordinate for the gallery);
- +100 %: the RMS error with the payload doubled over the same estimator's at nominal (bar: <= 1.25);
- payload: the share of runs whose payload scale stays within 10 % of the truth's from 1.5 s on (half the run
  where the run is shorter than 3 s) (bar: >= 95 %).

    python benchmarks/imm.py ROOT --models sixbar:20,fourbar:10 --md docs/imm.md --json docs/imm.json

``--speed LOG`` (no study needed) times instead the plain EKF and the IMM, each filtering and smoothing the
log ``LOG`` of ``--models``' first model, paired (the four one after the other, repeated), medians of
``--repeats``; ``--smoother`` holds the IMM smoother against the exact posterior over every mode sequence
(``tests/test_imm.py``'s linear two-mode system) at several dwell times.

The page's measured block (between its markers) is rewritten; the prose around it is the page's own.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from _pages import rewrite_block
from exuflex.measure import measure
from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, estimate, make_observer
from payload_frontier import _level

ROOT = Path(__file__).resolve().parents[1]
NOMINAL_BAR, DOUBLED_BAR, PAYLOAD_BAR, PAYLOAD_TOL = 1.05, 1.25, 0.95, 0.10


def run_model(model: Path, study_dir: Path, seeds: int, estimators: list[str], start_up: float) -> dict:
    """RMS errors per estimator and level, and the payload's hit rate, over ``seeds`` noise realisations."""
    mech, stem = load_mechanism(model), model.stem
    out: dict = {"seeds": seeds, "levels": {}}
    for scale in (1.0, 2.0):
        lt = _level(str(study_dir), scale)
        truth_mech = mech.with_payload_scale(scale) if scale != 1.0 else mech
        observers = {e: make_observer(mech, _config(mech, e)) for e in estimators}
        nq = len(mech.coordinate_names)
        r = observers["ekf"].model.r
        cols = list(range(nq)) + list(range(r, r + nq))
        names = [f"q{i + 1}" for i in range(nq)] + [f"dq{i + 1}" for i in range(nq)]
        se = {e: np.zeros(len(names)) for e in estimators}
        hits = {e: 0 for e in estimators}
        wall = {e: 0.0 for e in estimators}
        count = 0
        for seed in range(seeds):
            S = measure(truth_mech, lt.clean, lt.torque_t, lt.torques, seed=seed, t_end=float(lt.clean.t[-1])).signals
            U = S.select(mech.motor_names).data
            sel = S.t >= S.t[0] + start_up
            late = S.t >= S.t[0] + min(1.5, 0.5 * float(S.t[-1] - S.t[0]))
            tr = np.column_stack([np.interp(S.t, lt.truth.t, lt.truth[n]) for n in names])
            for e, obs in observers.items():
                w0 = time.perf_counter()
                res = estimate(obs, S.t, U, S.select(obs.channels).data).result
                wall[e] += time.perf_counter() - w0
                se[e] += np.sum((res.x_hat[sel][:, cols] - tr[sel]) ** 2, axis=0)
                it = getattr(obs.ekf.model, "i_theta", None)
                if it is not None:
                    hits[e] += bool(np.all(np.abs(res.x_hat[late, it] - scale) <= PAYLOAD_TOL * scale))
            count += int(sel.sum())
            print(f"{stem} payload x{scale:g}: seed {seed + 1}/{seeds}", file=sys.stderr, flush=True)
        out["names"] = names
        out["levels"][str(scale)] = {
            "rms": {e: np.sqrt(v / count).tolist() for e, v in se.items()},
            "payload_hits": {e: hits[e] / seeds for e in estimators if e != "ekf"},
            "wall_s": {e: wall[e] / seeds for e in estimators},
        }
    return out


def traces_figure(model: Path, study_dir: Path, seeds: int, path: str) -> None:
    """The IMM's nominal-mode probability and payload scale against time, seeds ``0 .. seeds - 1``, at the nominal and
    the doubled payload (one panel pair per level)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mech = load_mechanism(model)
    obs = make_observer(mech, _config(mech, "imm"))
    it = obs.ekf.model.i_theta
    fig, axes = plt.subplots(2, 2, figsize=(10, 5.5), sharex=True, constrained_layout=True)
    for col, scale in enumerate((1.0, 2.0)):
        lt = _level(str(study_dir), scale)
        truth_mech = mech.with_payload_scale(scale) if scale != 1.0 else mech
        for seed in range(seeds):
            S = measure(truth_mech, lt.clean, lt.torque_t, lt.torques, seed=seed, t_end=float(lt.clean.t[-1])).signals
            res = estimate(obs, S.t, S.select(mech.motor_names).data, S.select(obs.channels).data).result
            axes[0, col].plot(res.t, res.nominal_p, lw=0.7)
            axes[1, col].plot(res.t, res.x_hat[:, it], lw=0.7)
        axes[0, col].set_title(f"{model.stem}, payload x{scale:g}")
        axes[1, col].axhline(scale, color="k", lw=0.8, ls="--")
        axes[1, col].axhspan(0.9 * scale, 1.1 * scale, color="0.9")
        axes[1, col].set_xlabel("time (s)")
    axes[0, 0].set_ylabel("nominal mode's probability")
    axes[1, 0].set_ylabel("payload scale reported")
    fig.savefig(path, dpi=110)


def speed(model: Path, log_dir: Path, repeats: int) -> dict:
    """Wall times (s) of the EKF and the IMM filtering and smoothing the log, paired, medians of ``repeats``."""
    from exuflex.runs import read_run

    mech, S = load_mechanism(model), read_run(log_dir).sensors
    obs = {e: make_observer(mech, _config(mech, e)) for e in ("ekf", "imm")}
    U = S.select(mech.motor_names).data
    times: dict = {f"{e} {w}": [] for e in obs for w in ("filter", "smoother")}
    for _ in range(repeats + 1):  # the first round compiles and loads: not counted
        for e, o in obs.items():
            Y = S.select(o.channels).data
            for what in ("filter", "smoother"):
                w0 = time.perf_counter()
                estimate(o, S.t, U, Y, smooth=what == "smoother")
                times[f"{e} {what}"].append(time.perf_counter() - w0)
    out = {k: float(np.median(v[1:])) for k, v in times.items()}
    # where the IMM's filter time goes: its modes' model steps, one call from Python per mode and sample (the
    # compiled kernels' argument conversion paid at every call), against the EKF's compiled loop over stretches
    steps = []
    for _ in range(repeats):
        spent = [0.0]
        for m in obs["imm"].ekf.models:
            def timed(*a, f=m.predict, **k):
                w = time.perf_counter()
                try:
                    return f(*a, **k)
                finally:
                    spent[0] += time.perf_counter() - w
            m.predict = timed
        w0 = time.perf_counter()
        estimate(obs["imm"], S.t, U, S.select(obs["imm"].channels).data)
        steps.append(spent[0] / (time.perf_counter() - w0))
        for m in obs["imm"].ekf.models:
            del m.predict
    out["imm steps share"] = float(np.median(steps))
    return out


def smoother_accuracy(dwells: list[float], seeds: int) -> dict:
    """The IMM smoother against the exact posterior (``tests/test_imm.py``): per dwell time the largest error of the
    smoothed means in the exact posterior's standard deviations, of its standard deviations relative, of the mode
    probabilities, and the filter's mean error, over ``seeds`` records of 12 samples."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_imm import smoother_case

    return {str(d): np.max([smoother_case(d, s) for s in range(seeds)], axis=0).tolist() for d in dwells}


def _config(mech, spec: str) -> ObserverConfig:
    """``NAME`` or ``NAME@FIELD=VALUE;...``: the estimator with the model's settings and those fields changed."""
    name, _, rest = spec.partition("@")
    fields = {k: float(v) for k, v in (kv.split("=") for kv in rest.split(";") if kv)}
    return ObserverConfig.for_model(mech, estimator=name, **fields)


def _bars(stem: str, names: list[str]) -> list[int]:
    """The coordinates the bars are judged on: the six-bar's q3 and dq3 (the paper's), every joint elsewhere."""
    if stem == "sixbar":
        return [names.index("q3"), names.index("dq3")]
    return list(range(len(names)))


def markers(block: str) -> tuple[str, str]:
    """The page's markers around the block ``block`` writes."""
    name = f"imm.py{' ' + block if block else ''}"
    return f"<!-- {name}: begin -->", f"<!-- {name}: end -->"


def page(results: dict, command: str, start_up: float, block: str = "") -> str:
    begin, end = markers(block)
    lines = [begin, "", f"Written by `{command}`; `ROOT/<model>` holds the level truths of `exuflex study payload "
             "models/<model>.toml --levels 0,100 --runs 1 --out ROOT/<model>` (Exudyn). `imm` is the estimator above, "
             "`ekf-payload` the payload scale as a state with its report the model average against the nominal "
             "payload ({doc}`/payload_frontier`), all with the observer's default settings. "
             f"RMS errors after {start_up:g} s, all seeds together.", "",
             f"Nominal cost: RMS at the nominal payload over the plain EKF's (bar <= {NOMINAL_BAR}). +100 %: RMS with "
             f"the payload doubled over the same estimator's at nominal (bar <= {DOUBLED_BAR}). Payload: share of "
             f"runs whose payload scale stays within {PAYLOAD_TOL:.0%} of the truth's from 1.5 s on (half the run if "
             f"shorter than 3 s), at nominal / doubled (bar >= {PAYLOAD_BAR:.0%}). Judged on q3 and dq3 (six-bar) or "
             "every joint coordinate (the worst one shown).", "",
             "| model | seeds | estimator | nominal cost | +100 % | payload hits x1 / x2 | bars met |",
             "|---|---|---|---|---|---|---|"]
    for stem, res in results.items():
        names = res["names"]
        idx = _bars(stem, names)
        nom, dbl = res["levels"]["1.0"], res["levels"]["2.0"]
        base = np.array(nom["rms"]["ekf"])
        for e in nom["payload_hits"]:
            a, b = np.array(nom["rms"][e]), np.array(dbl["rms"][e])
            cost, up = (a / base)[idx], (b / a)[idx]
            hx1, hx2 = nom["payload_hits"][e], dbl["payload_hits"][e]
            ok = [cost.max() <= NOMINAL_BAR, up.max() <= DOUBLED_BAR, min(hx1, hx2) >= PAYLOAD_BAR]
            show = (lambda v: ", ".join(f"{names[i]} {v[j]:.3f}" for j, i in enumerate(idx))) if len(idx) <= 2 else (
                lambda v: f"{names[idx[int(np.argmax(v))]]} {v.max():.3f}")
            lines.append(f"| {stem} | {res['seeds']} | {e} | {show(cost)} | {show(up)} | {hx1:.0%} / {hx2:.0%} | "
                         + ("all" if all(ok) else ", ".join(n for n, k in zip(("nominal", "+100 %", "payload"), ok,
                                                                            strict=True) if not k) + " not met")
                         + " |")
    lines += ["", "RMS errors (rad, rad/s) and the filter's mean wall time per run:", "",
              "| model | payload | estimator | RMS errors | wall (s) |", "|---|---|---|---|---|"]
    for stem, res in results.items():
        for scale, lv in res["levels"].items():
            for e, v in lv["rms"].items():
                lines.append(f"| {stem} | x{float(scale):g} | {e} | "
                             + ", ".join(f"{n} {x:.3g}" for n, x in zip(res["names"], v, strict=True))
                             + f" | {lv['wall_s'][e]:.2f} |")
    from exuflex.runs import versions_text

    return "\n".join(lines + ["", f"Versions: {versions_text()}.", "", end])


def speed_page(res: dict, command: str, repeats: int) -> str:
    begin, end = markers("speed")
    head = (f"Written by `{command}`: wall time (s) of `estimate` on the log, the four runs paired (one after the "
            f"other, {repeats} rounds after one not counted), medians.")
    rows = [f"| {w} | {res['ekf ' + w]:.3f} | {res['imm ' + w]:.3f} | {res['imm ' + w] / res['ekf ' + w]:.2f} |"
            for w in ("filter", "smoother")]
    share = (f"Of the IMM's filter time, {100 * res['imm steps share']:.0f} % (median of {repeats} runs) is its modes' "
             "model steps (`predict`, one call from Python per mode and sample).")
    return "\n".join([begin, "", head, "", "| | EKF | IMM | IMM / EKF |", "|---|---|---|---|", *rows, "", share, "",
                      end])


def smoother_page(res: dict, command: str, seeds: int) -> str:
    begin, end = markers("smoother")
    head = (f"Written by `{command}`: {seeds} records of 12 samples each per dwell time (the sample interval "
            "0.01 s); the largest error over all samples and records.")
    cols = ("| dwell (s) | smoothed mean (exact sd) | smoothed sd (relative) | mode probability | filtered mean "
            "(exact smoothed sd) |")
    lines = [begin, "", head, "", cols, "|---|---|---|---|---|"]
    lines += [f"| {d} | {v[0]:.3g} | {v[1]:.3g} | {v[2]:.3g} | {v[3]:.3g} |" for d, v in res.items()]
    return "\n".join([*lines, "", end])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", nargs="?", default=".", help="folder of payload studies, one per model stem (not for "
                    "--speed, --smoother)")
    ap.add_argument("--models", default="sixbar:20", help="MODEL:SEEDS,... (MODEL: a stem of models/, or a .toml "
                    "file; its study in ROOT/<its stem>)")
    ap.add_argument("--estimators", default="ekf-payload,imm")
    ap.add_argument("--start-up", type=float, default=0.3)
    ap.add_argument("--json", default=None, help="results so far, rewritten after each model (resumed from)")
    ap.add_argument("--md", default=None)
    ap.add_argument("--figure", default=None, metavar="PNG", help="the IMM's mode probability and payload traces of "
                    "the first model's first 5 seeds, written to PNG (nothing else is run)")
    ap.add_argument("--block", default="", help="the page's block to rewrite (its markers name it)")
    ap.add_argument("--speed", default=None, metavar="LOG", help="time the EKF and the IMM on LOG (block 'speed')")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--smoother", default=None, metavar="DWELLS", help="the smoother against the exact posterior at "
                    "these dwell times (s, comma-separated; block 'smoother', --repeats records each)")
    args = ap.parse_args(argv)
    given = argv if argv is not None else sys.argv[1:]
    shown = [a for i, a in enumerate(given) if a != "--json" and (i == 0 or given[i - 1] != "--json")]
    command = "python benchmarks/imm.py " + " ".join("ROOT" if a == args.root else a for a in shown)
    if args.figure:
        name = args.models.split(",")[0].partition(":")[0]
        model = Path(name) if name.endswith(".toml") else ROOT / "models" / f"{name}.toml"
        traces_figure(model, Path(args.root) / model.stem, 5, args.figure)
        return 0
    if args.speed or args.smoother:
        if args.speed:
            name = args.models.split(",")[0].partition(":")[0]
            model = Path(name) if name.endswith(".toml") else ROOT / "models" / f"{name}.toml"
            text = speed_page(speed(model, Path(args.speed), args.repeats), command, args.repeats)
        else:
            dwells = [float(d) for d in args.smoother.split(",")]
            text = smoother_page(smoother_accuracy(dwells, args.repeats), command, args.repeats)
        print(text)
        if args.md:
            rewrite_block(args.md, *markers("speed" if args.speed else "smoother"), text)
        return 0
    estimators = ["ekf"] + [e for e in args.estimators.split(",") if e != "ekf"]
    results = {}
    if args.json and Path(args.json).exists():
        results = json.loads(Path(args.json).read_text())["results"]
    for item in args.models.split(","):
        name, _, seeds = item.partition(":")
        model = Path(name) if name.endswith(".toml") else ROOT / "models" / f"{name}.toml"
        if model.stem in results and results[model.stem]["seeds"] == int(seeds or 10):
            continue
        results[model.stem] = run_model(model, Path(args.root) / model.stem, int(seeds or 10), estimators,
                                        args.start_up)
        if args.json:
            Path(args.json).write_text(json.dumps({"command": command, "results": results}, indent=1))
    text = page(results, command, args.start_up, args.block)
    print(text)
    if args.md:
        rewrite_block(args.md, *markers(args.block), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

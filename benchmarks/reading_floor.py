"""The observer's noiseless error floor: the filter on logs without noise, of its own reduced model and of the
full-order ERLS model. Writes docs/reading_floor.md.

    python benchmarks/reading_floor.py [--models three_link_arm,...] [--truth-dir DIR] [--out docs/reading_floor.md]

For every model, two truths of its manoeuvre without noise (no sensor noise, no quantisation; the truth's torques
are the log's): ``reduced`` (:func:`exuflex.truth.engines.reduced_truth`, the observer's own reduced equations
integrated finely: what the filter misses there is its own approximations, the held model, the step map and the
measurement rows) and ``erls`` (the full-order model, as ``benchmarks/filter_requirement.py`` runs it: the
reduction's truncation as well). The observer with default settings filters each: its RMS error over the bound
along the truth per quantity (a noisy log adds the bound's own variance, about ``sqrt(1 + this^2)``), the NIS per
channel, the held configurations' and the measurement rows' evaluations, and the filter's CPU time (no bound).
Truths are kept in ``--truth-dir`` (reused when there).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from _pages import publish  # (a script: its folder is on the path)

from exuflex.mechanism import load_mechanism

ROOT = Path(__file__).resolve().parents[1]
MODELS = ["three_link_arm", "benchmarks/models/three_link_reach.toml", "benchmarks/models/swing_arm.toml",
          "benchmarks/models/long_two_link.toml", "benchmarks/models/wrist_gauge_arm.toml"]

FINDING = """\
What the floor was. On noiseless logs the relative encoders' readings kept an error of 0.4 to 0.7 of the bound
that no interior-mode count removed, and it was the same on the observer's own reduced model as the truth
(three_link_arm q3 0.43 there, 0.42 on the full-order log; three_link_reach q1 0.55, q2 0.39, q3 0.68 there): the
observer's approximations, not the reduction. It grew while the arm accelerated and decelerated and vanished at
constant speed, in the state's q of the wrist, not in the elastic rotation its encoder adds. Split at the exact
states of the reduced truth: the torque held over the interval, against the truth's table, made none of it (a
truth driven by the log's own held torques left the same 0.43); the exact step (``method="rk4"``) left 0.14;
the cached step with its measurement rows exact (``rows_tol`` 0.001) 0.14, with its held model exact but its rows
as they were 0.17 to 0.43 depending on where the radii fell. The rows' error was kept at a tenth of each
channel's own noise or standard deviation, and the held model's at a tenth of each state's standard deviation
per interval: both errors have one sign over a radius, and the filter averages several hundred samples (its
error map's spectral radius 0.997 on three_link_arm at 1 kHz), so a gauge's bias of 0.12 of its standard
deviation left a steady 0.5 of the bound on the wrist's reading and the decelerating arm's (0.84 of it, the
radius set before the torque stepped) 3.8.

What the radii keep now. Both errors are judged by what they do to the estimate: the filter's steady response to
the error repeated at every interval, ``b = (I - A)^-1 c`` with ``A = (I - K H) F`` its error map, in the
coordinates' readings and rates over the filter's standard deviation of them
(``ReducedObserverModel._persistent_bias``; ``tests/test_reading_floor.py`` checks it against the recursion
iterated). The figures below are of that code. Measured on the same truths before it (per channel and per
interval): three_link_arm on the reduced truth q3 0.43, q2 0.13, dq3 0.13 and on the ERLS truth q3 0.42 (0.21
after); three_link_reach on the reduced truth q1 0.55, q2 0.39, q3 0.68, dq3 0.27 (25 held configurations and
39 row centres against 175 and 67 after; `observe`'s wall time with the bound 21 s against 37 s, one run
each on the loaded machine);
long_two_link on its reduced truth q1 0.52, q2 1.33 (after: 0.18, 0.38; `--models
benchmarks/models/long_two_link.toml --engines reduced`, not in the table: its filter took over 400 s on the
loaded machine). swing_arm's floor on its reduced truth was 0.21 (q1) before: its 0.40 to 0.44 on the ERLS truth
and its per-run failures (seed 2, q1 1.62 of the bound on the ERLS truth, before and after) are the reduced
model's against the full-order one, not the observer's approximations.

Over the seeds (`python benchmarks/gallery.py --acceptance --engine erls --truth-dir DIR --models M --seeds 1-3`,
the truths of /tmp/acc/t25b; each run's worst RMS / bound, seeds 1, 2, 3, before -> after): three_link_reach
1.17 (q2), 1.20 (q3), 1.64 (q3) -> 1.17 (q2), 1.08 (q1), 1.36 (q3); three_link_reach_abs 1.16 (q3), 1.16 (q1),
1.56 (q3) -> 1.00 (dq1), 1.12 (q1), 1.20 (q3); long_two_link 1.11 (q2), 1.06 (q2), 1.10 (q2) -> 0.98 (dq1),
1.10 (q1), - (not run); swing_arm unchanged (1.10, 1.62, 1.09 -> 1.11, 1.62, 1.10). The absolute twin
(three_link_reach_abs) improved as well: the floor is not the relative readings' alone (its noiseless
floor was not measured here).
"""


def truth(path: Path, engine: str, out: Path) -> Path:
    """The noiseless truth of ``engine`` ("reduced" or "erls") for the model file, kept in ``out``."""
    from exuflex.measure import measure
    from exuflex.runs import write_run
    from exuflex.truth.engines import plan_drive, reduced_truth, simulate

    if (out / "sensors.csv").is_file():
        return out
    mech = load_mechanism(path)
    d = mech.manoeuvre.duration
    drive = plan_drive(mech, d, 1e-4, None)
    rec = (reduced_truth(mech, drive, d, 1e-4) if engine == "reduced"
           else simulate(mech, drive, "erls", d, 1e-4, erls_step="auto"))
    meas = measure(mech, rec.clean, rec.torque_t, rec.torques, seed=1, noise=False, quantisation=False, t_end=d)
    write_run(out, meas.signals, rec.truth, {"engine": engine, "mechanism": mech.name, "seed": 1,
                                             "settings": {"duration_s": d, "noise": False}}, motors=mech.motor_names)
    return out


def floor(path: Path, run_dir: Path) -> dict:
    """The default observer on the run: RMS / bound per quantity, NIS per channel, evaluations, CPU (no bound)."""
    from exuflex.observer.session import ObserverConfig, make_observer
    from exuflex.runs import read_run
    from exuflex.scoring.run import observe_run

    mech = load_mechanism(path)
    run = read_run(run_dir)
    config = ObserverConfig.for_model(mech)
    obs = make_observer(mech, config)
    o = observe_run(mech, run, config, observer=obs, keep="summary")
    m = obs.model
    counts = {"held": int(m.n_refresh), "rows": int(m.n_rows)}
    obs = make_observer(mech, config)
    c0 = time.process_time()
    observe_run(mech, run, config, observer=obs, with_bound=False, keep="summary")
    return {"ratio": {k: float(v) for k, v in o.summary["ratio_to_bound"].items()},
            "nis": float(o.summary["nis_mean"] / o.summary["nis_expected"]), **counts,
            "cpu_s": time.process_time() - c0}


def _path(name: str) -> Path:
    p = Path(name)
    return (p if p.is_absolute() else ROOT / p) if p.suffix == ".toml" else ROOT / "models" / f"{name}.toml"


def page(rows: list[dict], args: str) -> str:
    lines = ["# The observer's noiseless error floor", "",
             (f"Written by `python benchmarks/reading_floor.py{args}` (the command regenerates this page; its "
              "docstring says what is run)."), "", FINDING,
             ("| model | truth | RMS / bound per quantity | NIS per channel | held configurations | row centres | "
              "filter CPU (s) |"), "|---|---|---|---|---|---|---|"]
    for r in rows:
        q = ", ".join(f"{k} {v:.2f}" for k, v in r["ratio"].items())
        lines.append(f"| {r['model']} | {r['engine']} | {q} | {r['nis']:.4f} | {r['held']} | {r['rows']} | "
                     f"{r['cpu_s']:.1f} |")
    return "\n".join(lines) + "\n\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--engines", default="reduced,erls")
    ap.add_argument("--truth-dir", default=None, help="keep the noiseless truths here (reused when there)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "reading_floor.md"))
    ap.add_argument("--json", default="")
    a = ap.parse_args(argv)
    import tempfile

    keep = tempfile.TemporaryDirectory() if a.truth_dir is None else None
    tdir = Path(a.truth_dir or keep.name)
    rows = []
    for name in a.models.split(","):
        path = _path(name)
        for engine in a.engines.split(","):
            r = {"model": load_mechanism(path).name, "engine": engine,
                 **floor(path, truth(path, engine, tdir / engine / path.stem))}
            rows.append(r)
            print(json.dumps(r), flush=True)
    args = (f" --models {a.models}" if a.models != ",".join(MODELS) else "") + (
        f" --engines {a.engines}" if a.engines != "reduced,erls" else "")
    publish(page(rows, args), a.out)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

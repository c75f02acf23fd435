"""Gravity in the truths and the observer: mechanisms in a vertical plane. Writes ``docs/gravity.md``.

For each model file of ``--models`` and each gravity (the file's ``model.gravity`` replaced by ``--gravity``, and
by ``[0, 0]`` for comparison), in a temporary copy of the file:

1. the Exudyn truth (ANCF) and the full-order ERLS truth of the model's manoeuvre under the same computed torque
   (:func:`exuflex.truth.simulate_run`, ``exuflex simulate MODEL --engine exudyn|erls``): the largest difference
   of the joint coordinates over the run, and the tip's elastic displacement difference as its RMS over the ERLS
   truth's RMS;
2. the observer with default settings (:func:`exuflex.scoring.run.observe_run`, what ``exuflex observe MODEL RUN``
   runs) on the logs of three truths: Exudyn, the ERLS truth and the observer's own reduced model
   (``--engine reduced``, the consistent truth: what the observer gets wrong there is the filter's, not the
   model's): the worst RMS error over the observer's own bound (``ratio_to_bound``) and the time-averaged NIS
   against the mean number of channels per update;
3. the observer's step Jacobian ``F`` (the covariance's propagation, ``predict(...).F`` of the default step) at
   rest at ``q_ref``, against central differences of the exact step (``--method rk4``: every RK4 stage of the
   reduced model's equations at its own state): the block ``d q'_next / d q / dt`` (1/s^2). At rest the velocity forms
   vanish, so what the exact block holds beyond ``F``'s is the weight's change with the configuration (through
   the mass matrix, elastic rows included), the term ``F`` leaves out with the held matrices' change with q.

Usage: python benchmarks/gravity.py [--models benchmarks/models/vertical_link.toml,models/serial_arm.toml]
       [--gravity 0,-9.81] [--seeds 1,2,3] [--engines exudyn,erls,reduced] [--md docs/gravity.md]
       [--json docs/gravity.json]
"""

from __future__ import annotations  # noqa: I001  (exuflex first: single-threaded BLAS before NumPy loads it)

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import exuflex  # noqa: F401

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _pages import publish

ENGINES = ("exudyn", "erls", "reduced")
GRAVITY_LINE = re.compile(r"^gravity\s*=.*$", re.MULTILINE)


def with_gravity(model: Path, gravity: tuple[float, float], folder: Path) -> Path:
    """A copy of ``model`` in ``folder`` (same file name and model name) with ``model.gravity`` replaced."""
    text = model.read_text()
    line = f"gravity = [{gravity[0]!r}, {gravity[1]!r}]"
    if GRAVITY_LINE.search(text):
        text = GRAVITY_LINE.sub(line, text, count=1)
    else:
        text = text.replace("[model]\n", f"[model]\n{line}\n", 1)
    out = folder / model.name
    out.write_text(text)
    return out


def truth_difference(mech, exu, erls) -> dict:
    """Largest joint-coordinate difference (rad or m) and the tip elastic displacement's NRMS difference."""
    from exuflex.sensors import tip_dof_names

    n = min(len(exu.t), len(erls.t))
    dq = max(float(np.max(np.abs(exu[c][:n] - erls[c][:n]))) for c in mech.coordinate_names)
    tip = {}
    for name in tip_dof_names(mech):
        e, r = exu[name][:n], erls[name][:n]
        tip[name] = float(np.sqrt(np.mean((e - r) ** 2) / np.mean(r**2)))
    return {"q_max": dq, "tip_nrms": tip, "q_end_exudyn": [float(exu[c][n - 1]) for c in mech.coordinate_names],
            "q_end_erls": [float(erls[c][n - 1]) for c in mech.coordinate_names]}


def position_block(mech) -> dict:
    """``d q'_next / d q / dt`` (nq, nq; 1/s^2) of the step Jacobian ``F`` of the default (cached) step and of the
    exact step (``method="rk4"``: every RK4 stage at its own state), at rest at ``q_ref`` with zero torque."""
    from exuflex.observer.session import ObserverConfig, make_observer

    m = make_observer(mech, ObserverConfig()).model
    ref = make_observer(mech, ObserverConfig(method="rk4")).model
    z, u = m.initial_state(np.asarray(mech.q_ref, float)), np.zeros(len(mech.motors))
    dt = 1.0 / mech.sample_rate_hz
    r, nq = m.r, m.nq
    F = m.predict(z, u, dt).F
    d = 1e-6
    Fd = np.column_stack([(ref.predict(z + d * e, u, dt).x - ref.predict(z - d * e, u, dt).x)[r : r + nq] / (2 * d)
                          for e in np.eye(len(z))[:nq]])
    return {"F": (F[r : r + nq, :nq] / dt).tolist(), "exact": (Fd / dt).tolist()}


def measure(model: Path, gravity: tuple[float, float], seeds: list[int], engines=ENGINES) -> dict:
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.session import ObserverConfig
    from exuflex.runs import read_run
    from exuflex.scoring.run import observe_run
    from exuflex.truth import simulate_runs

    with tempfile.TemporaryDirectory() as tmp:
        path = with_gravity(model, gravity, Path(tmp))
        mech = load_mechanism(path)
        runs, wall = {}, {}
        for engine in engines:
            t0 = time.perf_counter()
            outs = {seed: Path(tmp) / f"{engine}_{seed}" for seed in seeds}
            runs[engine] = [read_run(p) for p in simulate_runs(path, outs, engine=engine)]
            wall[engine] = time.perf_counter() - t0
        row = {"model": model.stem, "gravity": list(gravity), "seeds": seeds, "truth_wall_s": wall,
               "position_block": position_block(mech), "observer": {}}
        if "exudyn" in runs and "erls" in runs:
            row.update(truth_difference(mech, runs["exudyn"][0].truth, runs["erls"][0].truth))
        for engine in engines:
            per_seed = []
            for run in runs[engine]:
                s = observe_run(mech, run, ObserverConfig()).summary
                ratios = s["ratio_to_bound"]
                worst = max(ratios, key=lambda k: ratios[k] if np.isfinite(ratios[k]) else np.inf)
                per_seed.append({"worst_quantity": worst, "worst_ratio": float(ratios[worst]),
                                 "ratio_to_bound": {k: float(v) for k, v in ratios.items()},
                                 "nis_mean": float(s["nis_mean"]), "nis_expected": float(s["nis_expected"]),
                                 "diverged": bool(s["diverged"])})
            row["observer"][engine] = per_seed
    return row


def markdown(rows: list[dict], command: str) -> str:
    lines = [
        "# Gravity: mechanisms in a vertical plane",
        "",
        (f"Written by `{command}` (each truth simulated once and measured with each seed's noise: an RMS over a "
         "short log scatters by some 10 %; {doc}`/acceptance` gives statistics over seeds)."),
        "",
        ("Each model file is copied with its `model.gravity` replaced (and with `[0, 0]` beside it). The computed "
        "torque of the manoeuvre includes gravity; the Exudyn truth (ANCF cables; the weight of every element, "
        "hub body and lumped mass, `exuflex.groundtruth.build_truth`) and the full-order ERLS truth "
        "(`--engine erls`) run under the same torque table. `benchmarks/models/vertical_link.toml` is a link "
        "lifted from hanging to horizontal, written for this check; the gallery models are horizontal "
        "mechanisms turned into a vertical plane. `tests/test_gravity.py` checks the static deflection of a "
        "cantilever under its weight against Euler-Bernoulli and the vertical link's dynamic agreement; "
        "`benchmarks/models/vertical_fourbar.toml`, a crank-rocker lifting a payload on its rocker's overhang, was "
        "written fresh for the weight's gradient in the observer's step."),
    ]
    compared = [r for r in rows if "tip_nrms" in r]
    if compared:
        lines += [
            "",
            "## Exudyn truth against the ERLS truth",
            "",
            ("| model | gravity (m/s^2) | max abs(dq) (rad) | tip elastic displacement: RMS difference / RMS | "
             "q at the end, Exudyn / ERLS (rad) |"),
            "|---|---|---|---|---|",
        ]
    for r in compared:
        tip = ", ".join(f"{k} {100 * v:.2f} %" for k, v in r["tip_nrms"].items())
        ends = ", ".join(f"{a:.4f} / {b:.4f}" for a, b in zip(r["q_end_exudyn"], r["q_end_erls"], strict=True))
        lines.append(f"| {r['model']} | {r['gravity']} | {r['q_max']:.2e} | {tip} | {ends} |")
    lines += [
        "",
        "## The observer (default settings) on the truths",
        "",
        ("Worst RMS error after the start-up over the observer's own bound (`ratio_to_bound`) and the time-averaged "
        "NIS against its expectation, the mean number of channels per update. `reduced` is the observer's own "
        "reduced model as the truth (`exuflex simulate --engine reduced`): there the model is exact and only the "
        "filter's approximations remain."),
        "",
        "| model | gravity (m/s^2) | truth | worst RMS / bound, per seed | NIS / channels, per seed | diverged |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        for engine, per_seed in r["observer"].items():
            worst = ", ".join(f"{o['worst_ratio']:.2f} ({o['worst_quantity']})" for o in per_seed)
            nis = ", ".join(f"{o['nis_mean']:.2f}" for o in per_seed)
            div = "yes" if any(o["diverged"] for o in per_seed) else "no"
            lines.append(f"| {r['model']} | {r['gravity']} | {engine} | {worst} | {nis} / "
                         f"{per_seed[0]['nis_expected']:.1f} | {div} |")
    lines += [
        "",
        "## The step Jacobian's configuration block at rest",
        "",
        ("`d q'_next / d q / dt` (1/s^2, rows and columns the joint coordinates) of the observer's step Jacobian "
         "`F` (its covariance propagation) and of the exact step (central differences of RK4 on the reduced "
         "model's equations), at rest at `q_ref` with zero torque: at rest the exact block is the weight's change "
         "with the configuration."),
        "",
        "| model | gravity (m/s^2) | F | exact step |",
        "|---|---|---|---|",
    ]
    for r in rows:
        pb = r["position_block"]
        fmt = lambda A: "[" + "; ".join(", ".join(f"{v:.3g}" for v in row) for row in A) + "]"
        lines.append(f"| {r['model']} | {r['gravity']} | {fmt(pb['F'])} | {fmt(pb['exact'])} |")
    lines += [
        "",
        "## The weight in the observer's step",
        "",
        ("The reduced weight is `fg = (W J)^T M_N g` (`W = [S, T]` the nodal velocities per coordinate, `J = H + "
         "[d(H p)/dq, 0]` the consistent velocity map, `M_N` the nodal mass matrix in global axes, `g` the nodal "
         "gravity vector). Its gradient in the positions, `Wg[c, m] = d fg_c / dp_m` "
         "(`ReducedModel.weight_gradient`, computed with the held configuration by `_compiled.held_evaluation`):"),
        "",
        ("- in `q_i` (columns `m < nq`): `d fg / dq_i = (d(W J)/dq_i)^T M_N g + (W J)^T (dM_N/dq_i) g`, with "
         "`d(W J)/dq_i = dS/dq_i J_q + W dH/dq_i` (the links turn, the static shapes change with the configuration; "
         "the same product as `dM_r/dq`) and `dM_N/dq_i = sum_e (dtheta_e/dq_i) R_e (G M_e - M_e G) R_e^T` (the "
         "element and offset masses turn with their links, `G` the rotation generator; point masses without "
         "offset are invariant);"),
        ("- in the elastic coordinates (columns `m >= nq`, q rows, consistent form): `J`'s q columns gain `sum_m p_m "
         "d(H e_m)/dq`, so `d fg_i / dp_m = (W dH/dq_i e_m)^T M_N g`, the last column of `elastic_forms`' `pG`;"),
        ("- exact on undeformed states (the basis's second derivatives times the elastic coordinates are left out, "
         "as in `dM_r/dq`); `tests/test_step_jacobian.py` compares it with central differences of the reduced "
         "forces at rest entry by entry, and the compiled with the NumPy evaluation."),
        "",
        ("The cached step holds `Wg` with the configuration (`HeldSystem.Wg`): over the refresh radius the weight "
         "follows `q` as `fg + Wg[:, :nq] (q - q0)` (first order in every direction, where the secant was first "
         "order along its line only), and the step Jacobian `F = P^n + S df/dz` gains, in its positions' columns, "
         "`Fp = Wg` less the held matrices' change with q as the forces it causes, `dK/dq_i (p + beta p') + "
         "dM/dq_i a` with the interval's mean positions, rates and accelerations (`expansion.position_forces`; `F` "
         "takes the forces as held over the interval, and at the start of a log, undeformed under the weight, the "
         "elastic accelerations are thousands of times their mean over it): under gravity "
         "the positions hold the links' static sag and the accelerations the weight's share, so in global elastic "
         "coordinates a sagging link turned by `dq` changes its elastic force by about as much as its weight's load "
         "changes, and the two terms enter together (the weight's gradient alone made the serial arm's "
         "own-model run worse). Without gravity `Wg` is empty: the held step and `F` are those of the held arrays "
         "alone, and the estimates are byte-identical to those before. Left out, measured: the input matrix's "
         "change with q (`G_r = (W J)^T B_N`; zero to rounding on every gallery model, the motors acting at "
         "joints whose nodal rotations are coordinates), the velocity forms' (quadratic in the rates, along the "
         "secant as before), the mass-proportional damping's (along the secant), the payload's share of the "
         "weight (the payload-scaled step keeps its Jacobian without `Fp`)."),
        "",
        ("How to read it: the rows with gravity 0 are the mechanisms as the gallery has them (the vertical link "
         "then turning in a horizontal plane). The truths' agreement under gravity is that of an open-loop motion "
         "under a computed torque: where the mechanism is unstable under its weight (the serial arm's forearm "
         "pointing up, an inverted pendulum) the two truths' small differences grow along the run, and they agree "
         "less than without gravity. The observer's rows on the `reduced` truth show what gravity does to the "
         "filter alone: a ratio above 1 there, where the model is exact, is not a truth's doing. The exact step's "
         "block at rest also holds what happens within the interval (the elastic coordinates start to sag under "
         "the weight during it), which `F`, first order in the interval, does not. What the weight's gradient "
         "leaves unexplained: the vertical link's own-model q1 is unchanged by it (its block at rest is exact now), "
         "and its ERLS-truth ratios are as large with gravity 0 (a horizontal link), so they are not gravity's; "
         "the serial arm under gravity (its forearm an inverted pendulum) stays above its bound with a NIS above "
         "its channel count on its own model (the cached step's prediction or its covariance is wrong there; "
         "not found here); the fresh four-bar lifting its payload comes close to its bound on both truths, as "
         "without gravity. `F`'s positions' columns are first order in the interval: on the double pendulum of "
         "`tests/test_step_jacobian.py` (gravity, undeformed at rest under its holding torque, and at a moving "
         "state) they are no closer to the exact step's with the held matrices' terms than without; the exact "
         "alternative carries the q-derivatives through every RK4 sub-step (docs/step_jacobian.md)."),
    ]
    return "\n".join(lines) + "\n\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="benchmarks/models/vertical_link.toml,models/serial_arm.toml")
    ap.add_argument("--gravity", default="0,-9.81", help="gx,gy (m/s^2)")
    ap.add_argument("--seeds", default="1", help="noise seeds, comma-separated (one truth per engine, measured "
                    "with each seed's noise)")
    ap.add_argument("--engines", default=",".join(ENGINES), help="truth engines, comma-separated")
    ap.add_argument("--md", default="")
    ap.add_argument("--json", default="")
    ap.add_argument("--page-from", default="", help="write the page (and --json) from the JSON of earlier runs "
                    "(comma-separated) instead of measuring")
    a = ap.parse_args(argv)
    g = tuple(float(v) for v in a.gravity.split(","))
    if len(g) != 2:
        ap.error(f"--gravity: expected gx,gy, got {a.gravity!r}")
    if a.page_from:  # one or several runs' JSON, their rows in order
        docs = [json.loads(Path(f).read_text()) for f in a.page_from.split(",")]
        rows = [r for d in docs for r in d["rows"]]
        command = "`, `".join(d["command"] for d in docs)
        if a.json:
            Path(a.json).write_text(json.dumps({"command": command, "rows": rows}, indent=1) + "\n")
        publish(markdown(rows, command), a.md)
        return
    rows = []
    for m in a.models.split(","):
        for gravity in (g, (0.0, 0.0)):
            rows.append(measure(ROOT / m, gravity, [int(v) for v in a.seeds.split(",")], a.engines.split(",")))
            print(json.dumps(rows[-1]), flush=True)
    command = ("python benchmarks/gravity.py " + " ".join(argv if argv is not None else sys.argv[1:])).strip()
    if a.json:
        Path(a.json).write_text(json.dumps({"command": command, "rows": rows}, indent=1) + "\n")
    publish(markdown(rows, command), a.md)


if __name__ == "__main__":
    main()

"""The implicit ERLS truth: speed against the Exudyn truth, accuracy against the explicit RK4 reference, and the
integrator's numerical damping at the first modes. Writes ``docs/erls_truth.md``.

1. ``exuflex simulate MODEL --duration T --elements-per-link N`` with ``--engine exudyn`` and ``--engine erls``
   (generalized-alpha, ``--erls-step`` k h for each k of ``--erls-steps``), one after the other in this process:
   the truths' wall and CPU times from
   their ``meta.json`` (``timings.truth_s``, ``timings.truth_cpu_s``: build, solve and probes) and their ratio;
2. the model file's (coarse) mesh, the manoeuvre's first ``T`` s: generalized-alpha against RK4 (the explicit
   reference, with the sub-steps its stability needs), max |dq| and the RMS of the tip's elastic displacement
   error over its RMS;
3. generalized-alpha's numerical damping ratio and frequency error at the model's first modes for the step
   (:func:`exuflex.erls.implicit.algorithmic_damping`), beside the model's Rayleigh damping.

Usage: python benchmarks/erls_truth.py [--model models/fourbar.toml] [--duration 1] [--elements-per-link 8]
       [--h 1e-4] [--erls-steps 1,2] [--no-reference] [--out docs/erls_truth.md]
"""

from __future__ import annotations  # noqa: I001  (exuflex first: single-threaded BLAS before NumPy loads it)

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import exuflex  # noqa: F401

import numpy as np

from exuflex.cli.simulate import simulate_run
from exuflex.erls.implicit import FREQ_TOL, GeneralizedAlpha, algorithmic_damping, band_step, erls_implicit
from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import ErlsModel
from exuflex.erls.simulate import rk4_substeps, simulate
from exuflex.manoeuvre import computed_torque, plan
from exuflex.mechanism import load_mechanism, remesh_mechanism

ROOT = Path(__file__).resolve().parents[1]


def timing(model: Path, duration: float, epl: int, h: float, steps: list[float]) -> dict:
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for engine, step in [("exudyn", None)] + [("erls", s) for s in steps]:
            d = simulate_run(model, Path(tmp) / f"{engine}{step}", engine=engine, duration=duration, seed=0, h=h,
                             elements_per_link=epl, erls_step=step)
            meta = json.loads((d / "meta.json").read_text())
            out[engine if step is None else f"erls {step:g}"] = {**meta["settings"]["timings"],
                                                                  "truth": meta["settings"]["truth"]}
    return out


def reference(mech, duration: float, h: float, steps: list[float]) -> dict:
    p = plan(mech, dt=h, t_end=duration)
    tau = computed_torque(mech, p)
    model = ErlsModel(mech)
    n, nq = model.n, model.nq
    y0 = np.zeros(2 * n)
    y0[:nq], y0[n : n + nq] = p.q[0], p.qd[0]
    every = max(1, round(1.0 / mech.sample_rate_hz / h))
    sub = rk4_substeps(model.state_matrix(model.configuration(p.q[0]))[0], h)
    c0 = time.process_time()
    ref = simulate(model.rhs, y0, duration, lambda t: tau[min(int(np.floor(t / h + 1e-6)), len(tau) - 1)],
                   h=h / sub, output_every=every * sub)
    out = {"rk4_substeps": sub, "cpu_rk4_s": time.process_time() - c0, "steps": {}}
    from exuflex.sensors import tip_dof_names

    try:
        names = [nm for nm in tip_dof_names(mech) if nm in model.names]
    except ValueError:  # no tip: the largest elastic coordinate
        names = []
    cols = [model.index(nm) for nm in names] or [int(np.abs(ref.y[:, nq:n]).max(axis=0).argmax()) + nq]
    for step in steps:
        c0 = time.process_time()
        imp = erls_implicit(model, p.t, tau, y0, duration, step, output_every=round(every * h / step))
        cpu = time.process_time() - c0
        nrms = {model.names[c]: float(np.sqrt(np.mean((imp.y[:, c] - ref.y[:, c]) ** 2) / np.mean(ref.y[:, c] ** 2)))
                for c in cols}
        out["steps"][step] = {"q_max_rad": float(np.max(np.abs(imp.y[:, :nq] - ref.y[:, :nq]))), "tip_nrms": nrms,
                              "cpu_s": cpu}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "fourbar.toml"))
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--elements-per-link", type=int, default=8)
    ap.add_argument("--h", type=float, default=1e-4)
    ap.add_argument("--erls-steps", default="1,auto",
                    help="ERLS generalized-alpha steps: multiples of --h, or auto (exuflex simulate's default; default 1,auto)")
    ap.add_argument("--no-reference", action="store_true", help="skip the RK4 comparison (slow on fine meshes)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "erls_truth.md"))
    a = ap.parse_args()
    model = Path(a.model)
    mech = load_mechanism(model)
    out_dt = 1.0 / mech.sample_rate_hz
    steps = [band_step(mech.reduction.band_hz, a.h, out_dt) if k == "auto" else int(k) * a.h
             for k in a.erls_steps.split(",")]
    t = timing(model, a.duration, a.elements_per_link, a.h, steps)
    ex = t["exudyn"]
    cmd = (f"python benchmarks/erls_truth.py --model {model.relative_to(ROOT) if model.is_relative_to(ROOT) else model}"
           f" --duration {a.duration:g} --elements-per-link {a.elements_per_link} --h {a.h:g} --erls-steps {a.erls_steps}")
    lines = [
        "# The implicit ERLS truth",
        "",
        f"Written by `{cmd}` (one run on this machine, whose speed drifts by 30-80 % within minutes; the ratios are",
        "of runs made one after the other in one process).",
        "",
        (f"## Speed: {mech.name}, {a.elements_per_link} elements per link, {a.duration:g} s of the manoeuvre, "
        f"torque table and Exudyn step h = {a.h:g} s"),
        "",
        "Truth time from `meta.json` (`timings.truth_s`, `truth_cpu_s`: model build, time integration and probes).",
        "",
        "| truth | size | wall (s) | CPU (s) | CPU / Exudyn | solver |",
        "|---|---|---|---|---|---|",
        (f"| Exudyn (ANCF, generalized-alpha, h = {a.h:g} s) | {ex['truth'].get('n_coordinates')} coordinates | "
         f"{ex['truth_s']:.2f} | {ex['truth_cpu_s']:.2f} | 1 | "
         f"{ex['truth'].get('newton_per_step', 0):.2f} Newton iterations per step |"),
    ]
    auto = f" = auto: {100 * FREQ_TOL:g} % at {mech.reduction.band_hz:g} Hz"
    for step in steps:
        er = t[f"erls {step:g}"]
        lines.append(
            f"| ERLS (generalized-alpha, step {step:g} s{auto if step == steps[-1] and 'auto' in a.erls_steps else ''}, "
            f"rho_inf {er['truth'].get('rho_inf')}) | "
            f"{er['truth'].get('n_elements')} elements | {er['truth_s']:.2f} | {er['truth_cpu_s']:.2f} | "
            f"{er['truth_cpu_s'] / ex['truth_cpu_s']:.2f} | {er['truth'].get('residuals_per_step', 0):.2f} residuals "
            f"per step, {er['truth'].get('factorisations')} matrix refreshes |"
        )
    lines.append("")
    print("\n".join(lines[5:]))
    if not a.no_reference:
        r = reference(mech, a.duration, a.h, steps)
        lines += [
            f"## Accuracy: the model file's mesh, {a.duration:g} s, against RK4",
            "",
            (f"RK4 with {r['rk4_substeps']} sub-steps of {a.h:g} s (the fewest that are stable) is the reference "
            f"(CPU {r['cpu_rk4_s']:.1f} s)."),
            "",
            "| generalized-alpha step | max abs(dq) (rad) | tip elastic displacement: RMS error / RMS | CPU (s) |",
            "|---|---|---|---|",
        ]
        for step, e in r["steps"].items():
            lines.append(f"| {step:g} s | {e['q_max_rad']:.2g} | "
                         + ", ".join(f"{k} {100 * v:.2f} %" for k, v in e["tip_nrms"].items())
                         + f" | {e['cpu_s']:.1f} |")
        lines.append("")
        print("\n".join(lines[-len(steps) - 6 :]))
    model_e = ErlsModel(remesh_mechanism(mech, a.elements_per_link))
    f = modal_analysis(model_e).frequencies_hz[:6]
    rho = GeneralizedAlpha().rho_inf
    al, be = mech.damping.alpha, mech.damping.beta
    lines += [
        f"## Numerical damping and frequency error at the first modes (rho_inf = {rho})",
        "",
        "Generalized-alpha's damping ratio and relative frequency error on each mode (motors free, at q_ref), from its",
        "amplification matrix (`exuflex.erls.implicit.algorithmic_damping`), beside the model's Rayleigh damping.",
        "",
        "| mode (Hz) | Rayleigh zeta | " + " | ".join(f"zeta, freq. error at {s:g} s" for s in steps) + " |",
        "|---|---|" + "---|" * len(steps),
    ]
    for fi in f:
        w = 2 * np.pi * fi
        cells = []
        for step in steps:
            z, e = algorithmic_damping(w * step, rho)
            cells.append(f"{z[0]:.1e}, {100 * e[0]:+.3f} %")
        lines.append(f"| {fi:.2f} | {100 * (al / (2 * w) + be * w / 2):.2f} % | " + " | ".join(cells) + " |")
    lines.append("")
    text = "\n".join(lines)
    print("\n".join(lines[-len(f) - 7 :]))
    Path(a.out).write_text(text)
    print(f"wrote {a.out}", file=sys.stderr)


if __name__ == "__main__":
    main()

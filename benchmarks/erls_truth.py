"""The implicit ERLS truth: speed against the Exudyn truth, accuracy against the explicit RK4 reference, and the
integrator's numerical damping at the first modes. Writes ``docs/erls_truth.md``.

1. ``exuflex simulate MODEL --duration T --elements-per-link N`` with ``--engine exudyn`` and ``--engine erls``
   (generalized-alpha, ``--erls-step`` k h for each k of ``--erls-steps``; ``auto``: the truth step rule,
   :func:`exuflex.truth.gen_alpha_step`), one after the other in this process: the truths' steps, wall and CPU
   times from their ``meta.json`` (``timings.truth_s``, ``timings.truth_cpu_s``: build, solve and probes) and
   their ratio; the Exudyn truth steps by the same rule below ``--h`` (:func:`exuflex.truth.engines.exudyn_step`);
2. the model file's (coarse) mesh, the manoeuvre's first ``T`` s: generalized-alpha against RK4 (the explicit
   reference, with the sub-steps its stability needs), max |dq| and the RMS of the tip's elastic displacement
   error over its RMS, beside the rule's predicted accumulated error
   (:func:`exuflex.erls.implicit.accumulated_error` of the modes below the band);
3. generalized-alpha's numerical damping ratio and frequency error at the model's first modes for the step
   (:func:`exuflex.erls.implicit.algorithmic_damping`), beside the model's Rayleigh damping.

Usage: python benchmarks/erls_truth.py [--model models/fourbar.toml] [--duration 1] [--elements-per-link 8]
       [--h 1e-4] [--erls-steps 1,2,auto] [--no-reference] [--out docs/erls_truth.md]
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

from exuflex.erls.implicit import (PHASE_TOL, GeneralizedAlpha, accumulated_error, algorithmic_damping, band_modes,
                                   erls_implicit)
from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import ErlsModel
from exuflex.erls.simulate import rk4_substeps, simulate
from exuflex.manoeuvre import computed_torque, plan
from exuflex.mechanism import load_mechanism, remesh_mechanism
from exuflex.truth import gen_alpha_step, simulate_run

ROOT = Path(__file__).resolve().parents[1]


def timing(model: Path, duration: float, epl: int, h: float, steps: list) -> dict:
    """Each truth's settings (its ``meta.json``'s ``truth``, with the step it took) and timings, keyed
    ``exudyn`` and ``erls <step as given>``."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for engine, step in [("exudyn", None)] + [("erls", s) for s in steps]:
            d = simulate_run(model, Path(tmp) / f"{engine}{step}", engine=engine, duration=duration, seed=0, h=h,
                             elements_per_link=epl, erls_step=step)
            meta = json.loads((d / "meta.json").read_text())
            out[engine if step is None else f"erls {step}"] = {**meta["settings"]["timings"],
                                                               "truth": meta["settings"]["truth"]}
    return out


def reference(mech, duration: float, h: float, steps: list) -> dict:
    """Generalized-alpha on the model file's mesh at each step of ``steps`` (a step in s or ``"auto"``: the
    truth step rule for this mesh and duration) against RK4."""
    p = plan(mech, dt=h, t_end=duration)
    tau = computed_torque(mech, p)
    model = ErlsModel(mech)
    n, nq = model.n, model.nq
    y0 = np.zeros(2 * n)
    y0[:nq], y0[n : n + nq] = p.q[0], p.qd[0]
    out_dt = 1.0 / mech.sample_rate_hz
    every = max(1, round(out_dt / h))
    band = mech.reduction.band_hz
    modes = band_modes(model, np.vstack([p.q[0], mech.q_ref]), band)
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
    for given in steps:
        step = gen_alpha_step(given, h, out_dt, band, modes, duration)
        err = accumulated_error(*modes, step, duration)
        c0 = time.process_time()
        imp = erls_implicit(model, p.t, tau, y0, duration, step, output_every=round(out_dt / step))
        cpu = time.process_time() - c0
        nrms = {model.names[c]: float(np.sqrt(np.mean((imp.y[:, c] - ref.y[:, c]) ** 2) / np.mean(ref.y[:, c] ** 2)))
                for c in cols}
        out["steps"][given] = {"step_s": step, "phase_error": float(err.max()) if err.size else 0.0,
                               "q_max_rad": float(np.max(np.abs(imp.y[:, :nq] - ref.y[:, :nq]))), "tip_nrms": nrms,
                               "cpu_s": cpu}
    return out


def _label(given, step: float) -> str:
    return f"{step:.3g} s (auto)" if given == "auto" else f"{step:.3g} s"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "fourbar.toml"))
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--elements-per-link", type=int, default=8)
    ap.add_argument("--h", type=float, default=1e-4)
    ap.add_argument("--erls-steps", default="1,2,auto",
                    help="ERLS generalized-alpha steps: multiples of --h, or auto (the truth step rule, exuflex "
                         "simulate's default; default 1,2,auto)")
    ap.add_argument("--no-reference", action="store_true", help="skip the RK4 comparison (slow on fine meshes)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "erls_truth.md"))
    a = ap.parse_args()
    model = Path(a.model)
    mech = load_mechanism(model)
    band = mech.reduction.band_hz
    steps = ["auto" if k == "auto" else int(k) * a.h for k in a.erls_steps.split(",")]
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
        (f"Both truths integrate by generalized-alpha (rho_inf {GeneralizedAlpha().rho_inf}). `auto` is the truth "
         "step rule ({doc}`/theory/truth_step`): the largest step dividing the sample interval that keeps every "
         f"mode below the band ({band:g} Hz) within an accumulated phase error of {PHASE_TOL:g} over its memory "
         "`min(1/zeta, omega T)` (`exuflex.erls.implicit.phase_step`) and the frequency error at the band's top "
         "within 0.5 % (`band_step`); it depends on the mesh (its modes) and on the run's duration `T`. The Exudyn "
         "truth takes the same rule's step for its own modes where it is below `--h`."),
        "",
        (f"## Speed: {mech.name}, {a.elements_per_link} elements per link, {a.duration:g} s of the manoeuvre, "
        f"torque table h = {a.h:g} s"),
        "",
        "Truth time from `meta.json` (`timings.truth_s`, `truth_cpu_s`: model build, time integration and probes);",
        "`phase error`: the rule's predicted accumulated error at that step (`accumulated_error`, largest mode).",
        "",
        "| truth | size | step (s) | phase error | wall (s) | CPU (s) | CPU / Exudyn | solver |",
        "|---|---|---|---|---|---|---|---|",
        (f"| Exudyn (ANCF, generalized-alpha) | {ex['truth'].get('n_coordinates')} coordinates | "
         f"{ex['truth'].get('step_s', a.h):.3g} | {ex['truth'].get('phase_error', float('nan')):.4f} | "
         f"{ex['truth_s']:.2f} | {ex['truth_cpu_s']:.2f} | 1 | "
         f"{ex['truth'].get('newton_per_step', 0):.2f} Newton iterations per step |"),
    ]
    mesh_steps = []
    for given in steps:
        er = t[f"erls {given}"]
        step = er["truth"]["step_s"]
        mesh_steps.append(step)
        lines.append(
            f"| ERLS ({'auto' if given == 'auto' else 'fixed'}) | {er['truth'].get('n_elements')} elements | "
            f"{step:.3g} | {er['truth'].get('phase_error', float('nan')):.4f} | "
            f"{er['truth_s']:.2f} | {er['truth_cpu_s']:.2f} | "
            f"{er['truth_cpu_s'] / ex['truth_cpu_s']:.2f} | {er['truth'].get('residuals_per_step', 0):.2f} residuals "
            f"per step, {er['truth'].get('factorisations')} matrix refreshes |"
        )
    lines.append("")
    print("\n".join(lines[7:]))
    if not a.no_reference:
        r = reference(mech, a.duration, a.h, steps)
        lines += [
            f"## Accuracy: the model file's mesh, {a.duration:g} s, against RK4",
            "",
            (f"RK4 with {r['rk4_substeps']} sub-steps of {a.h:g} s (the fewest that are stable) is the reference "
            f"(CPU {r['cpu_rk4_s']:.1f} s). `auto` on this mesh is the rule's step for its own modes."),
            "",
            ("| generalized-alpha step | phase error (predicted) | max abs(dq) (rad) | tip elastic displacement: "
             "RMS error / RMS | CPU (s) |"),
            "|---|---|---|---|---|",
        ]
        for given, e in r["steps"].items():
            lines.append(f"| {_label(given, e['step_s'])} | {e['phase_error']:.4f} | {e['q_max_rad']:.2g} | "
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
        "amplification matrix (`exuflex.erls.implicit.algorithmic_damping`), beside the model's Rayleigh damping,",
        f"at the speed table's steps ({a.elements_per_link} elements per link).",
        "",
        "| mode (Hz) | Rayleigh zeta | "
        + " | ".join(f"zeta, freq. error at {_label(g, s)}" for g, s in zip(steps, mesh_steps)) + " |",
        "|---|---|" + "---|" * len(steps),
    ]
    for fi in f:
        w = 2 * np.pi * fi
        cells = []
        for step in mesh_steps:
            z, e = algorithmic_damping(w * step, rho)
            cells.append(f"{z[0]:.1e}, {100 * e[0]:+.3f} %")
        lines.append(f"| {fi:.2f} | {100 * (al / (2 * w) + be * w / 2):.2f} % | " + " | ".join(cells) + " |")
    lines.append("")
    text = "\n".join(lines)
    print("\n".join(lines[-len(f) - 8 :]))
    Path(a.out).write_text(text)
    print(f"wrote {a.out}", file=sys.stderr)


if __name__ == "__main__":
    main()

"""The implicit ERLS truth: speed against the Exudyn truth, accuracy against the explicit RK4 reference, and the
integrator's numerical damping at the first modes. Writes ``docs/erls_truth.md``.

1. ``exuflex simulate MODEL --duration T --elements-per-link N`` with ``--engine exudyn`` and ``--engine erls``
   (generalized-alpha, step ``--h``), one after the other in this process: the truths' wall and CPU times from
   their ``meta.json`` (``timings.truth_s``, ``timings.truth_cpu_s``: build, solve and probes) and their ratio;
2. the model file's (coarse) mesh, the manoeuvre's first ``T`` s: generalized-alpha against RK4 (the explicit
   reference, with the sub-steps its stability needs), max |dq| and the RMS of the tip's elastic displacement
   error over its RMS;
3. generalized-alpha's numerical damping ratio and frequency error at the model's first modes for the step
   (:func:`exuflex.erls.implicit.algorithmic_damping`), beside the model's Rayleigh damping.

Usage: python benchmarks/erls_truth.py [--model models/fourbar.toml] [--duration 1] [--elements-per-link 8]
       [--h 1e-4] [--no-reference] [--out docs/erls_truth.md]
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
from exuflex.erls.implicit import GeneralizedAlpha, algorithmic_damping, erls_implicit
from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import ErlsModel
from exuflex.erls.simulate import rk4_substeps, simulate
from exuflex.manoeuvre import computed_torque, plan
from exuflex.mechanism import load_mechanism, remesh_mechanism

ROOT = Path(__file__).resolve().parents[1]


def timing(model: Path, duration: float, epl: int, h: float) -> dict:
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for engine in ("exudyn", "erls"):
            d = simulate_run(model, Path(tmp) / engine, engine=engine, duration=duration, seed=0, h=h,
                             elements_per_link=epl)
            meta = json.loads((d / "meta.json").read_text())
            out[engine] = {**meta["settings"]["timings"], "truth": meta["settings"]["truth"]}
    return out


def reference(mech, duration: float, h: float) -> dict:
    p = plan(mech, dt=h, t_end=duration)
    tau = computed_torque(mech, p)
    model = ErlsModel(mech)
    n, nq = model.n, model.nq
    y0 = np.zeros(2 * n)
    y0[:nq], y0[n : n + nq] = p.q[0], p.qd[0]
    every = max(1, round(1.0 / mech.sample_rate_hz / h))
    c0 = time.process_time()
    imp = erls_implicit(model, p.t, tau, y0, duration, h, output_every=every)
    c1 = time.process_time()
    sub = rk4_substeps(model.state_matrix(model.configuration(p.q[0]))[0], h)
    ref = simulate(model.rhs, y0, duration, lambda t: tau[min(int(np.floor(t / h + 1e-6)), len(tau) - 1)],
                   h=h / sub, output_every=every * sub)
    c2 = time.process_time()
    from exuflex.sensors import tip_dof_names

    try:
        names = [nm for nm in tip_dof_names(mech) if nm in model.names]
    except ValueError:  # no tip: the largest elastic coordinate
        names = []
    cols = [model.index(nm) for nm in names] or [int(np.abs(ref.y[:, nq:n]).max(axis=0).argmax()) + nq]
    nrms = [float(np.sqrt(np.mean((imp.y[:, c] - ref.y[:, c]) ** 2) / np.mean(ref.y[:, c] ** 2))) for c in cols]
    return {
        "q_max_rad": float(np.max(np.abs(imp.y[:, :nq] - ref.y[:, :nq]))),
        "tip_nrms": dict(zip([model.names[c] for c in cols], nrms, strict=True)),
        "rk4_substeps": sub,
        "cpu_gen_alpha_s": c1 - c0,
        "cpu_rk4_s": c2 - c1,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "fourbar.toml"))
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--elements-per-link", type=int, default=8)
    ap.add_argument("--h", type=float, default=1e-4)
    ap.add_argument("--no-reference", action="store_true", help="skip the RK4 comparison (slow on fine meshes)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "erls_truth.md"))
    a = ap.parse_args()
    model = Path(a.model)
    mech = load_mechanism(model)
    t = timing(model, a.duration, a.elements_per_link, a.h)
    ex, er = t["exudyn"], t["erls"]
    ratio_wall = er["truth_s"] / ex["truth_s"]
    ratio_cpu = er["truth_cpu_s"] / ex["truth_cpu_s"]
    cmd = (f"python benchmarks/erls_truth.py --model {model.relative_to(ROOT) if model.is_relative_to(ROOT) else model}"
           f" --duration {a.duration:g} --elements-per-link {a.elements_per_link} --h {a.h:g}")
    lines = [
        "# The implicit ERLS truth",
        "",
        f"Written by `{cmd}` (figures of one run on this machine; its speed drifts by 30-80 % within minutes, the",
        "ratios are of runs made one after the other in one process).",
        "",
        f"## Speed: {mech.name}, {a.elements_per_link} elements per link, {a.duration:g} s of the manoeuvre, h = {a.h:g} s",
        "",
        "| truth | coordinates | wall (s) | CPU (s) | solver |",
        "|---|---|---|---|---|",
        (f"| Exudyn (ANCF, generalized-alpha) | {ex['truth'].get('n_coordinates')} | {ex['truth_s']:.2f} | "
        f"{ex['truth_cpu_s']:.2f} | {ex['truth'].get('newton_per_step', 0):.2f} Newton iterations per step |"),
        (f"| ERLS (generalized-alpha, rho_inf {er['truth'].get('rho_inf')}) | {er['truth'].get('n_elements')} elements | "
        f"{er['truth_s']:.2f} | {er['truth_cpu_s']:.2f} | {er['truth'].get('residuals_per_step', 0):.2f} residuals "
        f"per step, {er['truth'].get('factorisations')} factorisations |"),
        "",
        f"ERLS / Exudyn: {ratio_wall:.2f} (wall), {ratio_cpu:.2f} (CPU).",
        "",
    ]
    print("\n".join(lines[5:]))
    if not a.no_reference:
        r = reference(mech, a.duration, a.h)
        lines += [
            f"## Accuracy: the model file's mesh, {a.duration:g} s, against RK4",
            "",
            f"Generalized-alpha at h = {a.h:g} s against RK4 ({r['rk4_substeps']} sub-steps of {a.h:g} s, the fewest "
            f"that are stable): max |dq| {r['q_max_rad']:.2g} rad; tip elastic displacement error RMS / RMS "
            + ", ".join(f"{k} {100 * v:.2f} %" for k, v in r["tip_nrms"].items())
            + f"; CPU {r['cpu_gen_alpha_s']:.1f} s (generalized-alpha) and {r['cpu_rk4_s']:.1f} s (RK4).",
            "",
        ]
        print(lines[-2])
    model_e = ErlsModel(remesh_mechanism(mech, a.elements_per_link))
    f = modal_analysis(model_e).frequencies_hz[:6]
    rho = GeneralizedAlpha().rho_inf
    zeta, err = algorithmic_damping(2 * np.pi * f * a.h, rho)
    al, be = mech.damping.alpha, mech.damping.beta
    lines += [
        f"## Numerical damping at the first modes (h = {a.h:g} s, rho_inf = {rho})",
        "",
        "| mode (Hz) | omega h | numerical zeta | frequency error | Rayleigh zeta (model) |",
        "|---|---|---|---|---|",
    ]
    for fi, z, e in zip(f, zeta, err, strict=True):
        w = 2 * np.pi * fi
        lines.append(f"| {fi:.2f} | {w * a.h:.4f} | {z:.2e} | {100 * e:+.4f} % | {100 * (al / (2 * w) + be * w / 2):.2f} % |")
    lines.append("")
    text = "\n".join(lines)
    print("\n".join(lines[-len(f) - 5 :]))
    Path(a.out).write_text(text)
    print(f"wrote {a.out}", file=sys.stderr)


if __name__ == "__main__":
    main()

"""The truths' step rule: accumulated phase error against the old per-cycle rule. Writes ``docs/truth_step.md``.

For each model file of ``--models``, under its manoeuvre's computed torque (planned once):

1. the ERLS truth (generalized-alpha) at the old rule's step (:func:`exuflex.erls.implicit.band_step`: the frequency
   error at ``band_hz`` within 0.5 %) and at the new one (``"auto"``: the smaller of that and
   :func:`exuflex.erls.implicit.phase_step`), against the same model by RK4 (exact to the model; ``--reference
   rk4``) or by generalized-alpha at a quarter of the new step (``fine``, the default: its error is 1/16 of the new
   step's, and RK4 needs many sub-steps on a fine mesh's stiff modes): per estimated
   quantity the RMS difference after 0.1 s over the observer's bound (the bound of seed 1 in ``--bounds``, an
   acceptance JSON of ``benchmarks/gallery.py``; without it, over the RK4 truth's RMS), the predicted accumulated
   error (:func:`exuflex.erls.implicit.accumulated_error`, the largest over the modes below the band), the steps
   and the CPU time of each (ratio new / old);
2. with ``--exudyn``, the Exudyn truth (ANCF) at its old step ``--h`` and at the rule's
   (:func:`exuflex.truth.engines.exudyn_step`), against Exudyn at half the rule's step.

Usage: python benchmarks/truth_step.py [--models fivebar,...,benchmarks/models/vertical_link.toml] [--bounds J]
       [--exudyn vertical_link,...] [--reference fine|rk4] [--h 1e-4] [--md docs/truth_step.md] [--json J]
"""

from __future__ import annotations  # noqa: I001  (exuflex first: single-threaded BLAS before NumPy loads it)

import argparse
import json
import sys
import time
from pathlib import Path

import exuflex  # noqa: F401

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _pages import COMMIT, publish

GALLERY = "fivebar,fourbar,l_arm,serial_arm,single_link,sixbar,slider_crank,three_link_arm"


def model_path(model: str) -> Path:
    return Path(model) if model.endswith(".toml") else ROOT / "models" / f"{model}.toml"


def rms_over(a, b, scale: dict) -> dict:
    scored = b.t >= 0.1
    return {k: float(np.sqrt(np.mean((a[k][scored] - b[k][scored]) ** 2)) / s) for k, s in scale.items() if s > 0}


def measure(model: str, h: float, bounds: dict, exudyn: bool, reference: str = "fine") -> dict:
    from exuflex.erls.implicit import accumulated_error, band_modes, band_step
    from exuflex.erls.model import ErlsModel
    from exuflex.groundtruth import simulate_truth
    from exuflex.mechanism import load_mechanism
    from exuflex.sensors import monotonic_record, true_states
    from exuflex.truth.engines import erls_truth, exudyn_mesh, exudyn_step, plan_drive

    mech = load_mechanism(model_path(model))
    name = model_path(model).stem
    duration, out = mech.manoeuvre.duration, 1.0 / mech.sample_rate_hz
    drive = plan_drive(mech, duration, h)
    modes = band_modes(ErlsModel(mech), np.vstack([drive.q0, mech.q_ref]), mech.reduction.band_hz)
    row = {"model": name, "duration_s": duration, "band_hz": mech.reduction.band_hz,
           "modes_hz": sorted({round(float(w) / (2 * np.pi), 1) for w in modes[0]}),
           "zeta": sorted({round(float(z), 4) for z in modes[1]})}

    def erls(integrator, step):
        st: dict = {}
        c = time.process_time()
        rec = erls_truth(mech, drive.t, drive.tau, duration, h, out, drive.q0, drive.qd0, integrator=integrator,
                         stats=st, step=step)
        return true_states(mech, rec), time.process_time() - c, st

    if reference == "rk4":
        ref, row["reference_cpu_s"], _ = erls("rk4", None)
    else:
        from exuflex.truth.engines import gen_alpha_step

        fine = gen_alpha_step("auto", h, out, mech.reduction.band_hz, modes, duration) / 4
        st: dict = {}
        c = time.process_time()
        ref = true_states(mech, erls_truth(mech, drive.t, drive.tau, duration, fine, out, drive.q0, drive.qd0,
                                           stats=st, step=fine))
        row["reference_cpu_s"] = time.process_time() - c
    row["reference"] = reference
    scale = bounds.get(name) or {k: float(np.sqrt(np.mean(ref[k] ** 2))) for k in ref.names if k != "t"}
    row["scale"] = "bound" if bounds.get(name) else "rms"
    for label, step in (("old", band_step(mech.reduction.band_hz, h, out)), ("new", "auto")):
        tr, cpu, st = erls(integrator="gen-alpha", step=step)
        row[label] = {"step_s": st["step_s"], "n_steps": st["n_steps"], "cpu_s": cpu,
                      "accumulated": float(np.max(accumulated_error(*modes, st["step_s"], duration), initial=0.0)),
                      "error": rms_over(tr, ref, scale)}
    row["cpu_ratio"] = row["new"]["cpu_s"] / row["old"]["cpu_s"]
    row["step_ratio"] = row["new"]["n_steps"] / row["old"]["n_steps"]
    if exudyn:
        mesh = exudyn_mesh(mech)
        step, stepping = exudyn_step(mech, h, out, duration, drive.q0, mesh, "ancf")
        runs = {}
        for label, s in (("old", h), ("new", step), ("reference", step / 2)):
            t0 = time.perf_counter()
            probes = simulate_truth(mech, drive.t, drive.tau, duration, h=s, output_dt=out, q0=drive.q0,
                                    elements_per_link=mesh, formulation="ancf")
            runs[label] = (true_states(mech, monotonic_record(probes)), time.perf_counter() - t0)
        row["exudyn"] = {"step_s": step, "accumulated": stepping["phase_error"],
                         **{label: {"step_s": s, "wall_s": runs[label][1],
                                    "error": rms_over(runs[label][0], runs["reference"][0], scale)}
                            for label, s in (("old", h), ("new", step))}}
    return row


def worst(err: dict) -> str:
    k = max(err, key=err.get)
    return f"{k} {err[k]:.2f}"


def page(rows: list[dict], command: str, models: list[str] | None = None) -> str:
    lines = ["# The truths' step: accumulated phase error", "",
             (f"Written by `{command}` (ERLS truths one after the other in one process; CPU ratios of runs made "
              "one after the other, on a shared machine)."), "",
             ("The rule and its derivation: {doc}`/theory/truth_step`. Errors: RMS after 0.1 s of the truth's "
              "difference from the reference, over the observer's bound (seed 1 of the acceptance JSON given by "
              "`--bounds`; `rms`: over the reference's RMS), the largest quantity; `predicted`: "
              "the largest accumulated error of the modes below the band (`accumulated_error`), the rule's "
              "measure, kept within `PHASE_TOL` = 0.004 by the new step."), "",
             f"## ERLS truth (generalized-alpha) against {'RK4' if rows and rows[0]['reference'] == 'rk4' else 'itself at a quarter of the new step'}", "",
             ("| model | modes below the band (Hz) | old step (s) | predicted | error | new step (s) | predicted | error "
              "| steps new/old | CPU new/old |"), "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        o, n = r["old"], r["new"]
        lines.append(f"| {r['model']} | {', '.join(f'{f:g}' for f in r['modes_hz'])} | {o['step_s']:.3g} | "
                     f"{o['accumulated']:.4f} | {worst(o['error'])} | {n['step_s']:.3g} | {n['accumulated']:.4f} | "
                     f"{worst(n['error'])} | {r['step_ratio']:.1f} | {r['cpu_ratio']:.1f} |")
    ex = [r for r in rows if "exudyn" in r]
    if ex:
        lines += ["", "## Exudyn truth (ANCF, generalized-alpha) against Exudyn at half the new step", "",
                  "| model | old step (s) | error | new step (s) | predicted | error | wall new/old |",
                  "|---|---|---|---|---|---|---|"]
        for r in ex:
            e = r["exudyn"]
            lines.append(f"| {r['model']} | {e['old']['step_s']:.3g} | {worst(e['old']['error'])} | "
                         f"{e['new']['step_s']:.3g} | {e['accumulated']:.4f} | {worst(e['new']['error'])} | "
                         f"{e['new']['wall_s'] / e['old']['wall_s']:.1f} |")
    lines += ["", *notes(rows, models)]
    return "\n".join(lines) + "\n\n"


def notes(rows: list[dict], models: list[str] | None = None) -> list[str]:
    """The page's remarks, from the rows: the models scored over the reference's RMS, and the rows whose error at
    the new step is above the tolerance's aim (0.2 of the bound: the rule's 0.004 times the factor of 50 its
    derivation allows a mode's ringing against the bound, {doc}`/theory/truth_step`)."""
    out = []
    missing = [model_path(m).stem for m in models or () if model_path(m).stem not in {r["model"] for r in rows}]
    if missing:
        out.append(f"Not measured in this run (the command's models the JSON does not hold yet): {', '.join(missing)}.")
    commits = sorted({r.get("commit") or "?" for r in rows})
    if len(commits) > 1:
        out.append("The rows were measured on the code at commits " + ", ".join(
            f"{c} ({', '.join(r['model'] for r in rows if (r.get('commit') or '?') == c)})" for c in commits) + ".")
    rms = [r["model"] for r in rows if r["scale"] == "rms"]
    if rms:
        out.append(f"{', '.join(rms)}: no acceptance bound in `--bounds`, errors over the reference's RMS.")
    high = [f"{r['model']} ({worst(r['new']['error'])})" for r in rows
            if r["scale"] == "bound" and max(r["new"]["error"].values()) > 0.2]
    high += [f"{r['model']} Exudyn ({worst(r['exudyn']['new']['error'])})" for r in rows
             if "exudyn" in r and r["scale"] == "bound" and max(r["exudyn"]["new"]["error"].values()) > 0.2]
    out.append("At the new step every truth is within 0.2 of the bound of its reference." if not high else
               f"Above 0.2 of the bound at the new step: {', '.join(high)}: its modes ring more against its bound "
               "than the rule's factor of 50 assumes ({doc}`/theory/truth_step`).")
    return [" ".join(out), ""]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default=GALLERY + ",benchmarks/models/vertical_link.toml")
    ap.add_argument("--bounds", default=None, help="an acceptance JSON (benchmarks/gallery.py --json): the bounds")
    ap.add_argument("--exudyn", default="", help="models (of --models) whose Exudyn truth is measured too")
    ap.add_argument("--reference", choices=("fine", "rk4"), default="fine")
    ap.add_argument("--h", type=float, default=1e-4)
    ap.add_argument("--md", default=None)
    ap.add_argument("--json", default=None, help="the rows, written after each model; a rerun of the same command "
                    "with it resumes (keeps the models it holds)")
    ap.add_argument("--from-json", default=None, help="re-render the page from an earlier run's --json (its "
                    "\"command\" kept) instead of measuring")
    a = ap.parse_args(argv)
    if a.from_json:
        saved = json.loads(Path(a.from_json).read_text())
        publish(page(saved["rows"], saved["command"], a.models.split(",")), a.md)
        return
    bounds = {}
    if a.bounds:
        for r in json.loads(Path(a.bounds).read_text())["runs"]:
            if r["engine"] == "erls" and r["model"] not in bounds:
                bounds[r["model"]] = r["bound_rms"]
    exudyn = {Path(m).stem for m in a.exudyn.split(",") if m}
    command = _command(a)
    done = {}
    if a.json and Path(a.json).exists():  # resume: the models an earlier run of the same command measured
        saved = json.loads(Path(a.json).read_text())
        if saved.get("command") == command:
            done = {r["model"]: r for r in saved["rows"]}
    rows = []
    for m in a.models.split(","):
        name = model_path(m).stem
        rows.append(done.get(name) or dict(measure(m, a.h, bounds, name in exudyn, a.reference), commit=COMMIT))
        print(json.dumps(rows[-1]), flush=True)
        if a.json:
            Path(a.json).write_text(json.dumps({"rows": rows, "command": command}, indent=1))
    publish(page(rows, command), a.md)


def _command(a) -> str:
    return ("python benchmarks/truth_step.py" + (f" --models {a.models}" if a.models else "")
               + (f" --bounds {a.bounds}" if a.bounds else "") + (f" --exudyn {a.exudyn}" if a.exudyn else "")
               + f" --reference {a.reference} --h {a.h:g}" + (f" --md {a.md}" if a.md else ""))


if __name__ == "__main__":
    main()

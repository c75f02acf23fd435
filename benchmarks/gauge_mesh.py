"""The curvature gauges' mesh rule (``exuflex.reduction.gauge_rule``): its figures, written to ``docs/gauge_mesh.md``.

    python benchmarks/gauge_mesh.py [--models M1,M2,...] [--acceptance A.json,...] [--before B.json,...]
                                    [--md docs/gauge_mesh.md]

1. The bubble against a converged mesh: on ``benchmarks/models/three_link_reach_abs.toml`` (its forearm gauge at a
   node between two 0.1125 m elements) every mode below 150 Hz (motors free, ``q_ref``) read per unit
   (mass-normalised) mode on the file's mesh and on a 24-element-per-link mesh, their difference and the bubble's
   estimate ``-beta rho A omega^2 v / EI`` (``v`` the mode's transverse displacement at the gauge).
2. For every model with curvature gauges (default: those of ``benchmarks/models`` and ``models``), per gauge: the
   file's ``beta``, ``b`` of that gauge alone on the file's mesh and its worst quantity, the rule's length ``h_g``,
   the link's elements in the file and with the rule, and ``b`` alone on the rule's mesh; per model the worst
   ``b`` of the gauges together (``exuflex.reduction.gauge_rule.mesh_bias``) for an observer on the file's or the
   rule's mesh against an exact truth and against the Exudyn truth's default mesh (``exudyn_mesh``, its own
   stations: ``beta`` of the difference), with the ratio ``sqrt(1 + b)`` it predicts.
3. With ``--acceptance`` (and ``--before``): the acceptance runs of ``benchmarks/gallery.py --acceptance --json`` on
   the rule's meshes and on the files' meshes (``--note`` says which code and truths), each model and truth's
   worst quantity's mean RMS / bound and the mean NIS / channels over the seeds.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _pages import publish

ROOT = Path(__file__).resolve().parents[1]
BUBBLE_MODEL = ROOT / "benchmarks" / "models" / "three_link_reach_abs.toml"
BUBBLE_GAUGE = "c_fore"
BUBBLE_FMAX = 150.0
BUBBLE_FINE = 24
PAIRS = (("file", "exact"), ("file", "exudyn"), ("rule", "exact"), ("rule", "exudyn"))


def bubble_rows() -> list[dict]:
    """Section 1 of the module docstring."""
    from exuflex.erls.modal import modal_analysis
    from exuflex.erls.model import ErlsModel
    from exuflex.mechanism import load_mechanism, remesh_mechanism
    from exuflex.reduction.gauge_rule import bubble_factor

    own = load_mechanism(BUBBLE_MODEL)
    s = next(x for x in own.sensors if x.name == BUBBLE_GAUGE)
    models = [ErlsModel(m) for m in (own, remesh_mechanism(own, BUBBLE_FINE))]
    modes = [modal_analysis(m) for m in models]
    k = int(np.sum(modes[0].frequencies_hz < BUBBLE_FMAX))
    nq = models[0].nq
    sign = np.sign(np.sum(modes[0].shapes[:nq, :k] * modes[1].shapes[:nq, :k], axis=0))
    read = []
    for m, md in zip(models, modes, strict=True):
        cfg = m.configuration(np.asarray(own.q_ref, float))
        read.append(m.curvature_row(cfg, s.link, s.station) @ md.shapes[nq:, :k])
    read[1] = read[1] * sign
    fine = models[1]
    cfg = fine.configuration(np.asarray(own.q_ref, float))
    e, xi = fine.locate(s.link, s.station)[0]
    node = fine.el_dofs[e][3 if xi == 1.0 else 0] // 3
    normal = cfg.R[e][:2, :2] @ np.array([0.0, 1.0])
    v = normal @ modes[1].nodal_shapes[3 * node : 3 * node + 2, :k] * sign
    lk = own.link(s.link)
    beta = bubble_factor(lk.stations, s.station, lk.length)
    w = 2 * np.pi * modes[0].frequencies_hz[:k]
    est = -beta * lk.material.rho * lk.section.A * w**2 * v / (lk.material.E * lk.section.I)
    return [{"f": float(modes[0].frequencies_hz[j]), "file": float(read[0][j]), "fine": float(read[1][j]),
             "error": float(read[0][j] - read[1][j]), "bubble": float(est[j])} for j in range(k)]


def model_rows(path: Path) -> tuple[list[dict], dict | None]:
    """Section 2 of the module docstring: per gauge, and per model the worst ``b`` of each observer and truth."""
    from exuflex.erls.model import ErlsModel
    from exuflex.groundtruth.builder import link_mesh_stations
    from exuflex.mechanism import load_mechanism
    from exuflex.reduction.gauge_rule import (
        bubble_factor,
        gauge_errors,
        gauge_lengths,
        observer_mesh,
        rule_configurations,
    )
    from exuflex.reduction.truncation import PlannedInput
    from exuflex.truth.engines import exudyn_mesh

    own = load_mechanism(path)
    before = gauge_lengths(own)
    if not before:
        return [], None
    rule = observer_mesh(own)
    after = gauge_lengths(rule)
    gauges = [next(x for x in own.sensors if x.name == g) for g in before]
    rows = [{"model": path.stem, "gauge": s.name, "noise": s.noise_std, "beta": before[s.name]["beta"],
             "b_file": before[s.name]["b_gauge"], "quantity": before[s.name]["quantity"], "h_g": before[s.name]["h_g"],
             "elements": (own.link(s.link).n_elements, rule.link(s.link).n_elements),
             "b_rule": after[s.name]["b_gauge"]} for s in gauges]
    planned = PlannedInput.of(own)
    if planned is None:
        return rows, None

    def betas(stations_of):
        return {s.name: bubble_factor(stations_of(s.link), s.station, own.link(s.link).length) for s in gauges}

    n_ex = exudyn_mesh(own)
    meshes = {"file": betas(lambda lk: own.link(lk).stations), "rule": betas(lambda lk: rule.link(lk).stations),
              "exudyn": betas(lambda lk: link_mesh_stations(own, lk, n_ex)), "exact": {s.name: 0.0 for s in gauges}}
    worst = {k: (0.0, None) for k in PAIRS}
    model = ErlsModel(own)
    for q in rule_configurations(own):
        err = gauge_errors(model, q, planned)
        var = np.where(err["var"] > 0, err["var"], np.inf)
        for obs, tru in PAIRS:
            d = sum((meshes[obs][g] - meshes[tru][g]) * err[g] for g in meshes[obs])
            b = (d**2).mean(axis=0) / var
            i = int(np.argmax(b))
            if b[i] > worst[(obs, tru)][0]:
                worst[(obs, tru)] = (float(b[i]), planned.quantities[i])
    return rows, {"model": path.stem, "exudyn_mesh": n_ex, "worst": worst}


def acceptance_rows(paths: str | None, seeds: dict | None = None) -> dict:
    """``(model, engine) -> (worst quantity, its mean RMS / bound, mean NIS / channels, N, seeds)`` from gallery
    JSONs (``FILE@LABEL``: the file's runs under the truth name ``LABEL``); with ``seeds`` (the same map's) only
    those seeds of each model and truth."""
    out = {}
    for one in (paths or "").split(","):
        if not one:
            continue
        one, _, label = one.partition("@")  # FILE@LABEL: its runs' truth named LABEL (e.g. another truth mesh)
        data = json.loads(Path(one).read_text())
        per: dict = {}
        for run in data["runs"]:
            key = (run["model"], label or run["engine"])
            if seeds is None or run["seed"] in seeds.get(key, ()):
                per.setdefault(key, []).append(run)
        for key, runs in per.items():
            ratios: dict = {}
            for run in runs:
                for q, v in (run.get("ratio_to_bound") or {}).items():
                    ratios.setdefault(q, []).append(v)
            means = {q: float(np.mean(v)) for q, v in ratios.items()}
            worst = max(means, key=means.get)
            nis = [run["nis_mean"] / run["nis_expected"] for run in runs if run.get("nis_expected")]
            out[key] = (worst, means[worst], float(np.mean(nis)) if nis else math.nan, len(runs),
                        sorted(run["seed"] for run in runs))
    return out




DERIVATION = """\
A curvature gauge reads the bending of its link at one station; the model reads it from the two-node cubic
(Hermite) elements there. The reduced model's size does not depend on the full model's mesh, but the row with which
the filter reads each of its coordinates does, and a gauge is a strong sensor: a percent of error in its row per
unit of a mode that rings at tens of noise standard deviations is a model error the filter turns into an error of
its estimates (`three_link_reach_abs`: the forearm gauge's 4-element mesh reads mode 2, 58 Hz, 1.5 % high against
a 24-element mesh; the observer's dq2 was 2.3-2.5 bounds on the Exudyn truth).

**The error of a reading.** Between its nodes an element carries the distributed transverse load `w(s, t) = rho A
(g - a(s, t)) . n`: the link's weight less the inertia of its material (`a` the whole acceleration, the rigid
motion's and the bending's; `n` the link's normal), and `EI v'''' = w`. The cubic element with the consistent
load vector holds the nodal values and slopes of the deflection under a point load exactly, so for a load that
varies slowly over the element the field's error is the quartic bubble `w / (24 EI) x^2 (h - x)^2` and the
reading's error is

    v_h'' - v'' = -beta w / EI,   beta = (h^2 - 6 h x + 6 x^2) / 12

at `x` from the element's start (`h^2 / 12` at its ends, `-h^2 / 24` at its middle); at a node the gauge reads the
mean of its two elements' ends, `beta = (h_1^2 + h_2^2) / 24` (`exuflex.reduction.gauge_rule.bubble_factor`). In a
mode of frequency `omega` the load is `rho A omega^2 v`; with the weight alone it is the static sag rule this page
held before (`exuflex.mechanism.refine.gauge_sag_length`, kept as a function). The dynamic nodal values are not
exact (their error is of higher order in `h`), so the bubble is an estimate; the first table checks it.

**What the filter makes of it.** Along the manoeuvre a gauge's error is `e(t) = -beta w(s, t) / EI`. As the
reduction's filter requirement does (`exuflex.reduction.truncation`, `docs/filter_requirement.md`), the full model
linearised at rest at a configuration is driven from rest by the torques that give the rigid mechanism the planned
acceleration there (the trapezoid's steps included); its accelerations give `a(s, t)` at every gauge, and the
weight is added. The full model's steady Kalman filter (the stated torque noise and the channels' noise, the
observer's tuning and the bound's) reading the channels with `e(t)` added makes an error `d(t)` in the estimated
quantities; with `s^2` its steady posterior variance,

    b = mean(d^2) / s^2

raises an RMS error over the bound from 1 to `sqrt(1 + b)` (the two parts are uncorrelated). `b` is quadratic in
the `beta`s; for a filter on one mesh against a truth on another it is that of the difference of their `beta`s.

**The rule.** `b <= GAUGE_MESH_MAX = 0.05` (a consistent ratio 1 becomes at most 1.025) in every estimated
quantity at `q_ref` and at 3 configurations of the manoeuvre; each of the `m` gauges gets `0.05 / m^2` alone (the
filter's responses add, so their RMS adds at most), which fixes its largest `|beta|` and its element length `h_g =
sqrt(12 |beta|)`; `exuflex.mechanism.refine.gauge_mesh` adds a node at `h_g` on either side of a gauge at a node
(halfway where the next node is within `2 h_g`) and splits an element holding a gauge into equal parts within
`h_g`. `exuflex.reduction.gauge_rule.observer_mesh(mech)` applies it (about a second); the file's nodes, ids and
masters are kept, and the reduced model's coordinates are chosen on the finer full model as before.

**Not the default.** The observer is built on the mechanism it is given: `make_observer(observer_mesh(mech))`
applies the rule, and an ERLS truth must then be at least as fine (`simulate(observer_mesh(mech), ...)`). Applied by
default (a branch that built every observer and ERLS truth on it; the last table), the rule makes the observer right
against converged truths (Exudyn with 16 elements per link: single_link's y11 1.97 -> 1.24, three_link_reach_abs's
dq2 1.86 -> 1.09) and fixes three_link_reach_abs on its default Exudyn truth, but it costs elsewhere: (1) the
Exudyn truth's default mesh (`exudyn_mesh`, 4 elements per link or the file's finest link) is not converged at the
gauges either, and where it shares the file's mesh its error cancels the observer's: with the observer converged
the truth's own error shows (crane_arm q2 1.05 -> 1.17, gauge_reach q2 1.06 -> 1.34, single_link x10 1.04 -> 1.11);
(2) the six-bar's crank (one element in the paper's mesh) gets interior modes, the file's fixed interior count
keeps a 360 Hz one in place of a 446 Hz one, and `exuflex bench --quick`'s cached path differs from its
rk4 reference over the 0.2 s start-up by 0.78 of the error in dq3 (0.37 on the paper's mesh; its test allows 0.75);
(3) the automatic interior count changes with the full model (serial_arm 6 -> 5 reduced coordinates,
three_link_reach 20 -> 16). The default needs an Exudyn truth converged at the gauges (the same bubble holds for its
cubic ANCF elements) and a decision on the six-bar's mesh.
"""


def page(bubble: list[dict], rows: list[dict], models: list[dict], after: dict, before: dict, command: str,
         note: str = "") -> str:
    lines = ["# The curvature gauges' mesh", "", f"Generated by `{command}` (do not edit: rerun the script).", "",
             "## The rule", "", DERIVATION, "## The bubble against a converged mesh", "",
             f"`{BUBBLE_MODEL.relative_to(ROOT)}`, gauge `{BUBBLE_GAUGE}`: every mode below {BUBBLE_FMAX:.0f} Hz "
             "(motors free, `q_ref`) read per unit (mass-normalised) mode on the file's mesh and on "
             f"{BUBBLE_FINE} elements per link, their difference and the bubble's estimate `-beta rho A omega^2 v / "
             "EI` (`v` the mode's transverse displacement at the gauge, from the fine mesh).", "",
             "| mode (Hz) | file (1/m) | fine (1/m) | file - fine | bubble | file - fine, % of fine | "
             "bubble / (file - fine) |", "|---|---|---|---|---|---|---|"]
    for r in bubble:
        lines.append(f"| {r['f']:.2f} | {r['file']:+.4g} | {r['fine']:+.4g} | {r['error']:+.3g} | "
                     f"{r['bubble']:+.3g} | {100 * r['error'] / r['fine']:+.2f} | {r['bubble'] / r['error']:.2f} |")
    lines += ["", "## The rule on the models", "",
              "Per curvature gauge: `beta` on the file's mesh, `b` of that gauge alone on the file's mesh (its worst "
              "estimated quantity), the rule's `h_g`, the gauge's link's elements in the file and with the rule, and "
              "`b` of the gauge alone on the rule's mesh (its share of the limit is `0.05 / m^2`).", "",
              "| model | gauge | noise (1/m) | file beta (m^2) | file: b alone | h_g (m) | link elements: file -> rule "
              "| rule: b alone |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['model']} | {r['gauge']} | {r['noise']:.3g} | {r['beta']:+.3g} | {r['b_file']:.3g} "
                     f"({r['quantity']}) | {r['h_g']:.4f} | {r['elements'][0]} -> {r['elements'][1]} | "
                     f"{r['b_rule']:.3g} |")
    lines += ["", "Per model, the gauges together: the worst `b` and the ratio `sqrt(1 + b)` it predicts for a "
              "consistent filter, for an observer on the file's or the rule's mesh against an exact truth and against "
              "the Exudyn truth's default mesh (`exudyn_mesh` elements per link; its gauges where its stations put "
              "them). The ERLS truth shares the observer's mesh: 0.", "",
              "| model | Exudyn elements per link | file vs exact | file vs Exudyn | rule vs exact | rule vs Exudyn |",
              "|---|---|---|---|---|---|"]
    for m in models:
        cells = []
        for key in PAIRS:
            b, q = m["worst"][key]
            cells.append(f"{b:.3f} {q or ''} ({math.sqrt(1 + b):.2f})")
        lines.append(f"| {m['model']} | {m['exudyn_mesh']} | " + " | ".join(cells) + " |")
    if after:
        lines += ["", "## The observer on the rule's meshes", "",
                  "Acceptance runs (`benchmarks/gallery.py --acceptance`, default settings): per model and truth the "
                  "worst quantity's mean RMS / bound over the seeds and the mean NIS / channels, on the rule's "
                  "meshes" + (" and on the files' meshes, the same seeds." if before else "."), "",
                  "| model | truth | N | rule: worst, mean RMS / bound | NIS / channels | "
                  + ("file: worst, mean RMS / bound | NIS / channels |" if before else ""),
                  "|---|---|---|---|---|" + ("---|---|" if before else "")]
        for key in sorted(after):
            w, v, nis, n, _ = after[key]
            row = f"| {key[0]} | {key[1]} | {n} | {w} {v:.2f} | {nis:.3f} |"
            if before:
                b = before.get(key)
                row += f" {b[0]} {b[1]:.2f} | {b[2]:.3f} |" if b else " - | - |"
            lines.append(row)
        worse = [f"{k[0]} on {k[1]} ({before[k][1]:.2f} -> {v[1]:.2f})" for k, v in sorted(after.items())
                 if k in before and v[1] > before[k][1] + 0.05]
        lines += ["", "Worse on the rule's meshes by more than 0.05 in the worst mean: "
                  + (", ".join(worse) if worse else "none") + "."]
    if note:
        lines += ["", note]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default=None, help="comma-separated model files (default: every one with curvature "
                    "gauges in benchmarks/models and models)")
    ap.add_argument("--acceptance", default=None, help="gallery.py --json files of runs on the rule's meshes")
    ap.add_argument("--before", default=None, help="gallery.py --json files of runs on the files' meshes")
    ap.add_argument("--md", default=None, help="write the page here")
    ap.add_argument("--note", default="", help="a sentence on the runs (the code and truths of each)")
    args = ap.parse_args(argv)
    paths = ([Path(m) for m in args.models.split(",")] if args.models
             else sorted((ROOT / "benchmarks" / "models").glob("*.toml")) + sorted((ROOT / "models").glob("*.toml")))
    rows, models = [], []
    for p in paths:
        r, m = model_rows(p)
        rows += r
        if m is not None:
            models.append(m)
    after = acceptance_rows(args.acceptance)
    before = acceptance_rows(args.before, {k: v[4] for k, v in after.items()})
    args_text = "".join(f" {a}" if " " not in a else f" '{a}'" for a in (argv or sys.argv[1:]))
    text = page(bubble_rows(), rows, models, after, before, "python benchmarks/gauge_mesh.py" + args_text, args.note)
    publish(text + "\n", args.md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

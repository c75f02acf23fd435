"""The gauge rule under gravity (``exuflex.mechanism.refine.gauge_sag_length``): its figures, written to
``docs/gauge_mesh.md``.

    python benchmarks/gauge_mesh.py [--models M1,M2,...] [--acceptance A.json,...] [--before B.json,...]
                                    [--md docs/gauge_mesh.md]

For every model with gravity and curvature gauges (default: those of ``benchmarks/models`` and ``models``):

1. per gauge the rule's element length ``h_g``, the model file's elements next to the gauge and the rule's, and
   the bound ``w h^2 / (12 EI)`` of each in the gauge's noise (``w = rho A |g|``);
2. the check of the derivation on the full-order ERLS model: the gauge's reading of the linear static sag under
   the weight (``exuflex.erls.validity.weight_sag``, ``ErlsModel.curvature_row``) at the model's ``q_ref`` on the
   file's mesh and on the rule's (``exuflex.mechanism.refine.gauge_mesh``), less the reading on a reference mesh
   (the rule's mesh with every element split to at most ``L / 128``, whose own error is at most ``w (L / 128)^2
   / (12 EI)``), in the gauge's noise;
3. with ``--acceptance`` (and ``--before``): the acceptance runs of ``benchmarks/gallery.py --acceptance --json``
   on the rule's meshes (runs of a code that applied it in the loader and kept the gauge stations in the Exudyn
   truth's link mesh; ``--note`` says which) and on the files' meshes, each model and truth's worst quantity's mean
   RMS / bound and the mean NIS / channels over the seeds.
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
REFERENCE_PER_LINK = 128


def neighbours(lk, station: float) -> list[float]:
    """The lengths of the elements next to a station (one inside an element, two at a node)."""
    st = lk.stations
    eps = 1e-9 * lk.length
    return [b - a for a, b in zip(st, st[1:]) if a - eps <= station <= b + eps]


def sag_readings(mech, names: list[str]) -> np.ndarray:
    """The gauges' readings of the full model's linear static sag under the weight at ``q_ref``."""
    from exuflex.erls.model import ErlsModel
    from exuflex.erls.validity import weight_sag

    model = ErlsModel(mech)
    cfg = model.configuration(np.asarray(mech.q_ref, float))
    u, _ = weight_sag(model, cfg)
    by = {s.name: s for s in mech.sensors}
    return np.array([model.curvature_row(cfg, by[n].link, by[n].station) @ u for n in names])


def model_rows(path: Path) -> list[dict]:
    """Per gauge of one model: the rule's length, the meshes' neighbouring elements, the bounds and the readings'
    errors (module docstring, 1. and 2.)."""
    from exuflex.mechanism import load_mechanism, remesh_mechanism
    from exuflex.mechanism.refine import gauge_mesh, gauge_sag_length

    own = load_mechanism(path)
    rule = gauge_mesh(own)
    g = math.hypot(*rule.gravity)
    gauges = [s for s in rule.sensors if math.isfinite(gauge_sag_length(rule, s))]
    if not gauges:
        return []
    ref = remesh_mechanism(rule, REFERENCE_PER_LINK)
    names = [s.name for s in gauges]
    r_file, r_rule, r_ref = sag_readings(own, names), sag_readings(rule, names), sag_readings(ref, names)
    rows = []
    for k, s in enumerate(gauges):
        lk = rule.link(s.link)
        EI, w = lk.material.E * lk.section.I, lk.material.rho * lk.section.A * g
        bound = lambda h: w * h * h / (12.0 * EI) / s.noise_std  # noqa: E731
        hf, hr = neighbours(own.link(s.link), s.station), neighbours(lk, s.station)
        rows.append({
            "model": path.stem, "gauge": s.name, "link": s.link, "station": s.station, "noise": s.noise_std,
            "h_g": gauge_sag_length(rule, s), "file_h": max(hf), "rule_h": max(hr),
            "file_bound": bound(max(hf)), "rule_bound": bound(max(hr)),
            "sag": float(r_ref[k]) / s.noise_std,
            "file_err": float(r_file[k] - r_ref[k]) / s.noise_std,
            "rule_err": float(r_rule[k] - r_ref[k]) / s.noise_std,
            "ref_bound": bound(lk.length / REFERENCE_PER_LINK),
            "elements": [sum(m.link(n).n_elements for n in {x.link for x in gauges}) for m in (own, rule)],
        })
    return rows


def acceptance_rows(paths: str | None, seeds: dict | None = None) -> dict:
    """``(model, engine) -> (worst quantity, its mean RMS / bound, mean NIS / channels, N, seeds)`` from gallery
    JSONs; with ``seeds`` (the same map's) only those seeds of each model and truth."""
    out = {}
    for one in (paths or "").split(","):
        if not one:
            continue
        data = json.loads(Path(one).read_text())
        per: dict = {}
        for run in data["runs"]:
            key = (run["model"], run["engine"])
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
A curvature gauge reads the bending of its link. Under gravity the link carries its weight as a distributed
transverse load ``w`` (at most ``rho A |g|``, the link across gravity). The Euler-Bernoulli deflection under it is
a quartic (its fourth derivative ``w / EI``). The model's two-node cubic (Hermite) elements with the consistent
load vector hold the nodal deflections and slopes exactly: the deflection under a point load is cubic between the
nodes, so the nodal values are exact for any load the consistent vector integrates. Within an element of length
``h`` the error is then the quartic bubble with zero end values and slopes,

    v - v_h = w / (24 EI) x^2 (h - x)^2,

and its curvature error

    v'' - v_h'' = w / (12 EI) (h^2 - 6 h x + 6 x^2)

is largest at the element's ends, ``w h^2 / (12 EI)`` (``-w h^2 / (24 EI)`` at its middle). A gauge at a node
reads the mean of its two elements' end curvatures (``ErlsModel.curvature_row``), each with the same sign, so
its error is at most ``w h^2 / (12 EI)`` with ``h`` the longer of its two elements; only those two enter it (the
rest of the mesh holds the nodal values exactly). The gauge's static sag is a constant bias the filter cannot
tell from the state: it turns into a bias of the estimate. The rule keeps it within ``GAUGE_SAG_TOL`` = 0.1 of
the gauge's noise standard deviation ``sigma``:

    h_g = sqrt(12 EI tol sigma / w),

and ``exuflex.mechanism.refine.gauge_mesh`` adds a node at ``h_g`` on either side of every curvature gauge where
the file's element there is longer (halfway to the next node where that is within ``2 h_g``; a gauge inside an
element has that element split into equal parts within ``h_g``). Without gravity, or without gauges, the mesh is
the file's.

Not the loader's default. Applied by the loader to every model file, with the Exudyn truth's link mesh keeping the
gauge and the stations ``h_g`` beside it as element boundaries, the rule gives the drooping four-bar the hand-set
0.05 m mesh's result from its 0.15 m file mesh, but makes the crane arm's Exudyn q2 worse (the table below), for a
reason not found; until that is understood a model file sets its mesh near the gauges (``h_g`` is what
``gauge_sag_length`` gives it).

What the rule leaves to the file. The deflection's error is ``O(h^4)`` and the slope's ``O(h^3)``: the tip
readings and the foreshortening (second order in the slopes, ``docs/shortening.md``) need nothing finer. The
manoeuvre's own distributed inertial loads (``rho A a`` of the rigid motion, varying along the link) give the
same kind of error with ``a`` for ``g``; the rule covers the static weight, the load every instant carries. Why
0.1: a bias of ``b`` gauge noise standard deviations biases the estimates by ``b`` times the square root of the
number of samples the filter averages over, in bounds (on the drooping four-bar's Exudyn truth 1.8 standard
deviations gave q1 9 bounds, some 5 per standard deviation); at 0.1 the bias adds at most about 0.5 bound in
quadrature there (a ratio of 1.12 at most from a consistent 1).
"""


def page(rows: list[dict], after: dict, before: dict, command: str, note: str = "") -> str:
    lines = ["# The gauge rule under gravity", "",
             f"Generated by `{command}` (do not edit: rerun the script).", "", "## The rule", "", DERIVATION, "",
             "## The rule on the models with gravity", "",
             "Per curvature gauge: the rule's element length `h_g`; the longer element next to the gauge in the "
             "model file and with the rule, and the bound `w h^2 / (12 EI)` of each in the gauge's noise; the "
             "full model's static sag under the weight at `q_ref` as the gauge reads it on a reference mesh "
             f"(every element at most `L / {REFERENCE_PER_LINK}`; its own bound in the last column), and the "
             "file's and the rule's readings less that one, in the gauge's noise (signed).", "",
             "| model | gauge | noise (1/m) | h_g (m) | file: element (m), bound | rule: element (m), bound | "
             "sag reading / noise | file's error / noise | rule's error / noise | reference's bound |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['model']} | {r['gauge']} | {r['noise']:.3g} | {r['h_g']:.4f} | {r['file_h']:.4f}, "
                     f"{r['file_bound']:.2f} | {r['rule_h']:.4f}, {r['rule_bound']:.3f} | {r['sag']:+.1f} | "
                     f"{r['file_err']:+.3f} | {r['rule_err']:+.3f} | {r['ref_bound']:.4f} |")
    if after:
        lines += ["", "## The observer on the rule's meshes", "",
                  "Acceptance runs (`benchmarks/gallery.py --acceptance`, default settings): per model and truth the "
                  "worst quantity's mean RMS / bound over the seeds and the mean NIS / channels, on the rule's "
                  "meshes" + (" and on the files' meshes before it, the same seeds." if before else "."), "",
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
    ap.add_argument("--models", default=None, help="comma-separated model files (default: every one with gravity "
                    "and curvature gauges in benchmarks/models and models)")
    ap.add_argument("--acceptance", default=None, help="gallery.py --json files of runs on the rule's meshes")
    ap.add_argument("--before", default=None, help="gallery.py --json files of runs on the files' meshes")
    ap.add_argument("--md", default=None, help="write the page here")
    ap.add_argument("--note", default="", help="a sentence on the runs (what the before files' meshes were)")
    args = ap.parse_args(argv)
    paths = ([Path(m) for m in args.models.split(",")] if args.models
             else sorted((ROOT / "benchmarks" / "models").glob("*.toml")) + sorted((ROOT / "models").glob("*.toml")))
    rows = [r for p in paths for r in model_rows(p)]
    after = acceptance_rows(args.acceptance)
    before = acceptance_rows(args.before, {k: v[4] for k, v in after.items()})
    args_text = "".join(f" {a}" if " " not in a else f" '{a}'" for a in (argv or sys.argv[1:]))
    text = page(rows, after, before, "python benchmarks/gauge_mesh.py" + args_text, args.note)
    publish(text + "\n", args.md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

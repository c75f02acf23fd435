"""The links' foreshortening (the second order of link points' positions in the elastic displacements) against the
noise and the observer's bound, and what it changes in the acceptance figures; writes docs/shortening.md.

    python benchmarks/shortening.py --truth-dir DIR --models M1,M2 --before BEFORE.json --after AFTER.json \
        --md docs/shortening.md --json OUT.json

Per model (by gallery name or by file), on the Exudyn truth of seed 1 in ``DIR/exudyn/<model>/s1`` (a run folder of
``benchmarks/gallery.py --truth-dir``):

1. the tip's second order ``w = C (Gr p)^2`` (``ReducedObserverModel.tip_maps``) along the observer's estimate
   on that log, RMS and largest per component, against the bound of the tip's elastic displacement (the run's
   ``bound_rms``): what the linear rows would leave out of the scored tip;
2. the same of the observer's point channels (slider encoders; the tip sensors are truth-only), against their
   noise: what the filter's measurement function (linear in p) leaves out;
3. the static part at five configurations along the plan (``exuflex.erls.validity.weight_sag``: the full model's
   linear sag under the weight; zero without gravity).

``--before`` / ``--after``: JSONs of ``benchmarks/gallery.py --acceptance`` on the same truths before and after the
second order (the observer's tip and the ERLS engines' probes), whose per-quantity means over the seeds the page
tables side by side.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def _model_path(model: str) -> Path:
    p = Path(model)
    return p if p.suffix == ".toml" else ROOT / "models" / f"{model}.toml"


def along_estimate(mech, run, every: int = 5) -> dict:
    """The tip's and the point channels' second order along the observer's estimate on ``run`` (module docstring,
    1. and 2.), every ``every``-th sample after the start-up."""
    from exuflex.erls.sensing import SecondOrderPlan, point_channel
    from exuflex.observer.session import ObserverConfig, make_observer
    from exuflex.scoring.run import observe_run
    from exuflex.sensors import tip_dof_names, tip_point

    config = ObserverConfig()
    obs = make_observer(mech, config)
    out = observe_run(mech, run, config, observer=obs)
    res = out.estimate.result
    som = obs.model
    nq, r = som.nq, som.r
    keep = np.flatnonzero(res.t >= res.t[0] + config.start_up)[::every]
    tp = tip_point(mech)
    names = tip_dof_names(mech)
    pts = [(c, s) for c in obs.channels for s in mech.sensors if s.name == c and s.kind == "slider"]
    plans = [(c, s, point_channel(som.model, s), SecondOrderPlan(som.model, [(s.link, point_channel(som.model, s)[0])]))
             for c, s in pts]
    W, Wp = [], []
    for k in keep:
        x = res.x_hat[k]
        q, p = x[:nq], x[:r]
        _, C, Gr = som.tip_maps(q, *tp)
        g = Gr @ p
        W.append(C @ (g * g))
        if plans:
            rc = som.rm.cb.at(q)
            u = rc.H[nq:] @ p
            Wp.append([wv @ pl.at(rc.cfg.pose).values(u)[0, :2] for _, _, (_, wv, _), pl in plans])
    W = np.array(W)
    bound = out.summary["bound_rms"]
    row = {"tip": {n: {"rms": float(np.sqrt(np.mean(W[:, i] ** 2))), "max": float(np.max(np.abs(W[:, i]))),
                       "bound": float(bound[n])} for i, n in enumerate(names)}}
    if plans:
        Wp = np.array(Wp)
        row["channels"] = {c: {"max": float(np.max(np.abs(Wp[:, i]))), "noise": float(s.noise_std)}
                           for i, (c, s, _, _) in enumerate(plans)}
    return row


def static_part(mech, points: int = 5) -> list[float]:
    """The tip's second order under the weight's linear static sag at ``points`` configurations along the plan, the
    largest magnitude per component (signed) (module docstring, 3.)."""
    from exuflex.erls.model import ErlsModel
    from exuflex.erls.sensing import SecondOrderPlan
    from exuflex.erls.validity import weight_sag
    from exuflex.manoeuvre import plan
    from exuflex.sensors import tip_point

    if not np.any(np.asarray(mech.gravity, float)):
        return [0.0, 0.0]
    model = ErlsModel(mech)
    so = SecondOrderPlan(model, [tip_point(mech)])
    pl = plan(mech, dt=1e-3, t_end=mech.manoeuvre.duration)
    worst = np.zeros(2)
    for k in np.linspace(0, len(pl.t) - 1, points).round().astype(int):
        cfg = model.configuration(pl.q[k])
        u, _ = weight_sag(model, cfg)
        w = so.at(cfg.pose).values(u)[0, :2]
        worst = np.where(np.abs(w) > np.abs(worst), w, worst)
    return worst.tolist()


def _commits(path: str | None) -> list[str]:
    """The code commits the gallery JSONs name (``settings.commit``)."""
    if not path:
        return []
    out = [json.loads(Path(one).read_text())["settings"].get("commit") for one in path.split(",")]
    return sorted({c for c in out if c})


def _bounds(path: str | None, engine: str) -> dict:
    """``{model: {quantity: mean bound over the seeds}}`` of one engine in gallery acceptance JSONs."""
    out: dict = {}
    for r in (r for one in (path or "").split(",") if one for r in json.loads(Path(one).read_text())["runs"]):
        if r["engine"] == engine:
            for q, v in r["bound_rms"].items():
                out.setdefault(r["model"], {}).setdefault(q, []).append(v)
    return {m: {q: float(np.mean(v)) for q, v in d.items()} for m, d in out.items()}


def _means(path: str | None, engine: str) -> dict:
    """``{model: {quantity: mean ratio over the seeds}}`` of one engine in gallery acceptance JSONs (``path``: comma
    separated)."""
    if not path:
        return {}
    out: dict = {}
    runs = [r for one in path.split(",") for r in json.loads(Path(one).read_text())["runs"]]
    for r in runs:
        if r["engine"] != engine:
            continue
        for q, v in r["ratio_to_bound"].items():
            out.setdefault(r["model"], {}).setdefault(q, []).append(v)
    return {m: {q: float(np.mean(v)) for q, v in d.items()} for m, d in out.items()}


def page(rows: list[dict], settings: dict) -> str:
    um = 1e6
    lines = [
        "# The links' foreshortening",
        "",
        f"Written by `{settings['command']}` (do not edit: rerun the script).",
        "",
        "The ERLS elastic displacements are linear: a node's displacement along its link is the link's stretch (the",
        "strain that EA resists), across it the bending. A bent link that keeps its stretch brings its far points back",
        "toward its start, at station `x` by `sigma(x) = int_0^x v'^2 / 2` along its axis (`v` the lateral elastic",
        "displacement in the link's frame, its tilt at the start included), and the joints, moved back by the same,",
        "turn the links of a closed loop a little (the closure's rigid motion of second order, `q` held). Linear",
        "elastic displacements leave this out; the geometrically exact Exudyn truth has it. `exuflex.erls.sensing."
        "SecondOrderPlan` gives it for any link point, `w = C (G u)^2`: the ERLS engine's point and slope probes",
        "(so the ERLS and reduced truths' positions are those of the same model to second order), the observer's",
        "physical tip (`Observer.physical`, `ReducedObserverModel.tip_maps`) and its covariance carry it.",
        "",
        "**What is scored.** The tip's elastic displacement the truths report is `p_tip - p_rigid(q)`, the tip's",
        "position (what a tip sensor or a tracker reads) less the rigid tip at the true `q`: defined by the truth",
        "alone, without the observer's formulation. The alternative, mapping the truth onto the ERLS coordinates (the",
        "axial coordinate as the centreline's stretch, not the chord), would score a quantity that only the ERLS",
        "formulation defines and that no sensor reads; the estimate is made physical instead.",
        "",
        "**What the filter's measurement leaves out.** Its point channels (slider encoders; tip positions are",
        "truth-only by default) are linear in `p`: their second order is listed against their noise below.",
        "",
        "## Size against the bound",
        "",
        "Along the observer's estimate on the Exudyn truth (seed 1, after the start-up): the tip's second order, RMS",
        "and largest (um), against the run's bound of the tip's elastic displacement (RMS, um); the static part at",
        "five configurations along the plan (the full model's linear sag under the weight, the largest magnitude,",
        "signed, um); the point channels' second order, largest, in their noise.",
        "",
        "| model | tip | second order RMS / max (um) | bound (um) | static, under the weight (um) | point channels / noise |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        for i, (n, d) in enumerate(row["along"]["tip"].items()):
            ch = row["along"].get("channels", {})
            chs = ", ".join(f"{c} {v['max'] / v['noise']:.1e}" for c, v in ch.items()) or "-"
            lines.append(f"| {row['model']} | {n} | {d['rms'] * um:.2f} / {d['max'] * um:.2f} | {d['bound'] * um:.2f} | "
                         f"{row['static'][i] * um:+.2f} | {chs if i == 0 else ''} |")
    before, after = settings.get("before_means", {}), settings.get("after_means", {})
    if before and after:
        lines += [
            "",
            "## The acceptance figures, before and after",
            "",
            "Per model, the Exudyn truth's mean RMS / bound over the seeds of every quantity, with the linear tip (the",
            "code before) and with its second order (after), on the same Exudyn truths (`benchmarks/gallery.py",
            "--acceptance`, the JSONs named in the command; code before: "
            + ", ".join(settings.get("before_commits", [])) + "; after: " + ", ".join(settings.get("after_commits", []))
            + "):",
            "",
        ]
        for m in after:
            if m not in before:
                continue
            qs = list(after[m])
            lines += [f"| {m} | " + " | ".join(qs) + " |", "|---|" + "---|" * len(qs),
                      "| before | " + " | ".join(f"{before[m].get(q, float('nan')):.2f}" for q in qs) + " |",
                      "| after | " + " | ".join(f"{after[m][q]:.2f}" for q in qs) + " |", ""]
        lines += [
            "How to read it: only the tip's columns change, the coordinates' and the NIS (the channels) do not (the",
            "filter is the same). The bounds move by at most "
            f"{settings.get('bound_change', float('nan')):.1e} of themselves: the bound runs along the truth's",
            "configurations with the elastic coordinates at zero (`exuflex.scoring.bound.bound_track`), where the",
            "second order's Jacobian `2 C diag(G p) G` vanishes; at a deflected state it is of the links' slopes' size",
            "against the linear rows (1e-3 to 1e-2 here).",
            "Where a tip column stays above the others on the Exudyn truth while its NIS per channel exceeds 1 (the",
            "upright two-link arm), what remains is in the channels, not in the tip's kinematics.",
        ]
    lines += ["", f"Versions: {settings.get('versions', '')}.", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="", help="comma-separated model names or files")
    ap.add_argument("--truth-dir", default="", help="benchmarks/gallery.py's truth dir (DIR/exudyn/<model>/s1)")
    ap.add_argument("--before", default=None, help="gallery --acceptance JSON(s), comma-separated, with the linear tip")
    ap.add_argument("--after", default=None, help="the same with the second order")
    ap.add_argument("--md", default=str(ROOT / "docs" / "shortening.md"))
    ap.add_argument("--json", default="")
    ap.add_argument("--markdown-from", default=None, help="rewrite --md from this JSON of an earlier run (no runs)")
    a = ap.parse_args(argv)
    if a.markdown_from:
        data = json.loads(Path(a.markdown_from).read_text())
        Path(a.md).write_text(page(data["rows"], data["settings"]))
        print(f"wrote {a.md}")
        return 0
    from exuflex.mechanism import load_mechanism
    from exuflex.runs import package_versions, read_run

    rows = []
    for m in a.models.split(","):
        mech = load_mechanism(_model_path(m))
        run = read_run(Path(a.truth_dir) / "exudyn" / Path(m).stem / "s1")
        rows.append({"model": Path(m).stem, "along": along_estimate(mech, run), "static": static_part(mech)})
        print(f"{Path(m).stem}: {rows[-1]}", flush=True)
    cmd = "python benchmarks/shortening.py " + " ".join(
        f"--{k.replace('_', '-')} {v}" for k, v in vars(a).items() if v and k not in ("md", "json", "markdown_from"))
    versions = ", ".join(f"{k} {v}" for k, v in package_versions().items())
    settings = {"command": cmd, "versions": versions, "before_means": _means(a.before, "exudyn"),
                "after_means": _means(a.after, "exudyn"), "before_commits": _commits(a.before),
                "after_commits": _commits(a.after)}
    b0, b1 = _bounds(a.before, "exudyn"), _bounds(a.after, "exudyn")
    settings["bound_change"] = max((abs(b1[m][q] / b0[m][q] - 1) for m in b1 if m in b0 for q in b1[m]
                                    if b0[m].get(q)), default=float("nan"))
    Path(a.md).write_text(page(rows, settings))
    if a.json:
        Path(a.json).write_text(json.dumps({"settings": settings, "rows": rows}, indent=1))
    print(f"wrote {a.md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

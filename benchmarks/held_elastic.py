"""The held step's elastic coordinates: what the second order of ``M_r`` and the damping in them changes, per interval
and in the filter's figures; writes ``docs/held_elastic.md``.

    python benchmarks/held_elastic.py intervals [--model benchmarks/models/three_link_reach.toml] --run DIR
                                                [--every 25] --json intervals.json
    python benchmarks/held_elastic.py page --intervals intervals.json [--acceptance BEFORE.json[,...] AFTER.json[,...]]
                                           [--label-before TEXT] [--label-after TEXT] [--md docs/held_elastic.md]

``intervals``: the default filter on the log of ``--run``; at every ``--every``-th interval (after the first 100) the
interval's step from the filter's state is taken three ways, each with the held configuration at the state's own
configuration (so only the elastic coordinates' terms differ): the cached step (:func:`exuflex.observer.expansion.
held_step`), the same without the damping's second-order form (``p2C`` zero: the first-order model), and two
references, the reduced model's frozen step (:meth:`~exuflex.observer.reduced.ReducedObserverModel.frozen_interval`,
the consistent truth's step) and a fine RK4 of the reduced model's equations (every stage at its own state, 8 times
the sub-steps). Per variant and reference: the mean and RMS of the joint rates' error over the filter's standard
deviations, and the share of intervals where the first-order damping matrix is indefinite. ``page``: the page, with
the acceptance JSONs of ``benchmarks/gallery.py --acceptance`` before and after, each a comma-separated list (per
model and truth, per quantity the mean of RMS / bound over the seeds, and the NIS / channels).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def intervals(model: str, run: str, every: int) -> dict:
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.expansion import held_step, held_system
    from exuflex.observer.reduced import ReducedObserverModel
    from exuflex.observer.session import ObserverConfig, make_observer
    from exuflex.runs import read_run
    from exuflex.scoring.run import observe_run

    mech = load_mechanism(model)
    cfg = ObserverConfig()
    obs = make_observer(mech, cfg)
    m = obs.model
    rec = []
    count = [0]

    class Recording(ReducedObserverModel):
        def predict(self, x, u, dt, u_next=None):
            count[0] += 1
            if count[0] >= 100 and count[0] % every == 0:
                rec.append((np.array(x[: self.nx], float), self._input(u).copy(), float(dt),
                            np.sqrt(np.diagonal(self.state_cov())[: self.nx])))
            return super().predict(x, u, dt, u_next)

    m.__class__ = Recording
    obs.ekf._loop = None  # sample by sample: every interval through predict()
    out = observe_run(mech, read_run(run), cfg, observer=obs)
    m.__class__ = ReducedObserverModel
    rm, r, nq = m.rm, m.r, m.nq
    err = {(v, ref): [] for v in ("damping to second order", "first order") for ref in ("frozen", "fine")}
    indefinite = []
    for x, u, dt, sig in rec:
        iv = m._configuration(x, held=True)
        iv.Ca = iv.mats.Cr - m.model.beta * iv.mats.Kr
        hs = m._held_system(iv)
        first = hs._replace(p2C=np.zeros_like(hs.p2C))
        n = m.substeps(iv, dt)
        frozen = m.frozen_interval(x, u, dt)[0].x
        y, h = x.copy(), dt / (8 * n)
        for _ in range(8 * n):
            k1 = rm.rhs(0.0, y, u)
            k2 = rm.rhs(0.0, y + 0.5 * h * k1, u)
            k3 = rm.rhs(0.0, y + 0.5 * h * k2, u)
            k4 = rm.rhs(0.0, y + h * k3, u)
            y = y + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        for v, sysv in (("damping to second order", hs), ("first order", first)):
            z = held_step(x, u, np.zeros(nq), 0.0, dt / n, n, sysv)[0]
            for ref, zr in (("frozen", frozen), ("fine", y)):
                err[(v, ref)].append(((z - zr) / sig)[r : r + nq])
        C1 = held_system(np.zeros(nq), 0.0, x[nq:r], tuple(first))[2]
        indefinite.append(bool(np.linalg.eigvalsh(0.5 * (C1 + C1.T)).min() < 0.0))
    rows = []
    for (v, ref), e in err.items():
        e = np.array(e)
        rows.append({"variant": v, "reference": ref, "mean": e.mean(0).tolist(),
                     "rms": np.sqrt((e**2).mean(0)).tolist()})
    path = Path(model).resolve()
    return {"model": str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else model,
            "run": run, "every": every, "n_intervals": len(rec), "rates": [f"d{q}" for q in mech.coordinate_names],
            "rows": rows, "indefinite_share": float(np.mean(indefinite)),
            "ratio_to_bound": out.summary["ratio_to_bound"],
            "nis_per_channel": out.summary["nis_mean"] / out.summary["nis_expected"]}


def _acceptance(paths: str) -> dict:
    """Per (engine, model): the mean over the seeds of each quantity's RMS / bound and of the NIS / channels, over
    the runs of the comma-separated JSON files ``paths``."""
    runs = [r for p in paths.split(",") for r in json.loads(Path(p).read_text())["runs"]]
    out: dict = {}
    for r in runs:
        d = out.setdefault((r["engine"], r["model"]), {})
        for q, v in r["ratio_to_bound"].items():
            d.setdefault(q, []).append(v)
        d.setdefault("NIS / channels", []).append(r["nis_mean"] / r["nis_expected"])
    return {k: {q: (float(np.mean(v)), len(v)) for q, v in d.items()} for k, d in out.items()}


def comparison_tables(before: dict, after: dict, labels: tuple) -> list:
    """Markdown lines: per (engine, model) of :func:`_acceptance`'s ``after`` also in ``before``, a table of the
    per-quantity means, one row per label."""
    L = []
    for key in sorted(after):
        if key not in before:
            continue
        quants = list(after[key])
        L += [f"### {key[1]}, {key[0]} truth (N = {after[key][quants[0]][1]})", "",
              "| | " + " | ".join(quants) + " |", "|---|" + "---|" * len(quants)]
        for label, d in zip(labels, (before, after)):
            L.append(f"| {label} | " + " | ".join(f"{d[key][x][0]:.2f}" if x in d[key] else "-" for x in quants)
                     + " |")
        L.append("")
    return L


def page(intervals_json: str, acceptance: list | None, labels: tuple, md: str) -> None:
    it = json.loads(Path(intervals_json).read_text())
    L = ["# The held step's elastic coordinates", "",
         ("Written by `python benchmarks/held_elastic.py page` (its docstring has the commands; the figures below "
          "come from the runs named in each section)."), "",
         ("The cached step holds the reduced model at an undeformed configuration `q0` and adds the elastic "
         "coordinates' terms (`exuflex.observer.expansion._elastic_terms`). The consistent velocity map `J = H + "
         "[d(H p)/dq, 0]` is linear in the elastic coordinates `e`: with `A_k = T d(H_u e_k)/dq` the rigid columns "
         "of `W J` gain `sum_k e_k A_k`. So `M_r = (W J)^T M_N W J` and the damping are quadratic in `e`, `K_r = "
         "J_u^T K_uu H_u`, `G_r` and the weight linear. The first order (`pM`, `pK`, `pC`, `pG`) left out the rigid "
         "block's second order, `e_k e_l A_k^T M_N A_l` in `M_r` and `e_k e_l X_kl` in the damping. The damping's "
         "is in now (`p2C`, `ReducedModel.elastic_forms`). The figures on this page were measured under the "
         "global-rate damping law (`alpha (T J_u)^T P T J_u + beta J_u^T K_uu J_u`, `X_kl = alpha A_k^T P A_l + "
         "beta (d(H_u e_k)/dq)^T K_uu d(H_u e_l)/dq`), whose beta part sees in `d(H_u e)/dq` the deflection turned "
         "with its link through the axial stiffness, so that a deflected link that turns was damped in proportion "
         "to `e^2 q'`. The damping now acts on the strain rate ({doc}`/damping`): `A_k` minus the turned "
         "deflection's rates `E_k`, so the second order holds the shapes' change with the configuration only and "
         "is far smaller (`tests/test_held_elastic.py`). Under the global-rate law, left out, the first-order damping matrix is indefinite at the deflections of a "
         "manoeuvre (it feeds energy into the joints), and its error has one sign over a whole refresh radius; the "
         "held error (`ReducedObserverModel._held_error`) cannot see it, since it compares two held models of the "
         "same form. `M_r`'s second order stays out: its error has no sign of its own, and where the elastic "
         "coordinates are poorly observed it did harm (with it in, the six-bar's 3 s ERLS log without its gauge c4, "
         "`tests/test_log_bound.py`, went past that test's limit in the tip position): the filter's estimates of "
         "them enter squared, and the step Jacobian leaves the matrices' change with them out. `tests/test_held_elastic.py` measures the orders (the first-order damping's and `M_r`'s error four "
         "times at twice the amplitude, the step's too as the amplitude falls), the damping's definiteness, and the "
         "step against the reduced model entry by entry."), ""]
    q = it["rates"]
    L += ["## Per interval", "",
          f"`python benchmarks/held_elastic.py intervals --model {it['model']} --run RUN --every {it['every']}` "
          f"(RUN: `{Path(it['run']).parent.parent.name}/{Path(it['run']).parent.name}/{Path(it['run']).name}` of the "
          f"acceptance's truths), {it['n_intervals']} intervals of the default filter's run (RMS / bound there: "
          + ", ".join(f"{k} {v:.2f}" for k, v in it["ratio_to_bound"].items())
          + f"; NIS / channels {it['nis_per_channel']:.3f}): the step from the filter's state with the held "
          "configuration at the state's own, against the reduced model's frozen step (the consistent truth's) and "
          "a fine RK4 of its equations, in the joint rates over the filter's standard deviations (mean: the part of "
          f"one sign). The first-order damping matrix was indefinite in {100 * it['indefinite_share']:.0f} % of "
          "the intervals.", "",
          "| step | reference | " + " | ".join(f"{x} mean" for x in q) + " | " + " | ".join(f"{x} RMS" for x in q)
          + " |", "|---|---|" + "---|" * (2 * len(q))]
    for row in it["rows"]:
        L.append(f"| {row['variant']} | {row['reference']} | " + " | ".join(f"{v:+.3f}" for v in row["mean"]) + " | "
                 + " | ".join(f"{v:.3f}" for v in row["rms"]) + " |")
    L.append("")
    if acceptance:
        before, after = (_acceptance(p) for p in acceptance)
        models = sorted({m for _, m in after})
        L += ["## In the filter's figures", "",
              "`python benchmarks/gallery.py --acceptance --truth-dir DIR --models MODEL --seeds 1-10` for "
              + ", ".join(f"`{m}`" for m in models) + " (`benchmarks/models/`), "
              f"{labels[0]} against {labels[1]} on the same truths: per quantity the mean over the seeds of RMS / "
              "bound, and the NIS / channels, both under the global-rate damping law. The full-order ERLS model "
              "then carried the same damping (its `beta K_uu u'` with `u'` holding the deflection turned with its "
              "link): on its truth the observer gained as on its own model. Exudyn's beams have no such damping (a "
              "rigid turn of a bent beam does not strain it): there the first-order model's error happened to lie "
              "closer, and the figures in the rates were worse. That difference of the ERLS model's damping is gone "
              "with the strain-rate law; its figures on these arms are on {doc}`/damping`.", ""]
        L += comparison_tables(before, after, labels)
    Path(md).write_text("\n".join(L).rstrip() + "\n")
    print(f"wrote {md}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("intervals")
    a.add_argument("--model", default=str(ROOT / "benchmarks" / "models" / "three_link_reach.toml"))
    a.add_argument("--run", required=True)
    a.add_argument("--every", type=int, default=25)
    a.add_argument("--json", required=True)
    b = sub.add_parser("page")
    b.add_argument("--intervals", required=True)
    b.add_argument("--acceptance", nargs=2, default=None, metavar=("BEFORE", "AFTER"))
    b.add_argument("--label-before", default="first order")
    b.add_argument("--label-after", default="damping to second order")
    b.add_argument("--md", default=str(ROOT / "docs" / "held_elastic.md"))
    args = ap.parse_args(argv)
    if args.cmd == "intervals":
        Path(args.json).write_text(json.dumps(intervals(args.model, args.run, args.every), indent=1))
        return 0
    page(args.intervals, args.acceptance, (args.label_before, args.label_after), args.md)
    return 0


if __name__ == "__main__":
    sys.exit(main())

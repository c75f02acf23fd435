"""Time cross-validation of the Exudyn ground truth against the ERLS full-order engine (paper's manoeuvre).

Both engines run the paper's 3 s manoeuvre under the same rigid computed-torque table (zero-order hold
on the h grid) from the same start; they must agree on q within 1e-3 rad and on the tip's elastic
displacement (x25, y26) within 10 % normalised RMS. Prints the figures; ``--plot FILE`` also draws them.

Usage:
    python benchmarks/truth_vs_erls.py [model.toml] [--duration S] [--erls-run DIR] [--plot out.png]

The ERLS engine takes about 5 min for 3 s; ``--erls-run DIR`` reuses the truth of an existing run
(``exuflex simulate models/sixbar.toml --engine erls --out DIR``), whose table was planned at h, so the
plan is recomputed at the run's torque-table step (about 1.5 min; ``--plan-cache FILE.npz`` keeps it).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from exuflex.mechanism import load_mechanism
from exuflex.truth.crossval import manoeuvre_table, truth_vs_erls

ROOT = Path(__file__).resolve().parents[1]


def _table_from_run(mech, run, cache):
    from exuflex.manoeuvre import computed_torque, plan

    st = run.meta["settings"]
    if st.get("payload_scale", 1.0) != 1.0:
        raise SystemExit("the ERLS run must have payload scale 1")
    dt, duration = st["torque_table_dt_s"], st["duration_s"]
    if cache and os.path.exists(cache):
        d = np.load(cache)
        if abs(d["t"][1] - dt) < 1e-15 and abs(d["t"][-1] - duration) < 1e-9:
            return d["t"], d["tau"], d["q"][0], d["qd"][0]
    p = plan(mech, dt=dt, t_end=duration)
    tau = computed_torque(mech, p)
    if cache:
        np.savez(cache, t=p.t, tau=tau, q=p.q, qd=p.qd)
    return p.t, tau, p.q[0], p.qd[0]


def _write_docs(path: Path, mech, cmp, args, duration: float) -> None:
    """Rewrite the page's block between ``<!-- truth_vs_erls.py MODEL FORM: begin -->`` and its end marker (appended
    if absent) with this comparison's figures."""
    key = f"truth_vs_erls.py {mech.name} {args.form}" + (
        f" mesh {args.elements_per_link}" if args.elements_per_link is not None else "")
    begin, end = f"<!-- {key}: begin -->", f"<!-- {key}: end -->"
    cmd = " ".join(["python benchmarks/truth_vs_erls.py", *sys.argv[1:]])
    q = ", ".join(f"{n} {v:.2e}" for n, v in cmp.q_max_abs.items())
    tip = ", ".join(f"{n} {100 * v:.2f} %" for n, v in cmp.tip_nrms.items())
    mesh = (", Exudyn on the ERLS mesh" if args.elements_per_link == "file" else
            f", Exudyn {args.elements_per_link} elements per link" if args.elements_per_link else "")
    block = (f"{begin}\n- ERLS `{args.form}` vs Exudyn{mesh}, {mech.name}, {duration:g} s manoeuvre (`{cmd}`): max |dq| (rad) "
             f"{q}; tip elastic displacement NRMS {tip}\n{end}")
    text = path.read_text() if path.exists() else ""
    if begin in text and end in text:
        text = text[: text.index(begin)] + block + text[text.index(end) + len(end) :]
    else:
        text = text + ("\n" if text and not text.endswith("\n") else "") + block + "\n"
    path.write_text(text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", nargs="?", default=str(ROOT / "models" / "sixbar.toml"))
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--h", type=float, default=1e-4)
    ap.add_argument("--erls-run", default=None, help="reuse the truth of an ERLS run folder")
    ap.add_argument("--plan-cache", default=None, help="npz cache of the plan at the run's table step")
    ap.add_argument("--plot", default=None, help="save a figure (PNG)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--form", default="lagrange", choices=("lagrange", "eq2"),
                    help="the ERLS full-order model's velocity forces (exuflex.erls.model)")
    ap.add_argument("--docs", default=None, help="docs page whose 'truth_vs_erls.py FORM' block is rewritten")
    ap.add_argument("--elements-per-link", default=None,
                    help="the Exudyn truth's mesh: N elements per link or 'file' (the ERLS mesh; default: "
                         "exuflex.groundtruth.simulate_truth's)")
    args = ap.parse_args()
    truth_kwargs = {}
    if args.elements_per_link is not None:
        truth_kwargs["elements_per_link"] = (args.elements_per_link if args.elements_per_link == "file"
                                             else int(args.elements_per_link))
    mech = load_mechanism(args.model)
    erls_truth = table = None
    duration = args.duration
    if args.erls_run:
        from exuflex.runs import read_run

        run = read_run(args.erls_run)
        if run.meta.get("engine") != "erls":
            raise SystemExit(f"{args.erls_run} is not an ERLS run")
        duration = run.meta["settings"]["duration_s"]
        h = run.meta["settings"]["h_s"]
        if abs(h - args.h) > 1e-15:
            raise SystemExit(f"the run used h = {h}, not {args.h}")
        erls_truth = run.truth
        table = _table_from_run(mech, run, args.plan_cache)
    elif duration is not None:
        table = manoeuvre_table(mech, duration, args.h)
    if args.erls_run and args.form != "lagrange":
        raise SystemExit("--erls-run holds a 'lagrange' ERLS truth; drop it to simulate another form")
    cmp, exu, erl = truth_vs_erls(mech, duration, h=args.h, erls_truth=erls_truth, table=table, form=args.form,
                                  **truth_kwargs)
    if args.json:
        print(json.dumps(cmp.as_dict(), indent=2))
    else:
        print(f"Exudyn truth vs ERLS full-order ({args.form}), {mech.name}, {exu.t[-1]:g} s manoeuvre, h = {args.h:g} s")
        for n, v in cmp.q_max_abs.items():
            print(f"  max |d{n}| = {v:.3e} rad   (end {exu[n][-1] - erl[n][-1]:+.2e})")
        for n, v in cmp.tip_nrms.items():
            rms = float(np.sqrt(np.mean(erl[n] ** 2)))
            print(f"  tip {n}: NRMS = {100 * v:.2f} %   (RMS of ERLS {rms * 1e3:.3f} mm)")
        ok = cmp.q_max < 1e-3 and cmp.tip_nrms_max < 0.1
        print(f"  acceptance (q < 1e-3 rad, tip NRMS < 10 %): {'PASS' if ok else 'FAIL'}")
        print("  wall: " + ", ".join(f"{k} {v:.1f} s" for k, v in cmp.extra.items()))
    if args.docs:
        _write_docs(Path(args.docs), mech, cmp, args, exu.t[-1])
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        names = list(mech.coordinate_names) + list(cmp.tip_nrms)
        fig, ax = plt.subplots(len(names), 2, figsize=(11, 2.0 * len(names)), sharex=True)
        for i, n in enumerate(names):
            sc = 1e3 if n in cmp.tip_nrms else 1.0
            unit = "mm" if n in cmp.tip_nrms else "rad"
            ax[i, 0].plot(erl.t, sc * erl[n], label="ERLS")
            ax[i, 0].plot(exu.t, sc * exu[n], "--", label="Exudyn")
            ax[i, 0].set_ylabel(f"{n} ({unit})")
            ax[i, 1].plot(exu.t, sc * (exu[n] - erl[n]))
            ax[i, 1].set_ylabel(f"diff ({unit})")
        ax[0, 0].legend()
        ax[-1, 0].set_xlabel("t (s)")
        ax[-1, 1].set_xlabel("t (s)")
        fig.suptitle(
            f"Exudyn truth vs ERLS: q max {cmp.q_max:.2e} rad, tip NRMS {100 * cmp.tip_nrms_max:.2f} %"
        )
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)
        print(f"  figure: {args.plot}")


if __name__ == "__main__":
    main()

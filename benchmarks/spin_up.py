"""Spin-up of a cantilever on a hub (Kane, Ryan and Banerjee type): where the ERLS model stops being valid.

The beam of ``models/spin_up.toml`` is clamped to a hub whose angle follows the smooth spin-up law

    theta(t) = W/Ts (t^2/2 + (Ts/2pi)^2 (cos(2pi t/Ts) - 1))   for t < Ts,   W (t - Ts/2) after,

from rest to the steady speed W. The ERLS full-order model (both forms of :mod:`exuflex.erls.model`; the hub
angle prescribed, the elastic rows integrated by the implicit trapezoidal rule) and Exudyn (ANCF cable and
geometrically exact beam elements, the hub node's rotation prescribed, :func:`exuflex.groundtruth.simulate_prescribed`)
give the tip's lateral deflection in the hub frame. With linear elasticity in the rotating frame (both forms
with ``geometric=False``: the observer's reduced model in rotation) the ERLS has no geometric stiffening (the
centrifugal tension's bending stiffness): the normalised RMS difference (RMS of ERLS - Exudyn ANCF over RMS of
Exudyn ANCF) grows with W, and the speed at which it passes 5 % is that model's validity limit for rotating links
(linear interpolation between the swept speeds). The default full-order model (``lagrange + K_G``) holds the
geometric stiffness of the rigid motion's axial loads (:data:`VARIANTS`).

Usage:
    python benchmarks/spin_up.py [--speeds 0.25,0.5,1,1.5,2,4] [--json] [--plot docs/spin_up.png]
                                 [--docs docs/validity.md] [--quick]

``--json`` prints ``{"slow_nrms_pct": ..., "departure_rad_s": ...}`` (the slowest speed's NRMS, worse of the two
forms, and the default form's departure speed) and the per-speed figures. ``--docs`` rewrites the block of the
page between its ``spin_up.py`` markers with the measured figures.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import FORMS, ErlsModel
from exuflex.erls.simulate import simulate
from exuflex.groundtruth import simulate_prescribed
from exuflex.mechanism import load_mechanism
from exuflex.probes import Probe

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 0.05  # the NRMS that defines the departure
BEGIN, END = "<!-- spin_up.py: begin -->", "<!-- spin_up.py: end -->"


def spin_law(omega: float, ts: float):
    """``t -> (theta, theta', theta'')`` of the spin-up law (module docstring)."""
    w = 2 * np.pi / ts

    def law(t: float) -> tuple[float, float, float]:
        if t < ts:
            return (omega / ts * (t * t / 2 + (np.cos(w * t) - 1) / w**2),
                    omega / ts * (t - np.sin(w * t) / w), omega / ts * (1 - np.cos(w * t)))
        return omega * (t - ts / 2), omega, 0.0

    return law


VARIANTS = {"lagrange": ("lagrange", False), "eq2": ("eq2", False), "lagrange + K_G": ("lagrange", True)}
"""The ERLS models compared: both forms with linear elasticity (the observer's reduced model in rotation: it holds
the geometric stiffness of the weight's static axial loads, not of the centrifugal tension; the validity guard's
departure) and the default full-order model, whose elastic rows hold the geometric stiffness of the rigid
motion's axial loads (``exuflex.erls.model``, "Geometric stiffness": the centrifugal stiffening)."""


def erls_tip(mech, form: str, law, duration: float, h: float, output_dt: float, geometric: bool = False):
    """(t, lateral tip deflection in the hub frame) of the ERLS model with the hub angle prescribed."""
    m = ErlsModel(mech, form=form, geometric=geometric)
    ne = m.ne
    link = mech.links[0]

    def xv(t, y):
        th, thd, _ = law(t)
        return np.r_[th, y[:ne]], np.r_[thd, y[ne:]]

    def rhs(t, y, _):
        x, v = xv(t, y)
        return np.r_[y[ne:], m.prescribed_accelerations(x, v, [law(t)[2]])]

    def jac(t, y):
        x, v = xv(t, y)
        A = np.zeros((2 * ne, 2 * ne))
        A[:ne, ne:] = np.eye(ne)
        A[ne:] = m.prescribed_jacobian(x, v, qdd=[law(t)[2]])
        return A

    tr = simulate(rhs, np.zeros(2 * ne), duration, lambda t: None, h=h, method="trapezoid", jac=jac,
                  output_every=round(output_dt / h), rtol=1e-9, atol=1e-12)
    tip = np.empty(len(tr.t))
    for i, (t, y) in enumerate(zip(tr.t, tr.y)):
        th = law(t)[0]
        d = m.point_displacement_rows(m.configuration(np.array([th])), link.name, link.length) @ y[:ne]
        tip[i] = -np.sin(th) * d[0] + np.cos(th) * d[1]
    return tr.t, tip


def exudyn_tip(mech, formulation: str, elements: int, law, duration: float, h: float, output_dt: float):
    """(t, lateral tip deflection in the hub frame, largest drive error) of the Exudyn model."""
    link = mech.links[0]
    probe = Probe("point", link.name, link.length)
    stats: dict = {}
    rec = simulate_prescribed(mech, lambda t: np.array([law(t)[0]]), duration, [probe], h=h, output_dt=output_dt,
                              elements_per_link=elements, formulation=formulation, stats=stats)
    th = np.array([law(t)[0] for t in rec.t])
    p = rec.values[probe.key] - np.asarray(mech.joints[0].ground)[None, :]
    return rec.t, -np.sin(th) * p[:, 0] + np.cos(th) * p[:, 1], stats["drive_error_rad"]


def nrms(a: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - ref) ** 2) / np.mean(ref**2)))


def departure(speeds, values, limit: float = LIMIT) -> float | None:
    """The first speed at which ``values`` passes ``limit`` (linear interpolation), None if it never does."""
    for k, (w, v) in enumerate(zip(speeds, values)):
        if v > limit:
            if k == 0:
                return float(w)
            w0, v0 = speeds[k - 1], values[k - 1]
            return float(w0 + (limit - v0) * (w - w0) / (v - v0))
    return None


def run(mech, speeds, ts: float, duration: float, h_erls: float, h_exu: float, output_dt: float,
        ancf_elements: int, ge_elements: int) -> dict:
    out = {"speeds_rad_s": list(speeds), "nrms": {f: [] for f in VARIANTS}, "ge_vs_ancf": [],
           "drive_error_rad": 0.0, "histories": {}, "wall_s": {}}
    walls = {k: 0.0 for k in (*VARIANTS, "ancf", "gebeam")}
    for w in speeds:
        law = spin_law(w, ts)
        t0 = time.perf_counter()
        t, ancf, e1 = exudyn_tip(mech, "ancf", ancf_elements, law, duration, h_exu, output_dt)
        walls["ancf"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        _, ge, e2 = exudyn_tip(mech, "gebeam", ge_elements, law, duration, h_exu, output_dt)
        walls["gebeam"] += time.perf_counter() - t0
        out["drive_error_rad"] = max(out["drive_error_rad"], e1, e2)
        out["ge_vs_ancf"].append(nrms(ge, ancf))
        hist = {"t": t, "ancf": ancf, "gebeam": ge}
        for form, (kind, geometric) in VARIANTS.items():
            t0 = time.perf_counter()
            te, tip = erls_tip(mech, kind, law, duration, h_erls, output_dt, geometric)
            walls[form] += time.perf_counter() - t0
            if len(te) != len(t) or np.abs(te - t).max() > 1e-9:
                raise RuntimeError("ERLS and Exudyn records are on different time grids")
            out["nrms"][form].append(nrms(tip, ancf))
            hist[form] = tip
        out["histories"][w] = hist
        print(f"  W = {w:g} rad/s: NRMS vs Exudyn ANCF " + ", ".join(
            f"{f} {100 * out['nrms'][f][-1]:.2f} %" for f in VARIANTS) + f"; GE vs ANCF {100 * out['ge_vs_ancf'][-1]:.3f} %",
            file=sys.stderr)
    out["wall_s"] = walls
    out["departure_rad_s"] = {f: departure(speeds, out["nrms"][f]) for f in VARIANTS}
    return out


def write_docs(path: Path, res: dict, args, figure: str | None) -> None:
    speeds = res["speeds_rad_s"]
    n_el = load_mechanism(args.model).links[0].n_elements
    measured = (f"Measured by `python benchmarks/spin_up.py {' '.join(args.argv)}` (beam of `models/spin_up.toml`, "
                f"spin-up time {args.spin_time:g} s, {args.duration:g} s simulated; ERLS {n_el} elements, trapezoidal "
                f"rule h = {args.h_erls:g} s; Exudyn ANCF {args.ancf_elements} and geometrically exact "
                f"{args.ge_elements} elements, generalized-alpha h = {args.h_exudyn:g} s; largest hub drive error "
                f"{res['drive_error_rad']:.1e} rad).")
    lines = [BEGIN, measured, "",
             "| final speed (rad/s) | " + " | ".join(f"ERLS {f} vs ANCF NRMS (%)" for f in VARIANTS)
             + " | GE vs ANCF NRMS (%) |",
             "|---|" + "---|" * (len(VARIANTS) + 1)]
    for k, w in enumerate(speeds):
        lines.append(f"| {w:g} | " + " | ".join(f"{100 * res['nrms'][f][k]:.2f}" for f in VARIANTS)
                     + f" | {100 * res['ge_vs_ancf'][k]:.3f} |")
    lines.append("")
    for f in VARIANTS:
        d = res["departure_rad_s"][f]
        lines.append(f"- departure (NRMS > {100 * LIMIT:g} %), ERLS `{f}`: "
                     + (f"**{d:.2f} rad/s**" if d is not None else "not reached in the sweep"))
    lines.append(f"- slowest speed ({speeds[0]:g} rad/s), worse form: NRMS {res['slow_nrms_pct']:.2f} %")
    w1 = res["clamped_rad_s"]
    lines.append(f"- first clamped-free frequency of the ERLS beam (hub locked): {w1:.2f} rad/s; departure / that: "
                 + ", ".join(f"`{f}` {d / w1:.2f}" for f, d in res["departure_rad_s"].items() if d is not None))
    if figure:
        lines += ["", f"![tip deflection histories]({Path(figure).name})"]
    lines.append(END)
    block = "\n".join(lines)
    text = path.read_text() if path.exists() else ""
    if BEGIN in text and END in text:
        text = text[: text.index(BEGIN)] + block + text[text.index(END) + len(END):]
    else:
        text = text + ("\n" if text else "") + block + "\n"
    path.write_text(text)


def plot(res: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    speeds = res["speeds_rad_s"]
    shown = [speeds[0], *[w for w in speeds[1:] if w in (1.0, 2.0)], speeds[-1]]
    shown = list(dict.fromkeys(shown))
    fig, ax = plt.subplots(len(shown), 1, figsize=(8, 2.4 * len(shown)), sharex=True)
    ax = np.atleast_1d(ax)
    for a, w in zip(ax, shown):
        hst = res["histories"][w]
        a.plot(hst["t"], 1e3 * hst["ancf"], "k", lw=2, label="Exudyn ANCF")
        a.plot(hst["t"], 1e3 * hst["gebeam"], "c--", label="Exudyn GE beam")
        for f, style in zip(VARIANTS, ("r-", "b:", "g-.")):
            a.plot(hst["t"], 1e3 * hst[f], style, label=f"ERLS {f}")
        k = speeds.index(w)
        a.set_ylabel("tip (mm)")
        a.set_title(f"final speed {w:g} rad/s: ERLS NRMS " + ", ".join(
            f"{f} {100 * res['nrms'][f][k]:.1f} %" for f in VARIANTS), fontsize=9)
        lim = 1.5e3 * np.abs(hst["ancf"]).max()
        a.set_ylim(-lim, lim)
    ax[0].legend(fontsize=8, ncol=2)
    ax[-1].set_xlabel("t (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "spin_up.toml"))
    ap.add_argument("--speeds", default="0.25,0.5,0.75,1,1.25,1.5,2,4", help="final speeds W (rad/s), ascending")
    ap.add_argument("--spin-time", type=float, default=15.0, help="Ts (s)")
    ap.add_argument("--duration", type=float, default=20.0, help="simulated time (s)")
    ap.add_argument("--h-erls", type=float, default=5e-3)
    ap.add_argument("--h-exudyn", type=float, default=1e-3)
    ap.add_argument("--output-dt", type=float, default=0.01)
    ap.add_argument("--ancf-elements", type=int, default=8)
    ap.add_argument("--ge-elements", type=int, default=32)
    ap.add_argument("--default-form", default="lagrange", choices=FORMS, help="the form whose departure --json reports")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--plot", default=None, help="figure of the tip deflection histories (PNG)")
    ap.add_argument("--docs", default=None, help="docs page whose spin_up.py block is rewritten")
    ap.add_argument("--quick", action="store_true", help="one slow speed, short run (for the test suite)")
    args = ap.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if args.quick:
        args.speeds, args.spin_time, args.duration = "0.25", 3.0, 3.0
    speeds = [float(s) for s in args.speeds.split(",")]
    if any(b <= a for a, b in itertools.pairwise(speeds)) or speeds[0] <= 0:
        raise SystemExit(f"--speeds must be positive and ascending, got {args.speeds!r}")
    mech = load_mechanism(args.model)
    if len(mech.links) != 1 or len(mech.coordinates) != 1:
        raise SystemExit(f"{args.model}: the spin-up benchmark needs one link with one hub coordinate")
    res = run(mech, speeds, args.spin_time, args.duration, args.h_erls, args.h_exudyn, args.output_dt,
              args.ancf_elements, args.ge_elements)
    res["slow_nrms_pct"] = 100 * max(res["nrms"][f][0] for f in VARIANTS)
    res["clamped_rad_s"] = float(2 * np.pi * modal_analysis(ErlsModel(mech), mech.q_ref, locked=True).frequencies_hz[0])
    summary = {"slow_nrms_pct": res["slow_nrms_pct"], "departure_rad_s": res["departure_rad_s"][args.default_form]}
    if args.plot:
        plot(res, args.plot)
    if args.docs:
        write_docs(Path(args.docs), res, args, args.plot)
    if args.json:
        print(json.dumps({**summary, "departure_by_form_rad_s": res["departure_rad_s"],
                          "speeds_rad_s": speeds, "nrms_pct": {f: [100 * v for v in res["nrms"][f]] for f in VARIANTS},
                          "ge_vs_ancf_pct": [100 * v for v in res["ge_vs_ancf"]],
                          "clamped_rad_s": res["clamped_rad_s"], "drive_error_rad": res["drive_error_rad"],
                          "wall_s": res["wall_s"]}, indent=2))
    else:
        print(f"slow spin-up ({speeds[0]:g} rad/s) NRMS {summary['slow_nrms_pct']:.2f} %; departure "
              + ", ".join(f"{f} {d if d is None else round(d, 3)} rad/s" for f, d in res["departure_rad_s"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

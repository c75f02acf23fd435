"""The reduced model against the full-order ERLS model when the payload is heavier: what departs, and why.

    python benchmarks/payload_mismatch.py [--model models/slider_crank.toml] [--scales 1,1.5,2]
        [--run SCALE=DIR[,DIR...] ...] [--md docs/payload_mismatch.md]

For each payload scale (the model file's payload mass times the scale, :meth:`Mechanism.with_payload_scale`) and the
observer's default reduction of that mechanism (:class:`exuflex.reduction.CraigBampton`, its static corrections
included, :mod:`exuflex.reduction.static`; "without corrections": ``static_max=0``):

1. **Modes at rest** (motors free) at five configurations of the manoeuvre: the full model's and the reduced
   model's frequencies.
2. **The truth's motion**: the full-order ERLS model (generalized-alpha at the truth step rule's step) under the *nominal* model's
   open-loop torques from the plan's start (the mismatch study's drive, :func:`exuflex.truth.engines.plan_drive`):
   the peak crank rate and acceleration and the peak gauge signal over its noise, overall and in the window of
   :data:`exuflex.reduction.truncation.WINDOW_SAMPLES` samples around the largest scale's peak acceleration.
3. **What the basis cannot hold there**: at each sample of the window the truth's elastic state in the basis'
   exact Craig-Bampton coordinates (masters exact; interior coordinates ``Psi^-1 (w_s - B w_m)`` over every
   interior mode), and the gauges' reading of the part outside the kept interior modes, over the gauge noise:
   without the static corrections, in total and in the modes that decay within a sample interval (the selection
   never keeps them, :mod:`exuflex.reduction.path`); and outside the default basis (its static corrections kept).
4. **The criterion's figures**: the static corrections' count, the largest residual reading without and with them
   (noise sd) and the load amplitudes (:mod:`exuflex.reduction.static`).
5. With ``--run SCALE=DIR[,DIR...]`` (run folders of that scale's truth, e.g. ``exuflex simulate MODEL --engine erls
   --payload-scale 1.5 --seed 1 --out DIR``): the observer given the correct payload (default settings), RMS error
   over the bound per quantity (mean and largest over the runs) and the mean NIS over the channel count, with the
   default basis and without its static corrections.
"""

from __future__ import annotations

import argparse
import logging
import sys

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _pages import publish

from exuflex.erls.implicit import band_modes, erls_implicit
from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import ErlsModel
from exuflex.erls.sensing import channel_matrix
from exuflex.mechanism import load_mechanism
from exuflex.reduction import CraigBampton, manoeuvre_configurations, reduced_modes
from exuflex.reduction.truncation import WINDOW_SAMPLES
from exuflex.truth.engines import gen_alpha_step, plan_drive

log = logging.getLogger(__name__)


def _fast(cb) -> np.ndarray:
    """The interior modes that decay within a sample interval (``zeta w > f_s``, as :mod:`exuflex.reduction.path`)."""
    model = cb.model
    w = 2 * np.pi * cb.interior_frequencies_hz
    zeta = model.alpha / (2 * np.maximum(w, 1e-12)) + model.beta * w / 2
    return zeta * w > model.mech.sample_rate_hz


def _gauges(mech) -> list[str]:
    return [s.name for s in mech.sensors if s.kind == "curvature" and s.noise_std > 0]


def truth(mech, nominal, duration):
    """The full-order ERLS model's trajectory under the nominal drive: t, y (n_t, 2n)."""
    drive = plan_drive(nominal, duration, 1e-4)
    model = ErlsModel(mech)
    n, nq = model.n, model.nq
    y0 = np.zeros(2 * n)
    y0[:nq], y0[n : n + nq] = drive.q0, drive.qd0
    dt = 1.0 / mech.sample_rate_hz
    band = mech.reduction.band_hz
    modes = band_modes(model, np.vstack([drive.q0, mech.q_ref]), band)
    step = gen_alpha_step("auto", 1e-4, dt, band, modes, duration)  # the truth step rule, as `exuflex simulate`
    tr = erls_implicit(model, drive.t, drive.tau, y0, duration, step, output_every=round(dt / step))
    return model, tr.t, tr.y


def truncated_content(cb, mech, t, Y, window):
    """Gauge readings over their noise (n_window, n_gauges) of the truth's elastic part outside the kept interior
    modes: in total and in the fast modes."""
    model = cb.model
    n, nq = model.n, model.nq
    names = _gauges(mech)
    sig = np.array([{s.name: s for s in mech.sensors}[c].noise_std for c in names])
    kept, k = cb.kept.copy(), cb.n_interior
    fast = _fast(cb)
    cb.set_interior(cb.Phi_all.shape[1])  # every interior mode, ascending: exact coordinates
    keep = np.zeros(cb.Phi_all.shape[1], bool)
    keep[kept] = True
    out = {"total": [], "fast": [], "signal": []}
    try:
        for j in np.flatnonzero((t >= window[0]) & (t < window[1])):
            q, u = Y[j, :nq], Y[j, nq:n]
            rc = cb.at(q)
            cfg = rc.cfg
            C = channel_matrix(model, cfg, mech, names)[:, nq:] / sig[:, None]
            qc, qs = cb._frame_cs(cfg)
            w = cb._to_frame(u, qc, qs)
            zeta = np.linalg.solve(rc.Psi, w[cb.is_] - rc.B @ w[cb.im])
            r = rc.Psi[:, ~keep] @ zeta[~keep]

            def read(ws, C=C, qc=qc, qs=qs):
                W = np.zeros(model.ne)
                W[cb.is_] = ws
                return C @ cb._to_frame(W, qc, qs, inverse=True)

            out["total"].append(read(r))
            out["fast"].append(read(rc.Psi[:, ~keep & fast] @ zeta[~keep & fast]))
            out["signal"].append(C @ u)
    finally:
        cb.order = np.r_[kept, [i for i in range(len(keep)) if not keep[i]]].astype(int)
        cb.set_interior(k)
    return names, {key: np.array(v) for key, v in out.items()}


def observe(mech, run_dir, static: bool):
    from exuflex.observer.session import ObserverConfig, make_observer
    from exuflex.runs import read_run
    from exuflex.scoring.run import observe_run

    cfg = ObserverConfig()
    cb = CraigBampton(ErlsModel(mech), static_max=None if static else 0.0)
    o = observe_run(mech, read_run(run_dir), cfg, observer=make_observer(mech, cfg, cb=cb))
    return cb, o.summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="models/slider_crank.toml")
    ap.add_argument("--scales", default="1,1.5,2")
    ap.add_argument("--run", action="append", default=[],
                    help="SCALE=DIR[,DIR...]: truth runs of that payload scale")
    ap.add_argument("--md", default="docs/payload_mismatch.md")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    scales = [float(s) for s in a.scales.split(",")]
    nominal = load_mechanism(a.model)
    duration = nominal.manoeuvre.duration
    cmd = "python benchmarks/payload_mismatch.py" + (f" --model {a.model}" if a.model != "models/slider_crank.toml"
                                                     else "") + (f" --scales {a.scales}" if a.scales != "1,1.5,2"
                                                                 else "")
    cmd += "".join(f" --run {r}" for r in a.run)
    page = [f"# The reduced model under a heavier payload ({nominal.name})", "",
            (f"Written by `{cmd}` (the command regenerates this page; the method is in its docstring). Each payload "
             "scale multiplies the model file's payload mass; the observer's reduction is built for that mechanism "
             "(the correct payload); the truth is the full-order ERLS model driven by the *nominal* model's "
             "open-loop torques, as in the payload-mismatch study."), ""]
    # 1. modes
    page += ["## Modes at rest (motors free)", "", "| scale | q | full (Hz) | reduced (Hz) |", "|---|---|---|---|"]
    qs = manoeuvre_configurations(nominal, 5)
    runs = {}
    for s in scales:
        mech = nominal.with_payload_scale(s) if s != 1.0 else nominal
        cb = CraigBampton(ErlsModel(mech))
        for q in qs:
            full = modal_analysis(cb.model, q).frequencies_hz[:4]
            red = reduced_modes(cb, q)[0][:4]
            page.append(f"| {s:g} | {', '.join(f'{v:.3f}' for v in q)} | {', '.join(f'{v:.1f}' for v in full)} | "
                        f"{', '.join(f'{v:.1f}' for v in red)} |")
        runs[s] = (mech, cb)
    # 2. the truth's motion
    traj = {s: truth(runs[s][0], nominal, duration)[1:] for s in scales}
    half = 0.5 * WINDOW_SAMPLES / nominal.sample_rate_hz
    windows = {}
    for s in scales:
        t, y = traj[s]
        m = runs[s][1].model
        acc = np.abs(np.gradient(y[:, m.n : m.n + m.nq], t, axis=0)).max(axis=1)
        lo = min(max(0.0, t[int(np.argmax(acc))] - half), t[-1] - 2 * half)
        windows[s] = (lo, lo + 2 * half)
    page += ["", "## The truth's motion", "",
             (f"Each scale's window: the {2 * half:.2f} s (the NIS test's window) around its peak coordinate "
              "acceleration."), "",
             "| scale | window (s) | peak q' (rad/s) | peak q'' (rad/s^2) | peak gauge / noise | in the window |",
             "|---|---|---|---|---|---|"]
    for s in scales:
        mech, cb = runs[s]
        t, y = traj[s]
        m = cb.model
        qd = y[:, m.n : m.n + m.nq]
        qdd = np.abs(np.gradient(qd, t, axis=0)).max(axis=1)
        window = windows[s]
        win = (t >= window[0]) & (t < window[1])
        names = _gauges(mech)
        sig = np.array([{x.name: x for x in mech.sensors}[c].noise_std for c in names])
        g = np.array([channel_matrix(m, m.configuration(y[k, : m.nq]), mech, names)[:, m.nq :] @ y[k, m.nq : m.n]
                      for k in range(len(t))]) / sig
        page.append(f"| {s:g} | [{window[0]:.3f}, {window[1]:.3f}) | {np.abs(qd).max():.2f} | {qdd.max():.0f} | "
                    f"{np.abs(g).max():.1f} | {np.abs(g[win]).max():.1f} |")
    # 3. the content outside the basis
    page += ["", "## What the basis cannot hold in the window", "",
             ("RMS over its window of each gauge's reading of the truth's elastic state outside the kept interior "
              "modes, over the gauge's noise (max in brackets): without the static corrections, in total and in the "
              "interior modes that decay within a sample interval; and outside the default basis, its static "
              "corrections kept."), "",
             ("| scale | kept interior modes without corrections (Hz at q*) | gauge signal RMS / noise | outside the "
              "basis without corrections | in fast modes | default basis: static corrections (Ritz Hz) | outside it |"),
             "|---|---|---|---|---|---|---|"]
    for s in scales:
        mech, cb = runs[s]
        cb0 = CraigBampton(ErlsModel(mech), static_max=0.0)
        t, y = traj[s]
        names, out = truncated_content(cb0, mech, t, y, windows[s])
        _, out1 = truncated_content(cb, mech, t, y, windows[s])

        def fmt(x, names=names):
            return ", ".join(f"{nm} {np.sqrt((x[:, i] ** 2).mean()):.2f} ({np.abs(x[:, i]).max():.1f})"
                             for i, nm in enumerate(names))
        kept_hz = ", ".join(f"{v:.0f}" for v in cb0.interior_frequencies_hz[cb0.kept])
        st = cb.static
        ritz = ", ".join(f"{v:.0f}" for v in cb.interior_frequencies_hz[st.rest[: st.n]]) if st and st.n else ""
        page.append(f"| {s:g} | {cb0.n_interior} ({kept_hz}) | {fmt(out['signal'])} | {fmt(out['total'])} | "
                    f"{fmt(out['fast'])} | {cb.n_static} ({ritz}) | {fmt(out1['total'])} |")
    # 4. the criterion
    page += ["", "## The criterion's figures", "",
             ("The largest quasi-static reading the reduced model can miss (noise sd; a load within the amplitude box, "
              "at the worst sampled configuration and channel) without corrections and with the count kept, against "
              "the limit; the amplitudes: the largest crank acceleration the planned torques can produce and the "
              "largest rate the plan's kinetic energy allows (`exuflex.reduction.static`)."), "",
             "| scale | corrections | figure without | with them | limit | a (rad/s^2) | v (rad/s) | picked |",
             "|---|---|---|---|---|---|---|---|"]
    for s in scales:
        st = runs[s][1].static
        if st is None:
            page.append(f"| {s:g} | 0 | | | | | | |")
            continue
        a_, v_ = st.amplitudes
        page.append(f"| {s:g} | {st.n} | {st.figure[0]:.2f} | {st.figure[st.n]:.2f} | {st.limit:.2f} | "
                    f"{', '.join(f'{x:.0f}' for x in a_)} | {', '.join(f'{x:.1f}' for x in v_)} | "
                    f"{'; '.join(w for _, w in st.picked)} |")
    # 5. the observer
    if a.run:
        page += ["", "## The observer (correct payload, default settings)", "",
                 ("RMS error over the bound per quantity, mean over the runs [largest]; mean NIS over the channel "
                  "count, mean [largest]; runs the NIS test flagged. A single run's ratio scatters by about 0.1."), "",
                 "| scale | runs | basis | reduced dofs | RMS / bound | NIS / channels | flagged | filter wall (s, median) |",
                 "|---|---|---|---|---|---|---|---|"]
        for spec in a.run:
            s_txt, dirs = spec.split("=", 1)
            dirs = dirs.split(",")
            mech = nominal.with_payload_scale(float(s_txt)) if float(s_txt) != 1.0 else nominal
            for static in (True, False):
                ratios, nis, flagged, cpu = [], [], 0, []
                for d in dirs:
                    cb, summ = observe(mech, d, static)
                    ratios.append(summ["ratio_to_bound"])
                    nis.append(summ["nis_mean"] / summ["nis_expected"])
                    flagged += bool(summ.get("nis_inconsistent"))
                    cpu.append(summ.get("wall_s", float("nan")))
                ratio = ", ".join(f"{q} {np.mean([r[q] for r in ratios]):.2f} [{max(r[q] for r in ratios):.2f}]"
                                  for q in ratios[0])
                page.append(f"| {float(s_txt):g} | {len(dirs)} | {'default' if static else 'without corrections'} | "
                            f"{cb.r} | {ratio} | {np.mean(nis):.3f} [{max(nis):.3f}] | {flagged} | "
                            f"{np.median(cpu):.2f} |")
    publish("\n".join(page) + "\n\n", a.md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

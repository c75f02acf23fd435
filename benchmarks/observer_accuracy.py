"""Observer accuracy on the paper's manoeuvre: errors vs the steady-state bound, FFT peaks, NEES/NIS.

    python benchmarks/observer_accuracy.py --runs 50 [--engine erls|exudyn|reduced] [--cache DIR]

1. simulates the truth once (full-order ERLS model by default, the paper's own setting; or Exudyn), keeping
   the clean sensor channels (cached in ``--cache``);
2. draws ``--runs`` seeded Table-3 noise realisations of the torques and sensors (``exuflex.measure``);
3. runs the reduced-order EKF (default settings) on each; prints the RMS errors after the 0.3 s start-up
   beside the steady-state bound (mean over runs and the ratio), the FFT peaks of the estimated tip elastic
   displacements against the truth's (0-180 Hz), and the Monte-Carlo NEES (on the 10 physical quantities
   q, dq/dt, tip displacement and velocity, with their covariance mapped from the filter's) and NIS
   against their 95 % chi-square bands.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
import sys
import time
from pathlib import Path

import numpy as np

from exuflex.measure import measure
from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig, make_observer, physical_names
from exuflex.scoring.physical import physical_covariance
from exuflex.scoring.run import metrics
from exuflex.scoring.bound import steady_bound
from exuflex.scoring.stats import fft_peaks, match_peaks, mc_consistency
from exuflex.sensors import Signals
from exuflex.truth import plan_drive, simulate

ROOT = Path(__file__).resolve().parents[1]


def truth(model: Path, engine: str, cache: Path | None):
    mech = load_mechanism(model)
    f = None if cache is None else cache / f"truth_{engine}.npz"
    if f is not None and f.exists():
        z = np.load(f, allow_pickle=False)
        clean = Signals(z["ct"], tuple(z["cn"]), z["cd"])
        tr = Signals(z["tt"], tuple(z["tn"]), z["td"])
        return mech, clean, tr, z["torque_t"], z["torques"]
    drive = plan_drive(mech, mech.manoeuvre.duration, 1e-4)
    lt = simulate(mech, drive, engine, mech.manoeuvre.duration, 1e-4)
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        np.savez(f, ct=lt.clean.t, cn=np.array(lt.clean.names), cd=lt.clean.data, tt=lt.truth.t,
                 tn=np.array(lt.truth.names), td=lt.truth.data, torque_t=lt.torque_t, torques=lt.torques)
    return mech, lt.clean, lt.truth, lt.torque_t, lt.torques


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "sixbar.toml"))
    ap.add_argument("--engine", choices=("erls", "exudyn", "reduced"), default="erls",
                    help="truth: full-order ERLS (the paper's setting), Exudyn, or the filter's own reduced model")
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--cache", default=None, help="folder caching the truth (npz)")
    ap.add_argument("--json", default=None, help="write the figures to this JSON file")
    ap.add_argument("--q-scale", type=float, default=None, help="process-noise scale (default: the observer's)")
    ap.add_argument("--q-extra", type=float, default=None, help="extra elastic-rate noise std per interval")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    mech, clean, tr, torque_t, torques = truth(Path(a.model), a.engine, Path(a.cache) if a.cache else None)
    print(f"truth ({a.engine}) ready in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    cfg = ObserverConfig()
    if a.q_scale is not None:
        cfg = replace(cfg, q_scale=a.q_scale)
    if a.q_extra is not None:
        cfg = replace(cfg, q_extra_std=a.q_extra)
    obs = make_observer(mech, cfg)
    obs.ekf.store_P = "full"
    names = physical_names(mech)
    bound = steady_bound(obs)  # the steady-state estimate at nine poses (docs/bound.md: the PCRB is within 6 %)
    start = obs.config.start_up
    rms, nees, nis, nis_dof, walls, peaks = [], [], [], [], [], []
    for j in range(a.runs):
        meas = measure(mech, clean, torque_t, torques, seed=a.seed + j).signals
        t = meas.t
        U = meas.select(mech.motor_names).data
        Y = meas.select(obs.channels).data
        w0 = time.perf_counter()
        res = obs.ekf.run(t, U, Y)
        walls.append(time.perf_counter() - w0)
        phys = obs.physical(res.t, res.x_hat)
        m = metrics(phys, tr, start)
        rms.append([m["rms_error"][n] for n in names])
        e = np.column_stack([phys[n] - np.interp(phys.t, tr.t, tr[n]) for n in names])
        Pp = physical_covariance(obs, res.x_hat, res.P)
        nees.append(np.einsum("ki,ki->k", e, np.linalg.solve(Pp, e[:, :, None])[:, :, 0]))
        nis.append(res.nis)
        nis_dof.append(res.nis_dof)
        if j == 0:
            sel = phys.t >= start
            for n in names[2 * mech_nq(mech) : 2 * mech_nq(mech) + 2]:
                # vibration peaks: above the manoeuvre's own (quasi-static) content
                ft, at = fft_peaks(phys.t[sel], np.interp(phys.t[sel], tr.t, tr[n]), fmax=180.0, n_peaks=6,
                                   fmin=5.0, return_amplitudes=True)
                fe = fft_peaks(phys.t[sel], phys[n][sel], fmax=180.0, n_peaks=6, fmin=5.0)
                significant = ft[at >= 0.1 * at.max()]  # side lobes of a few % are below the estimate's noise
                peaks.append((n, np.sort(significant).tolist(), np.sort(fe).tolist()))
        print(f"run {j + 1}/{a.runs}: {walls[-1]:.2f} s", file=sys.stderr)
    rms = np.array(rms)
    burn = int(round(start * mech.sample_rate_hz))
    cn = mc_consistency(np.array(nees), len(names), burn_in=burn)
    ci = mc_consistency(np.array(nis), np.array(nis_dof), burn_in=burn)
    print(f"\n{a.runs} runs, truth {a.engine}, reduced model {obs.info['reduced_ndof']} dofs, channels "
          f"{' '.join(obs.channels)}; errors after {start} s")
    print(f"{'quantity':9s} {'bound':>10s} {'mean RMS':>10s} {'ratio':>6s} {'worst ratio':>11s}")
    out = {"runs": a.runs, "engine": a.engine, "quantities": {}}
    for i, n in enumerate(names):
        mr = rms[:, i].mean()
        print(f"{n:9s} {bound[n]:10.3g} {mr:10.3g} {mr / bound[n]:6.2f} {rms[:, i].max() / bound[n]:11.2f}")
        out["quantities"][n] = {"bound": bound[n], "mean_rms": float(mr), "ratio": float(mr / bound[n]),
                                "worst_ratio": float(rms[:, i].max() / bound[n])}
    print(f"NEES (10 physical quantities): per-step average over the runs inside its 95 % band "
          f"{100 * cn.fraction_inside:.1f} % of the time; time average {cn.time_avg:.2f} (expected "
          f"{cn.expected:.0f}; band {cn.time_avg_lo_eff:.2f}..{cn.time_avg_hi_eff:.2f} for its autocorrelation "
          f"time of {cn.tau:.0f} steps, {cn.time_avg_lo:.2f}..{cn.time_avg_hi:.2f} if the steps were independent)")
    print(f"NIS: per-step inside its band {100 * ci.fraction_inside:.1f} % of the time; time average "
          f"{ci.time_avg:.3f} (expected {ci.expected:.1f}; band {ci.time_avg_lo_eff:.3f}..{ci.time_avg_hi_eff:.3f} "
          f"for its autocorrelation time of {ci.tau:.1f} steps, {ci.time_avg_lo:.3f}..{ci.time_avg_hi:.3f} if "
          "independent)")
    for n, ft, fe in peaks:
        matched, err = match_peaks(ft, fe)
        print(f"FFT peaks {n} (0-180 Hz, truth peaks >= 10 % of the largest): truth {np.round(ft, 2).tolist()} Hz, "
              f"nearest estimated peaks "
              f"{np.round(matched, 2).tolist()} Hz, error {np.round(err, 2).tolist()} %")
    print(f"observer wall per 3 s run: mean {np.mean(walls):.2f} s (real-time factor {3.0 / np.mean(walls):.2f})")
    out.update(nees={"time_avg": cn.time_avg, "expected": cn.expected, "band": [cn.time_avg_lo, cn.time_avg_hi],
                     "band_eff": [cn.time_avg_lo_eff, cn.time_avg_hi_eff], "tau": cn.tau,
                     "fraction_inside": cn.fraction_inside},
               nis={"time_avg": ci.time_avg, "expected": ci.expected, "band": [ci.time_avg_lo, ci.time_avg_hi],
                    "band_eff": [ci.time_avg_lo_eff, ci.time_avg_hi_eff], "tau": ci.tau,
                    "fraction_inside": ci.fraction_inside},
               fft_peaks=[{"quantity": n, "truth_hz": ft, "estimate_hz": fe} for n, ft, fe in peaks],
               wall_s_mean=float(np.mean(walls)))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


def mech_nq(mech) -> int:
    return len(mech.coordinates)


if __name__ == "__main__":
    sys.exit(main())

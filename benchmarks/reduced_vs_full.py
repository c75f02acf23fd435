"""Reduced (13 dofs) vs full-order (30 dofs) ERLS simulation of the paper's manoeuvre: tip elastic displacement.

    python benchmarks/reduced_vs_full.py [--full-run tests/data/sixbar_erls_3s] [--duration 3]

The full-order run is a run folder of ``exuflex simulate --engine erls`` (its truth.csv holds the tip elastic
displacement x25, y26); the reduced model is driven by the same computed torques (RK4, 0.1 ms) from rest.
Prints the normalised RMS difference (RMS of the difference / RMS of the full-order signal) and the wall times.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from exuflex.erls.model import ErlsModel
from exuflex.erls.simulate import simulate
from exuflex.manoeuvre import computed_torque, plan
from exuflex.mechanism import load_mechanism
from exuflex.reduction import CraigBampton, ReducedModel
from exuflex.runs import read_run

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "sixbar.toml"))
    ap.add_argument("--full-run", default=str(ROOT / "tests" / "data" / "sixbar_erls_3s"))
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--paper-form", action="store_true", help="the paper's eq. 7 (x' ~ H p'), not the consistent one")
    a = ap.parse_args(argv)
    mech = load_mechanism(a.model)
    full = read_run(a.full_run).truth
    h = 1e-4
    t0 = time.perf_counter()
    p = plan(mech, dt=h, t_end=a.duration)
    tau = computed_torque(mech, p)
    t_plan = time.perf_counter() - t0
    rm = ReducedModel(CraigBampton(ErlsModel(mech)), consistent=not a.paper_form)
    n_tab = len(tau)

    def torque(t):
        return tau[min(int(round(t / h)), n_tab - 1)]

    t0 = time.perf_counter()
    tr = simulate(rm.rhs, rm.rest_state(p.q[0]), a.duration, torque, h=h, output_every=20)
    wall = time.perf_counter() - t0
    names = rm.names
    print(f"plan + torque {t_plan:.1f} s; reduced simulation of {a.duration} s: {wall:.1f} s wall")
    for n in ("x25", "y26"):
        yr = tr.y[:, names.index(n)]
        yf = np.interp(tr.t, full.t, full[n])
        nrms = np.sqrt(np.mean((yr - yf) ** 2)) / np.sqrt(np.mean(yf**2))
        print(f"{n}: normalised RMS difference {100 * nrms:.2f} % (full-order RMS {np.sqrt(np.mean(yf ** 2)):.3g} m)")
    for i, n in enumerate(mech.coordinate_names):
        d = np.abs(tr.y[:, i] - np.interp(tr.t, full.t, full[n])).max()
        print(f"{n}: max difference {d:.2e} rad")
    return 0


if __name__ == "__main__":
    sys.exit(main())

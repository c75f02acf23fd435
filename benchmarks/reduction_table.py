"""The six-bar's reduced model: Table-2-style accuracy at q*, ranking vs truncation, and along the manoeuvre.

    python benchmarks/reduction_table.py [--model models/sixbar.toml] [--configs 25]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from exuflex.erls.model import ErlsModel
from exuflex.manoeuvre import plan
from exuflex.mechanism import load_mechanism
from exuflex.reduction import CraigBampton, accuracy_indices

ROOT = Path(__file__).resolve().parents[1]


def worst_along(cb, qs, variant: str):
    at = cb.at
    rc_star = at(cb.q_star)

    def constant(q, z0=None):
        return dataclasses.replace(at(q, z0), B=rc_star.B, Psi=rc_star.Psi, H=rc_star.H)

    def unrotated(q, z0=None):
        rc = at(q, z0)
        H = rc.H.copy()
        nq, me = cb.nq, len(cb.im)
        H[nq + cb.is_, nq + me :] = cb.Phi
        return dataclasses.replace(rc, Psi=cb.Phi, H=H)

    if variant == "constant H(q*)":
        cb.at = constant
    elif variant == "B(q), Phi not rotated":
        cb.at = unrotated
    try:
        accs = [accuracy_indices(cb, q) for q in qs]
    finally:
        cb.at = at
    return min(a.worst_nco for a in accs), max(a.worst_error_pct for a in accs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "sixbar.toml"))
    ap.add_argument("--configs", type=int, default=25)
    a = ap.parse_args(argv)
    mech = load_mechanism(a.model)
    model = ErlsModel(mech)
    t0 = time.perf_counter()
    cb = CraigBampton(model)
    print(f"basis built in {time.perf_counter() - t0:.3f} s ({cb.build_seconds:.3f} s inside): {cb.r} dofs = "
          f"{cb.n_m} masters + {cb.n_interior} interior modes {np.round(cb.interior_frequencies_hz[cb.kept], 1)} Hz")
    for ranking in ("imr", "frequency"):
        c = CraigBampton(model, ranking=ranking)
        acc = accuracy_indices(c, c.q_star)
        print(f"\nat q*, ranking={ranking}:")
        print(f"{'full (Hz)':>10s} {'reduced (Hz)':>13s} {'NCO':>8s} {'error %':>8s}")
        for f, fr, n, e in zip(acc.full_hz, acc.reduced_hz, acc.nco, acc.freq_error_pct):
            print(f"{f:10.2f} {fr:13.2f} {n:8.5f} {e:8.3f}")
    d = mech.manoeuvre.duration
    qs = plan(mech, dt=d / (a.configs - 1), t_end=d).q
    print(f"\nalong the manoeuvre ({len(qs)} configurations), one basis built at q*:")
    for variant in ("configuration-dependent (eqs. 5-6)", "B(q), Phi not rotated", "constant H(q*)"):
        nco, err = worst_along(cb, qs, variant)
        print(f"  {variant:38s} worst NCO {nco:.4f}, worst frequency error {err:.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())

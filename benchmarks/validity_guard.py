"""The validity guard on the gallery's manoeuvres: each link's fastest rate against its ERLS departure rate.

For every model in ``models/`` with a manoeuvre: the planned rigid motion (``exuflex.manoeuvre.plan``), each
link's absolute rotation rate along it (:func:`exuflex.erls.validity.link_rates`), its first clamped frequency
``omega_c`` (:func:`exuflex.erls.validity.clamped_frequencies`), the peak rate over the departure rate
``DEPARTURE_RATIO omega_c``, the guard's estimated error and its warnings (:func:`exuflex.erls.validity.rate_warnings`).

    python benchmarks/validity_guard.py [--dt 0.002] [--docs docs/validity.md]

``--docs`` rewrites the page's block between its ``validity_guard.py`` markers.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tomllib
from pathlib import Path

import numpy as np
from _pages import rewrite_block  # (a script: its folder is on the path)

from exuflex.erls.validity import (
    DEPARTURE_NRMS,
    DEPARTURE_RATIO,
    clamped_frequencies,
    link_rates,
    rate_warnings,
)
from exuflex.manoeuvre import plan
from exuflex.mechanism import load_mechanism

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- validity_guard.py: begin -->", "<!-- validity_guard.py: end -->"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dt", type=float, default=2e-3, help="plan step (s)")
    ap.add_argument("--docs", default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s: %(message)s")
    cmd = " ".join(["python benchmarks/validity_guard.py", *sys.argv[1:]])
    lines = [BEGIN, f"Measured by `{cmd}` (each model's own manoeuvre, planned rigid motion).", "",
             "| model | link | omega_c (rad/s) | peak rate (rad/s) | peak / departure rate | estimated error (%) | warning |",
             "|---|---|---|---|---|---|---|"]
    for path in sorted((ROOT / "models").glob("*.toml")):
        if "manoeuvre" not in tomllib.loads(path.read_text()):
            continue
        mech = load_mechanism(path)
        p = plan(mech, dt=args.dt, t_end=mech.manoeuvre.duration)
        wc = clamped_frequencies(mech)
        peak = np.abs(link_rates(mech, p.q, p.qd)).max(axis=0)
        warned = {w.link: w.level for w in rate_warnings(mech, p.t, p.q, p.qd)}
        for lk, r in zip(mech.links, peak):
            ratio = r / (DEPARTURE_RATIO * wc[lk.name])
            lines.append(f"| {mech.name} | {lk.name} | {wc[lk.name]:.1f} | {r:.3g} | {ratio:.3f} | "
                         f"{100 * DEPARTURE_NRMS * ratio**2:.2g} | {warned.get(lk.name, 'none')} |")
    lines.append(END)
    text = "\n".join(lines)
    print(text)
    if args.docs:
        rewrite_block(args.docs, BEGIN, END, text)


if __name__ == "__main__":
    main()

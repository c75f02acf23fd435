"""``exuflex design MODEL``: rank curvature-gauge stations by the steady-state bound of the tip displacement.

Candidates at ``--candidates`` evenly spaced interior stations of every link, each alone with the model's encoders;
then a greedy set of as many gauges as the model file has, and where the file's own gauges rank
(:func:`exuflex.scoring.design.rank_gauges`).
"""

from __future__ import annotations

import argparse
import sys

from ..runs import dump_json
from .args import positive_int


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("design", help="rank strain-gauge stations by the estimation bound",
                       description=__doc__.split("\n")[0])
    p.add_argument("model", help="mechanism model file (TOML)")
    p.add_argument("--candidates", type=positive_int, default=9, help="candidate stations per link (default 9)")
    p.add_argument("--top", type=positive_int, default=15, help="rows of the ranked table (default 15)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from dataclasses import asdict

    from ..mechanism import load_mechanism
    from ..scoring.design import rank_gauges

    mech = load_mechanism(args.model)
    res = rank_gauges(mech, n_candidates=args.candidates)
    if args.json:
        print(dump_json(asdict(res), default=float))
        return 0
    out = sys.stdout
    print(f"{mech.name}: gauge stations ranked by the steady-state RMS bound of the tip elastic displacement "
          f"(encoders + one gauge, gauge noise {res.gauge_noise:.3g} 1/m); encoders alone: {res.encoders_bound:.3g} m",
          file=out)
    print(f"{'rank':>4s} {'link':>6s} {'station (m)':>11s} {'bound (m)':>10s}", file=out)
    for i, d in enumerate(res.single[: args.top], 1):
        print(f"{i:4d} {d['link']:>6s} {d['station']:11.4g} {d['tip_bound']:10.3g}", file=out)
    print("the model file's gauges (same noise):", file=out)
    for g in res.model_gauges:
        print(f"  {g['name']}: {g['link']} at {g['station']:g} m, bound {g['tip_bound']:.3g} m, rank {g['rank']} of "
              f"{len(res.single)}", file=out)
    print(f"the file's set of {len(res.model_gauges)}: {res.model_set_bound:.3g} m; greedy set "
          f"{', '.join(res.greedy_set)}: {res.greedy_set_bound:.3g} m", file=out)
    return 0

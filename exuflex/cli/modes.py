"""``exuflex modes MODEL``: natural frequencies of the full-order ERLS model at a configuration.

The model is linearised at rest at ``q`` (default: the model's ``q_ref``) with the motors free
(torque-driven; the mechanism's zero-frequency modes are dropped) or ``--locked`` (q held). Optional
comparisons: ``--exudyn`` (the independent Exudyn model, :func:`exuflex.groundtruth.exudyn_frequencies`)
and ``--reduced`` (the Craig-Bampton reduced model, :func:`exuflex.reduction.reduced_modes_report`).
With ``--json`` one JSON object is printed::

    {"model": ..., "q": [...], "locked": false, "fmax_hz": 180.0,
     "full": {"ndof": 30, "n_elastic": 27, "frequencies_hz": [...]},
     "exudyn": {"frequencies_hz": [...]},          # with --exudyn
     "reduced": {...}}                               # with --reduced
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from .args import name_list, positive_float, positive_int

__all__ = ["MAX_ELEMENTS", "add_parser", "modes_report", "run"]

MAX_ELEMENTS = 1000
"""Most elements ``--refine`` may make (the modal analysis is a dense eigenproblem of 3 dofs per element)."""


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers such as 1.08,2.64,4.71, got {text!r}")


def _n_interior(text: str):
    if text == "auto":
        return "auto"
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer or 'auto', got {text!r}")
    return n


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("modes", help="natural frequencies of the full-order model (and Exudyn / reduced)",
                       description=__doc__.split("\n")[0])
    p.add_argument("model", help="model file (TOML), e.g. models/sixbar.toml")
    p.add_argument("--q", type=_floats, default=None, help="configuration Q1,Q2,... (rad); default: the model's q_ref")
    p.add_argument("--fmax", type=positive_float, default=180.0, help="report modes up to this frequency (Hz, default 180)")
    p.add_argument("--locked", action="store_true", help="motors locked (q held) instead of free")
    p.add_argument("--refine", type=positive_int, default=1, help="split every element into this many (default 1)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.add_argument("--exudyn", action="store_true", help="add the Exudyn model's frequencies")
    p.add_argument("--reduced", action="store_true", help="add the reduced model's frequencies, NCO and errors")
    p.add_argument("--masters", type=name_list("master dofs"), default=None,
                   help="elastic master dofs a,b,... for --reduced (default: the model's [reduction].masters)")
    p.add_argument("--n-interior", type=_n_interior, default=None,
                   help="interior modes N or 'auto' for --reduced (default: the model's)")
    p.add_argument("--qstar", type=_floats, default=None, help="reduction configuration Q1,Q2,... for --reduced")
    p.set_defaults(func=run)
    return p


def modes_report(model_path: str, *, q=None, fmax: float = 180.0, locked: bool = False, refine: int = 1,
                 exudyn: bool = False, reduced: bool = False, masters=None, n_interior=None, q_star=None) -> dict:
    """Library form of the command: the JSON-ready report."""
    from ..erls.modal import modal_analysis
    from ..erls.model import ErlsModel
    from ..mechanism import load_mechanism, refine_mechanism

    from ..errors import UsageError
    from ..validate import check_configurations, check_positive

    if isinstance(refine, bool) or not isinstance(refine, (int, np.integer)) or refine < 1:
        raise UsageError(f"refine (--refine): expected a positive integer, got {refine!r}")
    check_positive(fmax, "fmax", "--fmax")
    if masters is not None:
        masters = list(masters)
    mech = load_mechanism(model_path)
    n_el = sum(len(lk.stations) - 1 for lk in mech.links)
    if refine * n_el > MAX_ELEMENTS:
        raise UsageError(f"refine (--refine): {refine} x {n_el} elements is more than {MAX_ELEMENTS} elements "
                         "(dense eigenproblems grow with their cube); expected a smaller factor")
    check_configurations(mech)  # loops close, away from singularities
    if refine > 1:
        mech = refine_mechanism(mech, refine)
    q = np.asarray(mech.q_ref if q is None else q, float)
    if q.shape != (len(mech.coordinates),):
        raise ValueError(f"--q: expected {len(mech.coordinates)} values ({', '.join(mech.coordinate_names)}), "
                         f"got {q.size}")
    model = ErlsModel(mech)
    res = modal_analysis(model, q, locked=locked)
    out = {
        "model": mech.name,
        "source": str(model_path),
        "q": q.tolist(),
        "locked": locked,
        "fmax_hz": fmax,
        "full": {"ndof": model.n, "n_elastic": model.ne, "frequencies_hz": res.below(fmax).tolist()},
    }
    if exudyn:
        from ..groundtruth import exudyn_frequencies  # lazy: Exudyn is heavy and optional here

        f = np.asarray(exudyn_frequencies(mech, q))
        out["exudyn"] = {"frequencies_hz": f[f <= fmax].tolist()}
    if reduced:
        try:
            from ..reduction import reduced_modes_report
        except ImportError as exc:
            raise RuntimeError(f"--reduced needs exuflex.reduction.reduced_modes_report, not available: {exc}") from None
        out["reduced"] = reduced_modes_report(model, q, masters=masters, n_interior=n_interior, q_star=q_star,
                                              fmax=fmax)
    return out


def _table(rep: dict) -> str:
    full = rep["full"]["frequencies_hz"]
    exu = rep.get("exudyn", {}).get("frequencies_hz")
    red = rep.get("reduced")
    lines = [
        (f"{rep['model']} ({rep['source']}) at q = [{', '.join(f'{v:.4f}' for v in rep['q'])}], "
        f"motors {'locked' if rep['locked'] else 'free'}"),
        (f"full-order ERLS model: {rep['full']['ndof']} dofs ({rep['full']['n_elastic']} elastic), "
        f"{len(full)} modes <= {rep['fmax_hz']:g} Hz"),
    ]
    if red is not None:
        lines.append(f"reduced model: {red.get('ndof')} dofs, masters {red.get('masters')}, "
                     f"{red.get('interior_modes')} interior modes")
    head = f"{'mode':>4} {'full (Hz)':>10}"
    if exu is not None:
        head += f" {'Exudyn (Hz)':>11} {'diff %':>7}"
    if red is not None:
        head += f" {'reduced (Hz)':>12} {'NCO':>7} {'err %':>7}"
    lines.append(head)
    for i, f in enumerate(full):
        row = f"{i + 1:>4} {f:>10.2f}"
        if exu is not None:
            row += f" {exu[i]:>11.2f} {100 * (exu[i] - f) / f:>+7.2f}" if i < len(exu) else f" {'-':>11} {'':>7}"
        if red is not None:
            rf, nco, err = (red.get(k, []) for k in ("frequencies_hz", "nco", "freq_error_pct"))
            row += (f" {rf[i]:>12.2f} {nco[i]:>7.4f} {err[i]:>7.3f}" if i < min(len(rf), len(nco), len(err))
                    else f" {'-':>12}")
        lines.append(row)
    return "\n".join(lines)


def run(args) -> int:
    rep = modes_report(args.model, q=args.q, fmax=args.fmax, locked=args.locked, refine=args.refine,
                       exudyn=args.exudyn, reduced=args.reduced, masters=args.masters,
                       n_interior=args.n_interior, q_star=args.qstar)
    print(json.dumps(rep) if args.json else _table(rep))
    return 0

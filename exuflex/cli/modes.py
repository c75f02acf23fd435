"""``exuflex modes MODEL``: natural frequencies of the full-order ERLS model at a configuration.

The model is linearised at rest at ``q`` (default: the model's ``q_ref``) with the motors free
(torque-driven; the mechanism's zero-frequency modes are dropped) or ``--locked`` (every encoder's reading held:
``q + G u`` for a relative coordinate, :meth:`~exuflex.erls.model.ErlsModel.coordinate_reading_rows`). Optional
comparisons: ``--exudyn`` (the independent Exudyn model, :func:`exuflex.groundtruth.exudyn_frequencies`, on
the same mesh as the ERLS model, with the same motors free or locked; ``--beam``) and ``--reduced`` (the
Craig-Bampton reduced model, :func:`exuflex.reduction.reduced_modes_report`). The mesh is the model file's,
split by ``--refine`` and then by ``--elements-per-link`` (:func:`exuflex.mechanism.remesh_mechanism`).
With ``--json`` one JSON object is printed::

    {"model": ..., "q": [...], "locked": false, "fmax_hz": 180.0,
     "full": {"ndof": 30, "n_elastic": 27, "frequencies_hz": [...], "damping_ratio": [...]},
     "exudyn": {"frequencies_hz": [...], "damping_ratio": [...], "beam": "ancf", "locked": false,
                "elements_per_link": "file", "n_elements": 30},  # with --exudyn
     "reduced": {..., "along": {...}, "truncation": {...}, "static": {...}}}   # with --reduced

``damping_ratio``: each mode's ratio (a fraction, aligned with ``frequencies_hz``) from the damped eigenvalues
``s`` of the linearised system, ``-Re s / |s|`` (ERLS: :func:`exuflex.erls.modal.damping_ratios`; Exudyn:
:func:`exuflex.groundtruth.modal_damping`, its ``ComputeLinearizedSystem``); motors free, the model file's
``alpha / (2 w) + beta w / 2``.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from ..mechanism import MAX_ELEMENTS  # the loader's limit (exuflex.mechanism.limits), also for --refine
from ..runs import dump_json
from ..truth import BEAMS
from .args import n_interior, name_list, nonneg_int, positive_float, positive_int
from .simulate import elements_per_link_arg

__all__ = ["MAX_ELEMENTS", "add_parser", "modes_report", "run"]



def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers such as 1.08,2.64,4.71, got {text!r}")


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("modes", help="natural frequencies of the full-order model (and Exudyn / reduced)",
                       description=__doc__.split("\n")[0])
    p.add_argument("model", help="model file (TOML), e.g. models/sixbar.toml")
    p.add_argument("--q", type=_floats, default=None, help="configuration Q1,Q2,... (rad); default: the model's q_ref")
    p.add_argument("--fmax", type=positive_float, default=180.0, help="report modes up to this frequency (Hz, default 180)")
    p.add_argument("--locked", action="store_true", help="motors locked (every encoder's reading held) instead of free")
    p.add_argument("--refine", type=positive_int, default=1, help="split every element into this many (default 1)")
    p.add_argument("--elements-per-link", type=elements_per_link_arg, default="file", metavar="N|file",
                   help="then split elements so that no element is longer than 1/N of its link (default: file)")
    p.add_argument("--beam", choices=tuple(BEAMS), default="ancf",
                   help="Exudyn model for --exudyn: ANCF cable (default), geometrically exact beam (needs a fine mesh), "
                        "or ffrf (alias solid): floating-frame bodies from solid meshes (netgen, Hurty-Craig-Bampton)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.add_argument("--exudyn", action="store_true", help="add the Exudyn model's frequencies")
    p.add_argument("--reduced", action="store_true", help="add the reduced model's frequencies, NCO and errors")
    p.add_argument("--masters", type=name_list("master dofs"), default=None,
                   help="elastic master dofs a,b,... for --reduced, e.g. node9.transverse, or 'auto' (default: the "
                        "model's [reduction].masters)")
    p.add_argument("--n-interior", type=n_interior, default=None,
                   help="interior modes N or 'auto' for --reduced (default: the model's)")
    p.add_argument("--qstar", type=_floats, default=None, help="reduction configuration Q1,Q2,... for --reduced")
    p.add_argument("--along", type=nonneg_int, default=41,
                   help="--reduced: report the worst NCO and frequency error over this many configurations of the "
                        "model's manoeuvre (default 41; 0: skip)")
    p.set_defaults(func=run)
    return p


def modes_report(model_path: str, *, q=None, fmax: float = 180.0, locked: bool = False, refine: int = 1,
                 exudyn: bool = False, reduced: bool = False, masters=None, n_interior=None, q_star=None,
                 along: int = 41, elements_per_link: int | str = "file", beam: str = "ancf") -> dict:
    """Library form of the command: the JSON-ready report."""
    from ..erls.modal import aligned_ratios, damping_ratios, modal_analysis
    from ..erls.model import ErlsModel
    from ..errors import UsageError
    from ..mechanism import load_mechanism, refine_mechanism, remesh_mechanism, remeshed_element_count
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
    asm = check_configurations(mech)  # loops close, away from singularities; the branch against the guesses
    if refine > 1:
        mech = refine_mechanism(mech, refine)
    if elements_per_link != "file":
        n_new = remeshed_element_count(mech, int(elements_per_link_arg(str(elements_per_link))))
        if n_new > MAX_ELEMENTS:
            raise UsageError(f"elements_per_link (--elements-per-link): about {n_new} elements, more than "
                             f"{MAX_ELEMENTS}; expected a smaller number")
        mech = remesh_mechanism(mech, elements_per_link_arg(str(elements_per_link)))
    if beam not in BEAMS:
        raise ValueError(f"--beam: expected one of {tuple(BEAMS)}, got {beam!r}")
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
    out["full"]["damping_ratio"] = aligned_ratios(res.below(fmax), *damping_ratios(model, q, locked)).tolist()
    if asm is not None:
        out["assembly"] = asm.as_dict()
    if exudyn and BEAMS[beam] == "ffrf":
        if locked:
            raise UsageError("--locked: the FFRF truth's modes are reported with the motors free; expected no --locked")
        from ..groundtruth import ffrf_frequencies  # lazy: Exudyn, netgen and ngsolve are heavy

        r = ffrf_frequencies(mech, q, fmax=fmax, progress=lambda msg: print(msg, file=sys.stderr), with_damping=True)
        out["exudyn"] = {"frequencies_hz": r["frequencies_hz"].tolist(), "damping_ratio": r["damping_ratio"].tolist(),
                         "beam": beam, "locked": False,
                         "out_of_plane_hz": r["out_of_plane_hz"].tolist(), "solid": r["settings"]}
    elif exudyn:
        from ..groundtruth import exudyn_frequencies, modal_damping  # lazy: Exudyn is heavy and optional here

        f = np.asarray(exudyn_frequencies(mech, q, elements_per_link="file", formulation=BEAMS[beam], locked=locked))
        f = f[f <= fmax]
        zeta = aligned_ratios(f, *modal_damping(mech, q, elements_per_link="file", formulation=BEAMS[beam],
                                                locked=locked))
        out["exudyn"] = {"frequencies_hz": f.tolist(), "damping_ratio": zeta.tolist(), "beam": beam, "locked": locked,
                         "elements_per_link": elements_per_link, "n_elements": sum(lk.n_elements for lk in mech.links)}
    if reduced:
        try:
            from ..reduction import reduced_modes_report
        except ImportError as exc:
            raise RuntimeError(f"--reduced needs exuflex.reduction.reduced_modes_report, not available: {exc}") from None
        if isinstance(along, bool) or not isinstance(along, (int, np.integer)) or along < 0:
            raise UsageError(f"along (--along): expected a number of configurations >= 0, got {along!r}")
        from ..validate import check_work

        # a configuration: the full model's and the reduced model's eigenproblems (about 10 n^3 flop each) and a
        # few vectors of the full model's size kept for the worst case
        check_work(along, along, param="along", flag="--along", what="configurations", bytes_each=8 * 8 * model.n,
                   flops_each=2 * 10 * model.n**3)
        out["reduced"] = reduced_modes_report(model, q, masters=masters, n_interior=n_interior, q_star=q_star,
                                              fmax=fmax, along=along)
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
    if "assembly" in rep:
        lines.insert(1, rep["assembly"]["summary"])
    if exu is not None:
        ex = rep["exudyn"]
        if "solid" in ex:
            lk = ex["solid"]["links"]
            lines.append(f"Exudyn model: FFRF bodies from solid meshes ({sum(v['nodes'] for v in lk.values())} nodes, "
                         f"{sum(v['modes'] for v in lk.values())} modes), motors free; in-plane modes")
        else:
            lines.append(f"Exudyn model: {ex.get('beam', 'ancf')} beams on the same mesh ({ex.get('n_elements')} "
                         f"elements), motors {'locked' if ex.get('locked') else 'free'}")
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
    al = red.get("along") if red is not None else None
    if al:
        def _q(v):
            return "[" + ", ".join(f"{x:.3f}" for x in v) + "]"
        lines.append(
            f"along the manoeuvre ({al['configurations']} configurations): worst NCO {al['worst_nco']:.4f} at q = "
            f"{_q(al['worst_nco_q'])} (full mode {al['worst_nco_mode_hz']:.1f} Hz), worst frequency error "
            f"{al['worst_freq_error_pct']:.3f} % at q = {_q(al['worst_freq_error_q'])} (full mode "
            f"{al['worst_freq_error_mode_hz']:.1f} Hz){'' if al['ok'] else ', BELOW THE THRESHOLDS'}")
    tr = red.get("truncation") if red is not None else None
    if tr:
        ch = ", ".join(f"{c} {v:.3g}" for c, v in tr["rho_channels"].items())
        qu = ", ".join(f"{k} {v:.2e}" for k, v in tr["quantities_rms"].items())
        lines.append(
            f"truncation (docs/reduction.md): the manoeuvre's truncated output in the channels, whitened mean square "
            f"in the worst window, rho = {tr['rho']:.3g} (limit {tr['rho_max']:g}; {ch}; without interior modes "
            f"{tr['rho_without_interior']:.3g}){'' if tr['met'] else ', ABOVE THE LIMIT'}"
            + (f"; estimated quantities' truncated part (q, q', tip), RMS in the worst window: {qu}" if qu else ""))
        if tr.get("bias"):
            bi = ", ".join(f"{k} {v:.3g}" for k, v in tr["bias"].items())
            lines.append(
                f"filter (docs/reduction.md): the steady filter's mean-square error on the linearised full model under "
                f"the manoeuvre, over the bound's variance: {bi} (limit {tr['bias_max']:g}; without interior modes "
                f"{tr['bias_without_interior']:.3g}); its whitened innovations' mean square summed over the channels "
                f"{tr['innovation']:.3g} (limit {tr['innovation_max']:g}){'' if tr['bias_met'] else ', ABOVE THE LIMIT'}")
        dy = tr.get("dynamic")
        if dy:
            lines.append(
                f"both figures are the basis's the observer uses (static corrections in); its {dy['n_interior']} "
                f"dynamic modes alone: rho = {dy['rho']:.3g}"
                + (f", filter {max(dy['bias'].values()):.3g} ({max(dy['bias'], key=dy['bias'].get)}), innovations "
                   f"{dy['innovation']:.3g}" if dy.get("bias") else ""))
    st = red.get("static") if red is not None else None
    if st:
        hz = ", ".join(f"{f:.0f}" for f in st["ritz_hz"])
        acc = ", ".join(f"{k} {v:.3g}" for k, v in st["max_acceleration"].items())
        rate = ", ".join(f"{k} {v:.3g}" for k, v in st["max_rate"].items())
        lines.append(
            f"static corrections (docs/reduction.md): {st['count']} kept{f' (Ritz {hz} Hz)' if hz else ''}; the largest "
            f"quasi-static reading the basis misses under the loads the inputs can produce (q'' up to {acc} rad/s^2, "
            f"q' up to {rate} rad/s) is {st['figure']:.3g} noise sd ({st['worst_row']}; limit {st['limit']:.3g}; "
            f"without them {st['figure_without']:.3g}){'' if st['met'] else ', ABOVE THE LIMIT'}")
    return "\n".join(lines)


def run(args) -> int:
    rep = modes_report(args.model, q=args.q, fmax=args.fmax, locked=args.locked, refine=args.refine,
                       exudyn=args.exudyn, reduced=args.reduced, masters=args.masters,
                       n_interior=args.n_interior, q_star=args.qstar, along=args.along,
                       elements_per_link=args.elements_per_link, beam=args.beam)
    print(dump_json(rep, indent=None) if args.json else _table(rep))
    return 0

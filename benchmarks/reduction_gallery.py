"""The reduced models of every mechanism in models/: accuracy at q* and along the manoeuvre, masters from the
model file and automatic, interior modes chosen at q* only and over the manoeuvre. Writes docs/reduction.md.

    python benchmarks/reduction_gallery.py [--models sixbar,fourbar or path/to/model.toml,...] [--along 41] [--out docs/reduction.md]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism
from exuflex.reduction import CraigBampton, accuracy_along, accuracy_indices, manoeuvre_configurations, static
from exuflex.reduction.static import STATIC_MAX
from exuflex.reduction.truncation import BIAS_MAX, INNOVATION_MAX, TRUNCATION_MAX

ROOT = Path(__file__).resolve().parents[1]
# master sets beside the file's and the automatic ones: the four-bar's tip across the coupler alone, where the
# interior modes ranked at q* miss band modes later in the manoeuvre; the single link's tip in the global frame
# (its y is the arm's axial direction at the end of the quarter turn)
EXAMPLES = {"fourbar": [["node9.transverse"]], "single_link": [["node5.y", "node5.theta"]]}
# mechanisms written fresh for the interior-mode criterion (issue 28), in the criterion's table
FRESH = ["benchmarks/models/steel_arm.toml", "benchmarks/models/single_link_16.toml", "benchmarks/models/shaken_link.toml"]
# mechanisms written fresh for the static corrections (issue 28, heavy payload), and payload scales they are tried at
FRESH_STATIC = ["benchmarks/models/rocker_weight.toml"]
STATIC_SCALES = {"slider_crank": (1.0, 1.5, 2.0), "rocker_weight": (1.0, 1.5, 2.0)}


def _derivation(module=None) -> list[str]:
    """A requirement's derivation: the module docstring of ``module`` (default :mod:`exuflex.reduction.truncation`)
    from its first section on, its section underlines as markdown headings."""
    from exuflex.reduction import truncation

    module = truncation if module is None else module
    text = module.__doc__.split("\n\n", 1)[1].strip().splitlines()
    out = []
    for i, ln in enumerate(text):
        if set(ln) == {"-"} and i > 0:
            out[-1] = "### " + out[-1]
            continue
        out.append(ln.replace(":data:", "").replace(":func:", "").replace(":class:", "").replace(":mod:", ""))
    return out


def _q(q) -> str:
    return "[" + ", ".join(f"{v:.3f}" for v in q) + "]"


def rows_for(path: Path, n_along: int) -> list[str]:
    mech = load_mechanism(path)
    model = ErlsModel(mech)
    qs = manoeuvre_configurations(mech, n_along)
    out = []
    variants = [("file", None, None)] if mech.reduction.masters else []
    if mech.reduction.masters and mech.reduction.n_interior is not None:  # the file's count, and automatic
        variants.append(("file", None, "auto"))
    variants.append(("automatic", (), None))
    variants += [("example", m, "auto") for m in EXAMPLES.get(mech.name, [])]
    for label, masters, count in variants:
        for choice, p in (("q* only", False), ("manoeuvre", None)):
            cb = CraigBampton(model, masters=masters, path=p, n_interior=count)
            at = accuracy_indices(cb, cb.q_star)
            n_int = f"{cb.n_interior}" + (" (auto)" if count == "auto" or mech.reduction.n_interior is None else "")
            tr = cb.truncation
            seen = "-" if tr is None else f"{tr['rho']:.3g}" + ("" if tr["met"] else " (above)")
            cells = [mech.name, f"{label}: {', '.join(cb.masters)}", choice, str(cb.r), n_int, seen,
                     f"{at.worst_nco:.4f}", f"{at.worst_error_pct:.3f}"]
            if qs is None:
                cells += ["-", "-"]
            else:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    accs = [a for a in accuracy_along(cb, qs, warn=False) if a.nco.size]
                a = min(accs, key=lambda a: a.worst_nco)
                b = max(accs, key=lambda a: a.worst_error_pct)
                cells += [f"{a.worst_nco:.4f} at {_q(a.q)}", f"{b.worst_error_pct:.3f} at {_q(b.q)}"]
            out.append("| " + " | ".join(cells) + " |")
            print(out[-1], flush=True)
    return out


def _bias(tr) -> str:
    """The filter requirement's figure: the worst quantity's ``b`` and its name, '(above)' where not met."""
    if not tr or not tr.get("bias"):
        return "-"
    k = max(tr["bias"], key=tr["bias"].get)
    nu = f"; innovations {tr['innovation']:.3g}" if tr.get("innovation") is not None else ""
    return f"{tr['bias'][k]:.3g} ({k}){nu}" + ("" if tr["bias_met"] else " (above)")


def _dynamic(tr) -> str:
    """The default count's dynamic modes alone, before the static corrections: their count, ``rho`` and the filter
    requirement's worst figure (``truncation['dynamic']``)."""
    d = (tr or {}).get("dynamic")
    if not d:
        return "-"
    b = d.get("bias") or {}
    k = max(b, key=b.get) if b else None
    nu = f", innovations {d['innovation']:.3g}" if d.get("innovation") is not None else ""
    return f"{d['n_interior']}: {d['rho']:.3g}" + (f", {b[k]:.3g} ({k}){nu}" if k else "")


def _rho_parts(cb) -> str:
    """Where the final basis misses ``rho``: its parts at the worst sample, each the windowed whitened mean square
    summed over the channels alone (they add as signals, not as squares): the quasi-static part the basis leaves,
    the full modes' ringing it does not follow, and its own modes' ringing no full mode matches."""
    from exuflex.reduction import PathSamples
    from exuflex.reduction.truncation import PlannedInput, WINDOW_SAMPLES, window_mean_square

    planned = PlannedInput.of(cb.model.mech)
    n, kept = cb.n_interior, list(cb.kept)
    cb.set_interior(len(cb.order))
    try:
        ps = PathSamples(cb, cb.path_q, planned, bias_max=0)
    finally:
        cb.set_interior(n)
    c = int(np.argmax(ps.rho(kept)))
    t = ps.truncation[c]
    unf, spurious, _ = ps._ringing(c, kept)
    W, f = t._weights(kept, unf)
    n_i, n_m = t.Y.shape[1], t.G.shape[1]
    part = lambda e: float(window_mean_square(e, WINDOW_SAMPLES).sum(axis=1).max())
    return (f"quasi-static {part(t.S[:, :n_i] @ (t.Y @ W).T):.2g}, full modes' ringing "
            f"{part(t.S[:, n_i:n_i + n_m] @ (t.G * f).T):.2g}, its own unmatched ringing {part(spurious):.2g}")


def bench_rows(paths: list[Path]) -> list[str]:
    """The default reduction of each model file: the count (dynamic modes and static corrections), the final basis'
    ``rho`` and filter figure, met or not, and its dynamic modes' figures alone."""
    out = []
    for path in paths:
        mech = load_mechanism(path)
        if mech.manoeuvre is None:
            continue
        cb = CraigBampton(ErlsModel(mech))
        tr = cb.truncation
        if not tr:
            out.append(f"| {mech.name} | {cb.n_interior} | - | - | - | - |")
            continue
        parts = f" ({_rho_parts(cb)})" if tr["rho"] > tr["rho_max"] else ""
        out.append(f"| {mech.name} | {cb.n_interior - cb.n_static} + {cb.n_static} | {tr['rho']:.3g}"
                   f"{'' if tr['rho'] <= tr['rho_max'] else ' (above)'}{parts} | {_bias(tr)} | "
                   f"{'yes' if tr['met'] else 'no'} | {_dynamic(tr)} |")
        print(out[-1], flush=True)
    return out


def criterion_rows(path: Path) -> list[str]:
    """The file's masters (or the automatic ones), interior modes chosen over the manoeuvre: the count the band's
    thresholds alone need, the count with the channels' truncation requirement, and the default (the filter
    requirement too), each scored by ``rho``, the filter requirement's worst figure and the estimated tip
    quantities' truncated part."""
    mech = load_mechanism(path)
    if mech.manoeuvre is None:
        return []
    model = ErlsModel(mech)
    out = []
    for label, kw in (("band alone", {"truncation_max": 0, "n_interior": "auto"}),
                      ("band, channels", {"bias_max": 0, "n_interior": "auto"}), ("default", {})):
        cb = CraigBampton(model, **kw)
        if kw:  # scored by the default requirements with the same modes
            cb.truncation_max, cb.bias_max, cb._truncation = TRUNCATION_MAX, BIAS_MAX, False
        tr = cb.truncation
        dyn = [i for i in cb.kept if cb.static is None or i not in set(cb.static.rest[: cb.n_static].tolist())]
        kept = ", ".join(f"{f:.0f}" for f in cb.interior_frequencies_hz[dyn]) or "-"
        qu = "-" if not tr or not tr["quantities_rms"] else ", ".join(f"{k} {v:.2g}" for k, v in tr["quantities_rms"].items())
        ch = "-" if not tr else ", ".join(f"{k} {v:.2g}" for k, v in tr["rho_channels"].items() if v >= 5e-4)
        count = f"{len(dyn)}" + (f" (+{cb.n_static} static)" if cb.n_static else "")
        out.append(f"| {mech.name} | {label} | {count} | {kept} | "
                   + ("-" if tr is None else f"{tr['rho']:.3g}" + ("" if tr["rho"] <= tr["rho_max"] else " (above)"))
                   + f" | {ch or '-'} | {_bias(tr)} | {_dynamic(tr)} | {qu} |")
        print(out[-1], flush=True)
    return out


def static_rows(path: Path) -> list[str]:
    """The default basis's static corrections (:mod:`exuflex.reduction.static`) at the model's payload scales
    (:data:`STATIC_SCALES`, else the file's): the count, the largest missed reading without and with them, where,
    the load amplitudes, what they were taken from, their Ritz frequencies at q*."""
    nominal = load_mechanism(path)
    out = []
    for scale in STATIC_SCALES.get(nominal.name, (1.0,)):
        mech = nominal.with_payload_scale(scale) if scale != 1.0 else nominal
        cb = CraigBampton(ErlsModel(mech), static_max=STATIC_MAX)
        st = cb.static
        if st is None:
            out.append(f"| {mech.name} | {scale:g} | {cb.n_interior} | 0 | - | - | - | - | - | - |")
            continue
        row, c = st.worst[st.n]
        a_, v_ = st.amplitudes
        ritz = ", ".join(f"{f:.0f}" for f in cb.interior_frequencies_hz[st.rest[: st.n]]) or "-"
        picked = "; ".join(w for _, w in st.picked) or "-"
        out.append(f"| {mech.name} | {scale:g} | {cb.n_interior - st.n} | {st.n} | {st.figure[0]:.3g} | "
                   f"{st.figure[st.n]:.3g} ({row} at {_q(cb.path_q[c])}) | {', '.join(f'{x:.3g}' for x in a_)} | "
                   f"{', '.join(f'{x:.3g}' for x in v_)} | {picked} | {ritz} |")
        print(out[-1], flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default=None, help="comma-separated model names (default: every models/*.toml)")
    ap.add_argument("--along", type=int, default=41, help="configurations of the manoeuvre checked (default 41)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "reduction.md"))
    a = ap.parse_args(argv)
    names = a.models.split(",") if a.models else sorted(p.stem for p in (ROOT / "models").glob("*.toml"))
    lines = [
        "# Reduced models of the mechanism gallery",
        "",
        "Written by `python benchmarks/reduction_gallery.py` (the command regenerates this page). Each model with",
        "its file's masters and with the automatic ones (transverse dofs at the joints and tips,",
        "`exuflex/reduction/masters.py`); interior modes chosen at q* only (`CraigBampton(..., path=False)`) and",
        "over q* and 16 configurations of the manoeuvre (the default, `exuflex/reduction/path.py`), count from the",
        "model file or automatic. NCO (worst, eq. 16) and frequency error (worst, %, eq. 17) of the full modes below",
        f"the band limit at q* and over {a.along} configurations of the manoeuvre, equally spaced in time (not those",
        "the modes were chosen on). Thresholds: the model file's (default NCO >= 0.99, error <= 2 %). The automatic",
        "count also meets the truncation and filter requirements (below): the column 'truncation rho' gives the",
        "channels' figure with the modes kept (limit 0.1; '(above)' where the count does not meet both).",
        "",
        "## Interior modes by what the filter needs",
        "",
        "The automatic count keeps the interior modes the band's accuracy thresholds need *and* those the observer",
        "needs: what the reduced model leaves out of the manoeuvre's own motion must stay small against the",
        "channels' noise, and the steady filter's error it makes must stay small against the bound. The derivation",
        "(the docstring of `exuflex/reduction/truncation.py`):",
        "",
        *_derivation(),
        "",
        "### The gallery: the band's count against the default",
        "",
        "Masters from the file, else automatic; interior modes over the manoeuvre. 'band alone': the fewest interior",
        "modes meeting the band's thresholds; 'band, channels': with the channels' truncation requirement too (the",
        "filter requirement off, `bias_max=0`); 'default': the automatic count, the filter requirement too; each",
        "scored by the default requirements on its final basis (its static corrections in, the basis the observer",
        "uses); for the default, its dynamic modes' figures alone beside them. rho: the whitened mean square of the truncated output summed over the",
        "channels in the worst 100-sample window (limit 0.1), its largest shares per channel; filter b: the filter",
        f"requirement's largest figure (limit {BIAS_MAX:g}) and its quantity, and its innovations' figure (the",
        f"steady filter's whitened innovations' mean square summed over the channels, limit {INNOVATION_MAX:g}); the estimated quantities'",
        "truncated part (q, q' and the tip's; RMS in the worst window, rad, m and their rates). The paper's six-bar",
        "keeps the paper's five modes: its rows are that count. Besides the gallery, the mechanisms written fresh for",
        "the criterion: " + ", ".join(f"`{f}`" for f in FRESH) + ". The observer on noiseless logs with the two",
        "choices where they differ: `docs/filter_requirement.md`.",
        "",
        "| model | count | interior | kept (Hz at q*) | rho | channels | filter b | dynamic modes alone: count: rho, b | estimated quantities |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name in names + ([] if a.models else FRESH):
        lines += criterion_rows(ROOT / name if name.endswith(".toml") else ROOT / "models" / f"{name}.toml")
    if not a.models:
        lines += [
            "",
            "### Every mechanism in benchmarks/models with default settings",
            "",
            "The default reduction of each file in `benchmarks/models/` with a manoeuvre (written for other checks, not",
            "tuned for this one): the count (dynamic modes + static corrections), the final basis' rho (limit",
            f"{TRUNCATION_MAX:g}) and filter figures (b limit {BIAS_MAX:g}, innovations limit {INNOVATION_MAX:g}), whether all are met, and the dynamic modes'",
            "figures alone. Where rho is above its limit, its parts at the worst sample: the quasi-static part the",
            "basis leaves, the full modes' ringing it does not follow and its own modes' ringing that no full mode",
            "matches (the static corrections' Ritz vectors ring at frequencies of their own: `.truncation`).",
            "",
            "| model | interior + static | rho | filter b | met | dynamic modes alone: count: rho, b |",
            "|---|---|---|---|---|---|",
            *bench_rows(sorted((ROOT / "benchmarks" / "models").glob("*.toml"))),
        ]
    lines += [
        "",
        "## Static corrections: the quasi-static response to the loads the inputs can produce",
        "",
        "The interior modes above keep the dynamics; what a load concentrated between the masters bends",
        "quasi-statically in the modes not kept is added as static corrections, counted by the largest reading they",
        "leave (the docstring of `exuflex/reduction/static.py`):",
        "",
        *_derivation(static),
        "",
        "### The gallery",
        "",
        "Default basis with the static corrections (`static_max` " + f"{STATIC_MAX:.3g}" + "): interior modes kept",
        "for the dynamics, corrections kept, the largest quasi-static reading missed (noise sd) without and with them",
        "and where, the largest acceleration and rate the loads are scaled by (rad/s^2, rad/s), what each",
        "correction was taken from, its Ritz frequency at q*. Payload scales: the model file's payload mass times",
        "the scale. The paper's six-bar keeps the paper's fixed count: no corrections. Besides the gallery, the",
        "mechanism written fresh for them: " + ", ".join(f"`{f}`" for f in FRESH_STATIC) + ".",
        "",
        ("| model | payload scale | interior (dynamics) | corrections | missed without | with them (where) | a | v | "
         "taken from | Ritz (Hz) |"),
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in names + ([] if a.models else FRESH_STATIC):
        path = ROOT / name if name.endswith(".toml") else ROOT / "models" / f"{name}.toml"
        if load_mechanism(path).manoeuvre is not None:
            lines += static_rows(path)
    lines += [
        "",
        "## Accuracy of the reduced models",
        "",
        ("| model | masters | interior modes chosen | dofs | interior | truncation rho | NCO at q* | "
         "error % at q* | worst NCO along | worst error % along |"),
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in names:
        lines += rows_for(Path(name) if name.endswith(".toml") else ROOT / "models" / f"{name}.toml", a.along)
    Path(a.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Three-way modes: the ERLS model, the Exudyn ANCF truth and the FFRF truth (solid meshes) on every gallery
mechanism, the FFRF modes under mesh refinement, and the FFRF truth's modal damping.

    python benchmarks/ffrf_modes.py [--models sixbar,fourbar,...] [--scales 2,1.4,1,0.7] [--out docs/ffrf_modes.md]

Per model at ``q_ref`` with the motors free, every in-plane mode below the model's band (``reduction.band_hz``):
the ERLS model on the file's mesh and refined 4x (elements split in four: converged), the ANCF truth on its
default mesh (:func:`exuflex.truth.exudyn_mesh`) and the FFRF truth (:func:`exuflex.groundtruth.ffrf_frequencies`,
default mesh sizes). Each FFRF mode is paired with the nearest ERLS mode (file mesh and refined); a mode one of the
models has and the other misses is listed as such. The convergence table runs the FFRF truth with every link's mesh
size scaled by ``--scales`` on the six-bar and the four-bar. The damping table compares the FFRF truth's damping
ratios (linearised, damped) with the model file's Rayleigh ratio ``alpha / (2 w) + beta w / 2``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from _pages import publish  # (a script: its folder is on the path)

ROOT = Path(__file__).resolve().parents[1]
GALLERY = ("sixbar", "fourbar", "single_link", "serial_arm", "fivebar", "slider_crank")
CONVERGENCE = ("sixbar", "fourbar")


def _pair(f_ref: np.ndarray, f: np.ndarray, tol: float = 0.05):
    """One-to-one pairing: for each reference mode, a mode of ``f`` within ``tol`` (relative) or None, the closest
    pairs taken first (a mode pairs once)."""
    cand = sorted((abs(fj - fr) / fr, i, j) for i, fr in enumerate(f_ref) for j, fj in enumerate(f)
                  if abs(fj - fr) <= tol * fr)
    out: list[float | None] = [None] * len(f_ref)
    used: set[int] = set()
    for _, i, j in cand:
        if out[i] is None and j not in used:
            out[i] = float(f[j])
            used.add(j)
    return out


def model_modes(name: str, say) -> dict:
    from exuflex.erls.modal import modal_analysis
    from exuflex.erls.model import ErlsModel
    from exuflex.groundtruth import exudyn_frequencies, ffrf_frequencies
    from exuflex.mechanism import load_mechanism, refine_mechanism
    from exuflex.truth import exudyn_mesh

    mech = load_mechanism(ROOT / "models" / f"{name}.toml")
    band = mech.reduction.band_hz
    q = np.asarray(mech.q_ref, float)
    erls = modal_analysis(ErlsModel(mech), q).below(band)
    erls4 = modal_analysis(ErlsModel(refine_mechanism(mech, 4)), q).below(band)
    f_ancf = np.asarray(exudyn_frequencies(mech, q, elements_per_link=exudyn_mesh(mech)))
    t0 = time.perf_counter()
    r = ffrf_frequencies(mech, q, progress=say, with_damping=True)
    ffrf_s = time.perf_counter() - t0
    keep = r["frequencies_hz"] <= 1.05 * band
    f_ffrf, zeta = r["frequencies_hz"][keep], r["damping_ratio"][keep]
    w = 2 * np.pi * f_ffrf
    stated = mech.damping.alpha / (2 * w) + mech.damping.beta * w / 2
    return {"model": name, "band_hz": band, "erls": erls.tolist(), "erls4": erls4.tolist(),
            "ancf": f_ancf[f_ancf <= 1.05 * band].tolist(), "ffrf": f_ffrf.tolist(), "zeta": zeta.tolist(),
            "zeta_stated": stated.tolist(), "out_of_plane": r["out_of_plane_hz"][r["out_of_plane_hz"] <= band].tolist(),
            "links": r["settings"]["links"], "ffrf_s": ffrf_s, "cached": r["cached"]}


def damping(name: str, f_ffrf, say) -> dict:
    """The FFRF truth's damping ratios (default meshes) of the modes ``f_ffrf`` (nearest in frequency) and the
    stated ones."""
    from exuflex.groundtruth import ffrf_frequencies
    from exuflex.mechanism import load_mechanism

    mech = load_mechanism(ROOT / "models" / f"{name}.toml")
    r = ffrf_frequencies(mech, progress=say, with_damping=True)
    f = np.asarray(f_ffrf, float)
    zeta = [float(r["damping_ratio"][np.argmin(np.abs(r["frequencies_hz"] - fi))]) for fi in f]
    w = 2 * np.pi * f
    return {"zeta": zeta, "zeta_stated": (mech.damping.alpha / (2 * w) + mech.damping.beta * w / 2).tolist()}


def convergence(name: str, scales: list[float], say) -> dict:
    from exuflex.groundtruth import ffrf_frequencies
    from exuflex.mechanism import load_mechanism

    mech = load_mechanism(ROOT / "models" / f"{name}.toml")
    band = mech.reduction.band_hz
    rows = []
    for s in scales:
        r = ffrf_frequencies(mech, mesh_scale=s, progress=say)
        f = r["frequencies_hz"]
        rows.append({"scale": s, "nodes": sum(v["nodes"] for v in r["settings"]["links"].values()),
                     "f": f[f <= 1.05 * band].tolist()})
    return {"model": name, "rows": rows}


def _pct(a, b):
    return "-" if a is None or b is None else f"{100 * (a - b) / b:+.2f}"


def markdown(res: list[dict], conv: list[dict], cmd: str, damping_cmd: str | None = None) -> str:
    lines = [
        "# Three-way modes: ERLS, ANCF and FFRF (solid meshes)",
        "",
        f"Generated by `{cmd}` (do not edit: rerun the script). In-plane modes at `q_ref`, motors free, below each "
        "model's band. ERLS: the model file's mesh and refined 4x; ANCF: the Exudyn beam truth on its default mesh; "
        "FFRF: Exudyn `ObjectFFRFreducedOrder` bodies from netgen meshes of the links' solid sections (quadratic "
        "tetrahedra, Hurty-Craig-Bampton modes with rigid interfaces at the joints and masses, `exuflex.groundtruth."
        "ffrf`). Differences are FFRF against each column, in percent; a dash: no mode within 5 % there.",
        "",
    ]
    worst_file = worst_ref = 0.0
    for r in res:
        lines += [f"## {r['model']} (band {r['band_hz']:g} Hz)", "",
                  "| mode | FFRF (Hz) | ERLS file (Hz) | diff % | ERLS 4x (Hz) | diff % | ANCF (Hz) | diff % |",
                  "|---|---|---|---|---|---|---|---|"]
        pf = _pair(np.array(r["ffrf"]), np.array(r["erls"]))
        p4 = _pair(np.array(r["ffrf"]), np.array(r["erls4"]))
        pa = _pair(np.array(r["ffrf"]), np.array(r["ancf"]))
        for i, f in enumerate(r["ffrf"]):
            if f > r["band_hz"]:
                continue
            for p, which in ((pf[i], "file"), (p4[i], "ref")):
                if p is not None:
                    d = abs(f - p) / p
                    if which == "file":
                        worst_file = max(worst_file, d)
                    else:
                        worst_ref = max(worst_ref, d)
            cells = [f"{f:.2f}"]
            for p in (pf[i], p4[i], pa[i]):
                cells += ["-" if p is None else f"{p:.2f}", _pct(f, p)]
            lines.append(f"| {i + 1} | " + " | ".join(cells) + " |")
        back = _pair(np.array(r["erls"]), np.array(r["ffrf"]))
        missing = [f for f, p in zip(r["erls"], back) if p is None]
        if missing:
            lines.append(f"\nERLS (file mesh) modes without an FFRF mode within 5 %: {missing}.")
        links = "; ".join(f"{k}: {v['nodes']} nodes, {v['modes']} modes, mesh {1e3 * v['mesh_size_m']:.3g} mm"
                          for k, v in r["links"].items())
        lines += ["", f"Solid links: {links}. Out-of-plane modes below the band (not excited by in-plane loads; "
                  f"the joints hold the links in the plane only through the frames): "
                  f"{', '.join(f'{f:.1f}' for f in r['out_of_plane']) or 'none'} Hz.", ""]
    lines += [f"Largest |FFRF - ERLS| below the band over the gallery: {100 * worst_file:.2f} % against the file's "
              f"mesh, {100 * worst_ref:.2f} % against the ERLS refined 4x.", ""]
    lines += ["## Mesh convergence of the FFRF modes", "",
              "Every link's mesh size scaled (1 = the default: the section's height, `exuflex.groundtruth.solid."
              "default_mesh_size`; a model file's `mesh_size` sets it per link). netgen also grades the mesh by the "
              "surface's curvature (edges of about a quarter of a round section's diameter), so on round links a "
              "scale above about 0.25 leaves the mesh as it is; below, the largest edge refines it. Change: against "
              "the finest mesh.", ""]
    for c in conv:
        rows = c["rows"]
        n = min(len(r["f"]) for r in rows)
        fine = np.array(rows[-1]["f"][:n])
        lines += [f"### {c['model']}", "", "| mesh scale | nodes | " + " | ".join(f"mode {i + 1}" for i in range(n))
                  + " | largest change % |", "|---|---|" + "---|" * (n + 1)]
        for r in rows:
            f = np.array(r["f"][:n])
            lines.append(f"| {r['scale']:g} | {r['nodes']} | " + " | ".join(f"{v:.2f}" for v in f)
                         + f" | {100 * np.max(np.abs(f - fine) / fine):.3f} |")
        lines.append("")
    lines += ["## Damping", "",
              "The FFRF truth's damping as the model file states it (each free elastic mode `alpha / (2 w) + beta w / "
              "2`): `beta K_ff` on each body's modal coordinates and `alpha` times the mass matrix with the "
              "mechanism's rigid motions projected out, at system level (`exuflex.groundtruth.ffrf`'s module "
              "docstring). Ratios from Exudyn's linearised damped system (`ComputeLinearizedSystem`), as `exuflex "
              "modes MODEL --exudyn --beam ffrf --json` reports them"
              + (f"; refreshed by `{damping_cmd}`" if damping_cmd else "") + ".", "",
              "| model | mode (Hz) | FFRF ratio % | stated % | ratio / stated |", "|---|---|---|---|---|"]
    for r in res:
        for f, z, zs in zip(r["ffrf"], r["zeta"], r["zeta_stated"]):
            if f <= r["band_hz"]:
                lines.append(f"| {r['model']} | {f:.2f} | {100 * z:.3f} | {100 * zs:.3f} | {z / zs:.4f} |")
    lines.append("")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default=",".join(GALLERY))
    ap.add_argument("--scales", default="2,1.4,1,0.7", help="FFRF mesh-size scales for the convergence table")
    ap.add_argument("--out", default=str(ROOT / "docs" / "ffrf_modes.md"))
    ap.add_argument("--from-json", default=None, help="re-render the page from a JSON this script wrote")
    ap.add_argument("--refresh-damping", action="store_true",
                    help="with --from-json: recompute the FFRF damping ratios (default meshes, cached) and keep the rest")
    a = ap.parse_args(argv)

    def say(msg):
        print(msg, file=sys.stderr, flush=True)

    models = a.models.split(",")
    scales = sorted((float(s) for s in a.scales.split(",")), reverse=True)
    args = []
    if models != list(GALLERY):
        args.append(f"--models {a.models}")
    if a.scales != "2,1.4,1,0.7":
        args.append(f"--scales {a.scales}")
    cmd = " ".join(["python benchmarks/ffrf_modes.py", *args])
    if a.from_json:  # re-render a page from its numbers
        data = json.loads(Path(a.from_json).read_text())
        if a.refresh_damping:
            for r in data["modes"]:
                r.update(damping(r["model"], r["ffrf"], say))
            data["damping_command"] = f"python benchmarks/ffrf_modes.py --from-json {a.from_json} --refresh-damping"
            Path(a.from_json).write_text(json.dumps(data, indent=1))
        publish(markdown(data["modes"], data["convergence"], data.get("command", cmd), data.get("damping_command")),
                a.out)
        return 0
    res = [model_modes(m, say) for m in models]
    conv: list[dict] = []
    # the page after the gallery and after each convergence model: the finest meshes take longest
    for m in (None, *[m for m in CONVERGENCE if m in models]):
        if m is not None:
            conv.append(convergence(m, scales, say))
        if a.out:
            Path(a.out).with_suffix(".json").write_text(json.dumps({"command": cmd, "modes": res, "convergence": conv},
                                                                   indent=1))
        publish(markdown(res, conv, cmd), a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

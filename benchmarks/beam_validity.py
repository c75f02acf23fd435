"""Where beam theory stops: one link's slenderness L/d from 50 down to 3 (and a thin-walled tube), the beam models'
first mode and tip response against the FFRF truth (3D elasticity of the solid link).

    python benchmarks/beam_validity.py [--ratios 50,30,20,15,10,7,5,4,3] [--tube-ratios 50,20,10,5]
                                       [--response 50,10,5,3] [--out docs/beam_validity.md]

The mechanism is ``models/single_link.toml`` (a 1 m aluminium link on a hub with inertia, motor free, tip payload)
with the link's diameter set to L / ratio (a tube: outer diameter L / ratio, bore 0.9 of it). Frequencies: the first
two in-plane modes of the ERLS model and of the ANCF truth on 16 elements (converged beam theory), and of the FFRF
truth at the default mesh (and, for L/d <= 10, at 0.6 of it: the reference there). The L/d where the ERLS first mode departs
1 % and 5 % from the FFRF truth is interpolated (log L/d). Tip response (``--response`` ratios): 0.3 s under a
smooth torque pulse scaled with the link's inertia about the hub, h = 0.1 ms; the tip's deflection from the hub's
tangent (``p_tip - p_hub(angle)``, m) by the ANCF and the FFRF truth, their RMS difference relative to the FFRF
deflection's RMS.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tomllib
from pathlib import Path

import numpy as np
from _pages import COMMIT, publish  # (a script: its folder is on the path)

ROOT = Path(__file__).resolve().parents[1]
BEAM_ELEMENTS = 16
F2_MAX = 720.0  # the FFRF bases keep fixed-interface modes up to 4 x 180 Hz: a second mode above is not resolved
FINE, FINE_BELOW = 0.6, 10.0  # stubby links (L/d <= 10) also at 0.6 of the default mesh size: the reference there


def _mech(ratio: float, tube: bool):
    from exuflex.mechanism import parse_mechanism

    doc = tomllib.loads((ROOT / "models" / "single_link.toml").read_text())
    lk = doc["links"][0]
    d = lk["length"] / ratio
    lk["diameter"] = d
    if tube:
        lk["inner_diameter"] = 0.9 * d
    lk["n_elements"] = BEAM_ELEMENTS
    doc.pop("reduction", None)
    return parse_mechanism(doc, f"single_link, L/d = {ratio:g}{' tube' if tube else ''}")


def modes(ratio: float, tube: bool, say) -> dict:
    from exuflex.erls.modal import modal_analysis
    from exuflex.erls.model import ErlsModel
    from exuflex.groundtruth import exudyn_frequencies, ffrf_frequencies

    mech = _mech(ratio, tube)
    q = np.asarray(mech.q_ref, float)
    erls = np.asarray(modal_analysis(ErlsModel(mech), q).below(1e9))[:2]
    ancf = np.asarray(exudyn_frequencies(mech, q, elements_per_link=BEAM_ELEMENTS))[:2]
    scales = (1.0, FINE) if ratio <= FINE_BELOW else (1.0,)
    ff = {s: np.asarray(ffrf_frequencies(mech, q, mesh_scale=s, progress=say)["frequencies_hz"])[:2] for s in scales}
    return {"ratio": ratio, "tube": tube, "erls": erls.tolist(), "ancf": ancf.tolist(),
            "ffrf": ff[scales[-1]].tolist(), "ffrf_coarse": ff[1.0].tolist() if len(scales) > 1 else None}


def response(ratio: float, tube: bool, say) -> dict:
    from exuflex.groundtruth import simulate_ffrf, simulate_truth, smooth_torque_table
    from exuflex.probes import Probe

    mech = _mech(ratio, tube)
    lk = mech.links[0]
    J = lk.mass * lk.length**2 / 3 + sum(m.inertia + m.mass * mech.node_location(m.node)[1] ** 2
                                         for m in mech.all_masses())
    T = 20.0 * J  # a rigid angular acceleration of 20 rad/s^2 at the pulse's peak
    t, tau = smooth_torque_table(mech, 0.3, [T], period=0.1, dt=1e-4)
    probes = (Probe("slope", lk.name, 0.0), Probe("point", lk.name, lk.length))
    recs = {"ancf": simulate_truth(mech, t, tau, 0.3, h=1e-4, output_dt=1e-3, probes=probes,
                                   elements_per_link=BEAM_ELEMENTS),
            "ffrf": simulate_ffrf(mech, t, tau, 0.3, h=1e-4, output_dt=1e-3, probes=probes, messages=say)}
    defl = {}
    for k, r in recs.items():
        a = r.values[probes[0].key][:, 0]
        p = r.values[probes[1].key]
        defl[k] = -np.sin(a) * p[:, 0] + np.cos(a) * p[:, 1]  # the tip normal to the hub's tangent (hub at 0)
    d = defl["ancf"] - defl["ffrf"]
    rms = float(np.sqrt(np.mean(defl["ffrf"] ** 2)))
    return {"ratio": ratio, "tube": tube, "torque_Nm": T, "rms_ffrf_m": rms,
            "rms_diff_m": float(np.sqrt(np.mean(d**2))), "rel": float(np.sqrt(np.mean(d**2))) / rms}


def _crossing(ratios, err, level):
    """The L/d (log-interpolated) where the error first rises through ``level`` going from slender to stubby."""
    order = np.argsort(ratios)[::-1]
    r, e = np.asarray(ratios)[order], np.asarray(err)[order]
    for i in range(1, len(r)):
        if e[i - 1] < level <= e[i]:
            x0, x1 = math.log(r[i - 1]), math.log(r[i])
            return math.exp(x0 + (level - e[i - 1]) * (x1 - x0) / (e[i] - e[i - 1]))
    return None


def markdown(rows: list[dict], resp: list[dict], cmd: str, modes_of: dict | None = None) -> str:
    lines = [
        "# Where beam theory stops: the slenderness sweep against the FFRF truth",
        "",
        (f"Generated by `{cmd}` (do not edit: rerun the script). `models/single_link.toml` with the link's diameter "
        "set to L / (L/d) (tube: bore 0.9 of the outer diameter); motor free. ERLS and ANCF on "
        f"{BEAM_ELEMENTS} elements (converged Euler-Bernoulli beams); FFRF: solid link, quadratic tetrahedra at the "
        f"default mesh size (the section's diameter; `ffrf_modes.md` shows it converged on slender links) and, for "
        f"L/d <= {FINE_BELOW:g}, at {FINE:g} of it (then the reference; the last column: the default mesh's change "
        "against it). Errors: beam model minus FFRF, relative."),
        "",
    ]
    if modes_of:
        lines += [f"The mode tables are those of `{modes_of['command']}`"
                  + (f" (code {modes_of['commit']})" if modes_of.get("commit") else "")
                  + "; this run measured the tip response alone.", ""]
    for tube in (False, True):
        sel = [r for r in rows if r["tube"] == tube]
        if not sel:
            continue
        lines += [f"## {'Thin-walled tube (bore 0.9 d)' if tube else 'Solid round link'}", "",
                  ("| L/d | FFRF f1 (Hz) | ERLS f1 err % | ANCF f1 err % | FFRF f2 (Hz) | ERLS f2 err % | "
                  "FFRF f1 at the default mesh, change % |"), "|---|---|---|---|---|---|---|"]
        e1 = []
        for r in sel:
            f, fe, fa, fc = r["ffrf"], r["erls"], r["ancf"], r["ffrf_coarse"]
            e1.append(abs(fe[0] - f[0]) / f[0])
            change = "-" if fc is None else f"{100 * (fc[0] - f[0]) / f[0]:+.3f}"
            f2 = (f"{f[1]:.1f} | {100 * (fe[1] - f[1]) / f[1]:+.2f}" if f[1] <= F2_MAX
                  else f"({f[1]:.0f}) | -")
            lines.append(f"| {r['ratio']:g} | {f[0]:.2f} | {100 * (fe[0] - f[0]) / f[0]:+.2f} | "
                         f"{100 * (fa[0] - f[0]) / f[0]:+.2f} | {f2} | {change} |")
        lines.append(f"\nA second mode above {F2_MAX:g} Hz (in parentheses) lies beyond the FFRF bases' fixed-interface "
                     "modes (kept up to 4x the 180 Hz band; for stubby links it is the axial mode, which the static "
                     "modes alone place about 10 % high): not compared.")
        c1 = _crossing([r["ratio"] for r in sel], e1, 0.01)
        c5 = _crossing([r["ratio"] for r in sel], e1, 0.05)
        lines += ["", (f"The ERLS first mode departs from the FFRF truth by 1 % at L/d = "
                  f"{f'{c1:.1f}' if c1 else 'none in the sweep'} and by 5 % at L/d = "
                  f"{f'{c5:.1f}' if c5 else 'none in the sweep'}."), ""]
    if resp:
        lines += ["## Tip response", "",
                  ("0.3 s under a smooth torque pulse (amplitude 20 rad/s^2 times the link's inertia about the hub, "
                  "period 0.1 s), h = 0.1 ms: the tip's deflection normal to the hub's tangent by the ANCF and the "
                  "FFRF truth."), "",
                  ("Both truths at the same fixed step (not the truth step rule: the comparison is of the two "
                  "models, not of either against the observer's bound), each with the model file's damping (the "
                  "FFRF truth's modal ratios against the stated ones: {doc}`/ffrf_modes`)."),
                  "",
                  "| L/d | section | FFRF deflection RMS (m) | ANCF - FFRF RMS (m) | relative % |",
                  "|---|---|---|---|---|"]
        for r in resp:
            lines.append(f"| {r['ratio']:g} | {'tube' if r['tube'] else 'round'} | {r['rms_ffrf_m']:.3g} | "
                         f"{r['rms_diff_m']:.3g} | {100 * r['rel']:.2f} |")
        by = sorted(resp, key=lambda r: -r["ratio"])  # slender to stubby
        if len(by) > 1:
            rising = all(a["rel"] <= b["rel"] for a, b in zip(by, by[1:]))
            lines += ["", (f"The ANCF beam's tip deflection is within {100 * by[0]['rel']:.2f} % of the solid's at L/d = "
                      f"{by[0]['ratio']:g} and {100 * by[-1]['rel']:.2f} % at L/d = {by[-1]['ratio']:g}"
                      + (", rising as the link shortens: with both truths damped as stated, the difference left is "
                         "beam theory's own (shear and the section's rotary inertia)." if rising else
                         "; the difference does not rise steadily with stubbiness (the table)."))]
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ratios", default="50,30,20,15,10,7,5,4,3")
    ap.add_argument("--tube-ratios", default="50,20,10,5")
    ap.add_argument("--response", default="50,10,5,3", help="L/d of the solid link for the tip response ('' none)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "beam_validity.md"))
    ap.add_argument("--from-json", default=None, help="re-render the page from a JSON this script wrote")
    ap.add_argument("--modes-from", default=None, help="keep the mode tables of a JSON this script wrote (its run's "
                    "command and commit named on the page) and measure only the tip response")
    a = ap.parse_args(argv)

    def say(msg):
        print(msg, file=sys.stderr, flush=True)

    def floats(s):
        return [float(v) for v in s.split(",") if v.strip()]

    if a.from_json:  # re-render a page from its numbers
        data = json.loads(Path(a.from_json).read_text())
        publish(markdown(data["modes"], data.get("response", []), data.get("command", "python "
                                                                          "benchmarks/beam_validity.py"),
                         data.get("modes_of")), a.out)
        return 0
    args = [f"--{k.replace('_', '-')} {v}" for k, v, d in (("ratios", a.ratios, "50,30,20,15,10,7,5,4,3"),
                                                          ("tube_ratios", a.tube_ratios, "50,20,10,5"),
                                                          ("response", a.response, "50,10,5,3")) if v != d]
    modes_of = None
    if a.modes_from:  # the mode tables of an earlier run, kept as they were measured
        kept = json.loads(Path(a.modes_from).read_text())
        rows = kept["modes"]
        modes_of = kept.get("modes_of") or {"command": kept.get("command", "python benchmarks/beam_validity.py"),
                                            "commit": kept.get("commit")}
        args.append(f"--modes-from {a.modes_from}")
    else:
        rows = [modes(r, False, say) for r in floats(a.ratios)] + [modes(r, True, say)
                                                                    for r in floats(a.tube_ratios)]
    cmd = " ".join(["python benchmarks/beam_validity.py", *args])
    record = {"command": cmd, "commit": COMMIT, "modes_of": modes_of, "modes": rows}
    if a.out:
        Path(a.out).with_suffix(".json").write_text(json.dumps(record, indent=1))
    resp = [response(r, False, say) for r in floats(a.response)]
    record["response"] = resp
    if a.out:
        Path(a.out).with_suffix(".json").write_text(json.dumps(record, indent=1))
    publish(markdown(rows, resp, cmd, modes_of), a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

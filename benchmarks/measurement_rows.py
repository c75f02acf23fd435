"""The measurement rows about a held configuration: their error against the re-evaluated rows, first order and
with their exact first-order change with q.

    python benchmarks/measurement_rows.py [--models a,b,...] [--extra benchmarks/models/three_link_reach.toml]
                                          [--directions 6] [--run MODEL_FILE=RUN_DIR ...] [--md docs/measurement_rows.md]

``--run``: a run folder, e.g. one ``benchmarks/gallery.py --acceptance --truth-dir DIR`` keeps
(``DIR/<engine>/<model>/s<seed>``).

For each model (default: the gallery, ``models/*.toml`` with a manoeuvre, and the fresh mechanism
``benchmarks/models/three_link_reach.toml``) the observer's model with default settings holds the undeformed
configuration at ``q*`` (the reduction's reference). At ``q = q* + dl`` for ``|dl|`` = 0.01, 0.02, 0.04 rad (the
measurement radius reaches 0.06 rad) in several random directions it compares, with the rows of ``q``'s own
configuration evaluated anew:

- the elastic rows ``E_i = U_i H_u`` of every channel the observer uses, relative to their size at ``q*``
  (``|E_i(q) - approx| / |E_i(q*)|``, largest over channels and directions): the rows at ``q*`` alone (what the
  rows were before the expansion, off the secant's line) and with ``sum_k dl_k D_k``;
- the rigid part of an undeformed state, in units of the channel's noise: the first-order rows and with the
  second-order term.

And the cost: the expansion's terms (``D_k``, ``G``) against the held configuration's evaluation, CPU time per
configuration, medians of repeats in one process.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXTRA = ROOT / "benchmarks" / "models" / "three_link_reach.toml"
STEPS = (0.01, 0.02, 0.04)

HEAD = """# The measurement rows about a held configuration

Written by `python benchmarks/measurement_rows.py{args}` (do not edit: rerun the script).

The observer's cached step takes the measurement rows about a configuration `q0`
(`exuflex.observer.reduced.ReducedObserverModel.measure`): the held one or one evaluated for the rows alone, up to
the measurement radius from it, which the rows' own error controls (below). Every channel is `y(q, p) = rigid(q) + U(q) H_u(q) p`: the rigid
part a link angle or a point's coordinate, `U` the channel's row on the elastic displacements (a gauge's Hermite
curvature row turned into the global frame by its element's rotation, a point's displacement rows, an encoder's
nodal rotations), `H_u` the basis's elastic-displacement rows (zero in the q-columns).

## The expansion

With `dl = q - q0`, to first order in `dl`

    U(q) H_u(q) = U H_u + sum_k dl_k D_k,   D_k = dU/dq_k H_u + U dH_u/dq_k

at `q0`. The u rows depend on q only through the angle `theta_l` of their link: element rotations turn as
`dR_e/dtheta = R_e W` (`W` the 90-degree generator on each node's translations), so a gauge row `c R_e^T` turns at
`(W c) R_e^T`, a point's rows `r N R^T` at `r (w N - N W) R^T`, and `dU/dq_k = (dU/dtheta_l) dtheta_l/dq_k`
(`exuflex.observer.rows.ChannelRows.rates`); an encoder's rows (nodal rotations) do not turn. `dH_u/dq_k` is the
basis derivative (`CraigBampton.basis_derivative`: the Guyan shapes' change with the element stiffness matrices'
rotation and the interior modes turning with their nodes). The rigid part gains `1/2 dl^T G dl` with
`G = d^2 rigid/dq^2`, from the pose's second derivatives (`Kinematics.coordinate_rates` at the links' origins and
at the sensed points). The measurement is then

    y = c0 + (Hm + sum_k dl_k D_k) x + 1/2 dl^T G dl

(`c0 + Hm x` the rows at `q0`, rigid parts to first order), and its Jacobian in `x`

    H = Hm + sum_k dl_k D_k,   q-column j  +=  G dl .

The exact derivative would also add `D_j x` to q-column j: the gauges' reading changes with q at a fixed elastic
state. That term makes the gauges a source of information on q through a detail of the reduced model (the
elastic rows' q-sensitivity times the elastic state) less accurate than the filter would take it to be: with a
channel's bias as a state (the six-bar's q1, read once, `tests/test_bias.py`) the filter estimated the bias from
it at a standard deviation of 1.6 mrad and 22 mrad off on the full-order ERLS log. It is left out; q is informed
by the encoders and the rigid rows, and the value `y` follows q.

The error is `O(dl^2 |p_e|) + O(dl^3)` in `y` (the rows at `q0` alone: `O(dl |p_e|) + O(dl^2)`), `O(dl^2)` in
`H`'s elastic columns;
`tests/test_measurement_rows.py` checks y and H entry by entry against the re-evaluated measurement (halving `dl`
quarters every entry's error) on the three-link arm, the six-bar and the slider-crank. `D_k` and `G` are computed
once per centre and kept with it; a measurement adds `m r nq` products.

The secant the rows used before (the change of the rows from the previous held configuration, along the one
direction joining the two) gave the same first order along that line only; a three-joint arm moves off it, and
its hand gauge's row changes with the elbow angle at about the size of the row itself per radian.

## The measurement radius

The rows are rebuilt where q leaves the measurement radius around their centre
(`ReducedObserverModel._recentre`): about the held configuration if it lies within the radius of q and ahead of it
along its motion (no evaluation: the held evaluation's basis and `dH/dq` serve), else about a configuration
evaluated for the rows alone (the basis and the link angles, no reduced matrices) 0.8 radii ahead of q along its
motion (the rows are as good behind their centre as ahead of it). At each rebuild the rows they replace are
compared with the new ones where the new ones are exact: at the filter's state moved to the new centre, the
channels' error `dy = y_old - y_new`, a bias of one sign that persists over every update the rows serve
(`_rows_error`). Its figure `e` is what that bias does to the estimate: the filter's steady response to `dy` at
every update, `b = -(I - A)^-1 K dy` with `A = (I - K H) F` the filter's error map, in the coordinates' readings
and rates over the filter's standard deviation of them (`_persistent_bias`; docs/reading_floor.md); without the
filter's covariance, `max_i |dy_i| / sigma_i` against the channels' noise. (Against each channel's own noise or
standard deviation, as before, a gauge's bias of a tenth of its standard deviation left a steady 0.5 of the bound
on the three-link arm's wrist reading: the filter averages several hundred samples of the gauge.) The error grows
as `dist^2` (the elastic rows' second-order term, `O(dl^2 |p_e|)`; the rigid
parts' `O(dl^3)` grows faster, so the rule shrinks the radius more than they need), so the next radius is
`0.9 dist (rows_tol / e)^(1/2)` with `dist` the distance of the two centres, at most twice the last radius,
within `[rows_min, rows_max]` = [0.001, 0.06] rad (`_rows_radius`): an adaptive step size with an error estimate.
`rows_tol` = 0.1: a steady bias of a tenth of a coordinate's standard deviation adds 1 % to its mean square
error; on the runs below the observer's errors are those of rows evaluated exactly at every measurement (the last
two columns of the run table).

The estimate takes the filter's elastic state at the rebuild: where the elastic coordinates oscillate (the long
arm's hand gauge) the error between two rebuilds can exceed the tolerance (the run table's largest error), and a
radius grown while the arm was at rest is too large once it bends. The filter's figures do not see it (exact rows give the same), but an estimate from the elastic state's
amplitude (its coordinates and rates over each mode's frequency) would bound it.

The rows' centre is not the held configuration's: where a measurement left the radius before, the configuration
at the measured state replaced the held one, and the next interval evaluated a held configuration anew at the
smallest refresh radius. `tests/test_rows_radius.py` checks the error the rebuild measures against the
slider-crank's closed-form Taylor remainder, the radius rule, and, along a path of a deflected arm (the gallery's
three-link arm and the fresh long arm), that the adaptive radius keeps every channel's error within `rows_tol`
where rows held over the largest radius exceed it tenfold.

## The rows' error at the distance from the held configuration

Per model, at `|dl|` = 0.01 / 0.02 / 0.04 rad from `q*` in {n_dir} random directions: the elastic rows' largest
relative error over the observer's channels (`|E_i(q) - approx| / |E_i(q*)|`, over the channels with an elastic
row), first order (the rows at `q*`) and with the expansion; the elastic part's error in units of the channel's
noise for an elastic state whose largest reading is a tenth of its channel's full scale (random, one per
direction: the rows' size says little alone, a gauge reads its state with a signal-to-noise ratio of 100 or more);
the rigid part's largest error on an undeformed state in units of the channel's noise at 0.04 rad; the expansion's
cost per held configuration against the held evaluation's (CPU, median of {n_rep}).

| model | channels | rows at q*, relative | expansion, relative | rows at q*, elastic / noise | expansion, elastic / noise | rigid / noise, first order | with G | cost / held evaluation |
|---|---|---|---|---|---|---|---|---|
"""


RUN_HEAD = """
## Along a run

At every measurement of the filter on a run (the observer's default settings, the sample-by-sample path: the
same rows as the compiled loop's), the channels from the rows about their centre with their expansion against the
rows of the estimate's own configuration evaluated anew, in units of each channel's noise: the largest and the
RMS over the run, with the largest distance from the rows' centre; the rows' rebuilds and configuration
evaluations (held and for the rows alone) per 1000 samples; the error measured at the rebuilds (`e` above: median
and largest) and the radius (median, smallest); the observer's worst RMS error / bound and NIS / channels on the
run, and the same with rows evaluated exactly at every measurement (`exact`), the limit of a vanishing tolerance.

| model | run | measurements | largest max abs dl (rad) | largest error / noise | RMS error / noise | rebuilds / 1000 | evaluations / 1000 | e at rebuild: median, max | radius: median, min (rad) | worst RMS / bound, NIS / channels | exact rows |
|---|---|---|---|---|---|---|---|---|---|---|---|
"""



def gallery() -> list[Path]:
    return sorted(p for p in (ROOT / "models").glob("*.toml") if "manoeuvre" in tomllib.loads(p.read_text()))


def _cpu(f, n: int) -> float:
    ts = []
    for _ in range(n):
        t = time.process_time()
        f()
        ts.append(time.process_time() - t)
    return float(np.median(ts))


def measure(path: Path, n_dir: int, n_rep: int) -> dict:
    """The figures of one model (see the module docstring)."""
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.session import ObserverConfig, make_observer

    mech = load_mechanism(path)
    obs = make_observer(mech, ObserverConfig())
    m, channels = obs.model, tuple(obs.channels)
    nq, r = m.nq, m.r
    noise = np.array([m.sensors[c].noise_std for c in channels])
    q0 = np.asarray(m.rm.cb.q_star, float)
    iv = m._configuration(m.initial_state(q0), held=True)
    c0, Hm, D, G = m._expansion(iv, channels)
    E0 = np.linalg.norm(Hm[:, nq:r], axis=1)
    el = E0 > 1e-12 * E0.max()  # the channels with an elastic row (not a clamped joint's encoder)
    rng = np.random.default_rng(1)
    dirs = rng.standard_normal((n_dir, nq))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    first, expanded = np.zeros(len(STEPS)), np.zeros(len(STEPS))
    y_first, y_expanded = np.zeros(len(STEPS)), np.zeros(len(STEPS))
    rigid1 = rigid2 = 0.0
    scale = np.array([m.sensors[c].full_scale or np.inf for c in channels])
    for u in dirs:
        pe = rng.standard_normal(r - nq)  # an elastic state reading at most a tenth of a channel's full scale
        pe *= 0.1 / np.max(np.abs(Hm[:, nq:r] @ pe) / scale)
        for s, h in enumerate(STEPS):
            dl = h * u
            x = m.initial_state(q0 + dl)
            c, H = m._affine(m._configuration(x), channels)
            E = H[:, nq:r]
            approx = Hm[:, nq:r] + np.tensordot(dl, D[:, :, nq:], axes=1)
            first[s] = max(first[s], float(np.max(np.linalg.norm(E - Hm[:, nq:r], axis=1)[el] / E0[el])))
            expanded[s] = max(expanded[s], float(np.max(np.linalg.norm(E - approx, axis=1)[el] / E0[el])))
            y_first[s] = max(y_first[s], float(np.max(np.abs((E - Hm[:, nq:r]) @ pe) / noise)))
            y_expanded[s] = max(y_expanded[s], float(np.max(np.abs((E - approx) @ pe) / noise)))
            if h == STEPS[-1]:
                y = c + H @ x
                y1 = c0 + Hm @ x
                y2 = y1 + 0.5 * np.einsum("ijk,j,k->i", G, dl, dl)
                rigid1 = max(rigid1, float(np.max(np.abs(y1 - y) / noise)))
                rigid2 = max(rigid2, float(np.max(np.abs(y2 - y) / noise)))
    z = m.initial_state(q0)
    t_held = _cpu(lambda: m._configuration(z, held=True), n_rep)
    t_rows = _cpu(lambda: m._expansion(iv, channels), n_rep)
    t_affine = _cpu(lambda: m._affine(iv, channels), n_rep)
    return {"model": mech.name, "channels": ", ".join(channels), "first": first.tolist(),
            "expanded": expanded.tolist(), "y_first": y_first.tolist(), "y_expanded": y_expanded.tolist(), "rigid_first": rigid1, "rigid_second": rigid2,
            "cost": (t_rows - t_affine) / t_held}


def along_run(path: Path, run_dir: Path) -> dict:
    """The expansion's error along the filter's own estimates on a run: at every measurement of the observer
    (the Python path, the same rows as the compiled loop's), the channels from the rows about their centre with
    their expansion against the rows of the estimate's own configuration evaluated anew, in units of the channel's
    noise, with the distance ``max |dl|`` from the centre; the rebuilds, evaluations, errors measured at the
    rebuilds and radii; the observer's figures on the run, and with rows evaluated exactly at every measurement."""
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.base import Measurement
    from exuflex.observer.reduced import ReducedObserverModel
    from exuflex.observer.session import ObserverConfig, make_observer
    from exuflex.runs import read_run
    from exuflex.scoring.run import observe_run

    mech = load_mechanism(path)
    run = read_run(run_dir)
    obs = make_observer(mech, ObserverConfig())
    m = obs.model
    rec = []

    def exact(self, x, channels):
        held, warm, n = self._last, self.model.kin.warm_start, self.n_evaluations
        c0, Hm = self._affine(self._configuration(np.asarray(x, float)), tuple(channels))
        self._last, self.model.kin.warm_start, self.n_evaluations = held, warm, n
        return c0, Hm

    class Recording(ReducedObserverModel):
        def measure(self, x, channels):
            meas = super().measure(x, channels)
            c0, Hm = exact(self, x, channels)
            noise = self._noise(tuple(channels))
            rec.append((float(np.max(np.abs(x[: self.nq] - self._centre.q0))), *(np.abs(meas.y - c0 - Hm @ x) / noise)))
            return meas

    class Exact(ReducedObserverModel):
        def measure(self, x, channels):
            c0, Hm = exact(self, x, channels)
            return Measurement(c0 + Hm @ np.asarray(x, float), Hm)

    def figures(o):
        r = o.summary["ratio_to_bound"]
        worst = max(r, key=r.get)
        return worst, r[worst], o.summary["nis_mean"] / o.summary["nis_expected"]

    m.__class__ = Recording
    obs.ekf._loop = None  # the filter's compiled sample loop off: every sample through measure()
    o = observe_run(mech, run, ObserverConfig(), observer=obs, keep="summary")
    n_rows, n_eval, e = m.n_rows, m.n_evaluations, m.rows_errors.asarray()
    obs = make_observer(mech, ObserverConfig())
    obs.model.__class__ = Exact
    obs.ekf._loop = None
    ox = observe_run(mech, run, ObserverConfig(), observer=obs, keep="summary")
    a = np.array(rec)
    k = 1000.0 / len(a)
    return {"model": mech.name, "run": str(run_dir), "channels": list(obs.channels), "n": len(a),
            "dl_max": float(a[:, 0].max()), "max": a[:, 1:].max(axis=0).tolist(),
            "rms": np.sqrt((a[:, 1:] ** 2).mean(axis=0)).tolist(), "rebuilds": k * n_rows, "evaluations": k * n_eval,
            "e_median": float(np.median(e[:, 0])), "e_max": float(e[:, 0].max()),
            "rad_median": float(np.median(e[:, 1])), "rad_min": float(e[:, 1].min()),
            "observer": figures(o), "exact": figures(ox)}


def _row(f: dict) -> str:
    def trio(v):
        return " / ".join(f"{a:.1e}" for a in v)

    def trio2(v):
        return " / ".join(f"{a:.2g}" for a in v)

    return (f"| {f['model']} | {f['channels']} | {trio(f['first'])} | {trio(f['expanded'])} | "
            f"{trio2(f['y_first'])} | {trio2(f['y_expanded'])} | "
            f"{f['rigid_first']:.2g} | {f['rigid_second']:.2g} | {f['cost']:.2f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default=None, help="comma-separated model files (default: the gallery)")
    ap.add_argument("--extra", default=str(EXTRA.relative_to(ROOT)), help="a further model file ('' for none)")
    ap.add_argument("--directions", type=int, default=6, help="random directions of dl per distance")
    ap.add_argument("--repeats", type=int, default=21, help="repeats of the cost's timing")
    ap.add_argument("--run", action="append", default=[],
                    help="MODEL_FILE=RUN_DIR: also the expansion's error along the filter's estimates on that run")
    ap.add_argument("--md", default=str(ROOT / "docs" / "measurement_rows.md"), help="markdown page ('' for none)")
    a = ap.parse_args(argv)
    paths = [Path(p) for p in a.models.split(",")] if a.models else gallery()
    if a.extra:
        paths.append(ROOT / a.extra if not Path(a.extra).is_absolute() else Path(a.extra))
    rows = []
    for p in paths:
        f = measure(p, a.directions, a.repeats)
        rows.append(_row(f))
        print(rows[-1], flush=True)
    args = "".join(f" --{k} {v}" for k, v in (("models", a.models), ("directions", a.directions if a.directions != 6
                                                                         else None)) if v)
    args += "".join(f" --run {spec}" for spec in a.run)
    text = HEAD.format(args=args, n_dir=a.directions, n_rep=a.repeats) + "\n".join(rows) + "\n"
    if a.run:
        text += RUN_HEAD
        for spec in a.run:
            model, run_dir = spec.split("=", 1)
            f = along_run(Path(model), Path(run_dir))
            obs, ex = f["observer"], f["exact"]
            line = (f"| {f['model']} | `{'/'.join(Path(f['run']).parts[-3:])}` | {f['n']} | {f['dl_max']:.3f} | "
                    + ", ".join(f"{c} {v:.2f}" for c, v in zip(f["channels"], f["max"])) + " | "
                    + ", ".join(f"{c} {v:.3f}" for c, v in zip(f["channels"], f["rms"])) + " | "
                    + f"{f['rebuilds']:.0f} | {f['evaluations']:.0f} | {f['e_median']:.3f}, {f['e_max']:.2f} | "
                    + f"{f['rad_median']:.3f}, {f['rad_min']:.3f} | {obs[1]:.2f} ({obs[0]}), {obs[2]:.3f} | "
                    + f"{ex[1]:.2f} ({ex[0]}), {ex[2]:.3f} |")
            text += line + "\n"
            print(line, flush=True)
    text += (f"\nVersions: numpy {np.__version__}, python {platform.python_version()}.\n")
    if a.md:
        Path(a.md).write_text(text)
        print(f"wrote {a.md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

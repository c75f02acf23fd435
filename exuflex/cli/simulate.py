"""``exuflex simulate MODEL --out DIR``: simulate the "real mechanism" along the model's manoeuvre.

Pipeline (the library does the work; this module only wires it):

1. load the model and the manoeuvre (the model's, or ``--manoeuvre FILE``: a TOML file with a ``[manoeuvre]``
   table, or a CSV trajectory or measured-torque table, :func:`exuflex.mechanism.load_manoeuvre`); plan it
   (exact inverse kinematics, :func:`exuflex.manoeuvre.plan`);
2. open-loop computed torque from the rigid model with the *nominal* payload
   (:func:`exuflex.manoeuvre.computed_torque`), as the paper's controller knows only the nominal model; a
   measured-torque manoeuvre gives its torques instead (:func:`exuflex.manoeuvre.torque_table`);
3. simulate the truth with the payload scaled by ``--payload-scale``: Exudyn
   (:func:`exuflex.groundtruth.simulate_truth`; ``--beam``, ``--elements-per-link``) or the full-order ERLS
   model (``--integrator``: implicit generalized-alpha, :func:`exuflex.erls.implicit.erls_implicit`, or the
   explicit RK4 reference; the model file's mesh or ``--elements-per-link``);
4. clean sensor channels and true states from the probe record (:mod:`exuflex.sensors`);
5. noisy, quantised measurements (:func:`exuflex.measure.measure`, seeded);
6. write the run folder (:func:`exuflex.runs.write_run`): ``sensors.csv``, ``truth.csv``, ``meta.json``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from .args import out_path, positive_float
from .args import seed as seed_type

__all__ = ["BEAMS", "INTEGRATORS", "ProgressBar", "add_parser", "elements_per_link_arg", "run", "simulate_run"]

BEAMS = {"ancf": "ancf", "ge": "gebeam"}  # --beam: Exudyn's ANCF cable or geometrically exact beam
INTEGRATORS = ("gen-alpha", "rk4")  # --integrator of the ERLS engine
EXUDYN_ELEMENTS_PER_LINK = 4  # the Exudyn truth's default mesh (converged within 0.5 % to ~190 Hz on the six-bar)

log = logging.getLogger(__name__)


class ProgressBar:
    """Progress on stderr: on a terminal a one-line bar ``label [#####.....]  45%`` redrawn in place; otherwise
    (a log file, a pipe, a CI job) a plain line every 10 %, ``label  40%  12.3 s``. Silent if disabled."""

    def __init__(self, label: str, enabled: bool = True, width: int = 30, stream=None):
        self.label, self.enabled, self.width = label, enabled, width
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last = -1
        self._t0 = time.perf_counter()

    def __call__(self, frac: float) -> None:
        if not self.enabled:
            return
        pct = int(100 * min(max(frac, 0.0), 1.0))
        if not self.tty:
            pct = pct // 10 * 10
        if pct == self._last:
            return
        self._last = pct
        el = time.perf_counter() - self._t0
        if not self.tty:
            self.stream.write(f"{self.label:<12s} {pct:3d}% {el:6.1f} s\n")
            self.stream.flush()
            return
        n = self.width * pct // 100
        self.stream.write(f"\r{self.label:<12s} [{'#' * n}{'.' * (self.width - n)}] {pct:3d}% {el:6.1f} s")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self.tty and self._last >= 0:
            self.stream.write("\n")
            self.stream.flush()


def _erls_step_arg(text: str):
    if text == "auto":
        return "auto"
    try:
        v = float(text)
    except ValueError:
        v = 0.0
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive step in s or 'auto', got {text!r}")
    return v


def _check_erls_step(step, h: float, output_dt: float, band_hz: float = 180.0) -> float:
    """The ERLS generalized-alpha step: a multiple of ``h`` that divides ``output_dt``; ``None``: ``h``; ``"auto"``:
    :func:`~exuflex.erls.implicit.band_step` for the band ``band_hz``."""
    from ..errors import UsageError

    if step == "auto":
        from ..erls.implicit import band_step

        return band_step(band_hz, h, output_dt)
    step = h if step is None else float(step)
    k = round(step / h)
    if k < 1 or abs(k * h - step) > 1e-9 * h or round(output_dt / h) % k:
        raise UsageError(f"--erls-step: expected a multiple of --h = {h:g} s that divides the sample interval "
                         f"{output_dt:g} s, got {step:g} s")
    return step


def elements_per_link_arg(text: str):
    """``--elements-per-link``: a positive integer or ``file`` (the model file's own mesh)."""
    if text == "file":
        return "file"
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer or 'file', got {text!r}")
    return n


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "simulate",
        help="simulate the mechanism along its manoeuvre and write a run folder",
        description=__doc__.split("\n")[0],
    )
    p.add_argument("model", help="model file (TOML), e.g. models/sixbar.toml")
    p.add_argument("--out", required=True, type=out_path, help="run folder to write (created if needed)")
    p.add_argument(
        "--engine", choices=("exudyn", "erls"), default="exudyn", help="truth engine (default: exudyn)"
    )
    p.add_argument(
        "--duration", type=positive_float, default=None, help="simulated time (s); default: the manoeuvre's"
    )
    p.add_argument(
        "--payload-scale", type=positive_float, default=1.0, help="tip payload multiplier of the truth (default 1)"
    )
    p.add_argument(
        "--seed", type=seed_type, default=None, help="measurement noise seed (default: random, recorded)"
    )
    p.add_argument("--h", type=positive_float, default=1e-4,
                   help="integration step (s), also the torque table step; at most the model's sample interval")
    p.add_argument(
        "--manoeuvre", default=None, metavar="FILE",
        help="manoeuvre instead of the model's: a TOML file with a [manoeuvre] table, or a CSV table "
        "(t and coordinates or tip_x, tip_y: a trajectory; t and motor names: measured torques)",
    )
    p.add_argument(
        "--write-plan", action="store_true",
        help="also write the planned q, q', q'' as plan.csv (a trajectory file: --manoeuvre plan.csv plans it again)",
    )
    p.add_argument(
        "--elements-per-link",
        type=elements_per_link_arg,
        default=None,
        metavar="N|file",
        help="truth mesh: no element longer than 1/N of its link (joints and masses on nodes; the ERLS engine keeps "
        f"the file's nodes too) or 'file', the model file's mesh (default: {EXUDYN_ELEMENTS_PER_LINK} for Exudyn, "
        "the file's for ERLS)",
    )
    p.add_argument(
        "--beam",
        choices=tuple(BEAMS),
        default="ancf",
        help="Exudyn beam: ANCF cable (default) or geometrically exact (linear, needs 16-32 elements per link)",
    )
    p.add_argument(
        "--integrator",
        choices=INTEGRATORS,
        default="gen-alpha",
        help="ERLS engine: implicit generalized-alpha (default) or the explicit RK4 reference",
    )
    p.add_argument(
        "--erls-step", type=_erls_step_arg, default="auto", metavar="S|auto",
        help="generalized-alpha step of the ERLS engine (s): a multiple of --h that divides the sample interval; "
        "auto (default): the largest whose frequency error at the model's band_hz is within 0.5 %% (the error "
        "at a mode f is about (2 pi f S)^2 / 12)",
    )
    p.add_argument(
        "--no-progress", action="store_true",
        help="no progress (a bar on a terminal, a line every 10 %% otherwise)"
    )
    p.set_defaults(func=run)
    return p


def _erls_truth(mech, t_tab, tau, duration, h, output_dt, q0, qd0, progress, integrator="gen-alpha", stats=None,
                form: str = "lagrange", step=None):
    """Full-order ERLS model under the torque table (zero-order hold); returns a ProbeRecord.

    ``gen-alpha``: :func:`~exuflex.erls.implicit.erls_implicit` with step ``step`` (default ``h``; ``"auto"``:
    :func:`~exuflex.erls.implicit.band_step` for the model's ``reduction.band_hz``; stable whatever the mesh's
    stiffest mode; a multiple of ``h`` that divides ``output_dt``). ``rk4``: the explicit reference; the step ``h`` is
    split into the fewest RK4 sub-steps that keep the model's linearisation at the start stable (:func:`~exuflex.erls.simulate.rk4_substeps`; the six-bar needs none
    at 0.1 ms, a finer mesh with stiffness damping does: its highest modes are overdamped, with large real
    eigenvalues). ``form``: the full-order model's velocity forces (:class:`~exuflex.erls.model.ErlsModel`)."""
    from ..erls.implicit import erls_implicit
    from ..erls.model import ErlsModel
    from ..erls.simulate import rk4_substeps, simulate
    from ..sensors import erls_probe_record

    model = ErlsModel(mech, form=form)
    n = model.n
    y0 = np.zeros(2 * n)
    y0[: model.nq] = q0
    y0[n : n + model.nq] = qd0
    every = max(1, round(output_dt / h))
    if integrator == "gen-alpha":
        step = _check_erls_step(step, h, output_dt, mech.reduction.band_hz)
        k = round(step / h)
        if stats is not None:
            stats.update(step_s=step)
        traj = erls_implicit(model, t_tab, tau, y0, duration, step, output_every=every // k, progress=progress,
                             stats=stats)
        return erls_probe_record(model, traj.t, traj.y)
    if integrator != "rk4":
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    dt_tab = t_tab[1] - t_tab[0]

    def inputs(t):
        return tau[min(int(np.floor(t / dt_tab + 1e-6)), len(tau) - 1)]

    sub = rk4_substeps(model.state_matrix(model.configuration(np.asarray(q0, float)))[0], h)
    if sub > 1:
        log.info("ERLS truth: %d RK4 sub-steps per %g s step (stability at the start)", sub, h)
    if stats is not None:
        stats.update(rk4_substeps=sub)
    traj = simulate(model.rhs, y0, duration, inputs, h=h / sub, method="rk4", output_every=every * sub,
                    progress=progress)
    return erls_probe_record(model, traj.t, traj.y)


def simulate_run(
    model_path: str | Path,
    out: str | Path,
    *,
    engine: str = "exudyn",
    duration: float | None = None,
    payload_scale: float = 1.0,
    seed: int | None = None,
    h: float = 1e-4,
    progress: bool = False,
    manoeuvre: str | Path | None = None,
    write_plan: bool = False,
    elements_per_link: int | str | None = None,
    beam: str = "ancf",
    integrator: str = "gen-alpha",
    erls_step: float | str | None = "auto",
) -> Path:
    """Library form of the command: simulate and write a run folder; returns its path.

    ``elements_per_link``: ``None`` (Exudyn: 4 per link; ERLS: the file's mesh), a positive integer or ``"file"``
    (see ``--elements-per-link``); ``beam``: a key of :data:`BEAMS`; ``integrator``: the ERLS engine's, one of
    :data:`INTEGRATORS`; ``erls_step``: its generalized-alpha step (s, ``None``: ``h``, ``"auto"``: from the band,
    see ``--erls-step``).
    """
    from ..errors import UsageError
    from ..manoeuvre import open_loop_torque, plan
    from ..measure import measure, new_seed
    from ..mechanism import ModelFileError, load_manoeuvre, load_mechanism
    from ..runs import file_sha256, write_run
    from ..sensors import monotonic_record, sensor_channels, true_states
    from ..validate import check_actuation, check_configurations, check_positive, check_simulation_settings

    if not isinstance(model_path, (str, Path)):
        raise UsageError(f"model_path: expected the path of a model file (TOML), got {type(model_path).__name__}")
    if not isinstance(out, (str, Path)) or not str(out).strip():
        raise UsageError(f"out (--out): expected a folder path, got {out!r}")
    if engine not in ("exudyn", "erls"):
        raise UsageError(f"engine (--engine): expected 'exudyn' or 'erls', got {engine!r}")
    check_positive(payload_scale, "payload_scale", "--payload-scale")
    model_path = Path(model_path)
    mech = load_mechanism(model_path)
    check_configurations(mech)  # loops close, away from singularities
    if manoeuvre is not None:
        mech = mech.replace(manoeuvre=load_manoeuvre(manoeuvre, mech))
    if mech.manoeuvre is None:
        raise ModelFileError(str(model_path), "manoeuvre", "a [manoeuvre] table to simulate", has_got=False)
    duration = mech.manoeuvre.duration if duration is None else duration
    check_simulation_settings(mech, duration, h, seed)
    if mech.manoeuvre.kind != "torque":
        check_actuation(mech)  # before planning: computed torque needs every coordinate actuated
    duration = float(duration)
    if beam not in BEAMS:
        raise UsageError(f"beam (--beam): expected one of {tuple(BEAMS)}, got {beam!r}")
    if integrator not in INTEGRATORS:
        raise UsageError(f"integrator (--integrator): expected one of {INTEGRATORS}, got {integrator!r}")
    if elements_per_link is not None and elements_per_link != "file":
        elements_per_link = elements_per_link_arg(str(elements_per_link))
    output_dt = 1.0 / mech.sample_rate_hz
    if engine == "erls" and integrator == "gen-alpha":
        _check_erls_step(erls_step, h, output_dt, mech.reduction.band_hz)  # before the planning
    seed = new_seed() if seed is None else seed
    timings = {}

    t0, c0 = time.perf_counter(), time.process_time()
    bar = ProgressBar("plan", progress)
    pl = plan(mech, dt=h, t_end=duration, progress=bar)
    bar.close()
    timings["plan_s"] = time.perf_counter() - t0
    bar = ProgressBar("torque", progress)
    tau = open_loop_torque(mech, pl, progress=bar)  # computed on the nominal model (the controller's), or measured
    bar.close()
    timings["plan_and_torque_s"] = time.perf_counter() - t0
    timings["torque_s"] = timings["plan_and_torque_s"] - timings["plan_s"]
    timings["plan_and_torque_cpu_s"] = time.process_time() - c0

    truth_mech = mech if payload_scale == 1.0 else mech.with_payload_scale(payload_scale)
    t0 = time.perf_counter()
    c0 = time.process_time()
    bar = ProgressBar(engine, progress)
    solver: dict = {}
    if engine == "exudyn":
        from ..groundtruth import simulate_truth  # lazy: Exudyn is heavy and optional for the rest

        mesh = EXUDYN_ELEMENTS_PER_LINK if elements_per_link is None else elements_per_link
        record = simulate_truth(
            truth_mech, pl.t, tau, duration, h=h, output_dt=output_dt, q0=pl.q[0], progress=bar,
            elements_per_link=mesh, formulation=BEAMS[beam], stats=solver,
        )
        truth_settings = {
            "engine": "exudyn",
            "beam": beam,
            "formulation": BEAMS[beam],
            "elements_per_link": mesh,
            "hub_inertia": "rigid body welded to the node" if beam == "ancf" else "node rotation coordinate",
            "integrator": "generalized-alpha (Exudyn)",
            "n_coordinates": solver.get("n_coordinates"),
            "newton_per_step": solver.get("newton_per_step"),
        }
    elif engine == "erls":
        from ..erls.implicit import GeneralizedAlpha, algorithmic_damping
        from ..mechanism import remesh_mechanism

        if elements_per_link not in (None, "file"):
            truth_mech = remesh_mechanism(truth_mech, elements_per_link)
        record = _erls_truth(truth_mech, pl.t, tau, duration, h, output_dt, pl.q[0], pl.qd[0], bar,
                             integrator=integrator, stats=solver, step=erls_step)
        truth_settings = {
            "engine": "erls",
            "elements_per_link": "file" if elements_per_link is None else elements_per_link,
            "n_elements": sum(lk.n_elements for lk in truth_mech.links),
            "integrator": integrator,
            **({"rho_inf": GeneralizedAlpha().rho_inf, "band_hz": truth_mech.reduction.band_hz,
                "freq_error_at_band": float(algorithmic_damping(
                    2 * np.pi * truth_mech.reduction.band_hz * solver["step_s"], GeneralizedAlpha().rho_inf)[1][0])}
               if integrator == "gen-alpha" else {}),
            **solver,
        }
    else:
        raise ValueError(f"engine must be 'exudyn' or 'erls', got {engine!r}")
    bar.close()
    timings["truth_s"] = time.perf_counter() - t0
    timings["truth_cpu_s"] = time.process_time() - c0

    record = monotonic_record(record)
    clean = sensor_channels(mech, record)
    truth = true_states(mech, record)
    meas = measure(mech, clean, pl.t, tau, seed=seed, t_end=duration)
    payload = truth_mech.payload
    man = mech.manoeuvre
    man_meta = {"kind": man.kind, "duration_s": man.duration,
                "source": str(Path(manoeuvre).resolve()) if manoeuvre else "model"}
    if man.kind in ("joint", "tip_arc", "tip_line", "tip_polyline"):
        man_meta.update(time_law=man.time_law, ramp_time_s=man.ramp_time)
    if man.kind == "waypoints":
        man_meta.update(interpolation=man.interpolation, n_waypoints=len(man.times))
    if man.file:
        man_meta.update(file=str(Path(man.file).resolve()), file_sha256=file_sha256(man.file),
                        n_samples=len(man.samples))
    meta = {
        "engine": engine,
        "model": {"path": str(model_path.resolve()), "sha256": file_sha256(model_path)},
        "mechanism": mech.name,
        "seed": meas.seed,
        "settings": {
            "duration_s": duration,
            "h_s": h,
            "integrator": truth_settings["integrator"],
            "truth": truth_settings,
            "torque_table_dt_s": pl.dt,
            "output_dt_s": output_dt,
            "payload_scale": payload_scale,
            "payload_mass_kg": None if payload is None else payload.mass,
            "computed_torque_model": "measured torques (file), open loop" if man.kind == "torque"
            else "rigid ERLS, nominal payload",
            "manoeuvre": man_meta,
            "measurement": meas.settings,
            "timings": timings,
        },
    }
    sensors = meas.signals
    if write_plan:  # before write_run: its meta.json comes last and marks the folder complete
        from ..manoeuvre import trajectory_csv
        from ..runs import atomic_write_text

        Path(out).mkdir(parents=True, exist_ok=True)
        atomic_write_text(Path(out) / "plan.csv", trajectory_csv(pl))
    return write_run(out, sensors, truth, meta, motors=mech.motor_names)


def run(args) -> int:
    out = simulate_run(
        args.model,
        args.out,
        engine=args.engine,
        duration=args.duration,
        payload_scale=args.payload_scale,
        seed=args.seed,
        h=args.h,
        progress=not args.no_progress,
        manoeuvre=args.manoeuvre,
        write_plan=args.write_plan,
        elements_per_link=args.elements_per_link,
        beam=args.beam,
        integrator=args.integrator,
        erls_step=args.erls_step,
    )
    print(f"wrote {out}/sensors.csv, truth.csv, meta.json")
    return 0

"""A run folder from a model file: the library form of ``exuflex simulate``.

1. load the model; plan the manoeuvre (exact inverse kinematics, :func:`exuflex.manoeuvre.plan`) and its
   open-loop computed torque from the rigid model with the *nominal* payload
   (:func:`exuflex.manoeuvre.computed_torque`), as the paper's controller knows only the nominal model;
2. simulate the truth with the payload scaled by ``payload_scale`` (:func:`exuflex.truth.simulate`, any engine);
3. noisy, quantised measurements of its clean channels (:func:`exuflex.measure.measure`, seeded);
4. write the run folder (:func:`exuflex.runs.write_run`): ``sensors.csv``, ``truth.csv``, ``meta.json``.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

from .engines import BEAMS, ENGINES, INTEGRATORS, gen_alpha_step, plan_drive, simulate

__all__ = ["simulate_run", "simulate_runs"]


def simulate_run(model_path: str | Path, out: str | Path, *, seed: int | None = None, **kwargs) -> Path:
    """Simulate the model's manoeuvre with the truth ``engine`` and write a run folder; returns its path.

    ``duration`` defaults to the manoeuvre's; ``seed`` (default: a fresh one, recorded in ``meta.json``) draws
    the measurement noise; the other keyword arguments are :func:`simulate_runs`'.
    """
    from ..validate import check_seed

    check_seed(seed)  # before it keys simulate_runs' outs
    return simulate_runs(model_path, {seed: out}, **kwargs)[0]


def simulate_runs(
    model_path: str | Path,
    outs,
    *,
    engine: str = "exudyn",
    duration: float | None = None,
    payload_scale: float = 1.0,
    h: float = 1e-4,
    progress: Callable[[str, float], None] | None = None,
    manoeuvre: str | Path | None = None,
    write_plan: bool = False,
    elements_per_link: int | str | None = None,
    beam: str = "ancf",
    integrator: str = "gen-alpha",
    erls_step: float | str | None = "auto",
    messages: Callable[[str], None] | None = None,
    overwrite: bool = False,
) -> list[Path]:
    """Simulate the model's manoeuvre with the truth ``engine`` once and write a run folder per noise seed.

    ``outs`` maps each seed (None: a fresh one, recorded in ``meta.json``) to its folder: the truth's motion does
    not depend on the seed (the torques are the plan's, the engines deterministic), so every folder holds the same
    truth measured with its own noise (:func:`exuflex.measure.measure`); returns the folders' paths in ``outs``'
    order. ``duration`` defaults to the manoeuvre's; ``h`` is the integration step and the torque table's step; ``manoeuvre`` replaces the
    model's (a TOML file with a ``[manoeuvre]`` table, or a CSV trajectory or measured-torque table,
    :func:`exuflex.mechanism.load_manoeuvre`); ``write_plan``: also write the planned q, q', q'' as ``plan.csv`` (a
    trajectory file that plans the same motion again); ``elements_per_link``, ``beam``, ``integrator``, ``erls_step``: the
    truth's mesh and solver (:func:`exuflex.truth.simulate`; ``erls_step`` ``"auto"``: the truth step rule's
    generalized-alpha step for the model's modes below its band, :func:`exuflex.truth.gen_alpha_step`); ``messages`` receives one-line setup messages (the FFRF
    truth's meshing and modes). Bad arguments raise a
    :class:`~exuflex.errors.UsageError` naming the parameter and its command-line flag. ``progress`` is called with the phase (``"plan"``, ``"torque"``,
    the engine's name) and the fraction of it done. Every folder is claimed before the work
    (:func:`exuflex.runs.output_folder`): a folder holding anything exuflex did not write is refused, an earlier
    exuflex result is replaced only with ``overwrite``. With an ERLS engine, links whose rotation rate approaches the
    model's validity limit are logged as warnings and listed in ``meta.json`` under ``validity``
    (:func:`exuflex.erls.validity.signal_warnings`).
    """
    from ..errors import UsageError
    from ..measure import measure, new_seed
    from ..mechanism import ModelFileError, load_manoeuvre, load_mechanism
    from ..runs import MANOEUVRE_FILE, atomic_write_text, check_not_foreign, file_sha256, output_folder, write_run
    from ..validate import check_actuation, check_configurations, check_positive, check_simulation_settings

    if not isinstance(model_path, (str, Path)):
        raise UsageError(f"model_path: expected the path of a model file (TOML), got {type(model_path).__name__}")
    outs = dict(outs)
    if not outs:
        raise UsageError("outs: expected at least one seed and its folder")
    for out in outs.values():
        if not isinstance(out, (str, Path)) or not str(out).strip():
            raise UsageError(f"out (--out): expected a folder path, got {out!r}")
        check_not_foreign(out, "out (--out)")  # a file, or a lab's folder: refused before anything is read
    if engine not in ENGINES:
        raise UsageError(f"engine (--engine): expected one of {', '.join(ENGINES)}, got {engine!r}")
    check_positive(payload_scale, "payload_scale", "--payload-scale")
    model_path = Path(model_path)
    mech = load_mechanism(model_path)
    check_configurations(mech)  # loops close, away from singularities
    if manoeuvre is not None:
        mech = mech.replace(manoeuvre=load_manoeuvre(manoeuvre, mech))
    if mech.manoeuvre is None:
        raise ModelFileError(str(model_path), "manoeuvre", "a [manoeuvre] table to simulate", has_got=False)
    duration = mech.manoeuvre.duration if duration is None else duration
    for seed in outs:
        check_simulation_settings(mech, duration, h, seed)
    if mech.manoeuvre.kind != "torque":
        check_actuation(mech)  # before planning: computed torque needs every coordinate actuated
    duration = float(duration)
    if beam not in BEAMS:
        raise UsageError(f"beam (--beam): expected one of {tuple(BEAMS)}, got {beam!r}")
    if integrator not in INTEGRATORS:
        raise UsageError(f"integrator (--integrator): expected one of {INTEGRATORS}, got {integrator!r}")
    if elements_per_link is not None and elements_per_link != "file":
        try:
            elements_per_link = int(elements_per_link)
        except (TypeError, ValueError):
            elements_per_link = 0
        if elements_per_link < 1:
            raise UsageError("elements_per_link (--elements-per-link): expected a positive integer or 'file'")
        from ..mechanism import remeshed_element_count
        from ..mechanism.limits import element_count_error

        why = element_count_error(remeshed_element_count(mech, elements_per_link))
        if why is not None:
            raise UsageError(f"elements_per_link (--elements-per-link): {elements_per_link} per link: expected {why}")
    if engine == "exudyn" and BEAMS[beam] == "ffrf":
        if elements_per_link not in (None, "file"):
            raise UsageError("elements_per_link (--elements-per-link): the FFRF truth meshes solids (links' mesh_size "
                             "in the model file); expected no --elements-per-link with --beam ffrf")
        bare = [lk.name for lk in mech.links if lk.section.shape is None]
        if bare:
            raise UsageError(f"beam (--beam): ffrf needs solid sections (diameter, tube or rectangle); links {bare} "
                             "give only A and I")
    if engine == "erls" and integrator == "gen-alpha":
        gen_alpha_step(erls_step, h, 1.0 / mech.sample_rate_hz, mech.reduction.band_hz)  # before the planning
    with ExitStack() as claimed:
        for out in outs.values():  # claimed before the work
            claimed.enter_context(output_folder(out, "simulate", overwrite=overwrite))
        drive = plan_drive(mech, duration, h, progress)  # nominal model: the controller's knowledge
        truth_mech = mech if payload_scale == 1.0 else mech.with_payload_scale(payload_scale)
        rec = simulate(truth_mech, drive, engine, duration, h,
                       progress=None if progress is None else (lambda f: progress(engine, f)),
                       elements_per_link=elements_per_link, beam=beam, integrator=integrator, erls_step=erls_step,
                       messages=messages)
        validity = []
        if engine in ("erls", "reduced"):  # an ERLS truth: links turning fast against their clamped frequency
            from ..erls.validity import signal_warnings

            validity = [w.as_dict() for w in signal_warnings(truth_mech, rec.truth)]  # logged there
        payload = truth_mech.payload
        man = mech.manoeuvre
        man_meta = {"kind": man.kind, "duration_s": man.duration,
                    "source": str(Path(manoeuvre).resolve()) if manoeuvre else "model"}
        if manoeuvre and not man.file:  # a copy in the run folder: the run does not depend on the file staying put
            man_meta["copy"] = MANOEUVRE_FILE
        if man.kind in ("joint", "tip_arc", "tip_line", "tip_polyline"):
            man_meta.update(time_law=man.time_law, ramp_time_s=man.ramp_time)
        if man.kind == "waypoints":
            man_meta.update(interpolation=man.interpolation, n_waypoints=len(man.times))
        if man.file:
            man_meta.update(file=str(Path(man.file).resolve()), file_sha256=file_sha256(man.file),
                            n_samples=len(man.samples))
        timings = {"plan_s": drive.plan_s, "plan_and_torque_s": drive.seconds, "torque_s": drive.seconds - drive.plan_s,
                   "plan_and_torque_cpu_s": drive.cpu_s, **rec.timings}
        meta = {
            "engine": engine,
            "model": {"path": str(model_path.resolve()), "sha256": file_sha256(model_path)},
            "mechanism": mech.name,
            "seed": None,
            # between two samples the torque is the table's (every engine holds it over the table's step, h / 2
            # behind the smooth torque): linear where the planned torque is continuous, held where the time law's
            # acceleration steps (a trapezoid: the torque steps at its switches, which fall on samples, and a line
            # between the samples around a step misses by half the step; exuflex.runs.INPUT_HOLDS)
            "input_hold": "zoh" if man.kind in ("joint", "tip_arc", "tip_line", "tip_polyline")
            and man.time_law == "trapezoid" else "linear",
            "input_delay_s": 0.5 * float(drive.t[1] - drive.t[0]),
            "settings": {
                "duration_s": duration,
                "h_s": h,
                "integrator": rec.settings["integrator"],
                "truth": rec.settings,
                "torque_table_dt_s": float(drive.t[1] - drive.t[0]),
                "output_dt_s": 1.0 / mech.sample_rate_hz,
                "payload_scale": payload_scale,
                "payload_mass_kg": None if payload is None else payload.mass,
                "computed_torque_model": "measured torques (file), open loop" if man.kind == "torque"
                else "rigid ERLS, nominal payload",
                "manoeuvre": man_meta,
                "measurement": None,
                "timings": timings,
            },
        }
        if validity:
            meta["validity"] = validity
        written = []
        for seed, out in outs.items():
            meas = measure(mech, rec.clean, rec.torque_t, rec.torques, seed=new_seed() if seed is None else seed,
                           t_end=duration)
            meta["seed"] = meas.seed
            meta["settings"]["measurement"] = meas.settings
            if "copy" in man_meta:  # before write_run: its meta.json comes last and marks the folder complete
                Path(out).mkdir(parents=True, exist_ok=True)
                atomic_write_text(Path(out) / MANOEUVRE_FILE, Path(manoeuvre).read_text(encoding="utf-8"))
            if write_plan:
                from ..manoeuvre import trajectory_csv

                Path(out).mkdir(parents=True, exist_ok=True)
                atomic_write_text(Path(out) / "plan.csv", trajectory_csv(drive.plan))
            written.append(write_run(out, meas.signals, rec.truth, copy.deepcopy(meta), motors=mech.motor_names))
        return written

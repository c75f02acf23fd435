"""A run folder from a model file: the library form of ``exuflex simulate``.

1. load the model; plan the manoeuvre (exact inverse kinematics, :func:`exuflex.manoeuvre.plan`) and its
   open-loop computed torque from the rigid model with the *nominal* payload
   (:func:`exuflex.manoeuvre.computed_torque`), as the paper's controller knows only the nominal model;
2. simulate the truth with the payload scaled by ``payload_scale`` (:func:`exuflex.truth.simulate`, any engine);
3. noisy, quantised measurements of its clean channels (:func:`exuflex.measure.measure`, seeded);
4. write the run folder (:func:`exuflex.runs.write_run`): ``sensors.csv``, ``truth.csv``, ``meta.json``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from .engines import ENGINES, plan_drive, simulate

__all__ = ["simulate_run"]

def simulate_run(
    model_path: str | Path,
    out: str | Path,
    *,
    engine: str = "exudyn",
    duration: float | None = None,
    payload_scale: float = 1.0,
    seed: int | None = None,
    h: float = 1e-4,
    progress: Callable[[str, float], None] | None = None,
    manoeuvre: str | Path | None = None,
    elements_per_link: int | str | None = None,
    beam: str = "ancf",
    integrator: str = "gen-alpha",
) -> Path:
    """Simulate the model's manoeuvre with the truth ``engine`` and write a run folder; returns its path.

    ``duration`` defaults to the manoeuvre's; ``seed`` (default: a fresh one, recorded in ``meta.json``) draws
    the measurement noise; ``h`` is the integration step and the torque table's step; ``manoeuvre`` replaces the
    model's (a TOML file with a ``[manoeuvre]`` table, or a CSV trajectory or measured-torque table,
    :func:`exuflex.mechanism.load_manoeuvre`); ``elements_per_link``, ``beam``, ``integrator``: the truth's mesh
    and solver (:func:`exuflex.truth.simulate`). ``progress`` is called with the phase (``"plan"``, ``"torque"``,
    the engine's name) and the fraction of it done.
    """
    from ..measure import measure, new_seed
    from ..mechanism import ModelFileError, load_manoeuvre, load_mechanism
    from ..runs import file_sha256, write_run
    from ..validate import check_configurations

    model_path = Path(model_path)
    mech = load_mechanism(model_path)
    check_configurations(mech)  # loops close, away from singularities
    if manoeuvre is not None:
        mech = mech.replace(manoeuvre=load_manoeuvre(manoeuvre, mech))
    if mech.manoeuvre is None:
        raise ModelFileError(str(model_path), "manoeuvre", "a [manoeuvre] table to simulate", has_got=False)
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    duration = float(mech.manoeuvre.duration if duration is None else duration)
    if not duration > 0 or not h > 0 or not payload_scale > 0:
        raise ValueError(f"duration, h and payload_scale must be positive (got {duration}, {h}, {payload_scale})")
    if isinstance(elements_per_link, str) and elements_per_link != "file":
        try:
            elements_per_link = int(elements_per_link)
        except ValueError:
            raise ValueError(f"elements_per_link must be a positive integer or 'file', got {elements_per_link!r}") \
                from None
    seed = new_seed() if seed is None else seed

    drive = plan_drive(mech, duration, h, progress)  # nominal model: the controller's knowledge
    truth_mech = mech if payload_scale == 1.0 else mech.with_payload_scale(payload_scale)
    rec = simulate(truth_mech, drive, engine, duration, h,
                   progress=None if progress is None else (lambda f: progress(engine, f)),
                   elements_per_link=elements_per_link, beam=beam, integrator=integrator)
    meas = measure(mech, rec.clean, rec.torque_t, rec.torques, seed=seed, t_end=duration)
    payload = truth_mech.payload
    man = mech.manoeuvre
    man_meta = {"kind": man.kind, "duration_s": man.duration, "source": str(manoeuvre) if manoeuvre else "model"}
    if man.kind in ("joint", "tip_arc", "tip_line", "tip_polyline"):
        man_meta.update(time_law=man.time_law, ramp_time_s=man.ramp_time)
    if man.kind == "waypoints":
        man_meta.update(interpolation=man.interpolation, n_waypoints=len(man.times))
    if man.file:
        man_meta.update(file=str(Path(man.file).resolve()), file_sha256=file_sha256(man.file),
                        n_samples=len(man.samples))
    timings = {"plan_s": drive.plan_s, "plan_and_torque_s": drive.seconds, "torque_s": drive.seconds - drive.plan_s,
               **rec.timings}
    meta = {
        "engine": engine,
        "model": {"path": str(model_path.resolve()), "sha256": file_sha256(model_path)},
        "mechanism": mech.name,
        "seed": meas.seed,
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
            "measurement": meas.settings,
            "timings": timings,
        },
    }
    return write_run(out, meas.signals, rec.truth, meta, motors=mech.motor_names)

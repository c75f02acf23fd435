"""The truth engines: what the "real mechanism" does under the manoeuvre's open-loop torque.

One entry point, :func:`simulate`, runs a mechanism (possibly with changed parameters: the truth of a
model-mismatch study) under a :class:`Drive` (the torque table that the *nominal* model's rigid computed torque
gives, and the start state) with one of three engines:

- ``"exudyn"``: the independent Exudyn model (planar ANCF beams, :func:`exuflex.groundtruth.simulate_truth`;
  the only engine outside the ERLS formulation, so the one that tests the observer's model);
- ``"erls"``: the full-order ERLS model of eq. 2 under the torque table (zero-order hold), RK4
  (:func:`erls_truth`);
- ``"reduced"``: the observer's own reduced model stepped exactly as the filter assumes (:func:`reduced_truth`),
  a truth without model error for consistency tests.

Each returns a :class:`TruthRecord`: the clean sensor channels and the true states of
:mod:`exuflex.sensors`, and the torque table as the measurement sees it. Exudyn is imported only inside
:mod:`exuflex.groundtruth`, and only when the ``"exudyn"`` engine runs.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..mechanism import Mechanism

if TYPE_CHECKING:  # the sensors module pulls in the ERLS model: imported where a function needs it
    from ..sensors import Signals

__all__ = [
    "BEAMS",
    "ENGINES",
    "EXUDYN_ELEMENTS_PER_LINK",
    "INTEGRATORS",
    "Drive",
    "TruthRecord",
    "erls_truth",
    "exudyn_mesh",
    "gen_alpha_step",
    "plan_drive",
    "reduced_truth",
    "simulate",
]

log = logging.getLogger(__name__)

ENGINES = ("exudyn", "erls", "reduced")
"""The truth engines :func:`simulate` knows."""
BEAMS = {"ancf": "ancf", "ge": "gebeam", "ffrf": "ffrf", "solid": "ffrf"}
"""Exudyn model choices: ANCF cable or geometrically exact beam (:func:`exuflex.groundtruth.build_truth`), or
floating-frame bodies reduced from solid meshes (``ffrf``, alias ``solid``: :func:`exuflex.groundtruth.build_ffrf`)."""
INTEGRATORS = ("gen-alpha", "rk4")
"""Integrators of the ERLS engine: implicit generalized-alpha, or the explicit RK4 reference."""
EXUDYN_ELEMENTS_PER_LINK = 4
"""The Exudyn truth's coarsest default mesh (converged within 0.5 % to ~190 Hz on the six-bar); a model file
with a more refined link raises it (:func:`exudyn_mesh`)."""


def exudyn_mesh(mech: Mechanism) -> int:
    """The Exudyn truth's default elements per link: :data:`EXUDYN_ELEMENTS_PER_LINK`, or the element count of
    the model file's most refined link if larger.

    A truth coarser than the model it checks measures its own discretisation error: a cubic element's curvature
    is linear, and a gauge's curvature converges more slowly than the modes (the slider-crank's rod, 8 elements
    in its model file: with 4 ANCF elements per link its gauges' curvature is off the finer meshes' values by a
    bias of the order of the gauge noise, which the observer turns into a crank-angle error; measured by
    ``benchmarks/truth_mesh.py`` in ``docs/truth_mesh.md``)."""
    return max(EXUDYN_ELEMENTS_PER_LINK, max(len(lk.stations) - 1 for lk in mech.links))


@dataclass
class Drive:
    """The manoeuvre's torque table (``t``, ``tau``: the rigid computed torque of the *nominal* model, the
    controller's knowledge, or a measured-torque manoeuvre's torques) and the start state ``q0``, ``qd0``;
    ``seconds`` is the time planning and the torques took, ``plan_s`` the planning's part, ``cpu_s`` the process
    time of both; ``plan`` the :class:`~exuflex.manoeuvre.Plan` itself (None for a drive read from a cache)."""

    t: np.ndarray
    tau: np.ndarray
    q0: np.ndarray
    qd0: np.ndarray
    seconds: float = 0.0
    plan_s: float = 0.0
    cpu_s: float = 0.0
    plan: object = None


@dataclass
class TruthRecord:
    """A truth: clean sensor channels and true states (:func:`exuflex.sensors.sensor_channels`,
    :func:`~exuflex.sensors.true_states`), and the torques as the measurement sees them (``torque_t``,
    ``torques``: the zero-order-hold table); ``timings`` records the wall times (s), ``settings`` the engine's
    settings (mesh, beam, integrator, solver statistics)."""

    clean: Signals
    truth: Signals
    torque_t: np.ndarray
    torques: np.ndarray
    timings: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)


def plan_drive(nominal: Mechanism, duration: float, h: float,
               progress: Callable[[str, float], None] | None = None) -> Drive:
    """Plan the manoeuvre on a grid of step ``h`` up to ``duration`` and its open-loop computed torque on the
    nominal model (a measured-torque manoeuvre gives its torques instead). ``progress`` is called with the phase
    (``"plan"``, ``"torque"``) and its fraction done."""
    from ..manoeuvre import open_loop_torque, plan

    def phase(name):
        return None if progress is None else (lambda f: progress(name, f))

    t0, c0 = time.perf_counter(), time.process_time()
    pl = plan(nominal, dt=h, t_end=duration, progress=phase("plan"))
    plan_s = time.perf_counter() - t0
    tau = open_loop_torque(nominal, pl, progress=phase("torque"))  # the nominal model's (the controller's), or measured
    return Drive(np.asarray(pl.t, float), np.asarray(tau, float), np.asarray(pl.q[0], float),
                 np.asarray(pl.qd[0], float), time.perf_counter() - t0, plan_s, time.process_time() - c0, pl)


def gen_alpha_step(step, h: float, output_dt: float, band_hz: float = 180.0, modes=None,
                   duration: float | None = None) -> float:
    """The ERLS engine's generalized-alpha step: a multiple of ``h`` that divides ``output_dt``; ``None``: ``h``;
    ``"auto"``: the smaller of :func:`~exuflex.erls.implicit.band_step` for the band ``band_hz`` (the largest whose
    frequency error there is within its tolerance) and, given the ``modes`` below the band (``(omega, zeta)``,
    :func:`~exuflex.erls.implicit.band_modes`) and the run's ``duration``, :func:`~exuflex.erls.implicit.phase_step`
    (the largest ``output_dt / n`` whose phase error accumulated over each mode's ringing is within its tolerance;
    it may be below ``h``). Anything else is a :class:`~exuflex.errors.UsageError`."""
    from ..errors import UsageError

    if step == "auto":
        from ..erls.implicit import band_step, phase_step

        band = band_step(band_hz, h, output_dt)
        if modes is None:
            return band
        return min(band, phase_step(*modes, duration, output_dt))
    step = h if step is None else float(step)
    k = round(step / h)
    if k < 1 or abs(k * h - step) > 1e-9 * h or round(output_dt / h) % k:
        raise UsageError(f"--erls-step: expected a multiple of --h = {h:g} s that divides the sample interval "
                         f"{output_dt:g} s, got {step:g} s")
    return step


def exudyn_step(mech: Mechanism, h: float, output_dt: float, duration: float, q0, elements_per_link,
                formulation: str) -> tuple[float, dict]:
    """The Exudyn truth's generalized-alpha step: the smaller of ``h`` and
    :func:`~exuflex.erls.implicit.phase_step` for the Exudyn model's own modes below ``reduction.band_hz``
    (:func:`~exuflex.groundtruth.modal_damping`, linearised at rest at ``q0`` and at ``q_ref``); the same rule as
    the ERLS engine's (Exudyn's generalized-alpha with the same ``rho_inf`` has the same period error). Returns
    the step and the settings that state it."""
    from ..erls.implicit import GeneralizedAlpha, accumulated_error, phase_step
    from ..groundtruth.eigen import modal_damping

    band = mech.reduction.band_hz
    f, z = [], []
    for q in (q0, mech.q_ref):
        fq, zq = modal_damping(mech, np.asarray(q, float), elements_per_link=elements_per_link,
                               formulation=formulation, fmax=band)
        f.append(fq)
        z.append(zq)
    w, z = 2 * np.pi * np.concatenate(f), np.concatenate(z)
    rho = GeneralizedAlpha().rho_inf
    step = min(h, phase_step(w, z, duration, output_dt, rho))
    err = accumulated_error(w, z, step, duration, rho)
    return step, {"step_s": step, "phase_error": float(err.max()) if err.size else 0.0,
                  "modes_below_band": len(f[0])}


def erls_truth(mech: Mechanism, t_tab, tau, duration: float, h: float, output_dt: float, q0, qd0,
               progress: Callable[[float], None] | None = None, integrator: str = "gen-alpha",
               stats: dict | None = None, form: str = "lagrange", step=None):
    """The full-order ERLS model under the torque table (zero-order hold); returns a
    :class:`~exuflex.probes.ProbeRecord` sampled every ``output_dt``.

    ``gen-alpha``: :func:`~exuflex.erls.implicit.erls_implicit` with step ``step`` (:func:`gen_alpha_step`: default
    ``h``, ``"auto"`` from the model's ``reduction.band_hz``; stable whatever the mesh's stiffest mode). ``rk4``: the
    explicit reference; the step ``h`` is split into the fewest RK4 sub-steps that keep the model's linearisation
    at the start stable (:func:`~exuflex.erls.simulate.rk4_substeps`: RK4 is stable for ``h |lambda| < 2.83``; a
    finer mesh with stiffness damping has overdamped high modes with large real eigenvalues). ``form``: the
    full-order model's velocity forces (:class:`~exuflex.erls.model.ErlsModel`). ``stats`` (a dict) receives the
    solver's statistics."""
    from ..erls.implicit import erls_implicit
    from ..erls.model import ErlsModel
    from ..erls.simulate import rk4_substeps
    from ..erls.simulate import simulate as integrate
    from ..sensors import erls_probe_record

    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    model = ErlsModel(mech, form=form)
    n = model.n
    y0 = np.zeros(2 * n)
    y0[: model.nq] = q0
    y0[n : n + model.nq] = qd0
    every = max(1, round(output_dt / h))
    if integrator == "gen-alpha":
        from ..erls.implicit import accumulated_error, band_modes

        band = mech.reduction.band_hz
        modes = band_modes(model, np.vstack([np.asarray(q0, float), np.asarray(mech.q_ref, float)]), band)
        step = gen_alpha_step(step, h, output_dt, band, modes, duration)
        if stats is not None:
            err = accumulated_error(*modes, step, duration)
            stats.update(step_s=step, phase_error=float(err.max()) if err.size else 0.0)
        traj = erls_implicit(model, t_tab, tau, y0, duration, step, output_every=round(output_dt / step),
                             progress=progress, stats=stats)
        return erls_probe_record(model, traj.t, traj.y)
    dt_tab = t_tab[1] - t_tab[0]

    def inputs(t):
        return tau[min(int(np.floor(t / dt_tab + 1e-6)), len(tau) - 1)]

    sub = rk4_substeps(model.state_matrix(model.configuration(np.asarray(q0, float)))[0], h)
    if sub > 1:
        log.info("ERLS truth: %d RK4 sub-steps per %g s step (stability at the start)", sub, h)
    if stats is not None:
        stats.update(rk4_substeps=sub)
    traj = integrate(model.rhs, y0, duration, inputs, h=h / sub, method="rk4", output_every=every * sub,
                     progress=progress)
    return erls_probe_record(model, traj.t, traj.y)


def reduced_truth(truth_mech: Mechanism, drive: Drive, duration: float, h: float = 1e-4) -> TruthRecord:
    """The observer's own model as the truth (engine ``"reduced"``): a test of the filter's consistency.

    The reduced model of ``truth_mech`` (the observer's default reduction) is integrated as the continuous
    equations it states, ``M_r(p) p'' + C_r(p) p' + K_r(p) p = G_r(p) u + f_r(p, p')``: RK4 sub-steps over each
    sample interval, at most ``h`` long (shorter where the spectrum needs them for stability: the observer's
    reference step's count, :meth:`~exuflex.observer.reduced.ReducedObserverModel.substeps`), every stage at its own
    state and under the drive's torque table held over each table step (the value in force at the sub-step's
    midpoint for all its stages: sub-steps of at most ``h``, the table's step, lie within one table step), the
    input of the other engines, so that what this
    truth measures is the reduced model alone (docs/gravity.md, "The reduced equations under gravity"). Not a step map frozen at the interval's start: its held matrices and forces are a first-order
    approximation of its own, which would put into the truth an error the filter's step does not share
    (``tests/test_truth_reduced.py`` compares the result with a fine RK4 of the same equations). Its states are
    mapped to the full ERLS state (``x = H p``, ``x' = J p'``), so that the sensors and true states come from the
    same functions as for the other engines. A filter with the same model and the stated noise has no model error
    on this truth but its own step's approximations: its NEES and NIS must be consistent
    (``benchmarks/observer_accuracy.py --engine reduced``).
    """
    from ..observer.reduced import ReducedObserverModel
    from ..observer.session import make_observer
    from ..sensors import erls_probe_record, sensor_channels, true_states

    rm = make_observer(truth_mech).model.rm
    som = ReducedObserverModel(rm, h=h, method="rk4")
    dt = 1.0 / truth_mech.sample_rate_hz
    n = int(round(duration / dt)) + 1
    t = np.arange(n) * dt
    t_tab, tau_tab = np.asarray(drive.t, float), np.asarray(drive.tau, float).reshape(len(drive.t), -1)
    dt_tab = t_tab[1] - t_tab[0]

    def table(s: float) -> np.ndarray:  # the table's value in force at s
        return tau_tab[min(int(np.floor((s - t_tab[0]) / dt_tab + 1e-6)), len(tau_tab) - 1)]

    z = som.initial_state(drive.q0, drive.qd0)
    Y = np.empty((n, 2 * rm.model.n))
    for k in range(n):
        x, v = rm.full_state(z)
        Y[k, : rm.model.n], Y[k, rm.model.n :] = x, v
        if k < n - 1:
            m = som.substeps_at(z, dt)
            hs = dt / m
            for i in range(m):
                f = table(t[k] + (i + 0.5) * hs)  # held over the sub-step (it lies within one table step)
                k1 = rm.rhs(0.0, z, f)
                k2 = rm.rhs(0.0, z + hs / 2 * k1, f)
                k3 = rm.rhs(0.0, z + hs / 2 * k2, f)
                k4 = rm.rhs(0.0, z + hs * k3, f)
                z = z + hs / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    rec = erls_probe_record(rm.model, t, Y)
    return TruthRecord(sensor_channels(truth_mech, rec), true_states(truth_mech, rec), t_tab, tau_tab,
                       {"plan_and_torque_s": drive.seconds})


def solver_failure(mech, drive, engine: str, h: float, exc: BaseException):
    """A :class:`~exuflex.errors.SimulationError` for a truth solver's failure, naming the input's likely cause:
    the fields of the model file (or the arguments) far outside what a flexible mechanism's solver is set up for,
    largest first: a payload many times the links' mass (``payload.mass``, ``--payload-scale``), gravity far
    above the earth's (``model.gravity``), a link far shorter than the others (``links.NAME.length``), a planned
    torque far above the motors' full scale (the manoeuvre against ``motors.NAME.full_scale``); else the step."""
    from ..errors import SimulationError

    src = mech.source or mech.name
    causes: list[tuple[float, str]] = []
    link_mass = sum(lk.length * lk.material.rho * lk.section.A for lk in mech.links)
    if mech.payload is not None and link_mass > 0 and mech.payload.mass > 100 * link_mass:
        r = mech.payload.mass / link_mass
        causes.append((r, f"payload.mass (times --payload-scale) = {mech.payload.mass:.3g} kg, {r:.3g} times the "
                          f"links' {link_mass:.3g} kg (expected a payload comparable to the links')"))
    g = float(np.hypot(*mech.gravity)) if mech.gravity else 0.0
    if g > 100 * 9.81:
        causes.append((g / 9.81, f"model.gravity = {list(mech.gravity)} m/s^2, {g / 9.81:.3g} g (expected about "
                                 "9.81 m/s^2 or none)"))
    lengths = [lk.length for lk in mech.links]
    short = min(mech.links, key=lambda lk: lk.length)
    if len(lengths) > 1 and short.length < 1e-2 * max(lengths):
        r = max(lengths) / short.length
        causes.append((r, f"links.{short.name}.length = {short.length:.3g} m, 1/{r:.3g} of the longest link (expected "
                          "links of comparable length, or a rigid joint in its place)"))
    tau = np.asarray(getattr(drive, "tau", np.empty((0, 0))), float)
    for j, m in enumerate(mech.motors):
        if m.full_scale and tau.ndim == 2 and tau.shape[1] > j and len(tau):
            peak = float(np.max(np.abs(tau[:, j])))
            if peak > 100 * m.full_scale:
                causes.append((peak / m.full_scale, f"the planned torque of {m.name} peaks at {peak:.3g} N m, "
                                                    f"{peak / m.full_scale:.3g} times motors.{m.name}.full_scale "
                                                    "(expected a manoeuvre the motors can drive)"))
    causes.sort(key=lambda c: -c[0])
    why = " ".join(str(exc).split())
    if causes:
        hint = "the likely cause is in the input: " + "; ".join(c for _, c in causes)
    else:
        hint = (f"no input far out of range was found: try a smaller step (--h, now {h:g} s) or the other engine "
                f"(--engine {'erls' if engine == 'exudyn' else 'exudyn'})")
    return SimulationError(f"{src}: the {engine} truth's solver failed ({why}); {hint}")


def simulate(truth_mech: Mechanism, drive: Drive, engine: str = "exudyn", duration: float | None = None,
             h: float = 1e-4, progress: Callable[[float], None] | None = None, *,
             elements_per_link: int | str | None = None, beam: str = "ancf",
             integrator: str = "gen-alpha", erls_step: float | str | None = None,
             messages: Callable[[str], None] | None = None) -> TruthRecord:
    """Simulate ``truth_mech`` under ``drive`` for ``duration`` s (default: its manoeuvre's) with the truth
    ``engine`` (one of :data:`ENGINES`), step ``h``, output at the model's sample rate; ``progress`` is called
    with the fraction done.

    ``elements_per_link``: the truth's mesh, ``None`` (Exudyn: :func:`exudyn_mesh` elements per link; ERLS: the
    model file's), a positive integer (no element longer than 1/N of its link) or ``"file"``; ``beam``: Exudyn's
    beam, a key of :data:`BEAMS`; ``integrator``: the ERLS engine's, one of :data:`INTEGRATORS`, ``erls_step`` its
    generalized-alpha step (:func:`gen_alpha_step`). The record's ``settings`` state them with the solver's
    statistics; ``messages`` receives one-line setup messages (the FFRF truth's meshing and modes)."""
    from ..sensors import monotonic_record, sensor_channels, true_states

    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if beam not in BEAMS:
        raise ValueError(f"beam must be one of {tuple(BEAMS)}, got {beam!r}")
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    if not (elements_per_link is None or elements_per_link == "file"
            or (isinstance(elements_per_link, int) and elements_per_link >= 1)):
        raise ValueError(f"elements_per_link must be a positive integer or 'file', got {elements_per_link!r}")
    if duration is None:
        if truth_mech.manoeuvre is None:
            raise ValueError(f"{truth_mech.source or truth_mech.name}: no [manoeuvre]; give a duration")
        duration = truth_mech.manoeuvre.duration
    timings = {"plan_and_torque_s": drive.seconds}
    output_dt = 1.0 / truth_mech.sample_rate_hz
    t0, c0 = time.perf_counter(), time.process_time()
    if engine == "reduced":
        rec = reduced_truth(truth_mech, drive, duration, h)
        rec.timings.update(timings, truth_s=time.perf_counter() - t0, truth_cpu_s=time.process_time() - c0)
        rec.settings = {"engine": "reduced", "integrator": "the observer's reduced model, RK4 of its equations "
                        "(every stage at its own state), under the torque table"}
        return rec
    solver: dict = {}
    if engine == "exudyn" and BEAMS[beam] == "ffrf":
        from ..groundtruth import simulate_ffrf  # Exudyn, netgen and ngsolve are imported only there

        if elements_per_link not in (None, "file"):
            raise ValueError("elements_per_link: the FFRF truth meshes solids (mesh_size in the model file); "
                             f"expected none, got {elements_per_link!r}")
        probes = simulate_ffrf(truth_mech, drive.t, drive.tau, duration, h=h, output_dt=output_dt, q0=drive.q0,
                               progress=progress, messages=messages or log.info, stats=solver)
        settings = {"engine": "exudyn", "beam": beam, "formulation": "ffrf", "integrator": "generalized-alpha (Exudyn)",
                    **solver}
    elif engine == "exudyn":
        from ..groundtruth import simulate_truth  # Exudyn is imported only there

        mesh = exudyn_mesh(truth_mech) if elements_per_link is None else elements_per_link
        step, stepping = exudyn_step(truth_mech, h, output_dt, duration, drive.q0, mesh, BEAMS[beam])
        try:
            probes = simulate_truth(truth_mech, drive.t, drive.tau, duration, h=step, output_dt=output_dt, q0=drive.q0,
                                    progress=progress, elements_per_link=mesh, formulation=BEAMS[beam], stats=solver)
        except RuntimeError as exc:
            raise solver_failure(truth_mech, drive, "exudyn", h, exc) from exc
        settings = {
            "engine": "exudyn",
            "beam": beam,
            "formulation": BEAMS[beam],
            "elements_per_link": mesh,
            "hub_inertia": "rigid body welded to the node" if beam == "ancf" else "node rotation coordinate",
            "integrator": "generalized-alpha (Exudyn)",
            "n_coordinates": solver.get("n_coordinates"),
            "newton_per_step": solver.get("newton_per_step"),
            **stepping,
        }
    else:
        from ..erls.implicit import GeneralizedAlpha, algorithmic_damping
        from ..mechanism import remesh_mechanism

        mech = truth_mech
        if elements_per_link not in (None, "file"):
            mech = remesh_mechanism(truth_mech, elements_per_link)
        try:
            probes = erls_truth(mech, drive.t, drive.tau, duration, h, output_dt, drive.q0, drive.qd0, progress,
                                integrator=integrator, stats=solver, step=erls_step)
        except (RuntimeError, FloatingPointError, np.linalg.LinAlgError) as exc:
            raise solver_failure(truth_mech, drive, "erls", h, exc) from exc
        settings = {
            "engine": "erls",
            "elements_per_link": "file" if elements_per_link is None else elements_per_link,
            "n_elements": sum(lk.n_elements for lk in mech.links),
            "integrator": integrator,
            **({"rho_inf": GeneralizedAlpha().rho_inf, "band_hz": mech.reduction.band_hz,
                "freq_error_at_band": float(algorithmic_damping(
                    2 * np.pi * mech.reduction.band_hz * solver["step_s"], GeneralizedAlpha().rho_inf)[1][0])}
               if integrator == "gen-alpha" else {}),
            **solver,
        }
    timings["truth_s"] = time.perf_counter() - t0
    timings["truth_cpu_s"] = time.process_time() - c0
    probes = monotonic_record(probes)
    return TruthRecord(sensor_channels(truth_mech, probes), true_states(truth_mech, probes), drive.t, drive.tau,
                       timings, settings)

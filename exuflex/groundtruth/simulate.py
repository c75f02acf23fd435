"""Simulate the Exudyn ground truth under tabulated motor torques and record the probes."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from ..mechanism import Mechanism
from ..probes import Probe, ProbeRecord, probes_for
from .builder import TruthModel, _exu, ancf_shape, build_truth

__all__ = ["probe_values", "simulate_truth", "smooth_torque_table", "step_end_torques", "time_truth"]

log = logging.getLogger(__name__)


def step_grid(h: float, duration: float, output_dt: float | None) -> tuple[int, int]:
    """The fixed steps of a truth run: ``n_steps`` of ``h`` over ``duration``, and a record every ``every`` steps
    (``output_dt``, every step when None). ValueError unless both are whole multiples of ``h``."""
    if h <= 0 or duration <= 0:
        raise ValueError(f"h and duration must be positive, got h={h}, duration={duration}")
    n_steps = round(duration / h)
    if abs(n_steps * h - duration) > 1e-9 * max(1.0, duration):
        raise ValueError(f"duration {duration} s is not a multiple of the step h = {h} s")
    every = 1 if output_dt is None else round(output_dt / h)
    if every < 1 or (output_dt is not None and abs(every * h - output_dt) > 1e-9):
        raise ValueError(f"output_dt {output_dt} s must be a positive multiple of the step h = {h} s")
    return n_steps, every


def implicit_settings(exu, n_steps: int, duration: float, newton_tol: float, spectral_radius: float):
    """Exudyn's settings for a truth run: generalised-alpha with ``n_steps`` fixed steps over ``duration`` (no
    adaptive step: a reduced step would leave the grid of the torque table and the record), the given Newton
    tolerance and spectral radius, a sparse solver, and no files, sensors or statistics written."""
    ss = exu.SimulationSettings()
    ti = ss.timeIntegration
    ti.numberOfSteps = n_steps
    ti.endTime = duration
    ti.verboseMode = 0
    ti.newton.absoluteTolerance = newton_tol
    ti.adaptiveStep = False
    ti.generalizedAlpha.spectralRadius = spectral_radius
    ti.generalizedAlpha.computeInitialAccelerations = True
    ss.linearSolver.solverType = exu.LinearSolverType.EigenSparse
    ss.solution.file.write = False
    ss.solution.sensors.active = False
    ss.show.statistics = False
    ss.show.computationTime = False
    return ss


def smooth_torque_table(
    mech: Mechanism,
    duration: float,
    amplitudes: Sequence[float] | None = None,
    period: float = 0.5,
    dt: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray]:
    """A smooth test excitation: full-sine torque pulses ``A_j sin(2 pi t / period)`` of alternating sign.

    Each pulse accelerates and brakes; alternating signs keep the mechanism near its start
    configuration. Default amplitudes: 1 N m per motor (0.01 N m for a motor with a reaction link).

    Returns
    -------
    t (n_t,), torques (n_t, n_motors)
    """
    if amplitudes is None:
        amplitudes = [0.01 if m.reaction is not None else 1.0 for m in mech.motors]
    amplitudes = np.asarray(amplitudes, float)
    if amplitudes.shape != (len(mech.motors),):
        raise ValueError(
            f"amplitudes must have one entry per motor {list(mech.motor_names)}, got {amplitudes.shape}"
        )
    t = np.arange(0.0, duration + dt / 2, dt)
    k = np.floor(t / period)
    sign = np.where(k % 2 == 0, 1.0, -1.0)
    base = sign * np.sin(2 * np.pi * t / period)
    return t, amplitudes[None, :] * base[:, None]


def _interp_table(t_table, torque_table, t_query, n_motors):
    t_table = np.asarray(t_table, float)
    tau = np.asarray(torque_table, float)
    if tau.ndim == 1:
        tau = tau[:, None]
    if t_table.ndim != 1 or tau.shape != (len(t_table), n_motors):
        raise ValueError(
            f"torque table must be (n_t, {n_motors}) with one column per motor and t_table (n_t,), "
            f"got {tau.shape} and {t_table.shape}"
        )
    if np.any(np.diff(t_table) <= 0):
        raise ValueError("t_table must be strictly increasing")
    return np.column_stack([np.interp(t_query, t_table, tau[:, j]) for j in range(n_motors)])


def step_end_torques(t_table, torque_table, h: float, n_steps: int, every: int, n_motors: int) -> np.ndarray:
    """``(n_steps, n_motors)``: the torque generalized-alpha balances at the end ``t_k+1`` of each step ``k`` under
    the zero-order hold of the table, a record every ``every`` steps: the ERLS engine's
    (:meth:`exuflex.erls.implicit.HeldTable.step_ends`: the hold's mean over ``[t_k+1 - h/2, t_k+1 + h/2]``, the half
    before a recorded instant there and the rest at the next step end)."""
    if not n_motors:
        return np.zeros((n_steps, 0))
    from ..erls.implicit import HeldTable

    _interp_table(t_table, torque_table, t_table, n_motors)  # the table's shape and order, checked
    tab = HeldTable(t_table, np.asarray(torque_table, float).reshape(len(t_table), n_motors))
    return tab.step_ends(h, n_steps, every)[1:]


def _probe_geometry(tm: TruthModel, probe: Probe):
    """(element locations, coordinate indices) needed for a probe."""
    lm = tm.links[probe.link]
    locs = lm.locate(probe.station)
    if probe.kind != "curvature":
        locs = locs[:1]  # position and slope are continuous across nodes
    return [(e, xi, lm.stations[e + 1] - lm.stations[e], lm.ode2[e : e + 2].ravel()) for e, xi in locs]


def probe_values(
    tm: TruthModel, probe: Probe, c: np.ndarray, cd: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Probe values and rates (n_t, width) from total coordinates and their rates (n_t, n_coords).

    Slopes are wrapped to (-pi, pi] here; :func:`simulate_truth` unwraps them in time.
    """
    locs = _probe_geometry(tm, probe)
    vals, rates = [], []
    for _e, xi, L, idx in locs:
        ce, cde = c[:, idx], cd[:, idx]
        if tm.formulation == "ancf":
            ce = ce.reshape(-1, 4, 2)
            cde = cde.reshape(-1, 4, 2)
            S0, S1, S2 = (ancf_shape(xi, L, d) for d in (0, 1, 2))
            r, rd = S0 @ ce, S0 @ cde
            rp, rpd = S1 @ ce, S1 @ cde
            rpp, rppd = S2 @ ce, S2 @ cde
            n2 = np.einsum("ti,ti->t", rp, rp)
            cross = rp[:, 0] * rpp[:, 1] - rp[:, 1] * rpp[:, 0]
            if probe.kind == "point":
                vals.append(r)
                rates.append(rd)
            elif probe.kind == "slope":
                vals.append(np.arctan2(rp[:, 1], rp[:, 0])[:, None])
                rates.append(((rp[:, 0] * rpd[:, 1] - rp[:, 1] * rpd[:, 0]) / n2)[:, None])
            else:  # geometric curvature of the deformed axis, d(slope)/d(arc length)
                n3 = n2**1.5
                crossd = (
                    rpd[:, 0] * rpp[:, 1]
                    - rpd[:, 1] * rpp[:, 0]
                    + rp[:, 0] * rppd[:, 1]
                    - rp[:, 1] * rppd[:, 0]
                )
                n2d = 2 * np.einsum("ti,ti->t", rp, rpd)
                vals.append((cross / n3)[:, None])
                rates.append((crossd / n3 - 1.5 * cross * n2d / (n2 * n3))[:, None])
        else:
            ce = ce.reshape(-1, 2, 3)
            cde = cde.reshape(-1, 2, 3)
            w = np.array([1 - xi, xi])
            if probe.kind == "point":
                vals.append(w @ ce[:, :, :2])
                rates.append(w @ cde[:, :, :2])
            elif probe.kind == "slope":
                vals.append((ce[:, :, 2] @ w)[:, None])
                rates.append((cde[:, :, 2] @ w)[:, None])
            else:
                vals.append(((ce[:, 1, 2] - ce[:, 0, 2]) / L)[:, None])
                rates.append(((cde[:, 1, 2] - cde[:, 0, 2]) / L)[:, None])
    return np.mean(vals, axis=0), np.mean(rates, axis=0)


class DamperSchedule:
    """When to refresh a configuration-dependent alpha damper during a simulation, and at which configuration.

    Between refreshes a link turned by ``delta`` from the damper's configuration is braked at the relative rate
    ``alpha delta^2`` (:mod:`.builder`). The damper is evaluated at the configuration extrapolated to the middle of
    the coming interval ``dt`` (``c + c' dt / 2``), so ``delta`` runs over ``omega dt [-1/2, 1/2]`` with ``omega``
    the links' fastest rotation rate at the refresh, and ``dt`` is the longest interval (at most ``longest`` s)
    with the mean braking rate ``alpha (omega dt)^2 / 12 <= tol``. ``tol = None``: every ``longest`` s, at the
    refresh's configuration."""

    def __init__(self, alpha: float, h: float, longest: float, tol: float | None):
        if tol is not None and not tol > 0:
            raise ValueError(f"damping_tol must be positive or None, got {tol}")
        self.h, self.tol = h, tol
        self.every = max(1, round(longest / h))
        # longest rotation omega dt (rad) of a link over one refresh interval
        self.omega_dt_max = math.sqrt(12.0 * tol / alpha) if tol is not None and alpha > 0 else math.inf
        self.next = 0

    def due(self, k: int) -> bool:
        """Whether step ``k`` refreshes the damper."""
        return k >= self.next

    def plan(self, k: int, c: np.ndarray, cd: np.ndarray, rotation_rate: Callable) -> np.ndarray:
        """Schedule the refresh after the one at step ``k`` (coordinates ``c``, rates ``cd``) and return the
        configuration to evaluate the damper at; ``rotation_rate(c, cd)`` gives the links' fastest rate."""
        steps = self.every
        if self.tol is not None:
            omega_h = rotation_rate(c, cd) * self.h  # rotation per step
            if omega_h * self.every > self.omega_dt_max:
                steps = max(1, int(self.omega_dt_max / omega_h))
            c = c + (0.5 * steps * self.h) * cd
        self.next = k + steps
        return c


def simulate_truth(
    mech: Mechanism,
    t_table,
    torque_table,
    duration: float,
    h: float = 1e-4,
    output_dt: float | None = 1 / 500,
    q0=None,
    elements_per_link: int | None = 4,
    formulation: str = "ancf",
    probes: Sequence[Probe] | None = None,
    progress: Callable[[float], None] | None = None,
    damping: str | None = "rayleigh",
    damping_update: float = 0.02,
    damping_tol: float | None = 1e-5,
    newton_tol: float = 1e-4,
    spectral_radius: float = 0.9,
    solver_settings: dict | None = None,
    stats: dict | None = None,
    reduced_integration: bool = True,
    hub: str = "rigid",
) -> ProbeRecord:
    """Simulate the Exudyn model of ``mech`` from rest at ``q0`` under tabulated motor torques.

    Parameters
    ----------
    mech : Mechanism
    t_table : (n_t,) increasing times (s); torque_table : (n_t, n_motors) torques (N m), motors in
        ``mech.motors`` order, linearly interpolated at the step times ``t_k = k h`` (held constant
        outside the table) and held over each step ``[t_k, t_k+1]`` (zero-order hold, as the ERLS engine).
    duration : simulated time (s).
    h : time step of the implicit generalized-alpha integrator (s); 1e-4 resolves the 0-200 Hz band.
    output_dt : recording interval (s, a multiple of ``h``); ``None`` records every step.
    q0 : initial ERLS coordinates (default ``mech.q_ref``); the mechanism starts at rest, undeformed.
    elements_per_link, formulation, damping, hub : see :func:`exuflex.groundtruth.build_truth`.
    probes : default :func:`exuflex.probes.probes_for` ``(mech)``.
    progress : called with the fraction done (0..1) about 100 times.
    damping_update : longest refresh interval (s) of the configuration-dependent alpha damper.
    damping_tol : tolerance (1/s) on the stale damper's braking of the rigid motion. Between refreshes a link
        turned by ``delta`` from the damper's configuration is braked at the relative rate ``alpha delta^2``
        (see :mod:`.builder`). The damper is evaluated at the configuration extrapolated to the middle of
        the coming interval ``dt`` (``c + c' dt / 2``), so ``delta`` runs over ``omega dt [-1/2, 1/2]`` with
        ``omega`` the links' fastest rotation rate at the refresh, and ``dt`` is the longest interval (at most
        ``damping_update``) with the mean braking rate ``alpha (omega dt)^2 / 12 <= damping_tol``. The rigid
        velocities then lose about the fraction ``damping_tol`` per second, and the coordinates drift by about
        ``damping_tol T Q`` in ``T`` s, ``Q`` the angle the links travel (``tests/test_groundtruth.py`` checks it
        against a damper refreshed at every step). ``None``: every ``damping_update`` s,
        at the refresh's configuration.
    newton_tol : absolute Newton tolerance (residual in N); Exudyn's default 1e-10 stalls on round-off.
    spectral_radius : generalized-alpha numerical damping at infinite frequency.
    solver_settings : further Exudyn ``SimulationSettings`` by dotted path, e.g.
        ``{"timeIntegration.newton.useModifiedNewton": True}``.
    reduced_integration : ANCF reduced Gauss order (see :func:`exuflex.groundtruth.build_truth`).
    stats : if a dict, filled with the solver's statistics (Newton iterations and Jacobians per step,
        wall and CPU time of the solve, time spent in the pre-step function).

    Returns
    -------
    ProbeRecord
        ``values[key]`` and ``rates[key]`` (n_t, width) for every probe; slopes unwrapped in time and on
        the branch of the ERLS pose at ``q0``.

    Notes
    -----
    Torques are set once per step by a pre-step user function, so the C++ solver runs without Python
    calls inside Newton iterations. The function is the one Python call per step, so it is kept
    lean: the signed torque rows of every step are tabulated before the solve, the few loaded slopes
    are done in Python floats (the same IEEE arithmetic as :meth:`TruthModel.generalized_forces`),
    the damper is one mat-vec ``-D c'`` and the configuration-dependent ``D`` is rebuilt only every
    ``damping_update`` s (paper's 3 s manoeuvre at h = 1e-4 s: about 1/4 of the run; the
    rest is Exudyn, mostly the beams' forces, at 2.7 Newton iterations per step). Exudyn calls it with the step's *end* time ``t_k+1`` while the
    state is still the one at ``t_k``; the function records that state at ``t_k`` (so the record
    starts at ``t = 0`` and holds every ``output_dt``, the final state is recorded after the solve)
    sets the torque for the step.

    Torque timing: the ERLS engine (:func:`exuflex.erls.simulate.simulate`, RK4) holds the table
    value ``tau_k`` at the step's start over ``[t_k, t_k+1]`` (zero-order hold). Generalized-alpha
    balances forces at the step ends and, through its acceleration variable, acts as if the force
    were linear between them. Setting ``tau_k`` at the end ``t_k+1`` would therefore lag the ERLS
    hold by h/2 (and ``tau_k+1`` lead it by h/2): on the paper's 3 s open-loop manoeuvre either
    makes q drift 1.2-1.3e-3 rad from the ERLS engine. The force at ``t_k+1`` is the mean
    ``(tau_k + tau_k+1) / 2`` of the held values either side: its linear interpolation has the
    hold's impulse over every step and no lag (drift 4.5e-5 rad). A torque switched on at ``t_k``
    thus ramps over ``[t_k-1, t_k+1]``, centred on ``t_k``. A step finer than the table's takes the hold's mean
    over ``[t_k+1 - h/2, t_k+1 + h/2]`` (the same for a step equal to it), as the ERLS engine does
    (:func:`exuflex.erls.implicit.erls_implicit`). At a recorded instant the mean is over the half step before
    it and the next step end takes the rest of the impulse (:func:`step_end_torques`): a record depends on the
    torques before its instant alone, as the sampled model has it. The same function refreshes the damper.
    """
    exu, _ = _exu()
    n_steps, every = step_grid(h, duration, output_dt)
    probes = tuple(probes_for(mech) if probes is None else probes)
    tm = build_truth(
        mech,
        q0,
        elements_per_link=elements_per_link,
        formulation=formulation,
        damping=damping,
        reduced_integration=reduced_integration,
        hub=hub,
    )
    mbs = tm.mbs
    nm = len(mech.motors)
    t_steps = np.arange(n_steps + 1) * h
    tau = _interp_table(t_table, torque_table, t_steps, nm) if nm else np.zeros((n_steps + 1, 0))
    tau_end = step_end_torques(t_table, torque_table, h, n_steps, every, nm)  # at the end t_k+1 of step k (Notes)

    # coordinates needed by the probes (and all, if the damper needs q)
    need = sorted({int(i) for p in probes for (_, _, _, idx) in _probe_geometry(tm, p) for i in idx})
    need = np.array(need, dtype=int)
    ref = np.asarray(mbs.systemData.GetODE2Coordinates(exu.ConfigurationType.Reference))
    n_out = n_steps // every + 1
    C = np.empty((n_out, len(need)))
    Cd = np.empty((n_out, len(need)))
    T_out = np.empty(n_out)
    sd = mbs.systemData
    cur = exu.ConfigurationType.Current
    schedule = DamperSchedule(tm.alpha, h, damping_update, damping_tol)
    rep_every = max(1, n_steps // 100)
    state = {"i": 0}

    forces = tm.forces
    damped = tm.explicit_damping and tm.D_alpha is not None

    def record(t, u, cd):
        # u: displacement coordinates (total minus reference)
        i = state["i"]
        if i < n_out:
            C[i] = u[need]
            Cd[i] = cd[need]
            T_out[i] = t
            state["i"] = i + 1

    # motor torque rows: per loaded node, the signed torque of every step (fixed before the solve)
    ix, iy, sgn, jm = tm.motor_map()
    neg_T = -(sgn[None, :] * tau_end[:, jm]) if nm else np.zeros((n_steps, 0))
    ancf = tm.formulation == "ancf"
    # ANCF: slopes (x', y') of every loaded node, read and loaded in one fancy-index operation each;
    # the few rows are done in Python floats (IEEE arithmetic, the same results as numpy's)
    ixy = np.concatenate([ix, iy]) if ancf else ix
    fast = len(np.unique(ixy)) == len(ixy)
    # per loaded node: (row, index of x', index of y', reference x', reference y') as Python scalars
    rows = list(zip(range(len(ix)), ix.tolist(), iy.tolist(), ref[ix].tolist(), ref[iy].tolist()))
    n_c = len(ref)
    neg_D = [-tm.D_alpha if damped else None]
    inv_h = 1.0 / h
    pre_time = [0.0]
    f = np.zeros(n_c)  # the generalized force, rewritten every step (Exudyn copies it)
    f_links = f  # the force object spans all coordinates (links', then the hub bodies')
    f_items = memoryview(f)  # its entries as Python floats, without NumPy's per-element cost
    torques = neg_T.tolist()  # per step, the signed torques as Python floats

    def pre_step_timed(mbs_, t):
        c0 = time.perf_counter()
        out = pre_step(mbs_, t)
        pre_time[0] += time.perf_counter() - c0
        return out

    def pre_step(mbs_, t):
        # Exudyn passes the step's END time t_k+1 (verified on 1.13.6); the current state is the one at t_k
        k = int(t * inv_h + 0.5) - 1
        if abs(t - (k + 1) * h) > 1e-6 * h:
            raise RuntimeError(f"Exudyn left the step grid (t = {t!r}, h = {h!r})")
        u = sd.GetODE2Coordinates(cur)
        cd = sd.GetODE2Coordinates_t(cur)
        if k % every == 0:
            record(k * h, u, cd)
        if damped:
            if schedule.due(k):
                c_now = np.asarray(u) + ref
                tm.update_dampers(schedule.plan(k, c_now, np.asarray(cd), tm.rotation_rate))
                neg_D[0] = -tm.D_alpha
            np.dot(neg_D[0], cd, out=f)  # explicit alpha damper -D c' with the rates at t_k
        else:
            f.fill(0.0)
        # the ERLS engine's zero-order hold of tau[k] over [t_k, t_k+1], as generalized-alpha sees it
        # (forces at step ends, linear in between): the mean of the held values either side of t_k+1.
        # Same arithmetic as TruthModel.generalized_forces (T d(atan2(y', x'))/d(x', y') at t_k).
        if fast and ancf:
            mT = torques[k]
            item = u.item
            for i, a, b, ra, rb in rows:
                rx = item(a) + ra
                ry = item(b) + rb
                n2 = rx * rx + ry * ry
                f_items[a] += mT[i] * ry / n2
                f_items[b] += -mT[i] * rx / n2
        elif ancf:
            rx = u[ix] + ref[ix]
            ry = u[iy] + ref[iy]
            n2 = rx * rx + ry * ry
            np.add.at(f, ix, neg_T[k] * ry / n2)
            np.add.at(f, iy, -neg_T[k] * rx / n2)
        else:
            np.add.at(f, ix, -neg_T[k])
        mbs_.SetObjectParameter(forces, "forceVector", f_links)
        if progress is not None and k % rep_every == 0:
            progress(k / n_steps)
        return True

    ss = implicit_settings(exu, n_steps, duration, newton_tol, spectral_radius)
    for path, value in (solver_settings or {}).items():
        obj = ss
        *parents, leaf = path.split(".")
        for name in parents:
            obj = getattr(obj, name)
        if not hasattr(obj, leaf):
            raise ValueError(f"Exudyn SimulationSettings has no {path!r}")
        setattr(obj, leaf, value)
    tm.set_torques(tau[0])
    mbs.SetPreStepUserFunction(pre_step if stats is None else pre_step_timed)
    t0 = time.perf_counter()
    c0 = time.process_time()
    solver = exu.MainSolverImplicitSecondOrder()
    ok = solver.SolveSystem(mbs, ss)
    wall = time.perf_counter() - t0
    it = solver.it
    log.debug("Newton iterations %d, Jacobians %d", it.newtonStepsCount, it.newtonJacobiCount)
    if stats is not None:
        stats.update(
            wall_s=wall,
            cpu_s=time.process_time() - c0,
            pre_step_s=pre_time[0],
            newton_per_step=it.newtonStepsCount / n_steps,
            jacobians_per_step=it.newtonJacobiCount / n_steps,
            n_steps=n_steps,
            n_coordinates=len(ref),
        )
    if not ok:
        raise RuntimeError(
            f"Exudyn dynamic solver failed before t = {duration} s (see Exudyn's messages); a Newton tolerance "
            f"({newton_tol:g} N) far below the round-off of the axial forces stalls Newton, try 1e-4"
        )
    if n_steps % every == 0:
        record(n_steps * h, tm.coordinates() - ref, tm.velocities())
    if progress is not None:
        progress(1.0)
    n = state["i"]
    log.info(
        "Exudyn truth %s: %.3g s simulated in %.3g s wall (h = %g s, %d outputs)",
        mech.name,
        duration,
        wall,
        h,
        n,
    )

    c_full = np.zeros((n, len(ref)))
    cd_full = np.zeros((n, len(ref)))
    c_full[:, need] = C[:n] + ref[need]  # (C holds displacements)
    cd_full[:, need] = Cd[:n]
    rec = ProbeRecord(T_out[:n].copy())
    q_start = np.asarray(mech.q_ref if q0 is None else q0, float)
    from ..erls.kinematics import Kinematics

    pose = Kinematics(mech).pose(q_start)
    link_angle = {lk.name: pose.z[3 * i + 2] for i, lk in enumerate(mech.links)}
    for p in probes:
        v, r = probe_values(tm, p, c_full, cd_full)
        if p.kind == "slope":
            v = np.unwrap(v, axis=0)
            v += 2 * np.pi * np.round((link_angle[p.link] - v[0]) / (2 * np.pi))
        rec.values[p.key] = v
        rec.rates[p.key] = r
    return rec


def time_truth(
    mech: Mechanism,
    duration: float = 3.0,
    h: float = 1e-4,
    t_table=None,
    torque_table=None,
    q0=None,
    torques: str = "auto",
    **kwargs,
) -> float:
    """Wall time (s) of one ground-truth simulation of ``duration`` s (planning time excluded).

    Parameters
    ----------
    torques : "auto", "manoeuvre" or "smooth"
        Unless a table is given: the rigid computed torques of the mechanism's manoeuvre
        (:mod:`exuflex.manoeuvre`; "auto" uses them when the model has a manoeuvre) or
        :func:`smooth_torque_table`.
    **kwargs : passed to :func:`simulate_truth`.
    """
    if t_table is None or torque_table is None:
        if torques not in ("auto", "manoeuvre", "smooth"):
            raise ValueError(f"torques must be 'auto', 'manoeuvre' or 'smooth', got {torques!r}")
        if torques == "manoeuvre" or (torques == "auto" and mech.manoeuvre is not None):
            from ..manoeuvre import open_loop_torque, plan

            p = plan(mech, dt=1e-3, t_end=duration)
            t_table, torque_table = p.t, open_loop_torque(mech, p)
            q0 = p.q[0] if q0 is None else q0
        else:
            t_table, torque_table = smooth_torque_table(mech, duration)
    t0 = time.perf_counter()
    simulate_truth(mech, t_table, torque_table, duration, h=h, q0=q0, **kwargs)
    return time.perf_counter() - t0

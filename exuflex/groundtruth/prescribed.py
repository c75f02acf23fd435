"""The Exudyn ground truth under a prescribed motion of the ERLS coordinates (rheonomic drive).

For benchmarks in which the base motion is given rather than the motor torques, such as Kane, Ryan and
Banerjee's spin-up of a cantilever on a hub: every ERLS coordinate must be the absolute angle of its link at a
grounded joint (the link's tangent there is driven to ``q(t) + offset``; the joint's revolute pin holds the
position). The drive is a constraint on the driven node's rotation, set once per step for the step's end time:

- ``formulation="ancf"``: the slope ``r'`` stays parallel to ``(cos theta, sin theta)``,
  ``-sin(theta) x' + cos(theta) y' = 0`` (``ObjectConnectorCoordinateVector``, a linear constraint whose
  coefficients are rewritten every step); the slope's length, the axial strain at the hub, stays free;
- ``formulation="gebeam"``: the node's rotation coordinate equals ``theta`` (the same object, one coefficient).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

import numpy as np

from ..mechanism import Mechanism
from ..probes import Probe, ProbeRecord
from .builder import _exu, build_truth
from .simulate import implicit_settings, probe_values, step_grid

__all__ = ["simulate_prescribed"]

log = logging.getLogger(__name__)


def simulate_prescribed(
    mech: Mechanism,
    motion: Callable[[float], np.ndarray],
    duration: float,
    probes: Sequence[Probe],
    h: float = 1e-3,
    output_dt: float | None = None,
    elements_per_link: int | None = 4,
    formulation: str = "ancf",
    damping: str | None = None,
    newton_tol: float = 1e-5,
    spectral_radius: float = 0.9,
    stats: dict | None = None,
) -> ProbeRecord:
    """Simulate the Exudyn model of ``mech`` from rest, undeformed, at ``motion(0)`` with its coordinates following
    ``motion(t)`` (rad, one per ERLS coordinate).

    Parameters
    ----------
    motion : ``t -> q(t)``; should start at rest (the model starts at rest).
    probes : the probes to record (:class:`exuflex.probes.Probe`).
    h : time step of the implicit generalized-alpha integrator (s).
    output_dt : recording interval (s, a multiple of ``h``); ``None`` records every step.
    elements_per_link, formulation, damping : see :func:`exuflex.groundtruth.build_truth`.
    newton_tol : absolute Newton tolerance (residual in N).
    stats : if a dict, filled with the wall time and the largest drive error (rad) at the recorded times.

    Returns
    -------
    ProbeRecord
        ``values[key]``, ``rates[key]`` per probe (slopes wrapped to (-pi, pi]).
    """
    exu, it = _exu()
    n_steps, every = step_grid(h, duration, output_dt)
    q0 = np.asarray(motion(0.0), float)
    if q0.shape != (len(mech.coordinates),):
        raise ValueError(f"motion(t) must return one angle per coordinate {list(mech.coordinate_names)}, "
                         f"got shape {q0.shape}")
    tm = build_truth(mech, q0, elements_per_link=elements_per_link, formulation=formulation, damping=damping)
    mbs = tm.mbs
    ancf = tm.formulation == "ancf"
    ground = mbs.AddNode(it.NodePointGround(referenceCoordinates=[0.0, 0.0, 0.0]))
    m_ground = mbs.AddMarker(it.MarkerNodeCoordinates(nodeNumber=ground))
    drives = []  # (constraint, ODE2 indices of the node, coordinate index, offset)
    for j, co in enumerate(mech.coordinates):
        jt = mech.joint(co.joint)
        if jt.ground is None or co.relative_to is not None:
            raise ValueError(f"simulate_prescribed: coordinate {co.name!r} must be an absolute angle at a grounded "
                             f"joint (joint {co.joint!r})")
        st = next(p.station for p in jt.points if p.link == co.link)
        lm = tm.links[co.link]
        k = lm.node_at(st, mech.link(co.link).length)
        marker = mbs.AddMarker(it.MarkerNodeCoordinates(nodeNumber=lm.nodes[k]))
        obj = mbs.AddObject(it.ObjectConnectorCoordinateVector(
            markerNumbers=[marker, m_ground], scalingMarker0=np.zeros((1, tm.node_size)),
            scalingMarker1=np.zeros((1, 0)), offset=[0.0]))
        drives.append((obj, lm.ode2[k], j, co.offset))
    mbs.Assemble()
    ref = np.asarray(mbs.systemData.GetODE2Coordinates(exu.ConfigurationType.Reference))

    def set_drive(t: float) -> None:
        q = np.asarray(motion(t), float)
        for obj, idx, j, off in drives:
            th = q[j] + off
            # Exudyn's constraint reads scalingMarker0 c + offset = 0, c the node's total coordinates
            if ancf:  # n . r' = 0, n normal to the driven direction
                row = np.zeros((1, 4))
                row[0, 2], row[0, 3] = -np.sin(th), np.cos(th)
                offset = 0.0
            else:  # rotation = theta
                row = np.zeros((1, 3))
                row[0, 2] = 1.0
                offset = -float(th)
            mbs.SetObjectParameter(obj, "scalingMarker0", row)
            mbs.SetObjectParameter(obj, "offset", [offset])

    sd = mbs.systemData
    cur = exu.ConfigurationType.Current
    n_out = n_steps // every + 1
    C = np.empty((n_out, len(ref)))
    Cd = np.empty((n_out, len(ref)))
    T_out = np.empty(n_out)
    state = {"i": 0}

    def record(t, c, cd):
        i = state["i"]
        if i < n_out:
            C[i], Cd[i], T_out[i] = c, cd, t
            state["i"] = i + 1

    def pre_step(mbs_, t):
        # Exudyn passes the step's end time t_k+1; the state is still the one at t_k
        k = int(t / h + 0.5) - 1
        if k % every == 0:
            record(k * h, sd.GetODE2Coordinates(cur), sd.GetODE2Coordinates_t(cur))
        set_drive(t)
        return True

    ss = implicit_settings(exu, n_steps, duration, newton_tol, spectral_radius)
    set_drive(0.0)
    mbs.SetPreStepUserFunction(pre_step)
    t0 = time.perf_counter()
    solver = exu.MainSolverImplicitSecondOrder()
    if not solver.SolveSystem(mbs, ss):
        raise RuntimeError(f"Exudyn dynamic solver failed before t = {duration} s (prescribed motion)")
    if n_steps % every == 0:
        record(n_steps * h, sd.GetODE2Coordinates(cur), sd.GetODE2Coordinates_t(cur))
    n = state["i"]
    c_full, cd_full = C[:n] + ref, Cd[:n]
    rec = ProbeRecord(T_out[:n].copy())
    for p in probes:
        rec.values[p.key], rec.rates[p.key] = probe_values(tm, p, c_full, cd_full)
    if stats is not None:
        err = 0.0
        for _obj, idx, j, off in drives:
            slope = (np.arctan2(c_full[:, idx[3]], c_full[:, idx[2]]) if ancf else c_full[:, idx[2]])
            want = np.array([motion(t)[j] + off for t in rec.t])
            err = max(err, float(np.abs((slope - want + np.pi) % (2 * np.pi) - np.pi).max()))
        stats.update(wall_s=time.perf_counter() - t0, drive_error_rad=err, n_coordinates=len(ref))
    log.info("Exudyn prescribed motion %s (%s): %.3g s simulated", mech.name, formulation, duration)
    return rec

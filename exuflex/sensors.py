"""Sensor channels and true states from a :class:`~exuflex.probes.ProbeRecord`, identical for every engine.

An engine (the ERLS full model, the Exudyn ground truth, a lab rig) records the probes of
:func:`exuflex.probes.probes_for`; this module turns them into

- the *clean sensor channels* of the mechanism's sensors (:func:`sensor_channels`):
  ``encoder`` = slope of the link at the joint (absolute) or slope(link) - slope(relative_to) (relative),
  ``slider`` = ``axis . (point - ground)`` of the prismatic joint's node,
  ``curvature`` = curvature probe, ``tip_x`` / ``tip_y`` = components of the point probe.
  Motor torques are inputs and are handled separately (:mod:`exuflex.measure`);
- the *true states* an observer is judged against (:func:`true_states`):
  ``q_j = slope(link at joint) - slope(relative_to at joint) - offset`` (a slide coordinate:
  ``axis . (point - ground) - offset``) and its rate ``dq_j``;
  the tip elastic displacement ``e = p_tip - p_rigid(q)``, the actual tip position minus the ERLS
  (rigid) tip position at the true ``q``, and its rate ``e' = p_tip' - (dp_rigid/dq) q'``;
- the *absolute tip* position and velocity of true or estimated states (:func:`absolute_tip`):
  ``p_rigid(q) + e`` and ``(dp_rigid/dq) q' + e'``, the inverse of the split above.

Both are returned as :class:`Signals` (time-first table with named columns and units).

Angle branches
--------------
Slope probes are continuous in time but an engine may report them on any ``2 pi`` branch. Every
angle channel is shifted as a whole by the multiple of ``2 pi`` that brings its first sample closest
to the mechanism's reference (``mech.q_ref`` for a coordinate, else the links' ``angle_guess``), so
that the truth is on the ERLS coordinates' branch.

:func:`erls_probe_record` evaluates the probes from a full-order ERLS state history, so an ERLS run
yields the same sensor and truth definitions as an Exudyn run.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .erls.elements import GENERATOR
from .erls.kinematics import Kinematics, KinematicsError
from .erls.model import ErlsModel
from .erls.sensing import SecondOrderPlan
from .mechanism import Mechanism, elastic_dofs
from .probes import Probe, ProbeRecord, probes_for

__all__ = [
    "ABSOLUTE_TIP_NAMES",
    "SENSOR_UNITS",
    "Signals",
    "absolute_tip",
    "default_channels",
    "erls_probe_record",
    "monotonic_record",
    "sensor_channels",
    "tip_dof_names",
    "tip_point",
    "true_states",
    "truth_names",
]

log = logging.getLogger(__name__)

TWO_PI = 2.0 * np.pi
SENSOR_UNITS = {"encoder": "rad", "slider": "m", "curvature": "1/m", "tip_x": "m", "tip_y": "m"}
ABSOLUTE_TIP_NAMES = ("tip_x", "tip_y", "dtip_x", "dtip_y")
ABSOLUTE_TIP_UNITS = ("m", "m", "m/s", "m/s")


@dataclass(frozen=True)
class Signals:
    """Named time series: ``data[:, j]`` is channel ``names[j]`` in ``units[j]`` at times ``t``.

    Channels not sampled at a time hold NaN (see :mod:`exuflex.measure`).
    """

    t: np.ndarray  # (n_t,)
    names: tuple[str, ...]
    data: np.ndarray  # (n_t, n_channels)
    units: tuple[str, ...] = ()

    def __post_init__(self):
        if self.data.ndim != 2 or self.data.shape != (len(self.t), len(self.names)):
            raise ValueError(
                f"Signals: data must be (n_t, n_channels) = ({len(self.t)}, {len(self.names)}), got {self.data.shape}"
            )
        if self.units and len(self.units) != len(self.names):
            raise ValueError(f"Signals: {len(self.units)} units for {len(self.names)} channels")

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.data[:, self.names.index(name)]
        except ValueError:
            raise KeyError(f"no channel {name!r}; channels are {list(self.names)}") from None

    def __contains__(self, name: str) -> bool:
        return name in self.names

    def unit(self, name: str) -> str:
        return self.units[self.names.index(name)] if self.units else ""

    def select(self, names) -> Signals:
        """The named channels, in the given order."""
        cols = [self.names.index(n) if n in self.names else None for n in names]
        missing = [n for n, c in zip(names, cols, strict=True) if c is None]
        if missing:
            raise KeyError(f"no channel(s) {missing}; channels are {list(self.names)}")
        units = tuple(self.units[c] for c in cols) if self.units else ()
        return Signals(self.t, tuple(names), self.data[:, cols], units)

    def hstack(self, other: Signals) -> Signals:
        """Channels of both (same time grid)."""
        if len(other.t) != len(self.t) or not np.allclose(other.t, self.t, rtol=0, atol=1e-12):
            raise ValueError("Signals.hstack: the two tables have different time grids")
        units = (self.units or ("",) * len(self.names)) + (other.units or ("",) * len(other.names))
        return Signals(self.t, self.names + other.names, np.hstack([self.data, other.data]), units)


# ------------------------------------------------------------------------------------------ helpers
def _joint_station(mech: Mechanism, joint: str, link: str) -> float:
    for p in mech.joint(joint).points:
        if p.link == link:
            return p.station
    raise KeyError(f"{mech.source or mech.name}: link {link!r} is not at joint {joint!r}")


def _probe(record: ProbeRecord, p: Probe, rate: bool = False) -> np.ndarray:
    store = record.rates if rate else record.values
    if p.key not in store:
        what = "rate" if rate else "value"
        raise KeyError(f"probe record has no {what} of probe {p.key!r} (recorded: {sorted(store)})")
    return np.asarray(store[p.key], float).reshape(len(record.t), p.width)


def _slope(record, mech, link, joint, rate=False):
    return _probe(record, Probe("slope", link, _joint_station(mech, joint, link)), rate)[:, 0]


def _slide(record, mech, joint, rate=False):
    """``axis . (p - ground)`` of a prismatic joint's first point (its rate: ``axis . p'``)."""
    jt = mech.joint(joint)
    p0 = jt.points[0]
    p = _probe(record, Probe("point", p0.link, p0.station), rate)
    d = np.asarray(jt.axis, float)
    return p @ d if rate else (p - np.asarray(jt.ground, float)) @ d


def _branch(series: np.ndarray, ref: float | None) -> np.ndarray:
    """Shift a continuous angle series by 2 pi k so its first sample is closest to ``ref``."""
    if ref is None or len(series) == 0:
        return series
    k = np.round((series[0] - ref) / TWO_PI)
    return series - TWO_PI * k


def _guess_angle(mech: Mechanism, link: str, relative_to: str | None, offset: float = 0.0) -> float | None:
    a = mech.link(link).angle_guess
    if a is None:
        return None
    if relative_to is None:
        return a - offset
    b = mech.link(relative_to).angle_guess
    return None if b is None else a - b - offset


def _coordinate_ref(mech: Mechanism, j: int) -> float | None:
    c = mech.coordinates[j]
    if c.kind == "slide":  # a length: no branch
        return None
    if mech.q_ref:
        return float(mech.q_ref[j])
    return _guess_angle(mech, c.link, c.relative_to, c.offset)


def tip_point(mech: Mechanism) -> tuple[str, float] | None:
    """(link, station) of the tip: the manoeuvre's tip, else the first tip_x/tip_y sensor, else None."""
    if mech.manoeuvre is not None and mech.manoeuvre.tip is not None:
        return mech.manoeuvre.tip.link, mech.manoeuvre.tip.station
    for s in mech.sensors:
        if s.kind in ("tip_x", "tip_y"):
            return s.link, s.station
    return None


def tip_dof_names(mech: Mechanism) -> tuple[str, str]:
    """Truth names of the tip elastic displacement.

    The ERLS elastic dof names of the tip node's x and y translations (six-bar: ``x25``, ``y26``) when
    the tip is at a node whose translations are elastic dofs; otherwise ``tip_ex``, ``tip_ey``.
    """
    tp = tip_point(mech)
    if tp is None:
        raise ValueError(
            f"{mech.source or mech.name}: no tip point (no manoeuvre tip and no tip_x/tip_y sensor)"
        )
    try:
        node = mech.node_at(*tp)
    except KeyError:
        return "tip_ex", "tip_ey"
    dofs = elastic_dofs(mech)
    out = []
    for comp in ("x", "y"):
        k = dofs.nodal_to_u[dofs.nodal_index(node, comp)]
        if k < 0:
            return "tip_ex", "tip_ey"
        out.append(dofs.names[k])
    return out[0], out[1]


def truth_names(mech: Mechanism) -> tuple[str, ...]:
    """Column names of :func:`true_states`: q names, ``d`` + q names, tip elastic x, y and their rates."""
    qn = mech.coordinate_names
    names = qn + tuple("d" + n for n in qn)
    if tip_point(mech) is not None:
        ex, ey = tip_dof_names(mech)
        names += (ex, ey, "d" + ex, "d" + ey)
    return names


def monotonic_record(record: ProbeRecord) -> ProbeRecord:
    """The record with repeated times removed (the last sample of a repeated time is kept).

    Engines may record the final state twice; any decreasing time is an error.
    """
    t = np.asarray(record.t, float)
    d = np.diff(t)
    if np.any(d < 0):
        i = int(np.flatnonzero(d < 0)[0]) + 1
        raise ValueError(
            f"probe record: time decreases at sample {i} ({float(t[i - 1])!r} then {float(t[i])!r})"
        )
    keep = np.append(d > 0, True)
    if keep.all():
        return record
    log.warning("probe record: dropped %d sample(s) with a repeated time (kept the last)", int((~keep).sum()))
    return ProbeRecord(
        t[keep],
        {k: np.asarray(v)[keep] for k, v in record.values.items()},
        {k: np.asarray(v)[keep] for k, v in record.rates.items()},
    )


# ------------------------------------------------------------------------------------------ channels
def sensor_channels(mech: Mechanism, record: ProbeRecord) -> Signals:
    """Clean (noise-free) sensor channels of ``mech.sensors`` from a probe record.

    Parameters
    ----------
    mech : Mechanism
    record : ProbeRecord
        Must hold the values of ``probes_for(mech)``.

    Returns
    -------
    Signals
        One column per sensor, in ``mech.sensors`` order (rad, 1/m or m).
    """
    cols, names, units = [], [], []
    for s in mech.sensors:
        if s.kind == "encoder":
            y = _slope(record, mech, s.link, s.joint)
            if s.relative_to:
                y = y - _slope(record, mech, s.relative_to, s.joint)
            ref = None
            for j, c in enumerate(mech.coordinates):  # an encoder reading a coordinate uses its branch
                if c.link == s.link and c.joint == s.joint and c.relative_to == s.relative_to:
                    r = _coordinate_ref(mech, j)
                    ref = None if r is None else r + c.offset
                    break
            else:
                ref = _guess_angle(mech, s.link, s.relative_to)
            y = _branch(y, ref)
        elif s.kind == "slider":
            y = _slide(record, mech, s.joint)
        elif s.kind == "curvature":
            y = _probe(record, Probe("curvature", s.link, s.station))[:, 0]
        elif s.kind in ("tip_x", "tip_y"):
            y = _probe(record, Probe("point", s.link, s.station))[:, 0 if s.kind == "tip_x" else 1]
        else:
            raise ValueError(f"{mech.source or mech.name}: sensor {s.name!r} has unknown kind {s.kind!r}")
        cols.append(y)
        names.append(s.name)
        units.append(SENSOR_UNITS[s.kind])
    data = np.column_stack(cols) if cols else np.zeros((len(record.t), 0))
    return Signals(np.asarray(record.t, float), tuple(names), data, tuple(units))


def true_states(mech: Mechanism, record: ProbeRecord, *, kinematics: Kinematics | None = None) -> Signals:
    """True ERLS states from a probe record: q, q', tip elastic displacement and its rate.

    Parameters
    ----------
    mech : Mechanism
    record : ProbeRecord
        Values and rates of ``probes_for(mech)``.
    kinematics : Kinematics, optional
        Reuse a solver for ``mech``.

    Returns
    -------
    Signals
        Columns :func:`truth_names` (rad, rad/s, m, m/s). The tip columns are
        ``p_tip - p_rigid(q)`` and ``p_tip' - (dp_rigid/dq) q'`` with ``p_rigid`` the ERLS tip point.
    """
    t = np.asarray(record.t, float)
    nt = len(t)
    nq = len(mech.coordinates)
    q = np.empty((nt, nq))
    qd = np.empty((nt, nq))
    for j, c in enumerate(mech.coordinates):
        if c.kind == "slide":
            q[:, j] = _slide(record, mech, c.joint) - c.offset
            qd[:, j] = _slide(record, mech, c.joint, rate=True)
            continue
        a = _slope(record, mech, c.link, c.joint) - c.offset
        ad = _slope(record, mech, c.link, c.joint, rate=True)
        if c.relative_to:
            a = a - _slope(record, mech, c.relative_to, c.joint)
            ad = ad - _slope(record, mech, c.relative_to, c.joint, rate=True)
        q[:, j] = _branch(a, _coordinate_ref(mech, j))
        qd[:, j] = ad
    cols = [q, qd]
    slide = [c.kind == "slide" for c in mech.coordinates]
    units = ["m" if sl else "rad" for sl in slide] + ["m/s" if sl else "rad/s" for sl in slide]
    tp = tip_point(mech)
    if tp is not None:
        link, station = tp
        pt = Probe("point", link, station)
        p = _probe(record, pt)
        pv = _probe(record, pt, rate=True)
        kin = kinematics if kinematics is not None else Kinematics(mech)
        e = np.empty((nt, 2))
        ed = np.empty((nt, 2))
        z = None
        for k in range(nt):
            pose = kin.pose(q[k], z)
            z = pose.z
            pr, J = kin.point(pose, link, station)
            e[k] = p[k] - pr
            ed[k] = pv[k] - J @ qd[k]
        cols += [e, ed]
        units += ["m", "m", "m/s", "m/s"]
    return Signals(t, truth_names(mech), np.hstack(cols), tuple(units))


def absolute_tip(
    mech: Mechanism, signals: Signals, *, kinematics: Kinematics | None = None, on_error: str = "raise",
    carry: dict | None = None,
) -> Signals:
    """Absolute tip position and velocity (rigid + elastic) of true or estimated states.

    The inverse of the tip split of :func:`true_states`: ``p_tip = p_rigid(q) + e`` and
    ``p_tip' = (dp_rigid/dq) q' + e'``, with ``p_rigid`` the ERLS (rigid) tip point of ``mech`` at ``q``
    (:meth:`~exuflex.erls.kinematics.Kinematics.point`) and ``e``, ``e'`` the tip elastic columns
    (:func:`tip_dof_names`). On a truth it gives back the recorded tip point (the noise-free ``tip_x`` /
    ``tip_y`` sensor channels); applied the same way to an estimate, the difference of the two is the
    absolute tip estimation error, which the joint-angle errors drive through the lever of the links, unlike
    the elastic columns alone.

    Parameters
    ----------
    mech : Mechanism
        Its geometry defines ``p_rigid`` (a payload change does not alter it: pass the nominal model).
    signals : Signals
        Columns ``q``, ``d`` + ``q`` and the tip elastic displacement and rate, named as :func:`truth_names`
        (the layout of :func:`true_states` and of the observer's physical estimate); other columns are ignored.
    kinematics : Kinematics, optional
        Reuse a solver for ``mech``; each sample's pose (:meth:`Kinematics.pose`, :meth:`Kinematics.point`) is
        warm-started from the previous sample's.
    on_error : {"raise", "nan"}
        A sample whose closure cannot be solved, or whose closure Jacobian is singular or near it (condition
        number above ``kinematics.cond_max``, as :meth:`Kinematics.pose`), raises
        :class:`~exuflex.erls.kinematics.KinematicsError` (``"raise"``) or is NaN (``"nan"``).
    carry : dict, optional
        For successive blocks of rows of one record: a dict passed to every call (empty at the first) that
        carries the solver and its warm start from one block to the next, so that the blocks give the numbers
        of one call on the whole record.

    Returns
    -------
    Signals
        Columns :data:`ABSOLUTE_TIP_NAMES` = ``tip_x tip_y dtip_x dtip_y`` (m, m, m/s, m/s) at ``signals.t``.
        A sample with a non-finite input is NaN.

    Raises
    ------
    ValueError
        ``mech`` has no tip point, or ``on_error`` is neither ``"raise"`` nor ``"nan"``.
    KeyError
        ``signals`` lacks one of the columns.
    KinematicsError
        With ``on_error="raise"``: the closure fails at a sample (the message names its time).

    """
    if on_error not in ("raise", "nan"):
        raise ValueError(f"absolute_tip: on_error must be 'raise' or 'nan', got {on_error!r}")
    tp = tip_point(mech)
    if tp is None:
        raise ValueError(
            f"{mech.source or mech.name}: no tip point (no manoeuvre tip and no tip_x/tip_y sensor)"
        )
    link, station = tp
    qn = mech.coordinate_names
    nq = len(qn)
    ex, ey = tip_dof_names(mech)
    X = signals.select(qn + tuple("d" + n for n in qn) + (ex, ey, "d" + ex, "d" + ey)).data
    t = np.asarray(signals.t, float)
    out = np.full((len(t), 4), np.nan)
    if carry is not None and "kin" in carry:  # a later block of the record: go on where the last one ended
        kin, z = carry["kin"], carry["z"]
    else:
        kin = kinematics if kinematics is not None else Kinematics(mech)
        kin.reset_warm_start()  # the first sample from the initial guess: the result must not depend on kin's history
        z = None
    for k in np.flatnonzero(np.all(np.isfinite(X), axis=1)):
        try:
            pose = kin.pose(X[k, :nq], z)
        except KinematicsError as exc:
            if on_error == "raise":
                raise KinematicsError(f"absolute tip at t = {t[k]:.6g} s: {exc}") from exc
            z = None
            continue
        z = pose.z
        p, dp = kin.point(pose, link, station)
        out[k, :2] = p + X[k, 2 * nq : 2 * nq + 2]
        out[k, 2:] = dp @ X[k, nq : 2 * nq] + X[k, 2 * nq + 2 :]
    if carry is not None:
        carry["kin"], carry["z"] = kin, z
    return Signals(t, ABSOLUTE_TIP_NAMES, out, ABSOLUTE_TIP_UNITS)


# ------------------------------------------------------------------------------------------ ERLS engine
def _local_rows(model: ErlsModel, e: int, xi: float, kind: str) -> np.ndarray:
    """Rows acting on an element's local dofs: transverse slope (1, 6), curvature (1, 6), point (2, 6)."""
    L = model.el_len[e]
    if kind == "slope":  # d v / d s of the cubic Hermite interpolant
        r = np.zeros((1, 6))
        r[0, 1] = (-6 * xi + 6 * xi**2) / L
        r[0, 2] = 1 - 4 * xi + 3 * xi**2
        r[0, 4] = (6 * xi - 6 * xi**2) / L
        r[0, 5] = -2 * xi + 3 * xi**2
        return r
    if kind == "curvature":
        r = np.zeros((1, 6))
        r[0, 1] = (-6 + 12 * xi) / L**2
        r[0, 2] = (-4 + 6 * xi) / L
        r[0, 4] = (6 - 12 * xi) / L**2
        r[0, 5] = (-2 + 6 * xi) / L
        return r
    N = np.zeros((2, 6))  # axial linear, transverse cubic (as ErlsModel.point_displacement_rows)
    N[0, 0], N[0, 3] = 1 - xi, xi
    N[1, 1] = 1 - 3 * xi**2 + 2 * xi**3
    N[1, 2] = L * (xi - 2 * xi**2 + xi**3)
    N[1, 4] = 3 * xi**2 - 2 * xi**3
    N[1, 5] = L * (-(xi**2) + xi**3)
    return N


def _elastic_rows(
    model: ErlsModel, cfg, link: str, station: float, kind: str
) -> tuple[np.ndarray, np.ndarray]:
    """(A, A_th): elastic part ``A @ u`` of a probe and ``dA/dtheta`` (theta: the link angle), both (w, ne):
    :func:`_nodal_rows` times ``T``."""
    A, A_th = _nodal_rows(model, cfg, link, station, kind)
    return A @ model.T, A_th @ model.T


def _nodal_rows(
    model: ErlsModel, cfg, link: str, station: float, kind: str
) -> tuple[np.ndarray, np.ndarray]:
    """(A, A_th) on the nodal displacements ``d = T u``, both (w, N) (see :func:`_elastic_rows`).

    Element rows map global nodal displacements to the probe through ``R^T`` (global to local); a point
    is rotated back with the 2x2 rotation ``r2``. With ``dR/dtheta = G R``:
    ``d(l R^T)/dtheta = -l R^T G`` and ``d(r2 N R^T)/dtheta = r2 J2 N R^T - r2 N R^T G``.
    At an interior node slopes and curvatures average the two adjacent elements (as ErlsModel does).
    """
    locs = model.locate(link, station)
    if kind == "point":
        locs = locs[:1]
    w = 2 if kind == "point" else 1
    A = np.zeros((w, model.N))
    A_th = np.zeros((w, model.N))
    J2 = np.array([[0.0, -1.0], [1.0, 0.0]])
    for e, xi in locs:
        R = cfg.R[e]
        l = _local_rows(model, e, xi, kind)
        lRt = l @ R.T
        if kind == "point":
            r2 = R[:2, :2]
            a = r2 @ lRt
            a_th = r2 @ J2 @ lRt - a @ GENERATOR
        else:
            a = lRt
            a_th = -lRt @ GENERATOR
        A[:, model.el_dofs[e]] += a / len(locs)
        A_th[:, model.el_dofs[e]] += a_th / len(locs)
    return A, A_th


def erls_probe_record(model: ErlsModel, t, Y, probes: tuple[Probe, ...] | None = None) -> ProbeRecord:
    """Evaluate probes on a full-order ERLS state history.

    Parameters
    ----------
    model : ErlsModel
    t : (n_t,) array
    Y : (n_t, 2 n) array
        States ``[q; u; q'; u']`` (``ErlsModel.rhs`` layout).
    probes : tuple of Probe, optional
        Defaults to ``probes_for(model.mech)``.

    Returns
    -------
    ProbeRecord
        Values and exact time rates:

        - slope = rigid link angle + elastic rotation (the node's rotation dof at a node, else the
          Hermite slope of the local transverse displacement) + its second order ``w_th``; rate
          ``S_th q' + A u' + theta' A_th u + w_th'``;
        - point = rigid point (``Kinematics.point``) + ``A u`` (the rows of ``point_displacement_rows``) + its
          second order ``w`` (the links' foreshortening, :class:`~exuflex.erls.sensing.SecondOrderPlan`: the
          model's elastic displacements are linear, its axial ones the links' stretch); rate
          ``J q' + A u' + theta' A_th u + w'``;
        - curvature = ``A u`` (the rows of ``curvature_row``); rate ``A u' + theta' A_th u``.
    """
    probes = probes_for(model.mech) if probes is None else probes
    t = np.asarray(t, float)
    Y = np.asarray(Y, float)
    n, nq = model.n, model.nq
    if Y.ndim != 2 or Y.shape != (len(t), 2 * n):
        raise ValueError(f"erls_probe_record: Y must be (n_t, 2 n) = ({len(t)}, {2 * n}), got {Y.shape}")
    kin = model.kin
    li = {name: i for i, name in enumerate(kin.link_names)}
    node_ids = list(model.mech.node_ids)
    vals = {p.key: np.empty((len(t), p.width)) for p in probes}
    rates = {p.key: np.empty((len(t), p.width)) for p in probes}
    # per probe, what does not change with the configuration: the link, and for a slope at a node the nodal
    # row of its rotation dof (exact, also at joints where elements differ)
    plan = []
    for p in probes:
        row = None
        if p.kind == "slope":
            try:
                row = 3 * node_ids.index(model.mech.node_at(p.link, p.station)) + 2
            except KeyError:
                row = None
        plan.append((p, li[p.link], row))
    T = model.T
    # the points' and slopes' second order in u (the links' foreshortening, SecondOrderPlan): index per probe
    second = [j for j, (p, _, _) in enumerate(plan) if p.kind != "curvature"]
    so_plan = SecondOrderPlan(model, [(plan[j][0].link, plan[j][0].station) for j in second]) if second else None
    so_index = {j: i for i, j in enumerate(second)}
    z = None
    for k in range(len(t)):
        q, u, qd, ud = Y[k, :nq], Y[k, nq:n], Y[k, n : n + nq], Y[k, n + nq :]
        cfg = model.configuration(q, z)
        pose = cfg.pose
        z = pose.z
        d, dd = T @ u, T @ ud  # nodal elastic displacements and rates
        if so_plan is not None:
            so = so_plan.at(pose, qd)
            w2, w2d = so.values(u), so.rates(u, ud)
        for j, (p, i, row) in enumerate(plan):
            thd = pose.Sz[3 * i + 2] @ qd
            if p.kind == "slope":
                rig, rig_d = pose.z[3 * i + 2] + w2[so_index[j], 2], thd + w2d[so_index[j], 2]
                if row is not None:
                    vals[p.key][k] = rig + d[row]
                    rates[p.key][k] = rig_d + dd[row]
                    continue
                A, A_th = _nodal_rows(model, cfg, p.link, p.station, "slope")
            elif p.kind == "point":
                rig, J = kin.point(pose, p.link, p.station)
                rig, rig_d = rig + w2[so_index[j], :2], J @ qd + w2d[so_index[j], :2]
                A, A_th = _nodal_rows(model, cfg, p.link, p.station, "point")
            else:
                rig, rig_d = 0.0, 0.0
                A, A_th = _nodal_rows(model, cfg, p.link, p.station, "curvature")
            vals[p.key][k] = rig + A @ d
            rates[p.key][k] = rig_d + A @ dd + thd * (A_th @ d)
    return ProbeRecord(t, vals, rates)


def default_channels(mech: Mechanism) -> tuple[str, ...]:
    """The observer's default channels: the sensors with a stated noise, except tip positions (truth-only) and
    relative encoders duplicating an absolute one on the same link and joint (the six-bar: ``q1 q2 q3 c1 c2 c4``,
    the paper's set)."""
    absolute = {(s.link, s.joint) for s in mech.sensors if s.kind == "encoder" and not s.relative_to}
    out = []
    for s in mech.sensors:
        if s.noise_std <= 0 or s.kind in ("tip_x", "tip_y"):
            continue
        if s.kind == "encoder" and s.relative_to and (s.link, s.joint) in absolute:
            continue
        out.append(s.name)
    return tuple(out)

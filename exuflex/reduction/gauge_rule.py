"""The curvature gauges' mesh: how finely the full model must be meshed next to a gauge for the filter's sake.

A curvature gauge reads the bending of its link at one station; the model reads it from the two-node cubic
(Hermite) elements there (:meth:`~exuflex.erls.model.ErlsModel.curvature_row`). The reduced model's size does not
depend on the full model's mesh (its coordinates are the ERLS coordinates, the masters and the interior modes), but
the row with which the filter reads each of its coordinates does: a retained interior mode's curvature at a gauge
converges as ``h^2`` under refinement. A gauge is a strong sensor (a small noise against the bending it reads), so
an error of a percent in its row per unit of a mode that rings at tens of noise standard deviations is a model
error the filter turns into an error of its estimates. This module states that error and the mesh that keeps it
within a tolerance set by the filter's own bound (``docs/gauge_mesh.md``).

The error of a reading
----------------------
Between its nodes an element carries the distributed transverse load ``w(s, t) = rho A (g - a(s, t)) . n``: the
link's weight less the inertia of its material (``a`` the material's whole acceleration: the rigid motion's and
the bending's), ``n`` the link's normal. The Euler-Bernoulli deflection under it has ``EI v'''' = w``. The cubic
element with the consistent load vector holds the nodal values and slopes of the deflection under a point load
exactly, so for a load that varies slowly over the element the field's error is the quartic bubble with zero end
values and slopes, ``v - v_h = w / (24 EI) x^2 (h - x)^2``; its curvature error is

``v_h'' - v'' = -beta w / EI``,  ``beta = (h^2 - 6 h x + 6 x^2) / 12``

at ``x`` from the element's start: ``h^2 / 12`` at its ends, ``-h^2 / 24`` at its middle; a gauge at a node reads
the mean of its two elements' end curvatures, ``beta = (h_1^2 + h_2^2) / 24`` (:func:`bubble_factor`). In a mode
``phi`` of frequency ``omega`` the load is ``rho A omega^2 phi . n``; with the weight alone it is the gravity rule
of :func:`exuflex.mechanism.refine.gauge_sag_length`. The dynamic nodal values are not exact (their error is of
higher order in ``h``), so the bubble is an estimate: on ``benchmarks/models/three_link_reach_abs.toml`` it gives
the modes' curvature errors at the forearm's gauge within 25 % of those measured against a 24-element mesh
(``docs/gauge_mesh.md``).

What the filter makes of it
---------------------------
Along the manoeuvre the error of a gauge's reading is ``e(t) = -beta w(s, t) / EI``, with the load of the planned
motion. As the truncation requirement does (:mod:`.truncation`, "What the filter makes of it"), the full model
linearised at rest at a configuration of the manoeuvre is driven from rest by the torques that give the rigid
mechanism the planned acceleration there (:class:`.truncation.FilterSample`, the trapezoid's steps included); its
accelerations give ``a(s, t)`` at every gauge, and the weight ``g``. The full model's steady Kalman filter (the
stated torque noise, the channels' noise: the observer's tuning and the bound's) reading the channels with ``e(t)``
added to the gauge's makes an error ``d(t)`` in the estimated quantities (linear in ``e``: the filter's response
to it alone). Its mean square over the manoeuvre against the filter's steady posterior variance,

``b = mean(d^2) / s^2``,

raises an RMS error over the bound from 1 to ``sqrt(1 + b)`` (the two parts are uncorrelated). The rule keeps
``b <= GAUGE_MESH_MAX`` in every estimated quantity at every configuration it samples; each of the ``m`` gauges
gets ``(GAUGE_MESH_MAX / m^2)`` of it alone (the filter's responses add, so their RMS adds at most), which fixes
each gauge's largest ``|beta|`` and so its element length ``h_g = sqrt(12 |beta|)``
(:func:`gauge_lengths`; :func:`exuflex.mechanism.refine.gauge_mesh` places the nodes).

Not the default: :func:`observer_mesh` gives the mesh, and the observer and an ERLS truth built on it apply the rule
(``docs/gauge_mesh.md`` measures what applying it by default changes, and why it is not yet the default).
"""

from __future__ import annotations

import functools
import logging
import math
from types import SimpleNamespace

import numpy as np

from ..erls.model import ErlsModel
from ..mechanism import Mechanism
from ..mechanism.refine import gauge_mesh
from .path import manoeuvre_configurations
from .truncation import FilterSample, PlannedInput, steady_gain

__all__ = ["GAUGE_MESH_MAX", "GAUGE_MESH_POSES", "bubble_factor", "gauge_errors", "gauge_lengths", "mesh_bias",
           "observer_mesh", "rule_configurations"]

log = logging.getLogger(__name__)

#: the rule's limit on ``b``, the mean square of the filter's error that the gauges' mesh error makes, in its
#: bound's variance, in every estimated quantity (module docstring): ``sqrt(1.05)``, 2.5 % of a consistent ratio
GAUGE_MESH_MAX = 0.05
#: the configurations of the manoeuvre the rule samples besides ``q_ref`` (equally spaced in time)
GAUGE_MESH_POSES = 3


def bubble_factor(stations, station: float, length: float) -> float:
    """``beta`` of the curvature error ``-beta w / EI`` at ``station`` on a link meshed at ``stations``: ``(h^2 - 6
    h x + 6 x^2) / 12`` inside an element of length ``h`` (``x`` from its start), the mean of the two ends' ``h^2 /
    12`` at a node (one end's at the link's ends)."""
    st = np.asarray(stations, float)
    eps = 1e-9 * length
    at = np.flatnonzero(np.abs(st - station) <= eps)
    if at.size:
        i = int(at[0])
        hs = ([st[i] - st[i - 1]] if i > 0 else []) + ([st[i + 1] - st[i]] if i < len(st) - 1 else [])
        return float(np.mean(np.square(hs)) / 12.0)
    e = int(np.searchsorted(st, station)) - 1
    h, x = st[e + 1] - st[e], station - st[e]
    return float((h * h - 6.0 * h * x + 6.0 * x * x) / 12.0)


def _load_rows(model: ErlsModel, cfg, link: str, station: float) -> tuple[np.ndarray, float]:
    """``(r, g_n)``: the row ``r`` (n,) with ``r @ x''`` the link's transverse acceleration at the station (the
    element's Hermite interpolation of its nodes' whole accelerations ``W x''``, in its own frame), and the
    weight's transverse component ``g . n`` there (m/s^2)."""
    e, xi = model.locate(link, station)[0]
    L = model.el_len[e]
    N = np.zeros(6)
    N[1] = 1 - 3 * xi**2 + 2 * xi**3
    N[2] = L * (xi - 2 * xi**2 + xi**3)
    N[4] = 3 * xi**2 - 2 * xi**3
    N[5] = L * (-(xi**2) + xi**3)
    Re = cfg.R[e]
    row = np.zeros(cfg.W.shape[0])
    row[model.el_dofs[e]] = N @ Re.T
    normal = Re[:2, :2] @ np.array([0.0, 1.0])
    return row @ cfg.W, float(normal @ np.asarray(model.mech.gravity, float))


def gauge_errors(model: ErlsModel, q, planned: PlannedInput) -> dict:
    """At configuration ``q``: per curvature gauge the filter's error in the estimated quantities made by a
    reading error of ``-w(s, t) / EI`` (``beta = 1``) in that gauge alone, ``d`` (n_t, n_quantities), and the
    filter's steady posterior variance ``var`` (n_quantities,) (module docstring). Returns ``{"var": var, gauge:
    d, ...}``."""
    mech = model.mech
    cfg = model.configuration(np.asarray(q, float))
    n = model.n
    fs = FilterSample(model, SimpleNamespace(cfg=cfg, H=np.eye(n)), planned)
    A, B, X = fs.A, fs.B, fs.X  # the linearised response: x_k at t_k, then u_k held
    acc = np.linalg.solve(fs.M, (fs.u @ fs.G.T - X[:, n:] @ fs.D.T - X[:, :n] @ fs.K.T).T).T  # x'' at t_k
    C = np.hstack([fs.C, np.zeros_like(fs.C)])
    Q = (B * fs.torque_var) @ B.T
    P, Kg = steady_gain(A, C, 0.5 * (Q + Q.T), np.diag(fs.noise**2))
    k = len(fs.Z)
    Zr = np.zeros((2 * k, 2 * n))
    Zr[:k, :n] = fs.Z
    Zr[k:, n:] = fs.Z
    out = {"var": np.clip(np.einsum("ij,jk,ik->i", Zr, P - Kg @ C @ P, Zr), 0.0, None)}
    F = (np.eye(2 * n) - Kg @ C) @ A
    sensors = {s.name: s for s in mech.sensors}
    for j, name in enumerate(planned.channels):
        sn = sensors[name]
        if sn.kind != "curvature":
            continue
        lk = mech.link(sn.link)
        rhoA, EI = lk.material.rho * lk.section.A, lk.material.E * lk.section.I
        row, g_n = _load_rows(model, cfg, sn.link, sn.station)
        e = -rhoA * (g_n - acc @ row) / EI  # the reading's error per unit beta
        W = np.outer(e, Kg[:, j])
        est = np.empty_like(W)
        xe = est[0] = W[0]
        for i in range(1, len(W)):
            xe = est[i] = F @ xe + W[i]
        out[name] = est @ Zr.T
    return out


def rule_configurations(mech: Mechanism, poses: int = GAUGE_MESH_POSES) -> list[np.ndarray]:
    """The configurations the rule samples: ``q_ref`` and ``poses`` of the manoeuvre, equally spaced in time."""
    qs = [np.asarray(mech.q_ref, float)]
    path = manoeuvre_configurations(mech, poses) if poses else None
    return qs + ([] if path is None else list(path))


def mesh_bias(model: ErlsModel, betas: dict, poses: int = GAUGE_MESH_POSES) -> tuple[np.ndarray, tuple]:
    """``(b, names)``: per estimated quantity the largest over the rule's configurations of ``b`` (module
    docstring) for the gauges' reading errors ``-beta_g w / EI`` with ``betas`` (gauge name -> ``beta``, m^2; e.g.
    the difference of two meshes' factors: what a filter on one mesh makes of a truth on the other), and the
    quantities' names; ``b`` empty without a planned manoeuvre."""
    planned = PlannedInput.of(model.mech)
    if planned is None:
        return np.zeros(0), ()
    worst = np.zeros(len(planned.quantities))
    for q in rule_configurations(model.mech, poses):
        err = gauge_errors(model, q, planned)
        d = sum(beta * err[g] for g, beta in betas.items() if g in err)
        if np.isscalar(d):
            continue
        var = np.where(err["var"] > 0, err["var"], np.inf)
        worst = np.maximum(worst, (d**2).mean(axis=0) / var)
    return worst, planned.quantities


def gauge_lengths(mech: Mechanism, limit: float = GAUGE_MESH_MAX, poses: int = GAUGE_MESH_POSES,
                  model: ErlsModel | None = None) -> dict:
    """Per curvature gauge (with a noise) of ``mech`` the rule's figures on its own mesh: ``beta`` (m^2), the
    largest ``b`` in its quantities alone (``b_gauge``, at the worst configuration) and the element length
    ``h_g`` next to it that keeps ``b`` within ``limit / m^2`` (``m`` the number of gauges; module docstring), or
    ``inf`` where nothing asks for one (no manoeuvre or motors, a gauge that reads nothing). Configurations:
    ``q_ref`` and ``poses`` of the manoeuvre."""
    planned = PlannedInput.of(mech)
    gauges = [s for s in mech.sensors if s.kind == "curvature" and s.noise_std > 0
              and (planned is None or s.name in planned.channels)]
    out = {}
    if not gauges:
        return out
    if planned is None:
        return {s.name: {"beta": math.nan, "b_unit": 0.0, "b_gauge": 0.0, "h_g": math.inf, "quantity": None}
                for s in gauges}
    model = model or ErlsModel(mech)
    worst = {s.name: (0.0, None) for s in gauges}
    for q in rule_configurations(mech, poses):
        err = gauge_errors(model, q, planned)
        var = np.where(err["var"] > 0, err["var"], np.inf)
        for s in gauges:
            b = (err[s.name] ** 2).mean(axis=0) / var
            i = int(np.argmax(b))
            if b[i] > worst[s.name][0]:
                worst[s.name] = (float(b[i]), planned.quantities[i])
    share = limit / len(gauges) ** 2
    for s in gauges:
        lk = mech.link(s.link)
        beta = bubble_factor(lk.stations, s.station, lk.length)
        b_unit, quantity = worst[s.name]
        beta_max = math.sqrt(share / b_unit) if b_unit > 0 else math.inf
        out[s.name] = {"beta": beta, "b_unit": b_unit, "b_gauge": b_unit * beta**2, "quantity": quantity,
                       "h_g": math.sqrt(12.0 * beta_max) if math.isfinite(beta_max) else math.inf}
    return out


@functools.lru_cache(maxsize=16)  # the observer and the ERLS truth ask for the same mechanism's
def observer_mesh(mech: Mechanism, limit: float = GAUGE_MESH_MAX) -> Mechanism:
    """``mech`` with the elements next to each curvature gauge no longer than the rule's ``h_g``
    (:func:`gauge_lengths`, :func:`exuflex.mechanism.refine.gauge_mesh`); ``mech`` itself where the file's mesh
    is fine enough. ``make_observer(observer_mesh(mech))`` builds the observer on it (an ERLS truth for it should be
    at least as fine); the file's nodes, ids and masters are kept."""
    lengths = {name: r["h_g"] for name, r in gauge_lengths(mech, limit).items() if math.isfinite(r["h_g"])}
    return gauge_mesh(mech, lengths=lengths) if lengths else mech

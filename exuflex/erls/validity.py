"""Where the ERLS model stops being valid: links turning fast against their own first clamped frequency, and (in a
model without the geometric stiffness) links whose axial load under the weight acts across their elastic
displacements.

With linear elasticity in the rotating frame of each link (:mod:`exuflex.erls.model` with ``geometric=False``, and
the observer's reduced model, whose geometric stiffness is the weight's static part only) the ERLS keeps the
centrifugal softening but not the geometric stiffening of the centrifugal tension (the full-order model's default
holds it: ``docs/validity.md``, where it follows Exudyn through the spin-up). A link turning at the rate
``Omega`` misses a stiffness of order ``rho A Omega^2 L^2`` against its bending stiffness of order
``rho A omega_c^2 L^2`` (``omega_c``: its first clamped-free frequency, the link clamped at the joint it turns
about), so to first order the relative error of its elastic response grows as ``(Omega / omega_c)^2``, and the
model diverges where the softening cancels the bending stiffness, ``Omega = omega_c``.

``docs/validity.md`` measures this on a spinning cantilever (``benchmarks/spin_up.py``, ERLS against Exudyn's
geometrically exact beams): the normalised RMS error of the tip deflection passes 5 % at
``Omega = DEPARTURE_RATIO omega_c`` and follows the square law below it (the page's table). The guard therefore estimates each link's error along a trajectory as
``DEPARTURE_NRMS (Omega / (DEPARTURE_RATIO omega_c))^2`` from its own ``omega_c`` and warns, naming the link and
the time, where the estimate reaches :data:`WARN_NRMS` (half the departure criterion: the rate approaches the
departure speed), where it passes the departure (``"departed"``) and where the rate reaches ``omega_c``
(``"unstable"``).

``omega_c`` is computed from the link's own beam elements (its mesh in the model file, the ERLS element matrices)
and its lumped masses (rotary inertias, offsets, the payload), clamped at each end that carries a joint; the
lowest of those frequencies is used (a link turning about either end: the conservative choice).

The weight's P-delta effect
---------------------------
Linear elasticity leaves out the moment of an axial force acting across the lateral elastic displacements (the
geometric stiffness ``K_G(N)``: a link in compression softens, in tension stiffens). Measured against the
buckling load this is small in any mechanism that holds its shape (``N / N_cr`` of a few 1e-3 on
``benchmarks/models/vertical_serial_arm.toml``'s forearm), but what matters to the observer is the absolute
change of what its sensors read, and a persistent one: the forearm standing almost upright carries its payload's
weight axially while the upper arm's sag tilts it elastically (some 4 mrad at the elbow); its own transverse
weight is small (``cos 1.5``), so the P-delta moment is some 5 % of its bending there, 0.8 noise sd in its gauge
(``docs/gravity.md``). The ERLS model's elastic rows hold it (:meth:`.model.ErlsModel.geometric_stiffness`: the
axial forces of the rigid motion's loads, the weight's static part in the configuration's stiffness and so in the
reduction); its coordinate rows held their share before (below). A model built with ``geometric=False`` has
not, and for it:

:func:`weight_pdelta` estimates it at a configuration, to first order: the full model's linear static sag under the
weight ``u`` with the motor torques that hold the coordinates (:func:`weight_sag`), each element's axial force
``N_e = EA (u_2 - u_1) / L`` from it (element frame), and the static response of the elastic rows with the
coordinates held to the P-delta forces ``f = -K_G(N) T u`` of each link's elements: ``du = K_uu^-1 T^T f``, read
by the noisy channels (their rows of :func:`.sensing.channel_matrix`) in their noise sd (the material stiffness
throughout, whichever model is given: the reading of the effect itself). The coordinate rows' share ``S^T f`` the
model has: the strain energy ``u^T K(q) u / 2`` of the links' rotated stiffness has the q-gradient ``-S^T f``
(``tests/test_pdelta.py``). The reading is persistent (it follows the configuration, not the vibration), so the
filter takes it for signal: a reading left to the filter of ``b`` noise sd is at the limit the reduction allows
its own static truncation (``sqrt(0.1)``, the readings that move an update by at most ``b`` posterior sd;
``exuflex.reduction.truncation``), and a persistent one is amplified by the filter's gain at zero frequency (on
the vertical serial arm 4.5-5 posterior sd of an angle per noise sd of a gauge, ``docs/gravity.md``).
:func:`weight_warnings` (``geometric=False``) warns, naming the link, the channel and the time, where a link's
reading reaches :data:`PDELTA_WARN_SD` (``"approaching"``) and where it reaches :data:`PDELTA_DEPART_SD`
(``"departed"``).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np
import scipy.linalg as sla

from ..mechanism import Mechanism
from .elements import beam_geometric_stiffness, beam_mass, beam_stiffness
from .kinematics import Kinematics

__all__ = ["DEPARTURE_NRMS", "DEPARTURE_RATIO", "PDELTA_DEPART_SD", "PDELTA_WARN_SD", "WARN_NRMS", "AxialWarning",
           "RateWarning", "check_link_rates", "clamped_frequencies", "link_rates", "pdelta_forces", "rate_warnings",
           "signal_warnings", "weight_pdelta", "weight_sag", "weight_warnings"]

log = logging.getLogger(__name__)

DEPARTURE_RATIO = 0.31
"""Rate / first clamped frequency where the ERLS departs (tip deflection NRMS > 5 %) from a geometrically
stiffened beam, from the spin-up benchmark (``docs/validity.md``; ``tests/test_validity.py`` reads the
page and keeps the two equal)."""
DEPARTURE_NRMS = 0.05  # the departure criterion of that benchmark
WARN_NRMS = 0.025  # warn from this estimated error: Omega >= DEPARTURE_RATIO omega_c / sqrt(2)
MAX_POSES = 4000  # a trajectory is checked at this many samples at most (rates are smooth on that grid)
PDELTA_DEPART_SD = float(np.sqrt(0.1))
"""The weight's P-delta reading (noise sd) from which the ERLS model has departed: the
limit of the readings the reduction may leave to the filter (module docstring)."""
PDELTA_WARN_SD = 0.1
"""Warn from this reading: a persistent reading is amplified by the filter's gain at zero frequency (module
docstring), some 3 posterior sd per noise sd would take this one to ``PDELTA_DEPART_SD``."""
MAX_WEIGHT_POSES = 200  # the P-delta check's samples of a trajectory at most (it follows the configuration only)


@dataclass(frozen=True)
class RateWarning:
    """A link whose rotation rate along a trajectory approaches (or passes) the ERLS model's validity limit."""

    link: str
    level: str  # "approaching" (estimated error >= WARN_NRMS), "departed" (>= DEPARTURE_NRMS), "unstable" (>= omega_c)
    time_s: float  # first time the rate reaches the level's threshold
    peak_time_s: float
    peak_rate_rad_s: float
    clamped_rad_s: float  # the link's first clamped-free frequency omega_c
    departure_rate_rad_s: float  # DEPARTURE_RATIO omega_c
    estimated_nrms: float  # DEPARTURE_NRMS (peak / departure rate)^2

    @property
    def message(self) -> str:
        what = {"approaching": "approaches", "departed": "passes", "unstable": "reaches"}[self.level]
        limit = (f"its first clamped frequency {self.clamped_rad_s:.3g} rad/s (the ERLS model diverges there)"
                 if self.level == "unstable" else
                 f"the ERLS departure rate {self.departure_rate_rad_s:.3g} rad/s ({DEPARTURE_RATIO:g} x its first "
                 f"clamped frequency {self.clamped_rad_s:.3g} rad/s)")
        return (f"link {self.link!r} turns at {self.peak_rate_rad_s:.3g} rad/s at t = {self.peak_time_s:.3g} s "
                f"(from t = {self.time_s:.3g} s it {what} {limit}): no geometric stiffening in the model, estimated "
                f"elastic-response error {100 * self.estimated_nrms:.2g} % (docs/validity.md)")

    def as_dict(self) -> dict:
        return {**asdict(self), "message": self.message}


def clamped_frequencies(mech: Mechanism) -> dict[str, float]:
    """Each link's first clamped-free frequency ``omega_c`` (rad/s; module docstring): its beam elements and lumped
    masses, clamped at each end that carries a joint (or at its start if none), the lowest."""
    ends: dict[str, set[float]] = {lk.name: set() for lk in mech.links}
    for j in mech.joints:
        for p in j.points:
            lk = mech.link(p.link)
            if p.station in (0.0, lk.length) or abs(p.station - lk.length) < 1e-9 * lk.length:
                ends[p.link].add(0.0 if p.station == 0.0 else lk.length)
    out = {}
    for lk in mech.links:
        st = np.asarray(lk.stations, float)
        n = 3 * len(st)
        K, M = np.zeros((n, n)), np.zeros((n, n))
        E, A, I, rho = lk.material.E, lk.section.A, lk.section.I, lk.material.rho
        for a in range(len(st) - 1):
            L = st[a + 1] - st[a]
            idx = np.arange(3 * a, 3 * a + 6)
            K[np.ix_(idx, idx)] += beam_stiffness(E * A, E * I, L)
            M[np.ix_(idx, idx)] += beam_mass(rho * A, L)
        for m in mech.all_masses():
            name, s = mech.node_location(m.node)
            if name != lk.name:
                continue
            a, b = m.offset
            Np = np.array([[1.0, 0.0, -b], [0.0, 1.0, a]])  # the mass point's velocity in the link frame
            i = int(np.argmin(np.abs(st - s)))
            M[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += m.mass * Np.T @ Np + np.diag([0.0, 0.0, m.inertia])
        w = np.inf
        for end in sorted(ends[lk.name]) or [0.0]:
            i = int(np.argmin(np.abs(st - end)))
            free = np.setdiff1d(np.arange(n), np.arange(3 * i, 3 * i + 3))
            w2 = sla.eigh(K[np.ix_(free, free)], M[np.ix_(free, free)], eigvals_only=True, subset_by_index=[0, 0])
            w = min(w, float(np.sqrt(max(w2[0], 0.0))))
        out[lk.name] = w
    return out


def link_rates(mech: Mechanism, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """(n_t, n_links) absolute rotation rates of the links of the rigid mechanism at ``q``, ``q'`` (n_t, nq)."""
    kin = Kinematics(mech)
    q, qd = np.atleast_2d(np.asarray(q, float)), np.atleast_2d(np.asarray(qd, float))
    out = np.empty((len(q), len(mech.links)))
    for k in range(len(q)):
        out[k] = kin.pose(q[k]).Sz[2::3] @ qd[k]
    return out


def check_link_rates(mech: Mechanism, t: np.ndarray, rates: np.ndarray,
                     clamped: dict[str, float] | None = None) -> list[RateWarning]:
    """The warnings (module docstring) for link rates ``rates`` (n_t, n_links) at times ``t``: per link, its
    highest level reached, with the first time the rate reached it and the peak."""
    clamped = clamped_frequencies(mech) if clamped is None else clamped
    t, rates = np.asarray(t, float), np.abs(np.asarray(rates, float))
    out = []
    for i, lk in enumerate(mech.links):
        wc = clamped[lk.name]
        dep = DEPARTURE_RATIO * wc
        r = rates[:, i]
        if not len(r) or not np.isfinite(wc):
            continue
        k = int(np.nanargmax(r))
        est = DEPARTURE_NRMS * (r[k] / dep) ** 2
        for level, limit in (("unstable", wc), ("departed", dep), ("approaching", dep * np.sqrt(WARN_NRMS / DEPARTURE_NRMS))):
            if r[k] >= limit:
                first = int(np.flatnonzero(r >= limit)[0])
                out.append(RateWarning(lk.name, level, float(t[first]), float(t[k]), float(r[k]), wc, dep, float(est)))
                break
    return out


def rate_warnings(mech: Mechanism, t: np.ndarray, q: np.ndarray, qd: np.ndarray) -> list[RateWarning]:
    """:func:`check_link_rates` along a trajectory ``q``, ``q'`` (n_t, nq) at times ``t`` (at most
    :data:`MAX_POSES` samples of it), each warning logged."""
    t = np.asarray(t, float)
    stride = max(1, -(-len(t) // MAX_POSES))
    keep = np.r_[np.arange(0, len(t), stride), len(t) - 1] if len(t) else np.arange(0)
    keep = np.unique(keep)
    warnings = check_link_rates(mech, t[keep], link_rates(mech, np.asarray(q)[keep], np.asarray(qd)[keep]))
    for w in warnings:
        log.warning("%s", w.message)
    return warnings


def signal_warnings(mech: Mechanism, sig) -> list[RateWarning | AxialWarning]:
    """:func:`rate_warnings` and :func:`weight_warnings` along a record with the coordinates ``q`` and their rates
    ``d`` + ``q`` as columns (a truth record or the observer's physical estimates,
    :func:`exuflex.sensors.truth_names`); rows with a missing value are skipped. ``[]`` if the record lacks a
    column."""
    names = list(sig.names)
    qn = list(mech.coordinate_names)
    if any(n not in names or "d" + n not in names for n in qn):
        return []
    q = sig.data[:, [names.index(n) for n in qn]]
    qd = sig.data[:, [names.index("d" + n) for n in qn]]
    ok = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(qd), axis=1)
    t = np.asarray(sig.t)[ok]
    return rate_warnings(mech, t, q[ok], qd[ok]) + weight_warnings(mech, t, q[ok])


@dataclass(frozen=True)
class AxialWarning:
    """A link whose axial load under the weight, acting across the elastic displacements (the geometric
    stiffness the ERLS model has not), reads a persistent amount in a channel (module docstring)."""

    link: str
    level: str  # "approaching" (>= PDELTA_WARN_SD), "departed" (>= PDELTA_DEPART_SD)
    time_s: float  # first time the reading reaches the level's threshold
    peak_time_s: float
    peak_reading_sd: float  # in the channel's noise sd
    channel: str  # the channel that reads it most
    compression_n: float  # the link's largest axial compression (N; negative: tension) at the peak

    @property
    def message(self) -> str:
        what = "approaches" if self.level == "approaching" else "passes"
        limit = PDELTA_WARN_SD if self.level == "approaching" else PDELTA_DEPART_SD
        load = (f"{self.compression_n:.3g} N of compression" if self.compression_n > 0 else
                f"{-self.compression_n:.3g} N of tension")
        return (f"link {self.link!r} carries {load} under the weight at t = {self.peak_time_s:.3g} s: its P-delta "
                f"effect (geometric stiffness, not in the ERLS model) reads {self.peak_reading_sd:.2g} noise sd in "
                f"{self.channel} (from t = {self.time_s:.3g} s it {what} {limit:.2g} sd), a persistent error of the "
                "model's static sag (docs/validity.md)")

    def as_dict(self) -> dict:
        return {**asdict(self), "message": self.message}


def weight_sag(model, cfg, material: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(u, tau)``: the full-order model's static elastic displacements under its weight at the configuration
    ``cfg``, and the motor torques that hold its coordinates. Linear statics: the coordinate rows ``S^T (M_N g + B
    tau) = 0`` (least squares where the motors do not span them), the elastic rows ``K_uu u = T^T (M_N g + B
    tau)`` (the coordinate rows' strain-energy term ``dV/dq``, quadratic in ``u``, left out), ``K_uu`` the
    model's (with the geometric stiffness of the static axial loads where it has one,
    :meth:`~exuflex.erls.model.ErlsModel.static_geometric`) or with ``material`` the linear elastic one."""
    g = cfg.M_N @ model.g_N
    S, B, T = cfg.pose.S, model.B_N, model.T
    tau = -np.linalg.lstsq(S.T @ B, S.T @ g, rcond=None)[0]
    u = np.linalg.solve(T.T @ _stiffness(cfg, material) @ T, T.T @ (g + B @ tau))
    return u, tau


def _stiffness(cfg, material: bool) -> np.ndarray:
    """The nodal stiffness of ``cfg``, with its static geometric stiffness unless ``material``."""
    return cfg.K_N if material or cfg.K_G is None else cfg.K_N + cfg.K_G


def _channel_noise(mech) -> tuple[list[str], np.ndarray]:
    """The channels with a stated noise (tip positions are truth-only) and their noise sd."""
    chans = [s for s in mech.sensors if s.noise_std > 0 and s.kind not in ("tip_x", "tip_y")]
    return [s.name for s in chans], np.array([s.noise_std for s in chans])


def pdelta_forces(model, cfg, d: np.ndarray, elements) -> tuple[np.ndarray, np.ndarray]:
    """``(f, N)``: the nodal P-delta forces ``f = -sum_e R_e K_G(N_e) R_e^T d_e`` (N,) of the beam ``elements``
    at the configuration ``cfg`` and nodal elastic displacements ``d`` (global), with each element's axial force
    ``N_e = EA (d_2 - d_1) / L`` along it (tension positive, :func:`.elements.beam_geometric_stiffness`)."""
    mech = model.mech
    f = np.zeros(model.N)
    N = np.empty(len(elements))
    for i, e in enumerate(elements):
        lk = mech.links[model.el_link[e]]
        R, L, dofs = cfg.R[e], model.el_len[e], model.el_dofs[e]
        dl = R.T @ d[dofs]
        N[i] = lk.material.E * lk.section.A * (dl[3] - dl[0]) / L
        f[dofs] -= R @ (beam_geometric_stiffness(N[i], L) @ dl)
    return f, N


def weight_pdelta(model, q) -> dict[str, tuple[float, str, float]]:
    """Per link with beam elements, ``(reading, channel, compression)`` at the configuration ``q``: the largest
    reading (noise sd) of the static response of the elastic rows to the P-delta forces of the link's axial load under the
    weight (module docstring), the channel that reads it, and the link's largest axial compression (N;
    negative: in tension throughout). Empty without gravity."""
    from .sensing import channel_matrix

    mech = model.mech
    if not np.any(model.g_N):
        return {}
    cfg = model.configuration(np.asarray(q, float))
    u, _ = weight_sag(model, cfg, material=True)
    d = model.T @ u
    names, noise = _channel_noise(mech)
    C = channel_matrix(model, cfg, mech, names)[:, model.nq :] / noise[:, None] if names else np.zeros((0, model.ne))
    links = [(lk, els) for li, lk in enumerate(mech.links)
             if len(els := np.flatnonzero((model.el_link == li) & (model.el_len > 0)))]
    if not links:
        return {}
    forces = [pdelta_forces(model, cfg, d, els) for _, els in links]
    # every link's response in one solve of the elastic rows
    reads = np.abs(C @ np.linalg.solve(model.T.T @ _stiffness(cfg, True) @ model.T,
                                       model.T.T @ np.column_stack([f for f, _ in forces])))
    out = {}
    for (lk, _), (_, N_el), read in zip(links, forces, reads.T):
        best, chan = (float(read.max()), names[int(read.argmax())]) if len(read) else (0.0, "")
        out[lk.name] = (best, chan, float(-N_el.min()))
    return out


def weight_warnings(mech: Mechanism, t: np.ndarray, q: np.ndarray, geometric: bool = True) -> list[AxialWarning]:
    """The P-delta warnings (module docstring) along a trajectory ``q`` (n_t, nq) at times ``t`` (at most
    :data:`MAX_WEIGHT_POSES` samples of it), each logged, for a model without the geometric stiffness
    (``geometric=False``); none without gravity, and none for the model with it (``ErlsModel``'s default, whose
    elastic rows and whose reduction hold the static axial loads' P-delta effect)."""
    if geometric or not mech.gravity or not any(mech.gravity) or not len(t):
        return []
    from .model import ErlsModel

    model = ErlsModel(mech, geometric=False)
    t, q = np.asarray(t, float), np.atleast_2d(np.asarray(q, float))
    keep = np.unique(np.r_[np.arange(0, len(t), max(1, -(-len(t) // MAX_WEIGHT_POSES))), len(t) - 1])
    rows = [weight_pdelta(model, q[k]) for k in keep]
    out = []
    for lk in (rows[0] if rows else {}):
        r = np.array([row[lk][0] for row in rows])
        k = int(r.argmax())
        for level, limit in (("departed", PDELTA_DEPART_SD), ("approaching", PDELTA_WARN_SD)):
            if r[k] >= limit:
                first = int(np.flatnonzero(r >= limit)[0])
                w = AxialWarning(lk, level, float(t[keep[first]]), float(t[keep[k]]), float(r[k]), rows[k][lk][1],
                                 rows[k][lk][2])
                log.warning("%s", w.message)
                out.append(w)
                break
    return out

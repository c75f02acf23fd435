"""Where the ERLS model stops being valid: links turning fast against their own first clamped frequency.

The ERLS model (:mod:`exuflex.erls.model`) has linear elasticity in the rotating frame of each link: it keeps the
centrifugal softening but not the geometric stiffening of the centrifugal tension. A link turning at the rate
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
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np
import scipy.linalg as sla

from ..mechanism import Mechanism
from .elements import beam_mass, beam_stiffness
from .kinematics import Kinematics

__all__ = ["DEPARTURE_NRMS", "DEPARTURE_RATIO", "WARN_NRMS", "RateWarning", "check_link_rates",
           "clamped_frequencies", "link_rates", "rate_warnings", "signal_warnings"]

log = logging.getLogger(__name__)

DEPARTURE_RATIO = 0.31
"""Rate / first clamped frequency where the ERLS departs (tip deflection NRMS > 5 %) from a geometrically
stiffened beam, from the spin-up benchmark (``docs/validity.md``; ``tests/test_validity.py`` reads the
page and keeps the two equal)."""
DEPARTURE_NRMS = 0.05  # the departure criterion of that benchmark
WARN_NRMS = 0.025  # warn from this estimated error: Omega >= DEPARTURE_RATIO omega_c / sqrt(2)
MAX_POSES = 4000  # a trajectory is checked at this many samples at most (rates are smooth on that grid)


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


def signal_warnings(mech: Mechanism, sig) -> list[RateWarning]:
    """:func:`rate_warnings` along a record with the coordinates ``q`` and their rates ``d`` + ``q`` as columns
    (a truth record or the observer's physical estimates, :func:`exuflex.sensors.truth_names`); rows with a
    missing value are skipped. ``[]`` if the record lacks a column."""
    names = list(sig.names)
    qn = list(mech.coordinate_names)
    if any(n not in names or "d" + n not in names for n in qn):
        return []
    q = sig.data[:, [names.index(n) for n in qn]]
    qd = sig.data[:, [names.index("d" + n) for n in qn]]
    ok = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(qd), axis=1)
    return rate_warnings(mech, np.asarray(sig.t)[ok], q[ok], qd[ok])

"""Sensor design: rank curvature-gauge stations by the best RMS error any filter can reach with them.

For a candidate channel set the criterion is the quick, steady-state estimate of the bound,
:func:`.bound.steady_bound` (the Kalman filter's steady-state posterior covariance of the reduced model linearised
along the manoeuvre's plan and frozen at each of its poses, the stated torque
noise as process noise): the RMS bound of the tip elastic displacement, ``sqrt(b_x^2 + b_y^2)``, since the
encoders alone already give the rigid motion. A channel set that leaves states unobservable gets an infinite
bound.

Candidates: curvature gauges at ``n`` evenly spaced interior stations of every link, each with the same noise
(the median of the model file's gauges, so that stations and not gauges are compared), on top of the model's
encoders. :func:`rank_gauges` ranks single gauges, then builds a set of as many gauges as the model file has by
greedy forward selection (each step adds the station that lowers the bound most) and evaluates the model file's
own set with the same noise, so that its rank among the single stations and its bound against the greedy set say
how good the file's choice is.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..mechanism import Mechanism
from ..sensors import tip_point
from ..observer.session import ObserverConfig, default_channels, make_observer, physical_names
from .bound import UnobservableError, steady_bound

__all__ = ["DesignResult", "rank_gauges"]


@dataclass(frozen=True)
class _BoundFilter:
    """What :func:`.bound.steady_bound` reads of a filter: the channels' noise and the interval."""

    R_std: np.ndarray
    dt: float


@dataclass
class DesignResult:
    """Ranked gauge stations (see :func:`rank_gauges`).

    single : list of dict
        ``{"name", "link", "station", "tip_bound"}`` per candidate station, best first (encoders + that gauge).
    model_gauges : list of dict
        The model file's gauges: name, link, station, ``tip_bound`` alone with the encoders, ``rank`` (1-based)
        among the single candidates (where the station would fall).
    model_set_bound, greedy_set_bound : float
        Tip bound of the model file's gauge set and of the greedy set of as many gauges (same noise).
    greedy_set : list of str
    encoders_bound : float
        Tip bound with the encoders only (inf if the elastic states are then unobservable).
    gauge_noise : float
        The common gauge noise std (1/m).
    """

    single: list
    model_gauges: list
    model_set_bound: float
    greedy_set: list
    greedy_set_bound: float
    encoders_bound: float
    gauge_noise: float


def rank_gauges(mech: Mechanism, n_candidates: int = 9, config: ObserverConfig | None = None) -> DesignResult:
    """Rank gauge stations of ``mech`` by the tip-displacement bound (module docstring)."""
    from ..errors import UsageError
    from ..validate import check_mechanism_argument, check_work, state_size_estimate

    check_mechanism_argument(mech)
    if isinstance(n_candidates, bool) or not isinstance(n_candidates, (int, np.integer)) or n_candidates < 1:
        raise UsageError(f"n_candidates (--candidates): expected a positive integer, got {n_candidates!r}")
    # each candidate is a sensor of the ranking observer (its object and measurement rows, a few kB) and enters
    # a steady-state Riccati solve (about 30 nx^3 flop) alone and in each round of the greedy set
    nx = state_size_estimate(mech)
    n_gauges = sum(1 for s in mech.sensors if s.kind == "curvature")
    count = n_candidates * len(mech.links)
    check_work(n_candidates, count, param="n_candidates", flag="--candidates", what="candidate stations",
               bytes_each=4096 + 8 * 4 * nx, flops_each=(1 + n_gauges) * 30 * nx**3)
    gauges = [s for s in mech.sensors if s.kind == "curvature"]
    if not gauges:
        raise ValueError(f"{mech.source or mech.name}: no curvature gauge in the model file to take the gauge "
                         "noise from")
    if tip_point(mech) is None:
        raise ValueError(f"{mech.source or mech.name}: no tip point: nothing to rank the gauges by")
    noise = float(np.median([s.noise_std for s in gauges]))
    template = gauges[0]
    cands = []
    for lk in mech.links:
        for i in range(1, n_candidates + 1):
            st = round(lk.length * i / (n_candidates + 1), 6)
            cands.append(dataclasses.replace(template, name=f"{lk.name}@{st:g}", link=lk.name, station=st,
                                             noise_std=noise, rate_hz=None))
    own = [dataclasses.replace(s, name=f"{s.name}*", noise_std=noise, rate_hz=None) for s in gauges]
    big = dataclasses.replace(mech, sensors=tuple(mech.sensors) + tuple(cands) + tuple(own))
    encoders = [c for c in default_channels(mech) if next(s for s in mech.sensors if s.name == c).kind == "encoder"]
    obs = make_observer(big, dataclasses.replace(config or ObserverConfig(), channels=tuple(encoders)))
    std = {s.name: s.noise_std for s in big.sensors}

    nq = len(mech.coordinate_names)
    tip_x, tip_y = physical_names(mech)[2 * nq : 2 * nq + 2]  # the tip elastic displacement columns

    def bound(chans: list[str]) -> float:
        o = dataclasses.replace(obs, channels=tuple(chans),
                                ekf=_BoundFilter(np.array([std[c] for c in chans]), obs.ekf.dt))
        try:
            b = steady_bound(o)
        except UnobservableError:
            return math.inf
        return float(math.hypot(b[tip_x], b[tip_y]))

    single = sorted(({"name": c.name, "link": c.link, "station": c.station, "tip_bound": bound(encoders + [c.name])}
                     for c in cands), key=lambda d: d["tip_bound"])
    model_gauges = []
    for g, o in zip(gauges, own, strict=True):
        b = bound(encoders + [o.name])
        rank = 1 + sum(1 for d in single if d["tip_bound"] < b)
        model_gauges.append({"name": g.name, "link": g.link, "station": g.station, "tip_bound": b, "rank": rank})
    chosen: list[str] = []
    best = math.inf
    pool = [c.name for c in cands]
    for _ in range(len(gauges)):
        trial = sorted((bound(encoders + chosen + [c]), c) for c in pool if c not in chosen)
        best, pick = trial[0]
        chosen.append(pick)
    return DesignResult(single=single, model_gauges=model_gauges,
                        model_set_bound=bound(encoders + [o.name for o in own]), greedy_set=chosen,
                        greedy_set_bound=best, encoders_bound=bound(encoders), gauge_noise=noise)

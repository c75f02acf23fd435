"""Probes: the physical quantities both formulations must record, defined once.

A *probe* is a raw kinematic quantity of the flexible mechanism at a point of a link's axis:

- ``slope``: absolute angle (rad) of the deformed axis' tangent at the station (unwrapped in time);
- ``point``: global position (x, y, m) of the deformed axis at the station;
- ``curvature``: bending curvature (1/m) of the deformed axis at the station (positive
  counter-clockwise bending, i.e. d(slope)/ds).

Every engine (the exuflex ERLS model, the Exudyn ground truth, a lab rig) produces a
:class:`ProbeRecord` of the probes a mechanism needs (:func:`probes_for`); the sensor channels and the
true ERLS states are then computed from the record by :mod:`exuflex.sensors`, identically for all engines.
This is what makes the two formulations comparable.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .mechanism import Mechanism

__all__ = ["Probe", "ProbeRecord", "probes_for"]

KINDS = {"slope": 1, "point": 2, "curvature": 1}


@dataclass(frozen=True)
class Probe:
    kind: str  # slope | point | curvature
    link: str
    station: float

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"probe kind must be one of {sorted(KINDS)}, got {self.kind!r}")

    @property
    def width(self) -> int:
        return KINDS[self.kind]

    @property
    def key(self) -> str:
        return f"{self.kind}:{self.link}@{self.station:.9g}"


@dataclass
class ProbeRecord:
    """Time histories of probes: ``values[key]`` and ``rates[key]`` are (n_t, width) arrays.

    ``rates`` holds time derivatives (slope rate, point velocity, curvature rate); an engine that cannot
    provide a rate leaves it out.
    """

    t: np.ndarray
    values: dict[str, np.ndarray] = field(default_factory=dict)
    rates: dict[str, np.ndarray] = field(default_factory=dict)

    def value(self, probe: Probe) -> np.ndarray:
        return self.values[probe.key]

    def rate(self, probe: Probe) -> np.ndarray:
        return self.rates[probe.key]


def _station_of_joint(mech: Mechanism, joint: str, link: str) -> float:
    j = mech.joint(joint)
    for p in j.points:
        if p.link == link:
            return p.station
    raise KeyError(f"link {link!r} is not at joint {joint!r}")


def probes_for(mech: Mechanism) -> tuple[Probe, ...]:
    """All probes needed for the mechanism's coordinates, sensors and manoeuvre tip (no duplicates)."""
    out: list[Probe] = []

    def add(p: Probe):
        if p not in out:
            out.append(p)

    for c in mech.coordinates:
        if c.kind == "slide":  # the slider's position
            add(Probe("point", c.link, _station_of_joint(mech, c.joint, c.link)))
            continue
        add(Probe("slope", c.link, _station_of_joint(mech, c.joint, c.link)))
        if c.relative_to:
            add(Probe("slope", c.relative_to, _station_of_joint(mech, c.joint, c.relative_to)))
    for s in mech.sensors:
        if s.kind == "encoder":
            add(Probe("slope", s.link, _station_of_joint(mech, s.joint, s.link)))
            if s.relative_to:
                add(Probe("slope", s.relative_to, _station_of_joint(mech, s.joint, s.relative_to)))
        elif s.kind == "slider":
            add(Probe("point", s.link, _station_of_joint(mech, s.joint, s.link)))
        elif s.kind == "curvature":
            add(Probe("curvature", s.link, s.station))
        elif s.kind in ("tip_x", "tip_y"):
            add(Probe("point", s.link, s.station))
    m = mech.manoeuvre
    if m is not None and m.tip is not None:
        add(Probe("point", m.tip.link, m.tip.station))
    return tuple(out)

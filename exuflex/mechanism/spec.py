"""Frozen description of a planar flexible-link mechanism.

This module is the root of exuflex's data flow: it imports nothing from the rest of the
package. A :class:`Mechanism` is produced by :func:`exuflex.mechanism.load_mechanism` from a
TOML model file (schema in ``models/README.md``) and consumed by both formulations: the ERLS
model (:mod:`exuflex.erls`) and the Exudyn ground truth (:mod:`exuflex.groundtruth`).

Conventions
-----------
- SI units throughout (m, kg, s, rad, N, N m, Pa).
- A link is a straight beam; its *stations* are distances from the link's start along its axis.
  Every station carries one finite-element node; nodes have global 1-based ids.
- Joints are revolute (link stations pinned together, optionally to the ground), prismatic (pinned
  together and sliding on a fixed line of the frame) or welded (two link stations at one place with a
  fixed angle between the links).
- ERLS coordinates ``q`` are absolute link angles, relative angles at a joint, or the position of a
  prismatic joint along its axis.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

__all__ = [
    "Coordinate",
    "Damping",
    "JOINT_KINDS",
    "Joint",
    "Link",
    "LinkPoint",
    "LumpedMass",
    "Manoeuvre",
    "Material",
    "Mechanism",
    "Motor",
    "ReductionSpec",
    "Section",
    "Sensor",
]


@dataclass(frozen=True)
class Material:
    name: str
    E: float  # Young's modulus, Pa
    rho: float  # density, kg/m^3
    nu: float = 0.3  # Poisson's ratio (solid links only: the beam models do not use it)


@dataclass(frozen=True)
class Section:
    """Cross-section: area A (m^2) and second moment I (m^4) about the out-of-plane axis.

    ``shape`` names the solid the section belongs to (the FFRF truth meshes it): ``"round"`` (``diameter``),
    ``"tube"`` (outer ``diameter``, ``inner_diameter``), ``"rectangle"`` (``height`` in the mechanism's plane,
    ``width`` normal to it); ``None``: only A and I are known (a beam model can use it, a solid cannot).
    """

    A: float
    I: float
    diameter: float | None = None  # outer diameter of a round section or a tube (used for gauges, m)
    height: float | None = None  # distance from neutral axis to the surface * 2 (m)
    shape: str | None = None  # round | tube | rectangle | None (A and I only)
    inner_diameter: float | None = None  # tube: bore diameter (m)
    width: float | None = None  # rectangle: extent normal to the mechanism's plane (m)


@dataclass(frozen=True)
class Link:
    name: str
    length: float
    material: Material
    section: Section
    stations: tuple[float, ...]  # node stations along the axis, ascending, first 0, last length
    node_ids: tuple[int, ...]  # global 1-based node id of each station
    angle_guess: float | None = None  # absolute angle at the reference configuration (branch selection)
    mesh_size: float | None = None  # solid mesh: largest tetrahedron edge (m); None: the FFRF truth's default

    @property
    def n_elements(self) -> int:
        return len(self.stations) - 1

    @property
    def mass(self) -> float:
        return self.material.rho * self.section.A * self.length

    def station_index(self, s: float, tol: float = 1e-9) -> int:
        for i, si in enumerate(self.stations):
            if abs(si - s) <= tol * max(1.0, self.length):
                return i
        raise KeyError(f"link {self.name!r} has no station at {s} m")


@dataclass(frozen=True)
class LinkPoint:
    """A point on a link's axis: link name and distance from the link's start (m)."""

    link: str
    station: float


JOINT_KINDS = ("revolute", "prismatic", "weld")


@dataclass(frozen=True)
class Joint:
    """A joint joining link points that sit at one place.

    kind ``revolute``: the points are pinned together; ``ground`` pins them to the frame.
    kind ``prismatic``: the points are pinned together and slide on the fixed line through ``ground``
    with unit direction ``axis``; the slider position is ``s = axis . (p - ground)``.
    kind ``weld``: two points; the links keep the angle ``angle = th(points[1].link) - th(points[0].link)``
    (their nodes share translations and rotation).
    """

    name: str
    points: tuple[LinkPoint, ...]
    ground: tuple[float, float] | None = None  # ground pin position, or a point of a prismatic axis (m)
    kind: str = "revolute"
    axis: tuple[float, float] | None = None  # prismatic: unit direction of the sliding line
    angle: float = 0.0  # weld: th(points[1].link) - th(points[0].link) (rad)

    @property
    def grounded(self) -> bool:
        """True if the joint ties its points to the frame (a ground pin or a prismatic axis)."""
        return self.ground is not None

    @property
    def normal(self) -> tuple[float, float] | None:
        """Prismatic: the unit normal of the axis (the axis turned by +90 degrees)."""
        return None if self.axis is None else (-self.axis[1], self.axis[0])


@dataclass(frozen=True)
class Coordinate:
    """An ERLS coordinate: the absolute angle of ``link`` (or relative to ``relative_to``) at ``joint``,
    or (kind ``slide``) the position of the prismatic ``joint`` along its axis.

    Its ERLS-defining constraint sets the elastic rotation of ``link``'s node at ``joint`` to zero, absolute or
    relative, so that ``link``'s ERLS frame is its tangent there: an absolute ``q`` is the angle an encoder at that
    joint reads, a relative ``q`` the difference of the two links' ERLS frames (``relative_to``'s frame is its own
    tangent at its own coordinate's joint), which the relative encoder reads plus the difference of the two nodes'
    elastic rotations at ``joint`` (:meth:`exuflex.erls.model.ErlsModel.coordinate_reading_rows`; the truths and the
    observer's estimates report the reading); for a slide coordinate it sets the elastic displacement of
    the slider's node along the axis to zero (``link``: the link of the joint's first point), so that
    ``q = axis . (p - ground) - offset`` is what a linear encoder on the slider reads.
    """

    name: str
    link: str
    joint: str
    relative_to: str | None = None
    offset: float = 0.0  # q = frame(link) - frame(relative_to) - offset (slide: axis . (p - ground) - offset)
    kind: str = "angle"  # angle | slide


@dataclass(frozen=True)
class Motor:
    """A torque actuator at ``joint``: +T on ``link``'s node there, -T on ``reaction``'s (None: ground)."""

    name: str
    joint: str
    link: str
    reaction: str | None = None
    noise_std: float = 0.0  # std of the measured torque (N m)
    full_scale: float | None = None  # ADC full scale of the measured torque (N m)


@dataclass(frozen=True)
class LumpedMass:
    """A point mass and a rotary inertia (about the mass point) carried rigidly by ``node``.

    ``offset`` is the mass point's position relative to the node in the frame of the node's link
    ``link`` (along the axis, normal to it; m); ``(0, 0)``: at the node (``link`` may then be empty).
    """

    node: int
    mass: float
    inertia: float = 0.0
    label: str = ""
    offset: tuple[float, float] = (0.0, 0.0)
    link: str = ""


@dataclass(frozen=True)
class Sensor:
    """A measured channel.

    kind: ``encoder`` (absolute angle of ``link`` at ``joint``, or relative to ``relative_to``),
    ``slider`` (position of the prismatic ``joint`` along its axis, ``axis . (p - ground)``, m;
    ``link`` is the link of the joint's first point),
    ``curvature`` (bending curvature of ``link`` at ``station``, 1/m),
    ``tip_x`` / ``tip_y`` (position of ``link`` at ``station``, m).
    ``noise_std`` is the white-noise standard deviation in the channel's unit;
    ``full_scale`` is the ADC full scale in that unit (``None``: no quantisation).
    """

    name: str
    kind: str
    link: str
    joint: str | None = None
    station: float | None = None
    relative_to: str | None = None
    noise_std: float = 0.0
    full_scale: float | None = None
    rate_hz: float | None = None  # None: the model's default measurement rate


@dataclass(frozen=True)
class Damping:
    """Rayleigh damping on the elastic block: C = alpha M_uu + beta K_uu."""

    alpha: float = 0.0
    beta: float = 0.0


@dataclass(frozen=True)
class Manoeuvre:
    """A planned motion: a path (in task or joint space) and a time law on s in [0, 1], or a torque record.

    kind ``joint``: every coordinate follows a rule ``q = start + (end - start) s``.
    kind ``tip_arc``: the point ``tip`` follows centre + radius [cos phi, sin phi],
    phi = phi_start + (phi_end - phi_start) s; the coordinates in ``rules`` follow their rules.
    kind ``tip_line`` / ``tip_polyline``: the tip runs through ``points`` segment by segment, resting at every
    point (each segment its share of ``duration`` in proportion to its length, with the time law); ``rules`` as
    for ``tip_arc``.
    kind ``waypoints``: the coordinates pass through ``waypoints`` (one row of nq values each) at ``times``,
    by ``interpolation`` ``quintic`` (rest at every waypoint) or ``spline`` (C2 cubic, rest at both ends).
    kind ``trajectory``: samples of ``t`` and ``columns`` (all coordinates, or ``tip_x``, ``tip_y`` and the other
    coordinates; optionally ``d<name>`` and ``dd<name>`` rates) read from the CSV ``file``.
    kind ``torque``: measured motor torques (``columns`` the motor names) from ``file``, applied open loop from
    the configuration ``q0`` at rest.
    """

    kind: str
    duration: float
    time_law: str = "trapezoid"  # trapezoid | quintic | cycloidal
    ramp_time: float = 0.0  # trapezoid acceleration time (s)
    tip: LinkPoint | None = None
    centre: tuple[float, float] | None = None
    radius: float | None = None
    phi_start: float | None = None
    phi_end: float | None = None
    rules: tuple[tuple[str, float, float], ...] = ()  # (coordinate, start, end)
    torque_noise: tuple[tuple[str, float], ...] = ()  # (motor name, std N m)
    points: tuple[tuple[float, float], ...] = ()  # tip_line, tip_polyline: the tip's corner points (m)
    times: tuple[float, ...] = ()  # waypoints: their times (s), from 0
    waypoints: tuple[tuple[float, ...], ...] = ()  # waypoints: q at each time
    interpolation: str = "quintic"  # waypoints: quintic | spline
    file: str = ""  # trajectory, torque: the CSV file the samples came from
    columns: tuple[str, ...] = ()  # trajectory, torque: the sample columns after t
    samples: tuple[tuple[float, ...], ...] = ()  # trajectory, torque: rows (t, values in columns order)
    q0: tuple[float, ...] = ()  # torque: the starting configuration (default: the model's q_ref)
    source: str = ""  # the file it was read from (the model file, a manoeuvre file), for messages


@dataclass(frozen=True)
class ReductionSpec:
    masters: tuple[str, ...] = ()  # elastic master dof names (the q are always masters)
    q_star: tuple[float, ...] | None = None
    band_hz: float = 180.0
    n_interior: int | None = None  # None: automatic from the accuracy thresholds
    nco_min: float = 0.99
    freq_error_max_pct: float = 2.0


ESTIMATOR_NAMES = ("ekf", "ukf", "ekf-payload", "ekf-input", "imm")
"""The observer's estimators a model file's ``[observer] estimator`` may name (``exuflex.observer.ESTIMATORS``)."""


@dataclass(frozen=True)
class ObserverSpec:
    """The model file's ``[observer]`` table: how this mechanism's observer is tuned (the fields of
    ``exuflex.observer.ObserverConfig`` of the same names; None: the observer's default). Command-line options
    and an explicit ``ObserverConfig`` take precedence."""

    channels: tuple[str, ...] | None = None
    method: str | None = None
    h: float | None = None
    q0_std: float | None = None
    qd0_std: float | None = None
    elastic0_std: float | None = None
    elastic_rate0_std: float | None = None
    q_scale: float | None = None
    q_extra_std: float | None = None
    jump_p: float | None = None
    max_gap: float | None = None
    start_up: float | None = None
    gate_p: float | None = None
    fault_window: int | None = None
    fault_p: float | None = None
    fault_holdoff_s: float | None = None
    fault_isolation: bool | None = None
    estimator: str | None = None
    payload_std: float | None = None
    payload0_std: float | None = None
    payload_nominal_p: float | None = None

    def settings(self) -> dict:
        """The fields the file sets, as ``ObserverConfig`` keyword arguments."""
        return {k: v for k, v in self.__dict__.items() if v is not None}


@dataclass(frozen=True)
class Mechanism:
    """A planar flexible-link mechanism (see module docstring for conventions)."""

    name: str
    source: str  # path of the model file it came from ("" if built in code)
    links: tuple[Link, ...]
    joints: tuple[Joint, ...]
    coordinates: tuple[Coordinate, ...]
    motors: tuple[Motor, ...]
    masses: tuple[LumpedMass, ...] = ()
    payload: LumpedMass | None = None
    damping: Damping = field(default_factory=Damping)
    sensors: tuple[Sensor, ...] = ()
    q_ref: tuple[float, ...] = ()
    manoeuvre: Manoeuvre | None = None
    reduction: ReductionSpec = field(default_factory=ReductionSpec)
    observer: ObserverSpec = field(default_factory=ObserverSpec)
    sample_rate_hz: float = 500.0
    gravity: tuple[float, float] = (0.0, 0.0)
    description: str = ""

    # ------------------------------------------------------------------ look-ups
    def link(self, name: str) -> Link:
        for lk in self.links:
            if lk.name == name:
                return lk
        raise KeyError(f"no link named {name!r}")

    def joint(self, name: str) -> Joint:
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(f"no joint named {name!r}")

    @property
    def coordinate_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.coordinates)

    @property
    def motor_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.motors)

    @property
    def node_ids(self) -> tuple[int, ...]:
        return tuple(sorted({n for lk in self.links for n in lk.node_ids}))

    def node_location(self, node: int) -> tuple[str, float]:
        """(link name, station) of a node id."""
        for lk in self.links:
            if node in lk.node_ids:
                return lk.name, lk.stations[lk.node_ids.index(node)]
        raise KeyError(f"no node {node}")

    def node_at(self, link: str, station: float) -> int:
        lk = self.link(link)
        return lk.node_ids[lk.station_index(station)]

    def all_masses(self) -> tuple[LumpedMass, ...]:
        """Lumped masses including the tip payload."""
        return self.masses + ((self.payload,) if self.payload is not None else ())

    # ------------------------------------------------------------------ variants
    def with_payload_scale(self, scale: float) -> Mechanism:
        """A copy whose tip payload (mass and inertia) is multiplied by ``scale``."""
        if self.payload is None:
            raise ValueError(f"{self.source or self.name}: model has no [payload] to scale")
        p = dataclasses.replace(self.payload, mass=self.payload.mass * scale, inertia=self.payload.inertia * scale)
        return dataclasses.replace(self, payload=p)

    def replace(self, **changes) -> Mechanism:
        return dataclasses.replace(self, **changes)

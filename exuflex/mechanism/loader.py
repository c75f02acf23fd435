"""Load and validate TOML mechanism files (schema: ``models/README.md``).

Every mistake becomes a :class:`ModelFileError` naming the file, the field (a dotted path such
as ``links[2].diameter``) and what was expected.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import tomllib
from pathlib import Path
from typing import Any

from .limits import element_count_error, limit_errors
from .spec import (
    ESTIMATOR_NAMES,
    JOINT_KINDS,
    Coordinate,
    Damping,
    Joint,
    Link,
    LinkPoint,
    LumpedMass,
    Manoeuvre,
    Material,
    Mechanism,
    Motor,
    ObserverSpec,
    ReductionSpec,
    Section,
    Sensor,
)

__all__ = ["RESERVED_COLUMNS", "ModelFileError", "column_name_problem", "load_manoeuvre", "load_mechanism", "parse_mechanism", "read_samples"]

SENSOR_KINDS = ("encoder", "slider", "curvature", "tip_x", "tip_y")
TIME_LAWS = ("trapezoid", "quintic", "cycloidal")
MANOEUVRE_KINDS = ("joint", "tip_arc", "tip_line", "tip_polyline", "waypoints", "trajectory", "torque")
TIP_KINDS = ("tip_arc", "tip_line", "tip_polyline")
INTERPOLATIONS = ("quintic", "spline")


class ModelFileError(ValueError):
    """A model file is malformed; the message names the file, the field and what was expected."""

    def __init__(self, source: str, field: str, expected: str, got: Any = None, *, has_got: bool = True):
        self.source, self.field, self.expected = source, field, expected
        msg = f"{source}: {field}: expected {expected}"
        if has_got:
            msg += f", got {got!r}"
        super().__init__(msg)


class UsageError(ValueError):
    """An argument of a command or of a public function is invalid; the message names the argument (the
    command-line flag, or the function's parameter) and what was expected. (Defined here, with the model file's
    error, as the mechanism stage imports nothing from the rest; :mod:`exuflex.errors` exports it.)"""


class _Reader:
    """Typed access to a TOML table that reports errors with the field path."""

    def __init__(self, source: str, table: dict, path: str):
        self.source, self.table, self.path = source, table, path
        self.used: set[str] = set()

    def _f(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path and key else (self.path or key)

    def err(self, key: str, expected: str, got: Any = None, has_got: bool = True) -> ModelFileError:
        return ModelFileError(self.source, self._f(key), expected, got, has_got=has_got)

    def has(self, key: str) -> bool:
        return key in self.table

    def raw(self, key: str, default: Any = ...) -> Any:
        self.used.add(key)
        if key not in self.table:
            if default is ...:
                raise self.err(key, "this required key", has_got=False)
            return default
        return self.table[key]

    def str(self, key: str, default: Any = ...) -> str:
        v = self.raw(key, default)
        if v is default and default is not ...:
            return v
        if not isinstance(v, str) or not v:
            raise self.err(key, "a non-empty string", v)
        return v

    def column(self, key: str) -> str:
        """A name that becomes a CSV column header of the run files (sensor, motor, coordinate):
        see :func:`column_name_problem`."""
        v = self.str(key)
        why = column_name_problem(v)
        if why is not None:
            raise self.err(key, f"a name usable as a CSV column header ({why})", v)
        return v

    def num(self, key: str, default: Any = ..., *, positive=False, nonneg=False, lo=None, hi=None, unit="") -> float:
        v = self.raw(key, default)
        if v is default and default is not ...:
            return v
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.err(key, f"a finite number{(' in ' + unit) if unit else ''}", v)
        v = float(v)
        if positive and v <= 0:
            raise self.err(key, f"a positive number{(' in ' + unit) if unit else ''}", v)
        if nonneg and v < 0:
            raise self.err(key, f"a number >= 0{(' in ' + unit) if unit else ''}", v)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.err(key, f"a value in [{lo:g}, {hi:g}] {unit} (SI units)".rstrip(), v)
        return v

    def int(self, key: str, default: Any = ..., *, positive=False) -> int:
        v = self.raw(key, default)
        if v is default and default is not ...:
            return v
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.err(key, "an integer", v)
        if positive and v <= 0:
            raise self.err(key, "a positive integer", v)
        return v

    def nums(self, key: str, default: Any = ..., *, length: int | None = None) -> tuple[float, ...]:
        v = self.raw(key, default)
        if v is default and default is not ...:
            return v
        ok = isinstance(v, list) and all(
            not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) for x in v
        )
        if not ok or (length is not None and len(v) != length):
            what = f"a list of {length} numbers" if length is not None else "a list of numbers"
            raise self.err(key, what, v)
        return tuple(float(x) for x in v)

    def table_list(self, key: str, required: bool = True) -> list[_Reader]:
        v = self.raw(key, ... if required else [])
        if not isinstance(v, list) or not all(isinstance(x, dict) for x in v):
            raise self.err(key, "an array of tables ([[" + key + "]])", type(v).__name__)
        return [_Reader(self.source, x, f"{self._f(key)}[{i}]") for i, x in enumerate(v)]

    def sub(self, key: str, required: bool = False) -> _Reader | None:
        v = self.raw(key, ... if required else None)
        if v is None:
            return None
        if not isinstance(v, dict):
            raise self.err(key, "a table", v)
        return _Reader(self.source, v, self._f(key))

    def check_unknown(self) -> None:
        extra = sorted(set(self.table) - self.used)
        if extra:
            raise ModelFileError(
                self.source, self._f(extra[0]), f"one of the known keys {sorted(self.used)}", extra[0]
            )


RESERVED_COLUMNS = ("time",)
"""Names the run files use themselves (the time column of ``sensors.csv`` and ``truth.csv``)."""


def column_name_problem(name: str) -> str | None:
    """None if ``name`` can be a column of the run files' CSV header (``time,q1,...``, read back by splitting
    at commas and stripping each cell), else what is wrong: a comma or a double quote (CSV syntax), a control
    character such as a newline or a tab (the header is one line), a name that is blank or has leading or
    trailing spaces (stripped on reading, it would not match), or a reserved name (:data:`RESERVED_COLUMNS`)."""
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return "valid Unicode text (the run files are UTF-8)"
    if not name.strip():
        return "not blank"
    if name != name.strip():
        return "no leading or trailing spaces"
    bad = sorted({c for c in name if c in ',"' or ord(c) < 32 or ord(c) == 127})
    if bad:
        return f"no comma, double quote or control character such as a newline; it has {bad}"
    if name in RESERVED_COLUMNS:
        return f"not {name!r}, the run files' time column"
    return None


def load_mechanism(path: str | Path) -> Mechanism:
    """Read and validate a TOML mechanism file (UTF-8; a byte-order mark, as some editors write, is skipped)."""
    if not isinstance(path, (str, os.PathLike)) or not str(path).strip():
        raise UsageError(f"path: expected the path of a model file (str or pathlib.Path), got {type(path).__name__}"
                         + (" (already loaded: pass it on directly)" if isinstance(path, Mechanism) else ""))
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise ModelFileError(src, "(file)", "an existing TOML model file", has_got=False)
    try:
        raw = path.read_bytes()
        data = tomllib.loads(raw.decode("utf-8-sig"))
    except tomllib.TOMLDecodeError as exc:
        raise ModelFileError(src, "(syntax)", f"valid TOML ({exc})", has_got=False) from None
    except UnicodeDecodeError:
        raise ModelFileError(src, "(file)", "a UTF-8 text file", has_got=False) from None
    except OSError as exc:
        raise ModelFileError(src, "(file)", f"a readable file ({exc.strerror or exc})", has_got=False) from None
    return parse_mechanism(data, src)


def parse_mechanism(data: dict, source: str = "<model>") -> Mechanism:
    """Validate a parsed TOML document and build the :class:`Mechanism`."""
    root = _Reader(source, data, "")
    model = root.sub("model", required=True)
    name = model.str("name")
    description = model.str("description", "")
    sample_rate = model.num("sample_rate_hz", 500.0, positive=True, unit="Hz")
    gravity = model.nums("gravity", (0.0, 0.0), length=2)
    model.raw("reference", "")  # free-text provenance
    q_ref_raw = model.raw("q_ref", None)

    materials: dict[str, Material] = {}
    for r in root.table_list("materials"):
        m = Material(r.str("name"), r.num("E", lo=1e6, hi=1e13, unit="Pa"), r.num("rho", lo=30.0, hi=3e4, unit="kg/m^3"),
                     r.num("nu", 0.3, lo=0.0, hi=0.49))
        if m.name in materials:
            raise r.err("name", "a unique material name", m.name)
        materials[m.name] = m
        r.check_unknown()

    links = _parse_links(root, materials)
    link_by = {lk.name: lk for lk in links}

    def link_ref(r: _Reader, key: str, default: Any = ...) -> str | None:
        v = r.raw(key, default)
        if v is None and default is None:
            return None
        if not isinstance(v, str) or v not in link_by:
            raise r.err(key, f"a link name, one of {sorted(link_by)}", v)
        return v

    def point(r: _Reader, where: str) -> LinkPoint:
        return _point(r, link_by, where)

    joints: list[Joint] = []
    for r in root.table_list("joints"):
        pts = []
        raw_points = r.raw("points")
        if not isinstance(raw_points, list):
            raise r.err("points", "a list of points [{link = ..., station = ...}, ...]", raw_points)
        for i, p in enumerate(raw_points):
            if not isinstance(p, dict):
                raise r.err(f"points[{i}]", "an inline table {link = ..., station = ...}", p)
            pr = _Reader(source, p, f"{r.path}.points[{i}]")
            pts.append(point(pr, "node"))
            pr.check_unknown()
        jname = r.str("name")
        kind = r.str("kind", "revolute")
        if kind not in JOINT_KINDS:
            raise r.err("kind", f"one of {list(JOINT_KINDS)}", kind)
        axis, angle = None, 0.0
        if kind == "prismatic":
            ground = r.nums("ground", length=2)
            axis = r.nums("axis", length=2)
            na = math.hypot(*axis)
            axis = (axis[0] / na, axis[1] / na) if na > 0 else axis
            if min(abs(axis[0]), abs(axis[1])) > 1e-12:
                # the elastic dofs are global x, y displacements (0/1 map T): the line's normal must be one of them
                raise r.err("axis", "a direction along the global x or y axis ([1, 0], [0, 1], [-1, 0] or [0, -1]):"
                            " elastic displacements are global x, y components", list(axis))
            axis = (float(round(axis[0])), float(round(axis[1])))
        elif kind == "weld":
            ground = None
            if r.has("ground"):
                raise r.err("ground", "no ground position on a weld (it joins two links)", r.table["ground"])
            angle = r.num("angle", unit="rad")
            if len(pts) != 2:
                raise r.err("points", "exactly two link points (a weld joins two links)", len(pts))
        else:
            ground = r.nums("ground", None, length=2)
        if len(pts) < (1 if ground is not None else 2):
            raise r.err("points", "at least two link points (or one with a ground position)", len(pts))
        if any(j.name == jname for j in joints):
            raise r.err("name", "a unique joint name", jname)
        joints.append(Joint(jname, tuple(pts), ground, kind, axis, angle))
        r.check_unknown()
    joint_by = {j.name: j for j in joints}

    def joint_ref(r: _Reader, key: str, link: str | None = None) -> str:
        v = r.raw(key)
        if not isinstance(v, str) or v not in joint_by:
            raise r.err(key, f"a joint name, one of {sorted(joint_by)}", v)
        if link is not None and link not in [p.link for p in joint_by[v].points]:
            raise r.err(key, f"a joint that link {link!r} takes part in", v)
        return v

    coords = []
    for r in root.table_list("coordinates"):
        v = r.table.get("joint")
        if not r.has("link") and isinstance(v, str) and v in joint_by and joint_by[v].kind == "prismatic":
            # the slider position along its axis
            c = Coordinate(r.column("name"), joint_by[v].points[0].link, joint_ref(r, "joint"), None,
                           r.num("offset", 0.0, unit="m"), "slide")
        else:
            lk = link_ref(r, "link")
            c = Coordinate(
                r.column("name"), lk, joint_ref(r, "joint", lk), link_ref(r, "relative_to", None), r.num("offset", 0.0)
            )
        if c.relative_to is not None and c.relative_to not in [p.link for p in joint_by[c.joint].points]:
            raise r.err("relative_to", f"a link at joint {c.joint!r}", c.relative_to)
        coords.append(c)
        r.check_unknown()
    if not coords:
        raise root.err("coordinates", "at least one ERLS coordinate", has_got=False)
    _unique(source, "coordinates", [c.name for c in coords])

    motors = []
    for r in root.table_list("motors", required=False):
        lk = link_ref(r, "link")
        m = Motor(
            r.column("name"),
            joint_ref(r, "joint", lk),
            lk,
            link_ref(r, "reaction", None),
            r.num("noise_std", 0.0, nonneg=True, unit="N m"),
            r.num("full_scale", None, positive=True, unit="N m"),
        )
        if m.reaction is not None and m.reaction not in [p.link for p in joint_by[m.joint].points]:
            raise r.err("reaction", f"a link at joint {m.joint!r}", m.reaction)
        if m.reaction is None and (joint_by[m.joint].ground is None or joint_by[m.joint].kind == "prismatic"):
            raise r.err("reaction", f"a reaction link (joint {m.joint!r} is not a ground pin)", None)
        motors.append(m)
        r.check_unknown()
    _unique(source, "motors", [m.name for m in motors])

    all_nodes = {n for lk in links for n in lk.node_ids}

    def mass_entry(r: _Reader) -> LumpedMass:
        if r.has("node"):
            node = r.int("node", positive=True)
            if node not in all_nodes:
                raise r.err("node", f"an existing node id (1..{max(all_nodes)})", node)
            lname = next(lk.name for lk in links if node in lk.node_ids)
        else:
            p = point(r, "node")
            node = link_by[p.link].node_ids[link_by[p.link].station_index(p.station)]
            lname = p.link
        lm = LumpedMass(node, r.num("mass", nonneg=True, unit="kg"), r.num("inertia", 0.0, nonneg=True, unit="kg m^2"),
                        r.str("label", ""), r.nums("offset", (0.0, 0.0), length=2), lname)
        r.check_unknown()
        return lm

    masses = tuple(mass_entry(r) for r in root.table_list("masses", required=False))
    pr = root.sub("payload")
    payload = mass_entry(pr) if pr is not None else None

    dr = root.sub("damping")
    damping = Damping()
    if dr is not None:
        damping = Damping(dr.num("alpha", 0.0, nonneg=True, unit="1/s"), dr.num("beta", 0.0, nonneg=True, unit="s"))
        dr.check_unknown()

    sensors = []
    for r in root.table_list("sensors", required=False):
        kind = r.str("kind")
        if kind not in SENSOR_KINDS:
            raise r.err("kind", f"one of {list(SENSOR_KINDS)}", kind)
        joint = station = rel = None
        if kind == "slider":
            v = r.table.get("joint")
            if not (isinstance(v, str) and v in joint_by and joint_by[v].kind == "prismatic"):
                raise r.err("joint", "a prismatic joint name, one of "
                            f"{sorted(j.name for j in joints if j.kind == 'prismatic')}", v)
            lk = link_ref(r, "link", joint_by[v].points[0].link)
            joint = joint_ref(r, "joint", lk)
        else:
            lk = link_ref(r, "link")
        if kind == "encoder":
            joint = joint_ref(r, "joint", lk)
            rel = link_ref(r, "relative_to", None)
            if rel is not None and rel not in [p.link for p in joint_by[joint].points]:
                raise r.err("relative_to", f"a link at joint {joint!r}", rel)
            if rel is not None and rel == lk:  # an angle relative to itself: always zero
                others = [p.link for p in joint_by[joint].points if p.link != lk]
                raise r.err("relative_to", f"another link at joint {joint!r} than the encoder's own link {lk!r}"
                            + (f" (one of {others})" if others else " (or no relative_to: the absolute angle)"), rel)
        elif kind != "slider":
            station = point(r, "any").station
        sensors.append(
            Sensor(
                r.column("name"), kind, lk, joint, station, rel,
                r.num("noise_std", 0.0, nonneg=True),
                r.num("full_scale", None, positive=True),
                r.num("rate_hz", None, positive=True, unit="Hz"),
            )
        )
        r.check_unknown()
    _unique(source, "sensors", [s.name for s in sensors], {m.name: f"motors[{i}]" for i, m in enumerate(motors)})

    _check_mobility(source, links, joints, coords)  # a missing coordinate named before the lists sized by them
    nq = len(coords)
    q_ref: tuple[float, ...] = ()
    if q_ref_raw is not None:
        q_ref = model.nums("q_ref", length=nq)
    model.check_unknown()

    manoeuvre = _parse_manoeuvre(root.sub("manoeuvre"), link_by, [c.name for c in coords], [m.name for m in motors],
                                 _base_dir(source))

    red = root.sub("reduction")
    reduction = ReductionSpec()
    if red is not None:
        masters = red.raw("masters", [])
        if not isinstance(masters, list):
            raise red.err("masters", MASTERS_EXPECTED, masters)
        masters = [_master_name(red, i, m, link_by) for i, m in enumerate(masters)]
        n_int = red.raw("n_interior", "auto")
        if n_int != "auto" and (isinstance(n_int, bool) or not isinstance(n_int, int) or n_int < 0):
            raise red.err("n_interior", "a non-negative integer or \"auto\"", n_int)
        reduction = ReductionSpec(
            tuple(masters),
            red.nums("q_star", None, length=nq),
            red.num("band_hz", 180.0, positive=True, unit="Hz"),
            None if n_int == "auto" else n_int,
            red.num("nco_min", 0.99, lo=0.0, hi=1.0),
            red.num("freq_error_max_pct", 2.0, positive=True, unit="%"),
        )
        red.check_unknown()
    observer = _parse_observer(root.sub("observer"), [s.name for s in sensors])
    root.check_unknown()

    mech = Mechanism(
        name=name,
        source=source,
        links=links,
        joints=tuple(joints),
        coordinates=tuple(coords),
        motors=tuple(motors),
        masses=masses,
        payload=payload,
        damping=damping,
        sensors=tuple(sensors),
        q_ref=q_ref,
        manoeuvre=manoeuvre,
        reduction=reduction,
        observer=observer,
        sample_rate_hz=sample_rate,
        gravity=tuple(gravity),
        description=description,
    )
    _check_topology(mech)
    for fld, expected, got in limit_errors(mech):  # size and conditioning (exuflex.mechanism.limits)
        raise ModelFileError(source, fld, expected, got)
    return mech


def _point(r: _Reader, link_by: dict, where: str) -> LinkPoint:
    """A point ``{link, station}``: on the link (``where = "any"``) or at one of its node stations (``"node"``)."""
    v = r.raw("link")
    if not isinstance(v, str) or v not in link_by:
        raise r.err("link", f"a link name, one of {sorted(link_by)}", v)
    lk = link_by[v]
    s = r.num("station", lo=0.0, hi=lk.length, unit="m")
    if where == "node":
        try:
            lk.station_index(s)
        except KeyError:
            raise r.err("station", f"one of link {lk.name!r}'s stations {list(lk.stations)}", s) from None
    return LinkPoint(lk.name, s)


def _unique(source: str, field: str, names: list[str], others: dict[str, str] | None = None) -> None:
    """Each of ``field``'s entry names used once, and not one of ``others`` (name -> its field): names that
    share a CSV header (sensors and motors in ``sensors.csv``)."""
    seen = dict(others or {})
    for i, n in enumerate(names):
        if n in seen:
            raise ModelFileError(source, f"{field}[{i}].name",
                                 f"a name not used by {seen[n]} (sensor and motor names are the columns of "
                                 "sensors.csv and may not repeat)" if field != "coordinates"
                                 else f"a name not used by {seen[n]}", n)
        seen[n] = f"{field}[{i}]"


def _parse_section(r: _Reader, length: float) -> Section:
    """The link's cross-section: a round bar (``diameter``), a tube (``diameter``, ``inner_diameter``), a rectangle
    (``height`` in the plane, ``width`` normal to it) or only ``A`` and ``I`` (with an optional ``height``)."""
    solid_keys = [k for k in ("diameter", "inner_diameter", "width") if r.has(k)]
    if (r.has("A") or r.has("I")) and solid_keys:
        raise r.err("A", f"either {' and '.join(solid_keys)} or A and I, not both", r.table.get("A"))
    if r.has("diameter"):
        d = r.num("diameter", positive=True, unit="m")
        if d >= length:
            raise r.err("diameter", f"a diameter (m) smaller than the link length {length} m: mm by mistake?", d)
        if r.has("width") or r.has("height"):
            key = "width" if r.has("width") else "height"
            raise r.err(key, "no width or height with a diameter (a rectangle has width and height, no diameter)",
                        r.table[key])
        if r.has("inner_diameter"):
            di = r.num("inner_diameter", positive=True, unit="m")
            if di >= d:
                raise r.err("inner_diameter", f"a bore diameter (m) smaller than the outer diameter {d} m", di)
            return Section(math.pi * (d**2 - di**2) / 4, math.pi * (d**4 - di**4) / 64, d, d, "tube", di)
        return Section(math.pi * d**2 / 4, math.pi * d**4 / 64, d, d, "round")
    if r.has("inner_diameter"):
        raise r.err("diameter", "the outer diameter (m) of the tube", has_got=False)
    if r.has("width"):
        w = r.num("width", positive=True, unit="m")
        h = r.num("height", positive=True, unit="m")
        for k, v in (("width", w), ("height", h)):
            if v >= length:
                raise r.err(k, f"a section size (m) smaller than the link length {length} m: mm by mistake?", v)
        return Section(w * h, w * h**3 / 12, None, h, "rectangle", None, w)
    if not (r.has("A") and r.has("I")):
        raise r.err("diameter", "a diameter (m), a diameter and inner_diameter (tube), width and height "
                    "(rectangle) or both A (m^2) and I (m^4)", has_got=False)
    A = r.num("A", positive=True, unit="m^2")
    I = r.num("I", positive=True, unit="m^4")
    if A >= length**2:
        raise r.err("A", f"an area (m^2) much smaller than length^2 = {length**2:g}", A)
    h = r.num("height", None, positive=True, unit="m")
    return Section(A, I, None, h)


def _parse_links(root: _Reader, materials: dict[str, Material]) -> tuple[Link, ...]:
    links: list[Link] = []
    next_auto = None
    readers = root.table_list("links")
    if not readers:
        raise root.err("links", "at least one [[links]] table", has_got=False)
    explicit_ids = set()
    for r in readers:
        if r.has("nodes"):
            v = r.table["nodes"]
            if isinstance(v, list):
                explicit_ids.update(x for x in v if isinstance(x, int))
    next_auto = max(explicit_ids, default=0) + 1
    n_total = 0  # elements so far
    for r in readers:
        name = r.str("name")
        length = r.num("length", positive=True, unit="m")
        mat = r.raw("material")
        if not isinstance(mat, str) or mat not in materials:
            raise r.err("material", f"a material name, one of {sorted(materials)}", mat)
        sec = _parse_section(r, length)
        if r.has("stations"):
            st = r.nums("stations")
            if r.has("n_elements"):
                raise r.err("n_elements", "either stations or n_elements, not both", r.table["n_elements"])
            if len(st) < 2 or abs(st[0]) > 1e-12 or abs(st[-1] - length) > 1e-9 * length or any(
                b <= a for a, b in zip(st, st[1:])
            ):
                raise r.err("stations", f"ascending stations from 0 to the length {length} m", list(st))
            st = (0.0,) + tuple(st[1:-1]) + (length,)
        else:
            ne = r.int("n_elements", 1, positive=True)
            why = element_count_error(n_total + ne)
            if why is not None:  # before the stations are built
                raise r.err("n_elements", why + " with the links before it", ne)
            st = tuple(length * i / ne for i in range(ne + 1))
        n_total += len(st) - 1
        if r.has("nodes"):
            ids = r.raw("nodes")
            if not isinstance(ids, list) or len(ids) != len(st) or not all(
                isinstance(i, int) and not isinstance(i, bool) and i > 0 for i in ids
            ):
                raise r.err("nodes", f"a list of {len(st)} positive node ids (one per station)", ids)
            ids = tuple(ids)
        else:
            ids = tuple(range(next_auto, next_auto + len(st)))
            next_auto += len(st)
        for other in links:
            if other.name == name:
                raise r.err("name", "a unique link name", name)
            if set(other.node_ids) & set(ids):
                raise r.err("nodes", f"node ids not used by link {other.name!r} (links joined rigidly: a [[joints]] "
                            "table with kind = \"weld\")", list(ids))
        if len(set(ids)) != len(ids):
            raise r.err("nodes", "distinct node ids", list(ids))
        mesh_size = r.num("mesh_size", None, positive=True, unit="m")
        if mesh_size is not None and mesh_size >= length:
            raise r.err("mesh_size", f"a mesh size (m) smaller than the link length {length} m", mesh_size)
        links.append(Link(name, length, materials[mat], sec, st, ids, r.num("angle_guess", None), mesh_size))
        r.check_unknown()
    return tuple(links)


MASTERS_EXPECTED = ("a list of elastic dof names such as 'x14', 'node8.x', 'node8.theta' or 'node8.transverse', "
                    "or points { link, station, direction } with direction axial, transverse or theta")


def _parse_observer(obs: _Reader | None, sensor_names: list[str]) -> ObserverSpec:
    """The ``[observer]`` table (:class:`ObserverSpec`): each key type- and range-checked here, so that a bad
    value is an error naming the file and ``observer.<key>`` before anything runs."""
    if obs is None:
        return ObserverSpec()
    kw: dict[str, Any] = {}
    if obs.has("channels"):
        ch = obs.raw("channels")
        if not isinstance(ch, list) or not ch or not all(isinstance(c, str) for c in ch):
            raise obs.err("channels", "a non-empty list of sensor names", ch)
        for i, c in enumerate(ch):
            if c not in sensor_names:
                raise obs.err(f"channels[{i}]", f"one of the model's sensors {sensor_names}", c)
            if c in ch[:i]:
                raise obs.err(f"channels[{i}]", "a sensor not listed before", c)
        kw["channels"] = tuple(ch)
    if obs.has("method"):
        kw["method"] = obs.str("method")
        if kw["method"] not in ("cached", "rk4"):
            raise obs.err("method", '"cached" or "rk4"', kw["method"])
    if obs.has("estimator"):
        kw["estimator"] = obs.str("estimator")
        if kw["estimator"] not in ESTIMATOR_NAMES:
            raise obs.err("estimator", f"one of {list(ESTIMATOR_NAMES)}", kw["estimator"])
    for key, unit in (("h", "s"), ("q0_std", "rad"), ("qd0_std", "rad/s"), ("elastic0_std", ""),
                      ("elastic_rate0_std", ""), ("q_scale", ""), ("max_gap", "s"), ("payload_std", ""),
                      ("payload0_std", "")):
        if obs.has(key):
            kw[key] = obs.num(key, positive=True, unit=unit)
    for key, unit in (("q_extra_std", ""), ("start_up", "s"), ("fault_holdoff_s", "s")):
        if obs.has(key):
            kw[key] = obs.num(key, nonneg=True, unit=unit)
    for key in ("gate_p", "fault_p", "jump_p"):
        if obs.has(key):
            v = obs.num(key)
            if not 0.0 < v < 0.5:
                raise obs.err(key, "a false-alarm probability in (0, 0.5)", v)
            kw[key] = v
    if obs.has("payload_nominal_p"):
        v = obs.num("payload_nominal_p")
        if not 0.0 <= v <= 1.0:
            raise obs.err("payload_nominal_p", "a probability in [0, 1]", v)
        kw["payload_nominal_p"] = v
    if obs.has("fault_window"):
        w = obs.int("fault_window")
        if w != 0 and w < 2:
            raise obs.err("fault_window", "0 (no sensor-fault tests) or an integer >= 2 (samples)", w)
        kw["fault_window"] = w
    if obs.has("fault_isolation"):
        v = obs.raw("fault_isolation")
        if not isinstance(v, bool):
            raise obs.err("fault_isolation", "true or false", v)
        kw["fault_isolation"] = v
    obs.used.update(ObserverSpec.__dataclass_fields__)  # every key the table may have (the error lists them)
    obs.check_unknown()
    return ObserverSpec(**kw)


def _master_name(red: _Reader, i: int, m: Any, link_by) -> str:
    """A ``[reduction] masters`` entry as a dof name: strings as given, a point ``{ link, station, direction }``
    as ``node{n}.{direction}`` of the node at that station (axial and transverse in the link's frame)."""
    if isinstance(m, str) and m:
        return m
    if not isinstance(m, dict):
        raise red.err(f"masters[{i}]", MASTERS_EXPECTED, m)
    r = _Reader(red.source, m, red._f(f"masters[{i}]"))
    name = r.raw("link")
    if not isinstance(name, str) or name not in link_by:
        raise r.err("link", f"a link name, one of {sorted(link_by)}", name)
    lk = link_by[name]
    st = r.num("station", lo=0.0, hi=lk.length, unit="m")
    try:
        node = lk.node_ids[lk.station_index(st)]
    except KeyError:
        raise r.err("station", f"one of link {lk.name!r}'s stations {list(lk.stations)}", st) from None
    direction = r.raw("direction")
    if direction not in ("axial", "transverse", "theta"):
        raise r.err("direction", "'axial', 'transverse' or 'theta'", direction)
    r.check_unknown()
    return f"node{node}.{direction}"


def _base_dir(source: str) -> Path:
    """The folder that relative file names in a model file refer to."""
    p = Path(source)
    return p.parent if p.suffix else Path(".")


def read_samples(path: str | Path) -> tuple[tuple[str, ...], tuple[tuple[float, ...], ...]]:
    """Read a CSV table of samples: a header row of column names, the first ``t`` (s), then one row of numbers
    per time; times start at 0 and increase. Blank lines and lines starting with ``#`` are skipped.

    Returns the column names after ``t`` and the rows ``(t, values...)``. Every mistake raises
    :class:`ModelFileError` naming the file, the line and column, and what was expected.
    """
    src = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ModelFileError(src, "(file)", "an existing CSV file", has_got=False) from None
    except UnicodeDecodeError:
        raise ModelFileError(src, "(file)", "a UTF-8 text file", has_got=False) from None
    header: list[str] | None = None
    rows: list[tuple[float, ...]] = []
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        cells = [c.strip() for c in line.split(",")]
        if header is None:
            header = cells
            if header[0] != "t":
                raise ModelFileError(src, f"line {n}, column 1", "the header 't' (time, s) first", header[0])
            for i, c in enumerate(header):
                if not c:
                    raise ModelFileError(src, f"line {n}, column {i + 1}", "a column name", c)
                if c in header[:i]:
                    raise ModelFileError(src, f"line {n}, column {i + 1}", "unique column names", c)
            continue
        if len(cells) != len(header):
            raise ModelFileError(src, f"line {n}", f"{len(header)} values ({', '.join(header)})", len(cells))
        row = []
        for c, name in zip(cells, header, strict=True):
            try:
                v = float(c)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise ModelFileError(src, f"line {n}, column {name}", "a finite number", c)
            row.append(v)
        if not rows and row[0] != 0.0:
            raise ModelFileError(src, f"line {n}, column t", "0 (the samples start at t = 0 s)", row[0])
        if rows and not row[0] > rows[-1][0]:
            raise ModelFileError(src, f"line {n}, column t", f"a time after {rows[-1][0]!r} s", row[0])
        rows.append(tuple(row))
    if header is None or len(rows) < 2:
        raise ModelFileError(src, "(file)", "a header row and at least 2 rows of samples", has_got=False)
    return tuple(header[1:]), tuple(rows)


def position_columns(columns, coord_names) -> list[str]:
    """The position columns of a trajectory table: all but the rates ``d<name>`` and ``dd<name>`` of another
    column (a coordinate's own name is always a position)."""
    cols = set(columns)

    def rate(c: str) -> bool:
        return c not in coord_names and ((c.startswith("dd") and c[2:] in cols) or (c.startswith("d") and c[1:] in cols))

    return [c for c in columns if not rate(c)]


def _check_trajectory_columns(src: str, columns: tuple[str, ...], coord_names: list[str], tip: bool) -> None:
    """Positions: every coordinate, or ``tip_x``, ``tip_y`` and the other coordinates; rates ``d<name>`` for all
    of them or none, accelerations ``dd<name>`` only with the rates, for all or none."""
    pos = position_columns(columns, coord_names)
    if {"tip_x", "tip_y"} & set(pos):
        want = ["tip_x", "tip_y"]
    else:
        want = list(coord_names)
    for c in pos:
        if c not in want and c not in coord_names:
            raise ModelFileError(src, f"column {c}", f"a coordinate name {coord_names}, tip_x/tip_y or a rate "
                                 "d<name>/dd<name> of a position column", c)
    if "tip_x" in want:
        if not tip:
            raise ModelFileError(src, "column tip_x", "a tip point to follow (the [manoeuvre] table's tip, or the "
                                 "model's manoeuvre tip or tip_x sensor)", has_got=False)
        others = [c for c in pos if c not in want]
        if len(others) != len(coord_names) - 2 or len(pos) != len(set(pos)):
            raise ModelFileError(src, "(header)", f"t, tip_x, tip_y and {len(coord_names) - 2} of the coordinates "
                                 f"{coord_names} (the tip fixes the other 2)", list(columns))
        want = want + others
    missing = [c for c in want if c not in pos]
    if missing:
        raise ModelFileError(src, "(header)", f"a column for every coordinate {coord_names} (or tip_x, tip_y and "
                             f"{len(coord_names) - 2} of them)", list(columns))
    rates = [p + c for p in ("d", "dd") for c in want]
    have = [c for c in rates if c in columns]
    if have and len(have) != len(rates):
        miss = [c for c in rates if c not in columns]
        raise ModelFileError(src, f"column {miss[0]}", f"the rates d<name> and accelerations dd<name> of all of "
                             f"{want}, or none", has_got=False)


def _samples_manoeuvre(src: str, columns, rows, coord_names, motor_names, tip, kind: str | None = None,
                       q0: tuple[float, ...] = ()) -> Manoeuvre:
    """A trajectory or torque manoeuvre from a sample table (kind from the columns if not given)."""
    if kind is None:
        kind = "torque" if motor_names and set(columns) <= set(motor_names) else "trajectory"
    if kind == "torque":
        unknown = [c for c in columns if c not in motor_names]
        if unknown:
            raise ModelFileError(src, f"column {unknown[0]}", f"a motor name, one of {list(motor_names)}", unknown[0])
        missing = [m for m in motor_names if m not in columns]
        if missing:
            raise ModelFileError(src, "(header)", f"a column for every motor {list(motor_names)}", list(columns))
    else:
        _check_trajectory_columns(src, columns, coord_names, tip is not None)
    return Manoeuvre(kind, rows[-1][0], time_law="quintic", tip=tip, file=src, columns=tuple(columns),
                     samples=tuple(rows), q0=tuple(q0))


def _parse_manoeuvre(r: _Reader | None, link_by, coord_names, motor_names, base: Path) -> Manoeuvre | None:
    if r is None:
        return None
    man = _parse_manoeuvre_table(r, link_by, coord_names, motor_names, base)
    return dataclasses.replace(man, source=r.source)


def _parse_manoeuvre_table(r: _Reader, link_by, coord_names, motor_names, base: Path) -> Manoeuvre:
    nq = len(coord_names)
    kind = r.str("kind")
    if kind not in MANOEUVRE_KINDS:
        raise r.err("kind", f"one of {list(MANOEUVRE_KINDS)}", kind)
    tip = None
    if r.has("tip") or kind in TIP_KINDS:
        tr = r.sub("tip", required=True)
        tip = _point(tr, link_by, "any")
        tr.check_unknown()
    if kind in ("trajectory", "torque"):
        f = r.str("file")
        path = Path(f) if Path(f).is_absolute() else base / f
        columns, rows = read_samples(path)
        q0 = ()
        if kind == "torque":
            q0 = r.nums("q0", ()) if r.has("q0") else ()
            if q0 and len(q0) != nq:
                raise r.err("q0", f"{nq} numbers (rad), one per coordinate {coord_names}", list(q0))
        man = _samples_manoeuvre(str(path), columns, rows, coord_names, motor_names, tip, kind, q0)
        if r.has("duration") and r.num("duration", positive=True, unit="s") != man.duration:
            raise r.err("duration", f"the last sample's time {man.duration!r} s of {path} (or no duration)",
                        r.table["duration"])
        r.check_unknown()
        return man
    if kind == "waypoints":
        times = r.nums("times")
        if len(times) < 2 or times[0] != 0.0 or any(b <= a for a, b in itertools.pairwise(times)):
            raise r.err("times", "at least 2 increasing times (s) starting at 0", list(times))
        wp = r.raw("waypoints")
        if not isinstance(wp, list) or len(wp) != len(times):
            raise r.err("waypoints", f"{len(times)} rows (one per time) of {nq} numbers {coord_names}", wp)
        rows = []
        for i, row in enumerate(wp):
            ok = isinstance(row, list) and len(row) == nq and all(
                not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) for x in row)
            if not ok:
                raise r.err(f"waypoints[{i}]", f"{nq} numbers (rad) {coord_names}", row)
            rows.append(tuple(float(x) for x in row))
        interp = r.str("interpolation", "quintic")
        if interp not in INTERPOLATIONS:
            raise r.err("interpolation", f"one of {list(INTERPOLATIONS)}", interp)
        if r.has("duration") and r.num("duration", positive=True, unit="s") != times[-1]:
            raise r.err("duration", f"the last waypoint's time {times[-1]!r} s (or no duration)", r.table["duration"])
        r.check_unknown()
        return Manoeuvre(kind, times[-1], time_law="quintic", tip=tip, times=times, waypoints=tuple(rows),
                         interpolation=interp)
    law = r.str("time_law", "trapezoid")
    if law not in TIME_LAWS:
        raise r.err("time_law", f"one of {list(TIME_LAWS)}", law)
    duration = r.num("duration", positive=True, unit="s")
    ramp = r.num("ramp_time", 0.0, nonneg=True, unit="s")
    if law == "trapezoid" and not 0 < ramp <= duration / 2:
        raise r.err("ramp_time", f"a ramp time in (0, duration/2 = {duration / 2:g}] s", ramp)
    rules = []
    raw_rules = r.raw("rules", [])
    if not isinstance(raw_rules, list):
        raise r.err("rules", "a list of rules [{coordinate = ..., start = ..., end = ...}, ...]", raw_rules)
    for i, rule in enumerate(raw_rules):
        rr = _Reader(r.source, rule if isinstance(rule, dict) else {}, f"{r.path}.rules[{i}]")
        if not isinstance(rule, dict):
            raise rr.err("", "an inline table {coordinate, start, end}", rule)
        c = rr.str("coordinate")
        if c not in coord_names:
            raise rr.err("coordinate", f"an ERLS coordinate name, one of {coord_names}", c)
        if c in [x[0] for x in rules]:
            raise rr.err("coordinate", "one rule per coordinate", c)
        rules.append((c, rr.num("start", unit="rad"), rr.num("end", unit="rad")))
        rr.check_unknown()
    torque_noise = ()
    centre = radius = phi0 = phi1 = None
    points: tuple = ()
    if kind == "tip_arc":
        centre = r.nums("centre", length=2)
        radius = r.num("radius", positive=True, unit="m")
        phi0 = r.num("phi_start", unit="rad")
        phi1 = r.num("phi_end", unit="rad")
    elif kind in ("tip_line", "tip_polyline"):
        raw = r.raw("points")
        n_min = 2
        ok = isinstance(raw, list) and all(
            isinstance(p, list) and len(p) == 2
            and all(not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) for x in p)
            for p in raw)
        if not ok or len(raw) < n_min or (kind == "tip_line" and len(raw) != 2):
            what = "2 points [[x0, y0], [x1, y1]] (m)" if kind == "tip_line" else "at least 2 points [[x, y], ...] (m)"
            raise r.err("points", what, raw)
        points = tuple((float(p[0]), float(p[1])) for p in raw)
        for i in range(len(points) - 1):
            if points[i] == points[i + 1]:
                raise r.err(f"points[{i + 1}]", "a point different from the one before it", list(points[i + 1]))
    if kind in TIP_KINDS:
        if nq < 2 or len(rules) != nq - 2:
            raise r.err("rules", f"{nq - 2} coordinate rule(s) besides the 2 coordinates the tip fixes "
                        f"(a tip path needs at least 2 coordinates; the model has {nq})", len(rules))
    elif len(rules) != nq:
        raise r.err("rules", f"one rule per ERLS coordinate ({nq})", len(rules))
    r.check_unknown()
    return Manoeuvre(kind, duration, law, ramp, tip, centre, radius, phi0, phi1, tuple(rules), torque_noise,
                     points=points)


def load_manoeuvre(path: str | Path, mech: Mechanism) -> Manoeuvre:
    """A manoeuvre for ``mech`` from a file: a TOML file with a ``[manoeuvre]`` table (the model file's keys; its
    relative file names refer to its own folder), or a CSV sample table (:func:`read_samples`): motor-name
    columns make a measured-torque input (from ``q_ref``, or the model's manoeuvre's ``q0``), coordinate or
    ``tip_x``/``tip_y`` columns a trajectory (the tip: the model's manoeuvre tip, else its ``tip_x`` sensor)."""
    path = Path(path)
    src = str(path)
    link_by = {lk.name: lk for lk in mech.links}
    coords = list(mech.coordinate_names)
    motors = list(mech.motor_names)
    if path.suffix.lower() == ".csv":
        columns, rows = read_samples(path)
        tip = mech.manoeuvre.tip if mech.manoeuvre is not None else None
        if tip is None:
            tip = next((LinkPoint(s.link, s.station) for s in mech.sensors if s.kind == "tip_x"), None)
        q0 = mech.manoeuvre.q0 if mech.manoeuvre is not None else ()
        return dataclasses.replace(_samples_manoeuvre(src, columns, rows, coords, motors, tip, None, q0), source=src)
    if not path.is_file():
        raise ModelFileError(src, "(file)", "an existing TOML or CSV manoeuvre file", has_got=False)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ModelFileError(src, "(syntax)", f"valid TOML ({exc})", has_got=False) from None
    except UnicodeDecodeError:
        raise ModelFileError(src, "(file)", "a UTF-8 text file", has_got=False) from None
    root = _Reader(src, data, "")
    man = _parse_manoeuvre(root.sub("manoeuvre", required=True), link_by, coords, motors, path.parent)
    root.check_unknown()
    return man


def _check_mobility(src: str, links, joints, coordinates) -> None:
    """Joints connect every link to the ground; as many coordinates as the mobility (Gruebler's count): checked as
    soon as links, joints and coordinates are read, so that a missing coordinate is named as such."""
    if not any(j.grounded for j in joints):
        raise ModelFileError(src, "joints", "at least one joint with a ground position", has_got=False)
    adj: dict[str, set[str]] = {lk.name: set() for lk in links}
    grounded: set[str] = set()
    n_eq = 0
    for j in joints:
        names = [p.link for p in j.points]
        if len(set(names)) != len(names):
            raise ModelFileError(src, f"joints.{j.name}.points", "each link at most once per joint", names)
        for a in names:
            adj[a].update(n for n in names if n != a)
        if j.ground is not None:
            grounded.update(names)
        if j.kind == "prismatic":  # pinned together, one equation for the line
            n_eq += 2 * (len(names) - 1) + 1
        elif j.kind == "weld":  # coincident, one equation for the angle
            n_eq += 3
        else:
            n_eq += 2 * (len(names) - (0 if j.ground is not None else 1))
    seen, todo = set(grounded), list(grounded)
    while todo:
        for n in adj[todo.pop()]:
            if n not in seen:
                seen.add(n)
                todo.append(n)
    loose = sorted(set(adj) - seen)
    if loose:
        raise ModelFileError(src, "joints", f"joints that connect every link to the ground; not connected: {loose}",
                             has_got=False)
    mobility = 3 * len(links) - n_eq
    if mobility != len(coordinates):
        names = ", ".join(c.name for c in coordinates) or "none"
        k = mobility - len(coordinates)
        hint = (f"; {k} [[coordinates]] entr{'y' if k == 1 else 'ies'} missing?" if k > 0
                else "; a coordinate too many, or a joint missing?")
        raise ModelFileError(
            src, "coordinates",
            f"as many ERLS coordinates as the mechanism's mobility ({mobility}, from 3 x {len(links)} links "
            f"- {n_eq} joint equations); the file has {len(coordinates)} ({names}){hint}",
            has_got=False,
        )


def _check_topology(mech: Mechanism) -> None:
    """Joints connect every link to the ground; the coordinates match the mobility."""
    _check_mobility(mech.source, mech.links, mech.joints, mech.coordinates)
    src = mech.source
    # each coordinate's link node at its joint must be distinct (one ERLS constraint per node rotation)
    seen_c = set()
    for c in mech.coordinates:
        key = (c.link, c.joint, c.kind)
        if key in seen_c:
            raise ModelFileError(src, f"coordinates.{c.name}", "a link/joint pair not used by another coordinate",
                                 key)
        seen_c.add(key)
    from .dofs import elastic_dofs

    dofs = elastic_dofs(mech)
    for i, m in enumerate(mech.reduction.masters):
        try:
            dofs.locate(m)
        except KeyError:
            raise ModelFileError(
                src, f"reduction.masters[{i}]",
                f"an elastic dof name such as {dofs.names[0]!r}, {dofs.node_names[0]!r} or "
                f"'node{dofs.nodes[-1]}.transverse' (this mesh has {dofs.n} elastic dofs)", m) from None

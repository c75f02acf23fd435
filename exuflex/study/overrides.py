"""Parameter overrides on a :class:`~exuflex.mechanism.Mechanism`: ``"links.L1.diameter" = 0.031``.

A field path names a model-file field the way the TOML spells it:

- top-level scalars: ``sample_rate_hz``, ``gravity``;
- tables: ``payload.mass``, ``payload.inertia``, ``damping.alpha``, ``damping.beta``, ``manoeuvre.duration``,
  ``reduction.n_interior``;
- named entries of an array of tables: ``links.L1.diameter``, ``sensors.c1.noise_std``, ``motors.T1.noise_std``,
  ``joints.O.ground``, ``coordinates.q1.offset``; lumped masses by node id: ``masses.12.mass``;
- materials by name: ``materials.aluminium.E`` (changes every link of that material);
- the manoeuvre: its scalar fields (``manoeuvre.duration``, ``manoeuvre.ramp_time``, ``manoeuvre.time_law``,
  ``manoeuvre.radius``, ``manoeuvre.phi_end``, ``manoeuvre.centre``, ``manoeuvre.interpolation``, ...), a rule's
  ends ``manoeuvre.rules.q3.end``, and ``manoeuvre.file`` (another CSV table, read as the model file's would be).
  A study plans each level's manoeuvre (and its computed torque) anew.

Link fields as written in a model file: ``length`` (keeps the fractions of its stations and of the joints,
sensors and manoeuvre tip on it), ``diameter`` (solid circle:
A and I recomputed), ``A``, ``I``, ``E``, ``rho`` (this link's material only), ``material`` (a material's name),
``mesh_size`` (the FFRF truth's solid mesh).
Values keep the field's type (numbers, tuples for lists). Every error names the field path, what exists, and
what was expected. After each override the mechanism passes through the model file loader's checks
(:func:`exuflex.mechanism.writer.revalidate`: units and ranges, limits, topology), so a value the loader would
refuse in the file (a diameter in mm, a modulus in GPa) is refused here, naming the override.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from typing import Any

from ..mechanism import Mechanism

__all__ = ["OverrideError", "apply_overrides", "parse_set", "parse_value"]


class OverrideError(ValueError):
    """A parameter override names an unknown field or gives a value of the wrong kind."""


# arrays of tables addressed by an entry's name (or, for masses, the node id)
_NAMED = {"links": "name", "joints": "name", "coordinates": "name", "motors": "name", "sensors": "name",
          "masses": "node"}
_TABLES = ("payload", "damping", "manoeuvre", "reduction")


def parse_value(text: str) -> Any:
    """``"0.031"`` -> 0.031, ``"5"`` -> 5, ``"[1,2]"`` -> (1.0, 2.0), ``"none"`` -> None, else the string."""
    s = text.strip()
    if s.lower() in ("none", "null"):
        return None
    if s.lower() in ("true", "false"):
        return s.lower() == "true"
    if s.startswith("[") and s.endswith("]"):
        inner = s[1:-1].strip()
        return tuple(parse_value(x) for x in inner.split(";" if ";" in inner else ",")) if inner else ()
    try:
        return int(s)
    except ValueError:
        pass
    try:
        return float(s)
    except ValueError:
        return s


def _split_values(text: str) -> list[str]:
    """Split ``"1,2,[3;4]"`` at top-level commas (brackets may hold a list; use ``;`` inside them)."""
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
        if ch == "," and depth == 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    out.append(cur)
    return [v for v in (x.strip() for x in out) if v]


def parse_set(spec: str) -> tuple[str, list[Any]]:
    """``"links.L1.diameter=0.03,0.031"`` -> ``("links.L1.diameter", [0.03, 0.031])``."""
    if "=" not in spec:
        raise OverrideError(f"--set {spec!r}: expected FIELD=V1,V2,... (e.g. links.L1.diameter=0.03,0.031)")
    field, _, values = spec.partition("=")
    field = field.strip()
    vals = [parse_value(v) for v in _split_values(values)]
    if not field or not vals:
        raise OverrideError(f"--set {spec!r}: expected FIELD=V1,V2,... with at least one value")
    return field, vals


def _coerce(path: str, old: Any, value: Any) -> Any:
    """Give ``value`` the kind of ``old`` (a number for a number, a tuple of numbers for a tuple)."""
    if isinstance(old, bool):
        if not isinstance(value, bool):
            raise OverrideError(f"{path}: expected true or false, got {value!r}")
        return value
    if isinstance(old, (int, float)) or (old is None and isinstance(value, (int, float))):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise OverrideError(f"{path}: expected a number, got {value!r}")
        if isinstance(old, int) and not isinstance(old, bool) and isinstance(value, float):
            if not value.is_integer():
                raise OverrideError(f"{path}: expected an integer, got {value!r}")
            return int(value)
        return float(value) if isinstance(old, float) else value
    if isinstance(old, tuple):
        if not isinstance(value, tuple):
            value = (value,)
        if old and len(value) != len(old):
            raise OverrideError(f"{path}: expected {len(old)} values, got {len(value)}: {value!r}")
        return tuple(_coerce(f"{path}[{i}]", o, v) for i, (o, v) in enumerate(zip(old, value, strict=False))) \
            if old else value
    if isinstance(old, str) or old is None:
        return value
    raise OverrideError(f"{path}: a {type(old).__name__} cannot be overridden; set its fields (e.g. {path}.mass)")


def _fields(obj) -> list[str]:
    return [f.name for f in dataclasses.fields(obj)]


def _set_field(path: str, obj, name: str, value: Any):
    if not dataclasses.is_dataclass(obj) or name not in _fields(obj):
        raise OverrideError(f"{path}: no field {name!r}; {type(obj).__name__} has {_fields(obj)}")
    return dataclasses.replace(obj, **{name: _coerce(path, getattr(obj, name), value)})


def _positive(path: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise OverrideError(f"{path}: expected a positive number, got {value!r}")
    return float(value)


def _set_link(path: str, link, name: str, value: Any, mech: Mechanism):
    sec = link.section
    if name == "diameter":
        d = _positive(path, value)
        di = sec.inner_diameter if sec.shape == "tube" else 0.0  # a tube keeps its bore
        sec = dataclasses.replace(sec, diameter=d, A=math.pi * (d**2 - di**2) / 4, I=math.pi * (d**4 - di**4) / 64,
                                  height=d if sec.height is not None or sec.shape == "rectangle" else None,
                                  shape="tube" if sec.shape == "tube" else "round", width=None)
        return dataclasses.replace(link, section=sec)
    if name in ("A", "I"):
        v = _positive(path, value)
        return dataclasses.replace(link, section=dataclasses.replace(sec, **{name: v}, diameter=None, shape=None,
                                                                     inner_diameter=None, width=None))
    if name in ("E", "rho"):
        v = _positive(path, value)
        return dataclasses.replace(link, material=dataclasses.replace(link.material, **{name: v}))
    if name == "material":
        mats = {lk.material.name: lk.material for lk in mech.links}
        if value not in mats:
            raise OverrideError(f"{path}: no material {value!r}; the model has {sorted(mats)}")
        return dataclasses.replace(link, material=mats[value])
    if name == "length":
        L = _positive(path, value)
        f = L / link.length
        return dataclasses.replace(link, length=L, stations=tuple(s * f for s in link.stations))
    if name in ("name", "stations", "node_ids", "section"):
        raise OverrideError(f"{path}: {name!r} is structural and cannot be overridden in a study")
    if name == "mesh_size":  # the FFRF truth's solid mesh (the beam models ignore it)
        return dataclasses.replace(link, mesh_size=None if value is None else _positive(path, value))
    if name != "angle_guess":
        raise OverrideError(f"{path}: no link field {name!r}; a link has "
                            "['length', 'diameter', 'A', 'I', 'E', 'rho', 'material', 'angle_guess', 'mesh_size']")
    return _set_field(path, link, name, value)


def _scale_points(mech: Mechanism, link: str, f: float) -> Mechanism:
    """Every point given by a station on ``link`` (joints, sensors, the manoeuvre's tip) moved to the same fraction
    of the link after its length was multiplied by ``f``, as its nodes were."""

    def pt(p):
        return dataclasses.replace(p, station=p.station * f) if p.link == link else p

    joints = tuple(dataclasses.replace(j, points=tuple(pt(p) for p in j.points)) for j in mech.joints)
    sensors = tuple(dataclasses.replace(s, station=s.station * f)
                    if s.link == link and s.station is not None else s for s in mech.sensors)
    man = mech.manoeuvre
    if man is not None and man.tip is not None:
        man = dataclasses.replace(man, tip=pt(man.tip))
    return dataclasses.replace(mech, joints=joints, sensors=sensors, manoeuvre=man)


def _override_one(mech: Mechanism, path: str, value: Any) -> Mechanism:
    parts = path.split(".")
    if any(not p for p in parts):
        raise OverrideError(f"{path!r}: empty part in the field path (expected e.g. links.L1.diameter)")
    head = parts[0]
    if head in _NAMED:
        if len(parts) != 3:
            raise OverrideError(f"{path}: expected {head}.<{_NAMED[head]}>.<field>")
        key, name = parts[1], parts[2]
        entries = list(getattr(mech, head))
        attr = _NAMED[head]
        idx = [i for i, e in enumerate(entries) if str(getattr(e, attr)) == key]
        if head == "masses" and not idx and mech.payload is not None and str(mech.payload.node) == key:
            raise OverrideError(f"{path}: node {key} carries the payload; use payload.{name}")
        if not idx:
            have = [str(getattr(e, attr)) for e in entries]
            raise OverrideError(f"{path}: no {head[:-1]} with {attr} {key!r}; the model has {have}")
        i = idx[0]
        old = entries[i]
        if head == "links":
            entries[i] = _set_link(path, old, name, value, mech)
            if name == "length":
                return _scale_points(dataclasses.replace(mech, links=tuple(entries)), old.name,
                                     entries[i].length / old.length)
        else:
            if name == attr:
                raise OverrideError(f"{path}: {name!r} identifies the entry and cannot be overridden")
            entries[i] = _set_field(path, old, name, value)
        return dataclasses.replace(mech, **{head: tuple(entries)})
    if head == "materials":
        if len(parts) != 3:
            raise OverrideError(f"{path}: expected materials.<name>.<E|rho>")
        key, name = parts[1], parts[2]
        mats = {lk.material.name for lk in mech.links}
        if key not in mats:
            raise OverrideError(f"{path}: no material {key!r}; the model has {sorted(mats)}")
        if name not in ("E", "rho"):
            raise OverrideError(f"{path}: no field {name!r}; a material has ['E', 'rho']")
        v = _positive(path, value)
        links = tuple(dataclasses.replace(lk, material=dataclasses.replace(lk.material, **{name: v}))
                      if lk.material.name == key else lk for lk in mech.links)
        return dataclasses.replace(mech, links=links)
    if head == "manoeuvre":
        return _override_manoeuvre(mech, path, parts[1:], value)
    if head in _TABLES:
        sub = getattr(mech, head)
        if sub is None:
            raise OverrideError(f"{path}: the model has no [{head}] table")
        if len(parts) != 2:
            raise OverrideError(f"{path}: expected {head}.<field>; [{head}] has {_fields(sub)}")
        name = parts[1]
        if head == "payload" and name in ("mass", "inertia") and value is not None:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
                raise OverrideError(f"{path}: expected a non-negative number, got {value!r}")
        return dataclasses.replace(mech, **{head: _set_field(path, sub, name, value)})
    if len(parts) == 1:
        if head in ("links", "joints", "name", "source", "coordinates", "motors", "sensors", "masses"):
            raise OverrideError(f"{path}: structural field; name an entry's field, e.g. links.L1.diameter")
        return _set_field(path, mech, head, value)
    top = [f for f in _fields(Mechanism) if f not in ("name", "source", "description")]
    raise OverrideError(f"{path}: unknown field {head!r}; the model has {top + ['materials']}")


def _override_manoeuvre(mech: Mechanism, path: str, parts: list[str], value: Any) -> Mechanism:
    """``manoeuvre.<field>``, ``manoeuvre.rules.<coordinate>.<start|end>`` or ``manoeuvre.file``; the result is
    checked as the model file's would be (time law, ramp time)."""
    from ..mechanism.loader import ModelFileError, load_manoeuvre

    man = mech.manoeuvre
    if man is None:
        raise OverrideError(f"{path}: the model has no [manoeuvre] table")
    if parts and parts[0] == "rules":
        if len(parts) != 3 or parts[2] not in ("start", "end"):
            raise OverrideError(f"{path}: expected manoeuvre.rules.<coordinate>.<start|end>")
        names = [r[0] for r in man.rules]
        if parts[1] not in names:
            raise OverrideError(f"{path}: no rule for {parts[1]!r}; the manoeuvre has rules for {names}")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise OverrideError(f"{path}: expected a number (rad), got {value!r}")
        i = names.index(parts[1])
        c, a, b = man.rules[i]
        rule = (c, float(value), b) if parts[2] == "start" else (c, a, float(value))
        man = dataclasses.replace(man, rules=man.rules[:i] + (rule,) + man.rules[i + 1 :])
    elif len(parts) == 1 and parts[0] == "file":
        if man.kind not in ("trajectory", "torque"):
            raise OverrideError(f"{path}: a {man.kind!r} manoeuvre has no file (only 'trajectory' and 'torque')")
        try:
            new = load_manoeuvre(str(value), mech)
        except ModelFileError as exc:
            raise OverrideError(f"{path}: {exc}") from None
        if new.kind != man.kind:
            raise OverrideError(f"{path}: {value} is a {new.kind!r} table, the manoeuvre is {man.kind!r}")
        man = dataclasses.replace(new, tip=man.tip or new.tip, q0=man.q0 or new.q0)
    elif len(parts) == 1 and parts[0] in ("samples", "columns", "waypoints", "times", "rules", "tip", "points"):
        raise OverrideError(f"{path}: set in a manoeuvre file (exuflex simulate --manoeuvre), not by a sweep")
    elif len(parts) == 1:
        if parts[0] == "duration" and man.kind in ("waypoints", "trajectory", "torque"):
            raise OverrideError(f"{path}: a {man.kind!r} manoeuvre lasts until its last time")
        man = _set_field(path, man, parts[0], value)
    else:
        raise OverrideError(f"{path}: expected manoeuvre.<field>; [manoeuvre] has {_fields(man)}")
    from ..manoeuvre import KINDS, TIME_LAWS

    if man.kind not in KINDS:
        raise OverrideError(f"{path}: expected a manoeuvre kind, one of {list(KINDS)}, got {man.kind!r}")
    if man.time_law not in TIME_LAWS:
        raise OverrideError(f"{path}: expected a time law, one of {list(TIME_LAWS)}, got {man.time_law!r}")
    if not man.duration > 0:
        raise OverrideError(f"{path}: expected a positive duration (s), got {man.duration!r}")
    if man.time_law == "trapezoid" and man.kind not in ("waypoints", "trajectory", "torque") \
            and not 0 < man.ramp_time <= man.duration / 2:
        raise OverrideError(f"{path}: expected a ramp time in (0, duration/2 = {man.duration / 2:g}] s, "
                            f"got ramp_time {man.ramp_time!r}")
    return dataclasses.replace(mech, manoeuvre=man)


def apply_overrides(mech: Mechanism, overrides: Mapping[str, Any] | Iterable[tuple[str, Any]]) -> Mechanism:
    """A copy of ``mech`` with each ``field path -> value`` applied in order (see the module docstring).

    Raises
    ------
    OverrideError
        Naming the field path, what the model has there and what was expected.
    """
    from ..mechanism import ModelFileError
    from ..mechanism.writer import revalidate

    items = overrides.items() if isinstance(overrides, Mapping) else overrides
    for path, value in items:
        path = str(path).strip()
        mech = _override_one(mech, path, value)
        try:  # the model file's own checks (units, ranges, limits, topology), one override at a time
            mech = revalidate(mech)
        except ModelFileError as exc:
            shown = value if not isinstance(value, tuple) else list(value)
            raise OverrideError(f"override {path}={shown!r}: the model file's check refuses it: "
                                f"{str(exc).removeprefix(f'{exc.source}: ')}") from None
    return mech

"""A :class:`~exuflex.mechanism.spec.Mechanism` written back as the TOML document the loader reads, so that a
mechanism changed in code (a study's overrides) passes through exactly the model file's validation.

``parse_mechanism(mechanism_document(mech), mech.source)`` rebuilds ``mech`` field for field, except the
manoeuvre, which is left out of the document (it may come from a separate CSV file; the planner checks it) and
put back by :func:`revalidate`. Links that share a material name but no longer its values (an override of one
link's ``E``) get materials of their own, named ``<material>@<link>``.
"""

from __future__ import annotations

from typing import Any

from .spec import LumpedMass, Mechanism

__all__ = ["mechanism_document", "revalidate"]


def _drop_none(d: dict) -> dict:
    return {k: v for k, v in d.items() if v is not None}


def _mass(m: LumpedMass) -> dict:
    return {"node": m.node, "mass": m.mass, "inertia": m.inertia, "label": m.label, "offset": list(m.offset)}


def mechanism_document(mech: Mechanism) -> dict[str, Any]:
    """The TOML document (as parsed by ``tomllib``: dicts, lists, numbers, strings) that the loader turns into
    ``mech`` without its manoeuvre."""
    materials: dict[str, Any] = {}  # name -> Material
    link_material: dict[str, str] = {}
    for lk in mech.links:
        name = lk.material.name
        if name in materials and materials[name] != lk.material:
            name = f"{name}@{lk.name}"
        materials.setdefault(name, lk.material)
        link_material[lk.name] = name
    links = []
    for lk in mech.links:
        sec = lk.section
        entry: dict[str, Any] = {"name": lk.name, "length": lk.length, "material": link_material[lk.name]}
        if sec.shape in ("round", "tube"):
            entry["diameter"] = sec.diameter
            if sec.shape == "tube":
                entry["inner_diameter"] = sec.inner_diameter
        elif sec.shape == "rectangle":
            entry.update(width=sec.width, height=sec.height)
        elif sec.diameter is not None:
            entry["diameter"] = sec.diameter
        else:
            entry.update(_drop_none({"A": sec.A, "I": sec.I, "height": sec.height}))
        entry.update(stations=list(lk.stations), nodes=list(lk.node_ids))
        if lk.angle_guess is not None:
            entry["angle_guess"] = lk.angle_guess
        if lk.mesh_size is not None:
            entry["mesh_size"] = lk.mesh_size
        links.append(entry)
    joints = []
    for j in mech.joints:
        entry = {"name": j.name, "kind": j.kind,
                 "points": [{"link": p.link, "station": p.station} for p in j.points]}
        if j.ground is not None:
            entry["ground"] = list(j.ground)
        if j.kind == "prismatic":
            entry["axis"] = list(j.axis)
        if j.kind == "weld":
            entry["angle"] = j.angle
        joints.append(entry)
    coords = []
    for c in mech.coordinates:
        entry = {"name": c.name, "joint": c.joint, "offset": c.offset}
        if c.kind != "slide":  # a slide coordinate is the one without a link
            entry["link"] = c.link
            if c.relative_to is not None:
                entry["relative_to"] = c.relative_to
        coords.append(entry)
    motors = [_drop_none({"name": m.name, "joint": m.joint, "link": m.link, "reaction": m.reaction,
                          "noise_std": m.noise_std, "full_scale": m.full_scale}) for m in mech.motors]
    sensors = []
    for s in mech.sensors:
        entry = {"name": s.name, "kind": s.kind, "link": s.link, "noise_std": s.noise_std}
        if s.kind in ("encoder", "slider"):
            entry["joint"] = s.joint
        if s.kind == "encoder" and s.relative_to is not None:
            entry["relative_to"] = s.relative_to
        if s.kind not in ("encoder", "slider"):
            entry["station"] = s.station
        entry.update(_drop_none({"full_scale": s.full_scale, "rate_hz": s.rate_hz}))
        sensors.append(entry)
    red = mech.reduction
    model = {"name": mech.name, "description": mech.description, "sample_rate_hz": mech.sample_rate_hz,
             "gravity": list(mech.gravity)}
    if mech.q_ref:
        model["q_ref"] = list(mech.q_ref)
    doc: dict[str, Any] = {
        "model": model,
        "materials": [{"name": n, "E": m.E, "rho": m.rho, **({"nu": m.nu} if m.nu != 0.3 else {})} for n, m in materials.items()],
        "links": links,
        "joints": joints,
        "coordinates": coords,
        "damping": {"alpha": mech.damping.alpha, "beta": mech.damping.beta},
        "reduction": _drop_none({"masters": list(red.masters),
                                 "q_star": None if red.q_star is None else list(red.q_star),
                                 "band_hz": red.band_hz,
                                 "n_interior": "auto" if red.n_interior is None else red.n_interior,
                                 "nco_min": red.nco_min, "freq_error_max_pct": red.freq_error_max_pct}),
    }
    obs = mech.observer.settings()
    if obs:
        doc["observer"] = {k: list(v) if isinstance(v, tuple) else v for k, v in obs.items()}
    if motors:
        doc["motors"] = motors
    if sensors:
        doc["sensors"] = sensors
    if mech.masses:
        doc["masses"] = [_mass(m) for m in mech.masses]
    if mech.payload is not None:
        doc["payload"] = _mass(mech.payload)
    return doc


def revalidate(mech: Mechanism) -> Mechanism:
    """``mech`` passed through the model file loader's checks (:func:`~exuflex.mechanism.parse_mechanism` on
    :func:`mechanism_document`), its manoeuvre kept; raises the loader's
    :class:`~exuflex.mechanism.ModelFileError` (naming ``mech.source`` and the field) if it would be refused
    as a model file."""
    from .loader import parse_mechanism

    out = parse_mechanism(mechanism_document(mech), mech.source)
    return out.replace(manoeuvre=mech.manoeuvre)

"""Sensor channels as functions of the ERLS state ``x = [q; u]``: the rows the observers and the reduction use.

Every channel is ``rigid(q) + row @ u``: the rigid part is a combination of link angles (encoders) or a
rigid point coordinate (tip position, slider), the elastic part a row acting on the elastic displacements ``u``
(global frame) at the configuration: the elastic rotation at a joint, the Hermite curvature at a gauge
station, or the interpolated displacement of a link point. :func:`channel_matrix` linearises the rigid parts in q,
giving each channel's row on the full coordinates (what a mode's shape reads in the channel).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["channel_matrix", "point_channel", "sensor", "sensor_rows"]


def sensor(mech, sensors: dict, channel: str):
    """The model file's sensor named ``channel``, with an error naming the model and the channels it has."""
    s = sensors.get(channel)
    if s is None:
        raise KeyError(
            f"{mech.source or mech.name}: no sensor channel {channel!r}; the model has {sorted(sensors)}"
        )
    return s


def sensor_rows(model, cfg, s, link_names: list[str]):
    """``(kind, rigid, u_row)`` of sensor ``s`` at configuration ``cfg``.

    kind ``"angle"``: ``rigid`` weights the link angles; ``"point"``: ``rigid = (p0, dp0/dq)`` of one
    coordinate of the rigid point; ``"linear"``: no rigid part. ``u_row`` acts on the elastic displacements.
    """
    if s.kind == "encoder":
        a = np.zeros(len(link_names))
        a[link_names.index(s.link)] = 1.0
        row = model.rotation_row(s.link, s.joint)
        if s.relative_to:
            a[link_names.index(s.relative_to)] -= 1.0
            row = row - model.rotation_row(s.relative_to, s.joint)
        return "angle", a, row
    if s.kind == "curvature":
        return "linear", None, model.curvature_row(cfg, s.link, s.station)
    if s.kind in ("tip_x", "tip_y", "slider"):
        station, w, offset = point_channel(model, s)
        rows = model.point_displacement_rows(cfg, s.link, station)
        p0, Sp = model.kin.point(cfg.pose, s.link, station)
        return "point", (w @ p0 - offset, w @ Sp), w @ rows
    raise KeyError(f"unsupported sensor kind {s.kind!r}")  # pragma: no cover - the loader admits only these


def point_channel(model, s) -> tuple[float, np.ndarray, float]:
    """``(station, w, offset)`` of a point sensor (tip_x, tip_y, slider): the channel reads ``w . p - offset``
    with ``p`` the position of the point at ``station`` on the sensor's link (tip: ``w`` a unit axis, no offset;
    slider: ``axis . (p - ground)`` of the prismatic joint's node)."""
    if s.kind == "slider":
        jt = model.mech.joint(s.joint)
        d = np.asarray(jt.axis, float)
        return next(p.station for p in jt.points if p.link == s.link), d, float(d @ np.asarray(jt.ground, float))
    return s.station, np.array([1.0, 0.0] if s.kind == "tip_x" else [0.0, 1.0]), 0.0


def channel_matrix(model, cfg, mech, channels: Sequence[str]) -> np.ndarray:
    """(m, n) rows of the channels on the full coordinates ``x = [q; u]`` at ``cfg``: ``y - y(cfg) = C dx`` to
    first order (encoders: their link-angle weights times the link angles' q-sensitivities; points: the rigid
    point's q-Jacobian; plus every channel's elastic row)."""
    sensors = {s.name: s for s in mech.sensors}
    link_names = [lk.name for lk in mech.links]
    nq = model.nq
    Sz = cfg.pose.Sz[2::3]
    C = np.zeros((len(channels), model.n))
    for i, ch in enumerate(channels):
        kind, rigid, urow = sensor_rows(model, cfg, sensor(mech, sensors, ch), link_names)
        C[i, nq:] = urow
        if kind == "angle":
            C[i, :nq] += rigid @ Sz
        elif kind == "point":
            C[i, :nq] += rigid[1]
    return C

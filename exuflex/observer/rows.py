"""Sensor channels as functions of the ERLS state, shared by the reduced and the full-order observer models.

Every channel is ``rigid(q) + row @ u``: the rigid part is a combination of link angles (encoders) or a
rigid point coordinate (tip position), the elastic part a row acting on the elastic displacements ``u``
(global frame) at the configuration: the elastic rotation at a joint, the Hermite curvature at a gauge
station, or the interpolated displacement of a link point.
"""

from __future__ import annotations

import numpy as np

__all__ = ["sensor", "sensor_rows"]


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
    if s.kind in ("tip_x", "tip_y"):
        c = 0 if s.kind == "tip_x" else 1
        rows = model.point_displacement_rows(cfg, s.link, s.station)
        p0, Sp = model.kin.point(cfg.pose, s.link, s.station)
        return "point", (p0[c], Sp[c]), rows[c]
    raise KeyError(f"unsupported sensor kind {s.kind!r}")  # pragma: no cover - the loader admits only these

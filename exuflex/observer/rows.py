"""Sensor channels as functions of the ERLS state, shared by the reduced and the full-order observer models.

Every channel is ``rigid(q) + row @ u``: the rigid part is a combination of link angles (encoders) or a
rigid point coordinate (tip position), the elastic part a row acting on the elastic displacements ``u``
(global frame) at the configuration: the elastic rotation at a joint, the Hermite curvature at a gauge
station, or the interpolated displacement of a link point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..erls.elements import hermite_curvature_row
from ..erls.sensing import sensor, sensor_rows

__all__ = ["ChannelRows", "channel_rows", "sensor", "sensor_rows"]  # sensor, sensor_rows: from erls.sensing


@dataclass(frozen=True)
class ChannelRows:
    """The configuration-independent parts of :func:`sensor_rows` for a tuple of channels, so that the rows at a
    configuration take a few array operations for all channels together (:meth:`at`) instead of a dozen per
    channel: the reduced observer evaluates them at every held configuration.

    ``angle`` (m, n_links): link-angle weights (encoders; zero rows elsewhere); ``u_fixed`` (m, ne): the
    q-independent u rows (the encoders' elastic rotations); per curvature station on an element ``(element,
    Hermite row / number of elements averaged)`` in ``curv_element``, ``curv_row``, and where each of its six
    element-frame entries lands in the flattened u rows: ``curv_take`` (entries of a nodal dof with an elastic
    coordinate, flat indices into the (stations, 6) entries) and ``curv_flat`` (their flat indices into the
    (m, ne) u rows); ``points``: ``(channel index, sensor)`` of the tip-position channels (rows per
    configuration as in :func:`sensor_rows`).
    """

    angle: np.ndarray
    u_fixed: np.ndarray
    curv_element: np.ndarray
    curv_row: np.ndarray
    curv_take: np.ndarray
    curv_flat: np.ndarray
    points: tuple

    def at(self, model, cfg) -> tuple[np.ndarray, list]:
        """``(U, points)`` at configuration ``cfg``: the u rows (m, ne) of every channel (those of the point
        channels included) and ``(channel index, p0, dp0/dq)`` of the point channels' rigid parts."""
        U = self.u_fixed.copy()
        if len(self.curv_element):
            # c R_e^T per station, summed into the elastic coordinates of the element's nodal dofs: the rows of
            # ErlsModel.curvature_row
            local = np.einsum("lb,lab->la", self.curv_row, cfg.R[self.curv_element])
            U += np.bincount(self.curv_flat, local.reshape(-1)[self.curv_take], minlength=U.size).reshape(U.shape)
        pts = []
        for i, s in self.points:
            _, (p0, Sp), urow = sensor_rows(model, cfg, s, [])
            U[i] = urow
            pts.append((i, p0, Sp))
        return U, pts


def channel_rows(model, sensors, link_names: list[str]) -> ChannelRows:
    """:class:`ChannelRows` of a sequence of sensors (in channel order) of ``model``."""
    m = len(sensors)
    angle = np.zeros((m, len(link_names)))
    u_fixed = np.zeros((m, model.ne))
    cc, ce, cr, points = [], [], [], []
    for i, s in enumerate(sensors):
        if s.kind == "encoder":
            _, angle[i], u_fixed[i] = sensor_rows(model, None, s, link_names)
        elif s.kind == "curvature":
            locs = model.locate(s.link, s.station)
            for e, xi in locs:
                cc.append(i)
                ce.append(e)
                cr.append(hermite_curvature_row(model.el_len[e], xi) / len(locs))
        elif s.kind in ("tip_x", "tip_y", "slider"):
            points.append((i, s))
        else:  # pragma: no cover - the loader admits only these
            raise KeyError(f"unsupported sensor kind {s.kind!r}")
    ce = np.array(ce, dtype=np.int64)
    u = model.t_index[model.el_dofs[ce]].reshape(-1)  # (stations * 6,) elastic coordinate of each entry, -1: none
    take = np.flatnonzero(u >= 0)
    flat = (np.repeat(np.array(cc, dtype=np.int64), 6) * model.ne + u)[take]
    return ChannelRows(angle, u_fixed, ce, np.array(cr, dtype=float).reshape(-1, 6), take, flat, tuple(points))

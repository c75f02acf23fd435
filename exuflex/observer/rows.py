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
from ..erls.sensing import point_channel, sensor, sensor_rows

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

    For the rows' change with the configuration (:meth:`rates`): ``link`` (m,) the link whose angle turns each
    channel's u row (-1: none, the encoders' rows do not turn), ``curv_rate`` the Hermite rows turned by 90
    degrees (``W c``, see :meth:`rates`), ``point_at`` ``(links, stations, weights)``: the point channels' points
    (link index, station) and the weights ``w`` of their reading ``w . p - offset`` (:func:`point_channel`);
    ``rate_points`` ``(links, stations)``: every link's origin, then the point channels' points (the points whose
    pose derivatives :meth:`rates` takes).
    """

    angle: np.ndarray
    u_fixed: np.ndarray
    curv_element: np.ndarray
    curv_row: np.ndarray
    curv_take: np.ndarray
    curv_flat: np.ndarray
    points: tuple
    link: np.ndarray
    curv_rate: np.ndarray
    point_at: tuple
    rate_points: tuple

    def at(self, model, cfg) -> tuple[np.ndarray, list]:
        """``(U, points)`` at configuration ``cfg``: the u rows (m, ne) of every channel (those of the point
        channels included) and ``(channel index, p0, dp0/dq)`` of the point channels' rigid parts."""
        U = self.u_fixed.copy()
        self._curvature(U, self.curv_row, cfg)
        pts = []
        for i, s in self.points:
            _, (p0, Sp), urow = sensor_rows(model, cfg, s, [])
            U[i] = urow
            pts.append((i, p0, Sp))
        return U, pts

    def _curvature(self, U: np.ndarray, rows: np.ndarray, cfg) -> None:
        """Add ``c R_e^T`` per curvature station (``c`` from ``rows``) into the elastic coordinates of the
        element's nodal dofs in ``U``: the rows of ErlsModel.curvature_row."""
        if len(self.curv_element):
            local = np.einsum("lb,lab->la", rows, cfg.R[self.curv_element])
            U += np.bincount(self.curv_flat, local.reshape(-1)[self.curv_take], minlength=U.size).reshape(U.shape)

    def rates(self, model, cfg) -> tuple[np.ndarray, np.ndarray]:
        """``(U_theta, G)`` at configuration ``cfg``: the derivative of every channel's u row in the angle of its
        link ``theta_l`` (l = :attr:`link`; the u rows depend on q only through it, so ``dU_i/dq_j = U_theta_i
        dtheta_l/dq_j``) (m, ne), and the rigid parts' second derivatives ``G_i = d^2 rigid_i / dq^2`` (m, nq, nq).

        Element rotations turn as ``dR_e/dtheta = R_e W`` (``W`` the 90-degree generator ``[[0, -1], [1, 0]]`` on
        each node's translations, zero on its rotation): a curvature row ``c R_e^T`` turns at ``(W c) R_e^T``, a
        point's displacement rows as :meth:`~exuflex.erls.model.ErlsModel.point_displacement_rows` with
        ``rate``; the encoders' rows (nodal rotations) do not turn. A link-angle channel ``a . theta(q)`` has
        ``G = sum_l a_l d^2 theta_l/dq^2``, a point channel ``w . p(q) - offset`` has ``G = w . d^2 p/dq^2``, both
        from the pose's second derivatives (:meth:`~exuflex.erls.kinematics.Kinematics.coordinate_rates` at
        the links' origins and at the points)."""
        m, nl = self.angle.shape
        Ut = np.zeros_like(self.u_fixed)
        self._curvature(Ut, self.curv_rate, cfg)
        links, stations, weights = self.point_at
        for (i, s), st in zip(self.points, stations):
            w = weights[i]
            Ut[i] = w @ model.point_displacement_rows(cfg, s.link, st, rate=True)
        P = model.kin.coordinate_rates(cfg.pose, *self.rate_points)  # (nq, 3 (nl + points), nq)
        G = np.einsum("il,jlk->ijk", self.angle, P[:, 2 : 3 * nl : 3])
        for k, (i, _) in enumerate(self.points):
            G[i] += np.einsum("c,jck->jk", weights[i], P[:, 3 * (nl + k) : 3 * (nl + k) + 2])
        return Ut, G


def channel_rows(model, sensors, link_names: list[str]) -> ChannelRows:
    """:class:`ChannelRows` of a sequence of sensors (in channel order) of ``model``."""
    m = len(sensors)
    angle = np.zeros((m, len(link_names)))
    u_fixed = np.zeros((m, model.ne))
    link = np.full(m, -1, dtype=np.int64)
    weights = np.zeros((m, 2))
    cc, ce, cr, points, p_link, p_station = [], [], [], [], [], []
    for i, s in enumerate(sensors):
        if s.kind == "encoder":
            _, angle[i], u_fixed[i] = sensor_rows(model, None, s, link_names)
            continue
        link[i] = link_names.index(s.link)
        if s.kind == "curvature":
            locs = model.locate(s.link, s.station)
            for e, xi in locs:
                cc.append(i)
                ce.append(e)
                cr.append(hermite_curvature_row(model.el_len[e], xi) / len(locs))
        elif s.kind in ("tip_x", "tip_y", "slider"):
            points.append((i, s))
            station, weights[i], _ = point_channel(model, s)
            p_link.append(link[i])
            p_station.append(station)
        else:  # pragma: no cover - the loader admits only these
            raise KeyError(f"unsupported sensor kind {s.kind!r}")
    ce = np.array(ce, dtype=np.int64)
    u = model.t_index[model.el_dofs[ce]].reshape(-1)  # (stations * 6,) elastic coordinate of each entry, -1: none
    take = np.flatnonzero(u >= 0)
    flat = (np.repeat(np.array(cc, dtype=np.int64), 6) * model.ne + u)[take]
    cr = np.array(cr, dtype=float).reshape(-1, 6)
    rate = np.zeros_like(cr)  # W c: each node's translation pair (a, b) turned to (-b, a)
    rate[:, [0, 3]], rate[:, [1, 4]] = -cr[:, [1, 4]], cr[:, [0, 3]]
    p_link, p_station = np.array(p_link, dtype=np.int64), np.array(p_station, dtype=float)
    nl = len(link_names)
    return ChannelRows(angle, u_fixed, ce, cr, take, flat, tuple(points), link, rate, (p_link, p_station, weights),
                       (np.concatenate([np.arange(nl, dtype=np.int64), p_link]),
                        np.concatenate([np.zeros(nl), p_station])))

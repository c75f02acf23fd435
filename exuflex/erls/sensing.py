"""Sensor channels as functions of the ERLS state ``x = [q; u]``: the rows the observers and the reduction use.

Every channel is ``rigid(q) + row @ u``: the rigid part is a combination of link angles (encoders) or a
rigid point coordinate (tip position, slider), the elastic part a row acting on the elastic displacements ``u``
(global frame) at the configuration: the elastic rotation at a joint, the Hermite curvature at a gauge
station, or the interpolated displacement of a link point. :func:`channel_matrix` linearises the rigid parts in q,
giving each channel's row on the full coordinates (what a mode's shape reads in the channel).

A link point's position and angle also have a second order in ``u``, the links' foreshortening
(:class:`SecondOrderPlan`): the ERLS engine's probes (:func:`exuflex.sensors.erls_probe_record`) and the
observer's physical tip carry it; the channels' rows here are linear (a point channel's second order, the
slider-crank's slider, is 1.5e-5 of its noise: docs/shortening.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["SecondOrder", "SecondOrderPlan", "channel_matrix", "point_channel", "sensor", "sensor_rows"]


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


# ------------------------------------------------------------------------------------------ second order
_GAUSS_X, _GAUSS_W = np.polynomial.legendre.leggauss(3)


def _slope_row(xi, L: float) -> np.ndarray:
    """(..., 4) lateral slope ``dv/dx`` of the cubic Hermite interpolant at ``xi`` on ``[v1, phi1, v2, phi2]``."""
    xi = np.asarray(xi, float)
    return np.stack([(-6 * xi + 6 * xi**2) / L, 1 - 4 * xi + 3 * xi**2, (6 * xi - 6 * xi**2) / L,
                     -2 * xi + 3 * xi**2], axis=-1)


@dataclass(frozen=True)
class SecondOrder:
    """The second-order kinematics of link points at one configuration: ``w = C (G u)^2`` (squares entry by entry),
    ``C`` (k, 3, n_g) and ``G`` (n_g, ne): per point its ``(x, y, angle)`` beyond ``rigid(q) + A u``
    (:class:`SecondOrderPlan`); with a motion of the configuration, ``Cd``, ``Gd`` their time derivatives."""

    C: np.ndarray
    G: np.ndarray
    Cd: np.ndarray | None = None
    Gd: np.ndarray | None = None

    def values(self, u: np.ndarray) -> np.ndarray:
        """(k, 3) ``w(u)``."""
        g = self.G @ u
        return self.C @ (g * g)

    def jacobian(self, u: np.ndarray) -> np.ndarray:
        """(k, 3, ne) ``dw/du = 2 C diag(G u) G``."""
        return 2.0 * (self.C * (self.G @ u)) @ self.G

    def rates(self, u: np.ndarray, ud: np.ndarray) -> np.ndarray:
        """(k, 3) ``dw/dt = Cd (G u)^2 + 2 C ((G u) (G u' + Gd u))`` (needs ``Cd``, ``Gd``)."""
        g = self.G @ u
        return self.Cd @ (g * g) + self.C @ (2.0 * g * (self.G @ ud + self.Gd @ u))


class SecondOrderPlan:
    """What a link point's position and angle hold beyond the linear ERLS map ``rigid(q) + A u``, to second order in
    the elastic displacements: the foreshortening of bent links.

    The ERLS elastic displacements are linear: a node's axial displacement carries the link's stretch (the axial
    strain that EA resists), its lateral one the bending. A bent link whose centreline keeps that stretch brings its
    far points toward its start: at station ``x`` of link ``l``, along the link's axis ``t_l``, by

        sigma_l(x) = int_0^x v_l'(s)^2 / 2 ds

    with ``v_l`` the lateral elastic displacement in the link's frame (the Hermite field of its elements; its slope
    at station 0 included: a link turned elastically at its start swings on a circle, ``1 - cos a ~ a^2 / 2``), the
    difference of arc length and chord of ``x + v(x)`` (``sqrt(1 + v'^2) - 1 ~ v'^2 / 2``; the stretch's product
    with the slope, ``eps v'``, is of third order against it: strains of 1e-5 against slopes of 1e-3). The links
    then no longer meet where the linear map has them meet: the joints' closure equations ``Phi(z, q) = 0``
    (:class:`~exuflex.erls.kinematics.Kinematics`), with every joint station ``s`` moved to ``s - sigma(s)`` and
    ``q`` held (the encoders read the tangents at the coordinate joints, which the ERLS map keeps), give the links'
    rigid motion of second order ``dz = -Phi_z^-1 Phi_s (-sigma)``: nothing on an open chain's links but the
    translation of each link's start by the shortening of the links before it; on a closed loop the turn of its
    links that keeps it closed. A point at station ``x`` of link ``l`` moves by

        w = (dx_l, dy_l) + x dth_l n_l - sigma_l(x) t_l ,   its angle by dth_l

    (``n_l`` the link's normal). Every ``sigma`` is a sum of squares of slope rows at Gauss points (three per element
    segment: exact for the quartic integrand), ``sigma = sum_g c_g (G_g u)^2``, so ``w = C (G u)^2`` with ``C`` the
    closure's linear map of the Gauss weights (:class:`SecondOrder`). Exact to second order in ``u`` (up to the
    ``eps v'`` terms); the lateral second order (of the link's own shape) is a rigid turn, in ``dth``.
    """

    def __init__(self, model, points: Sequence[tuple[str, float]]):
        self.model = model
        kin = model.kin
        self.kin = kin
        li = {n: i for i, n in enumerate(kin.link_names)}
        self.points = [(li[link], float(station)) for link, station in points]
        # the stations whose sigma is needed: the closure equations' (position and point-scalar) and the points'
        stations: list[tuple[int, float]] = []

        def sid(link: int, s: float) -> int:
            key = (link, float(s))
            if key not in stations:
                stations.append(key)
            return stations.index(key)

        self._pos = [(sid(a, sa), a, sid(b, sb) if b >= 0 else -1, b) for a, sa, b, sb, _ in kin._pos_eqs]
        base = 2 * len(kin._pos_eqs)
        self._scalar = [(base + j, sid(e[0], e[1]), e[0], np.asarray(e[2], float))
                        for j, e in enumerate(kin._sc_eqs) if e[1] != 0.0]
        self._point_sid = [sid(lk, s) for lk, s in self.points]
        self.stations = stations
        # Gauss points of every element segment [0, xi_b] that a station's integral needs, deduplicated
        segs: list[tuple[int, float]] = []
        Sigma_rows = []
        for link, s in stations:
            els = np.flatnonzero((model.el_link == link) & (model.el_len > 0))
            cover = []
            for e in els:
                a, L = model.el_station[e], model.el_len[e]
                xi_b = min((s - a) / L, 1.0)
                if xi_b > 1e-12:
                    seg = (int(e), 1.0 if xi_b > 1 - 1e-9 else float(xi_b))
                    if seg not in segs:
                        segs.append(seg)
                    cover.append(segs.index(seg))
            Sigma_rows.append(cover)
        ng = 3 * len(segs)
        Sigma = np.zeros((len(stations), ng))
        for i, cover in enumerate(Sigma_rows):
            for j in cover:
                e, xi_b = segs[j]
                Sigma[i, 3 * j : 3 * j + 3] = 0.5 * _GAUSS_W * xi_b * model.el_len[e] / 2  # 1/2 int v'^2 dx
        self.Sigma = Sigma
        # slope rows at the Gauss points on the nodal displacements d: lateral v = n . (dx, dy), so a translation
        # entry splits into its x and y parts by the link's normal (-sin th, cos th); rotations enter as they are
        N, ne = model.N, model.ne
        Px, Py, Pr = np.zeros((ng, N)), np.zeros((ng, N)), np.zeros((ng, N))
        g_link = np.zeros(ng, dtype=np.int64)
        for j, (e, xi_b) in enumerate(segs):
            xi = xi_b * (_GAUSS_X + 1) / 2
            s = _slope_row(xi, model.el_len[e])  # (3, 4)
            dof = model.el_dofs[e]
            rows = slice(3 * j, 3 * j + 3)
            Px[rows, dof[0]], Py[rows, dof[1]], Pr[rows, dof[2]] = s[:, 0], s[:, 0], s[:, 1]
            Px[rows, dof[3]], Py[rows, dof[4]], Pr[rows, dof[5]] = s[:, 2], s[:, 2], s[:, 3]
            g_link[rows] = model.el_link[e]
        T = model.T
        self._Px, self._Py, self._Pr = Px @ T, Py @ T, Pr @ T
        self._g_link = g_link
        self.ne = ne

    def _closure(self, z: np.ndarray, thd: np.ndarray | None = None) -> np.ndarray:
        """(n_eq, n_stations) ``-Phi_s``: the closure residual per unit ``sigma`` at each station (a station moved
        back by ``sigma`` moves its point by ``-sigma t``); with the link angles' rates ``thd`` its time derivative
        (``t' = th' n``)."""
        th = z[2::3]
        t = np.stack([np.cos(th), np.sin(th)], axis=1)
        if thd is not None:
            t = thd[:, None] * np.stack([-np.sin(th), np.cos(th)], axis=1)
        R = np.zeros((self.kin.n_eq, len(self.stations)))
        for k, (sa, a, sb, b) in enumerate(self._pos):
            R[2 * k : 2 * k + 2, sa] -= t[a]
            if b >= 0:
                R[2 * k : 2 * k + 2, sb] += t[b]
        for row, s, a, n in self._scalar:
            R[row, s] -= n @ t[a]
        return R

    def at(self, pose, qd: np.ndarray | None = None) -> SecondOrder:
        """:class:`SecondOrder` of the points at the ERLS ``pose``; with the coordinate rates ``qd`` also the time
        derivatives of its maps (``dPhi_z/dt`` by :meth:`~exuflex.erls.kinematics.Kinematics._jacobian_rate`, the
        links' axes turning at their angles' rates)."""
        z = pose.z
        th = z[2::3]
        kin = self.kin
        Jinv = pose.Jinv if pose.Jinv is not None else np.linalg.inv(kin.jacobian(z))
        R = self._closure(z)
        dz = -Jinv @ R  # (3 nl, n_stations): the links' rigid motion per unit sigma
        W = self._point_rows(th, dz)
        tg = th[self._g_link][:, None]
        G = -np.sin(tg) * self._Px + np.cos(tg) * self._Py + self._Pr
        if qd is None:
            return SecondOrder(W @ self.Sigma, G)
        zd = pose.Sz @ np.asarray(qd, float)
        thd = zd[2::3]
        Rd = self._closure(z, thd)
        dzd = -Jinv @ (kin._jacobian_rate(z, zd) @ dz + Rd)
        Wd = self._point_rows(th, dzd, thd, dz)
        Gd = thd[self._g_link][:, None] * (-np.cos(tg) * self._Px - np.sin(tg) * self._Py)
        return SecondOrder(W @ self.Sigma, G, Wd @ self.Sigma, Gd)

    def _point_rows(self, th, dz, thd=None, dz0=None) -> np.ndarray:
        """(k, 3, n_stations) the points' ``(x, y, angle)`` per unit ``sigma`` at each station, from the links'
        rigid motion ``dz`` per unit sigma; with ``thd`` (the link angles' rates) and ``dz0``: the time derivative,
        ``dz`` then the rigid motion's rate."""
        W = np.zeros((len(self.points), 3, len(self.stations)))
        for k, ((lk, x), s) in enumerate(zip(self.points, self._point_sid, strict=True)):
            c, sn = np.cos(th[lk]), np.sin(th[lk])
            W[k, 0] = dz[3 * lk] - x * sn * dz[3 * lk + 2]
            W[k, 1] = dz[3 * lk + 1] + x * c * dz[3 * lk + 2]
            W[k, 2] = dz[3 * lk + 2]
            if thd is None:
                W[k, 0, s] -= c
                W[k, 1, s] -= sn
            else:  # the turning of n_l and t_l
                W[k, 0] -= x * c * thd[lk] * dz0[3 * lk + 2]
                W[k, 1] -= x * sn * thd[lk] * dz0[3 * lk + 2]
                W[k, 0, s] += sn * thd[lk]
                W[k, 1, s] -= c * thd[lk]
        return W

"""Static corrections: the slaves' quasi-static response to the loads the mechanism's motion can produce.

Why
---
The interior modes are chosen for the dynamics the filter follows (:mod:`.path`): the band's modes and the modes
that ring for a sample interval. A load concentrated at a slave dof (a heavy payload at a joint between masters)
bends the slaves quasi-statically in many fast interior modes, each a small share, none of which that selection
keeps. On the slider-crank with its slider 1.5 times heavier driven by the nominal torques, the crank spins up
near the dead centre and the rod's bend outside the kept modes reads 2.3 noise sd RMS in ``c_rod_quarter``
(``docs/payload_mismatch.md``). The classical remedy (residual flexibility, modal-truncation augmentation) adds
the truncated modes' static response to the load patterns as basis vectors.

The load patterns and their largest amplitudes
----------------------------------------------
At every sampled configuration ``q_c`` (q* and the manoeuvre's, :mod:`.path`) the elastic rows of

- the inertial load of each coordinate's acceleration, ``-M_uq e_i`` (the payload's mass is in ``M``),
- the velocity loads ``-h_u(q' = e_i)`` and ``-(h_u(e_i + e_j) - h_u(e_i) - h_u(e_j))`` (``h`` is quadratic in q'),
- the weight (with gravity),
- each motor's own elastic load, ``G_u e_j`` (the reaction of a motor between two links on the other link's node:
  the joint's relative coordinate puts each link's ERLS frame on its own tangent, :mod:`exuflex.mechanism.dofs`),
  scaled by the motor's largest planned torque ``|tau_j|``,

(the slaves' static response to a load concentrated there is what the interior modes kept for the dynamics miss),
each scaled by the largest value its factor can take (:func:`load_amplitudes`): 

- ``|q'_i| <= v_i = sqrt(2 T max_c (M_qq(q_c)^-1)_ii)``: the plan's largest kinetic energy ``T = max_t q'^T M_qq
  q' / 2`` released into the coordinate's lightest inertia over the configurations (at least the plan's largest
  rate). The truth's kinetic energy is the work of the same torques; where its motion departs from the plan (a
  heavier payload driven by nominal torques) the energy the plan holds in a heavy direction can come out where
  the inertia is small: the slider-crank's crank spins up near the dead centre, where the slider adds no inertia
  (``v`` is 2.2 times the plan's rate at the nominal payload, 2.5 at 1.5 times; that truth reaches 2.0).
- ``|q''_i| <= a_i = max_c sum_j |M_qq^-1 G_q|_ij tau_j + sum_(k,l) |M_qq^-1 c_kl|_i v_k v_l + |M_qq^-1 g_q|_i``:
  the motors' largest planned torques ``tau``, those rates' velocity forces (coefficients ``c_kl``) and the weight through the inverse inertia at the worst
  sampled configuration (a heavier payload driven by nominal torques reaches ten times the plan's ``q''`` near
  the slider-crank's dead centre).

The residual and its readings
-----------------------------
At a configuration the full model's static response to an elastic load ``f`` is ``u_m`` from the condensed
stiffness and ``u_s = B u_m + K_ss^-1 f_s`` (partition frame ``w``, :mod:`.basis`). The Craig-Bampton basis
reproduces the first exactly (the Guyan columns are ``K``-orthogonal to every slave-only vector, so the Galerkin
model condenses exactly) and the second by its Galerkin solution in the turned interior columns ``V``:

``r = K_ss^-1 f_s - V (V^T K_ss V)^-1 V^T f_s``

is all the reduced model's static response misses, with ``K_ss`` the slave stiffness at that configuration (not
q*'s turned: the links turn by different angles). Its reading in channel ``i`` is ``y_i^T r`` (the channel's
elastic row plus the coordinates' recoil ``-M_qq^-1 M_qu``, in the channel's noise sd, as in :mod:`.truncation`;
with the observer's limits, the estimated displacement quantities over their limit too).

The figure and the count
------------------------
For the scaled load columns at sample ``c`` the readings form ``E_c`` (rows, loads); a load within the amplitude
box (``|z_j| <= 1`` per scaled column) reads at most ``||E_c[i]||_1`` in row ``i``. The figure

``s = max_c max_i ||E_c[i]||_1``

is the largest quasi-static reading the reduced model can miss. Corrections are added one at a time until ``s <=
STATIC_MAX``; the count is the first that meets it. Each step tries as the next correction (the part outside the
kept modes and the corrections so far, in q*'s frame) the residual ``r`` of each load read above the limit and
each row's static response ``K_ss^-1 y_i`` (its adjoint: with it in the basis the Galerkin residual reads zero in
that row for every load, ``y_i^T r = (K_ss^-1 y_i)^T K_ss r = 0`` by the Galerkin orthogonality), the most read
first (:data:`_CANDIDATES` of each), and keeps the one that leaves the smallest figure. A Rayleigh-Ritz analysis in
the corrections' span and in its ``M_ss``-orthogonal complement among the modes not kept re-bases them
(:func:`rebase`): the interior basis still spans the slave space and stays ``M_ss``-orthonormal, so the truncation
figures' coordinates stay valid.

:data:`STATIC_MAX` = ``sqrt(TRUNCATION_MAX)``: a reading of ``b`` sd left to the filter raises the NIS by at most
``b^2`` (:mod:`.truncation`, "The requirement"), so a peak of 0.32 sd stays within the 0.1 that requirement grants
for a whole mean square.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ..erls.sensing import channel_matrix
from ..manoeuvre import plan
from .truncation import TRUNCATION_MAX, PlannedInput, quantity_rows

__all__ = ["STATIC_MAX", "StaticCorrections", "load_amplitudes", "load_shapes", "motor_loads", "reading_rows", "rebase",
           "static_corrections"]

#: the count's limit on the largest residual reading, in noise sd (module docstring)
STATIC_MAX = float(np.sqrt(TRUNCATION_MAX))
#: singular values (energy-weighted) below this fraction of the largest are round-off: no corrections from them
_RANK_TOL = 1e-10
#: the plan's points its largest kinetic energy is taken over
_ENERGY_POINTS = 201
#: the loads tried as the next correction per step, the most read first (each costs one figure's evaluation)
_CANDIDATES = 16


def _velocity_pairs(nq: int) -> list[tuple[int, int]]:
    return [(i, i) for i in range(nq)] + [(i, j) for i in range(nq) for j in range(i + 1, nq)]


def load_shapes(model, cfg) -> tuple[np.ndarray, list[str]]:
    """``(L, names)``: the elastic rows (ne, k) of the load patterns at ``cfg`` (module docstring), unscaled: ``-M_uq
    e_i`` per coordinate, the velocity loads ``-h_u`` of the rate pairs (``(i, i)``: ``q'_i^2``; ``(i, j)``: the cross
    term of ``q'_i q'_j``), with gravity the weight, and the motors' own elastic loads (:func:`motor_loads`)."""
    nq = model.nq
    cn = model.mech.coordinate_names
    names = [f"inertia {c}" for c in cn]
    names += [f"velocity {cn[i]}^2" if i == j else f"velocity {cn[i]} {cn[j]}" for i, j in _velocity_pairs(nq)]
    cols = [-model.mass(cfg)[nq:, :nq], -_velocity_coefficients(model, cfg)[nq:]]
    if np.any(model.g_N):
        cols.append((cfg.W.T @ (cfg.M_N @ model.g_N))[nq:, None])
        names.append("weight")
    m = motor_loads(model)
    cols.append((model.T.T @ model.B_N)[:, m])
    names += [f"motor {model.mech.motors[j].name}" for j in m]
    return np.hstack(cols), names


def motor_loads(model) -> np.ndarray:
    """The motors whose torque loads the elastic coordinates directly (``T' B_N`` non-zero: a motor reacting on a
    link whose node at the joint turns elastically), in :func:`load_shapes`' order."""
    return np.flatnonzero(np.any(model.T.T @ model.B_N != 0.0, axis=0))


def _velocity_coefficients(model, cfg) -> np.ndarray:
    """(n, pairs) the velocity forces' coefficient vectors at ``cfg``: ``h(q') = sum_pairs c_ij q'_i q'_j`` over
    :func:`_velocity_pairs` (``h`` is quadratic in ``q'``)."""
    nq, n = model.nq, model.n
    x = np.zeros(n)
    x[:nq] = cfg.q

    def h(qd):
        v = np.zeros(n)
        v[:nq] = qd
        return model.velocity_forces(cfg, x, v)

    e = np.eye(nq)
    hd = [h(e[i]) for i in range(nq)]
    return np.column_stack([hd[i] if i == j else h(e[i] + e[j]) - hd[i] - hd[j] for i, j in _velocity_pairs(nq)])


def load_amplitudes(model, planned: PlannedInput, qs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(a, v)`` (nq,), (nq,): the largest coordinate accelerations the inputs can produce over the configurations
    ``qs`` and the largest rates the plan's kinetic energy allows there (module docstring)."""
    nq = model.nq
    mech = model.mech
    p = plan(mech, dt=mech.manoeuvre.duration / (_ENERGY_POINTS - 1))
    T = max(0.5 * qd @ model.mass(model.configuration(q))[:nq, :nq] @ qd for q, qd in zip(p.q, p.qd))
    qs = np.atleast_2d(qs)
    cfgs = [model.configuration(q) for q in np.vstack([qs, p.q])]
    Minv = [np.linalg.inv(model.mass(c)[:nq, :nq]) for c in cfgs]
    # the largest |q'_i| at kinetic energy T is sqrt(2 T (M_qq^-1)_ii): at the lightest configuration
    v = np.maximum(np.sqrt(2.0 * T * np.max([np.diag(Mi) for Mi in Minv], axis=0)), np.abs(planned.qd).max(axis=0))
    tau = np.abs(planned.u).max(axis=0)
    vv = np.array([v[i] * v[j] for i, j in _velocity_pairs(nq)])
    a = np.abs(planned.qdd).max(axis=0)
    for cfg, Mi in zip(cfgs[: len(qs)], Minv):
        G = model.input_matrix(cfg)[:nq]
        Hc = _velocity_coefficients(model, cfg)[:nq]
        g = (cfg.W.T @ (cfg.M_N @ model.g_N))[:nq] if np.any(model.g_N) else np.zeros(nq)
        a = np.maximum(a, np.abs(Mi @ G) @ tau + np.abs(Mi @ Hc) @ vv + np.abs(Mi @ g))
    return a, v


def _scales(a: np.ndarray, v: np.ndarray, n_cols: int, tau: np.ndarray | None = None) -> np.ndarray:
    """The amplitude of each column of :func:`load_shapes` (the weight's: 1; the motors' loads: ``tau``, their
    largest planned torques)."""
    nq = len(a)
    tau = np.zeros(0) if tau is None else np.asarray(tau, float)
    s = np.r_[a, [v[i] * v[j] for i, j in _velocity_pairs(nq)]]
    return np.r_[s, np.ones(n_cols - len(s) - len(tau)), tau]


@dataclass(frozen=True)
class StaticCorrections:
    """The re-based interior modes and the count's figures.

    ``Phi`` (s, s) the interior modes with the columns ``rest`` (those not kept for the dynamics) replaced by the
    corrections, then their complement (:func:`rebase`); ``w2`` their ``K_ss`` eigenvalues at q* (Ritz values for
    the re-based columns); ``D`` (len(rest), n) the corrections in the order they were added, in the coordinates of
    the original ``rest`` modes (``M_ss``-orthonormal); ``n`` the count; ``figure[k]`` the largest residual reading
    with the first ``k`` corrections (noise sd, or a quantity over its limit); ``worst[k]`` (row, sample index) of
    it; ``picked[k]`` (sample index, what) the load (or the reading whose static response) that became correction
    ``k + 1``; ``limit``; ``amplitudes`` the coordinates' ``a`` and rates ``v``; ``G``, ``g2`` the original ``rest``
    modes and their eigenvalues (``rebase`` of them with ``D[:, :k]`` gives the basis with ``k`` corrections)."""

    Phi: np.ndarray
    w2: np.ndarray
    rest: np.ndarray
    D: np.ndarray
    n: int
    figure: np.ndarray
    worst: list
    picked: list
    limit: float
    amplitudes: tuple[np.ndarray, np.ndarray]
    G: np.ndarray
    g2: np.ndarray

    @property
    def met(self) -> bool:
        return bool(self.figure[self.n] <= self.limit)


def rebase(Phi_all: np.ndarray, w2_all: np.ndarray, rest: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Phi, w2)``: the modes ``rest`` of ``Phi_all`` (``M_ss``-orthonormal, ``K_ss`` eigenvalues ``w2_all``)
    replaced by a Rayleigh-Ritz basis of the span of ``D`` (their coordinates, (len(rest), k)) followed by one of its
    complement among them: the same space, still ``M_ss``-orthonormal; ``K_ss``-orthogonal within the corrections
    and within their complement (the two are ``M_ss``-orthogonal, not ``K_ss``-orthogonal, to each other: the
    complement's ``w2`` are Rayleigh quotients), and to the modes not re-based (eigenvectors)."""
    Om2 = w2_all[rest]
    k = D.shape[1]
    if k:
        V, _ = np.linalg.qr(D)
        lv, Ev = np.linalg.eigh(V.T @ (Om2[:, None] * V))
        Cc = sla.null_space(V.T)
        X = V @ Ev
    else:
        lv, Cc, X = np.zeros(0), np.eye(len(rest)), np.zeros((len(rest), 0))
    lc, Ec = np.linalg.eigh(Cc.T @ (Om2[:, None] * Cc))
    Phi = Phi_all.copy()
    Phi[:, rest] = Phi_all[:, rest] @ np.hstack([X, Cc @ Ec])
    w2 = np.array(w2_all, float).copy()
    w2[rest] = np.r_[lv, lc]
    return Phi, w2


def _turn(cb, cfg) -> np.ndarray:
    """(s, s) the map from q*'s slave coordinates (the interior modes' frame) to the slave rows of ``w = Q(q)^T u``
    at ``cfg`` (the turn of :meth:`.basis.CraigBampton.rotated_modes`)."""
    ne, s = cb.model.ne, len(cb.is_)
    P = np.zeros((ne, s))
    P[cb.is_] = np.eye(s)
    P = cb._to_frame(P, *cb._frame_cs(cb.cfg_star), inverse=True)
    return cb._to_frame(cb.rotation(cfg) @ P, *cb._frame_cs(cfg))[cb.is_]


def reading_rows(cb, cfg, planned: PlannedInput, quantity_max=None) -> tuple[np.ndarray, list[str]]:
    """``(Y, names)``: rows (m, ne) on the global elastic coordinates at ``cfg`` whose products read a displacement
    in units of each channel's noise sd (the elastic row plus the coordinates' recoil ``-M_qq^-1 M_qu``, as
    :func:`.truncation.truncation_sample`) and, with ``quantity_max``, the estimated displacement quantities over
    their limits."""
    model, nq = cb.model, cb.nq
    C = channel_matrix(model, cfg, model.mech, planned.channels) / planned.noise[:, None]
    M = model.mass(cfg)
    recoil = -np.linalg.solve(M[:nq, :nq], M[:nq, nq:])
    rows = [C[:, nq:] + C[:, :nq] @ recoil]
    names = list(planned.channels)
    if quantity_max is not None:
        Zq, Zt = quantity_rows(model, cfg, planned.tip)
        Z = recoil + Zq if Zt is None else np.vstack([recoil + Zq, Zt])
        qn = [k for k in planned.quantities if not k.startswith("d")][: Z.shape[0]]
        lim = np.array([quantity_max.get(k, np.inf) for k in qn], float)
        ok = np.isfinite(lim) & (lim > 0)
        rows.append(Z[ok] / lim[ok, None])
        names += [k for k, o in zip(qn, ok) if o]
    return np.vstack(rows), names


@dataclass
class _Sample:
    """One configuration's slave problem in the partition's frame: stiffness ``K`` (s, s), scaled loads ``F`` (s,
    m), their exact responses ``U`` = K^-1 F, the turn ``A`` from q*'s slave coordinates, the readings ``Y`` of a
    slave vector, row names and load names."""

    K: np.ndarray
    F: np.ndarray
    U: np.ndarray
    A: np.ndarray
    Y: np.ndarray
    rows: list
    loads: list


def _sample(cb, q, a, v, planned, quantity_max) -> _Sample:
    model = cb.model
    cfg = model.configuration(q)
    qc, qs = cb._frame_cs(cfg)
    Kw = cb._congruence(model.stiffness(cfg)[cb.nq:, cb.nq:], qc, qs)[np.ix_(cb.is_, cb.is_)]
    L, loads = load_shapes(model, cfg)
    tau = np.abs(planned.u).max(axis=0)[motor_loads(model)]
    F = cb._to_frame(L * _scales(a, v, L.shape[1], tau)[None, :], qc, qs)[cb.is_]
    Y, rows = reading_rows(cb, cfg, planned, quantity_max)
    E = np.zeros((model.ne, len(cb.is_)))
    E[cb.is_] = np.eye(len(cb.is_))
    return _Sample(Kw, F, np.linalg.solve(Kw, F), _turn(cb, cfg), Y @ cb._to_frame(E, qc, qs, inverse=True), rows,
                   loads)


def _residual_readings(smp: _Sample, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, e)``: the Galerkin residual ``U - V (V^T K V)^-1 V^T F`` of the sample's responses with the slave
    basis ``V`` (q*'s coordinates, turned by ``A``) and its readings ``e = Y R``."""
    W = smp.A @ V
    R = smp.U - W @ np.linalg.solve(W.T @ smp.K @ W, W.T @ smp.F) if W.shape[1] else smp.U
    return R, smp.Y @ R


def static_corrections(cb, kept, qs: np.ndarray, planned: PlannedInput, quantity_max=None,
                       limit: float = STATIC_MAX) -> StaticCorrections | None:
    """The static corrections of ``cb``'s interior modes beside the modes ``kept`` (module docstring), over the
    configurations ``qs``; None where no interior mode is left or no load reaches the slaves."""
    model = cb.model
    Phi_all = cb.Phi_all
    w2_all = (2 * np.pi * cb.interior_frequencies_hz) ** 2
    kept = np.sort(np.asarray(kept, int))
    rest = np.setdiff1d(np.arange(Phi_all.shape[1]), kept)
    if rest.size == 0:
        return None
    a, v = load_amplitudes(model, planned, qs)
    samples = [_sample(cb, q, a, v, planned, quantity_max) for q in np.atleast_2d(qs)]
    if not any(np.any(s.F) for s in samples):
        return None
    Gm = Phi_all[:, rest]
    Ms = cb._congruence(model.mass(cb.cfg_star)[cb.nq:, cb.nq:], *cb._frame_cs(cb.cfg_star))[np.ix_(cb.is_, cb.is_)]
    Pinv = [np.linalg.pinv(s.A) for s in samples]
    def figure(D):
        """The largest reading over the samples with the corrections ``D``, where, and each sample's residuals."""
        V = np.hstack([Phi_all[:, kept], Gm @ D])
        worst, where, res = 0.0, None, []
        for c, smp in enumerate(samples):
            R, e = _residual_readings(smp, V)
            tot = np.abs(e).sum(axis=1)  # the largest reading of a load in the amplitude box
            i = int(np.argmax(tot))
            if tot[i] > worst:
                worst, where = float(tot[i]), (smp.rows[i], c)
            res.append((R, np.abs(e).max(axis=0), tot))
        return worst, where, res

    D = np.zeros((len(rest), 0))  # the corrections, orthonormal in rest's coordinates
    worst, where, res = figure(D)
    figs, worsts, picked = [worst], [where], []
    while worst > limit and D.shape[1] < len(rest):
        # candidates: the residual (outside the kept modes and the corrections) of each load read above the limit,
        # the most read first; the next correction is the one that leaves the smallest figure
        # and the static response to each row read above the limit (its adjoint: with it in the basis, the Galerkin
        # model's static readings in that row are exact for every load, y^T r = (K^-1 y)^T K r = 0)
        cands = sorted([(float(col[j]), c, "load", j) for c, (_, col, _) in enumerate(res) for j in range(len(col))
                        if col[j] > limit], reverse=True)[:_CANDIDATES]
        cands += sorted([(float(tot[i]), c, "row", i) for c, (_, _, tot) in enumerate(res) for i in range(len(tot))
                         if tot[i] > limit], reverse=True)[:_CANDIDATES]
        best = None
        for _, c, kind, j in cands:
            smp = samples[c]
            x = res[c][0][:, j] if kind == "load" else np.linalg.solve(smp.K, smp.Y[j])
            d = Gm.T @ (Ms @ (Pinv[c] @ x))
            scale = np.linalg.norm(d)
            d -= D @ (D.T @ d)
            nd = np.linalg.norm(d)
            if nd <= _RANK_TOL * max(scale, 1e-300):
                continue
            Dn = np.hstack([D, (d / nd)[:, None]])
            f = figure(Dn)
            if best is None or f[0] < best[0][0]:
                best = (f, Dn, (c, smp.loads[j] if kind == "load" else f"reading {smp.rows[j]}"))
        if best is None:
            break
        (worst, where, res), D, pk = best
        figs.append(worst)
        worsts.append(where)
        picked.append(pk)
    Phi, w2 = rebase(Phi_all, w2_all, rest, D)
    return StaticCorrections(Phi, w2, rest, D, D.shape[1], np.array(figs), worsts, picked, float(limit), (a, v), Gm,
                             w2_all[rest])

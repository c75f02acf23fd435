"""One whole filter sample of the cached reduced observer in a single compiled call.

:class:`~exuflex.observer.ekf.MultirateEKF` over :class:`~exuflex.observer.reduced.ReducedObserverModel`
(``method="cached"``) does per sample: the held model's step (:mod:`.held`), a step-map rebuild when q has
moved by ``remap_rad``, the Jacobian ``F = Pn + SQM dF/dz``, ``P = F P F' + Q``, the measurement rows along
the secant, the Joseph update and the end-of-sample symmetrisation. Each part is compiled, but called one
by one from Python it costs about as much in Python glue as in arithmetic (some 130 us per sample, against
the 100 us that 20x real time allows at 500 Hz). :func:`cached_sample` runs them all in one call, with the
same compiled functions in the same order, so the results equal the step-by-step path's (bit for bit on the
six-bar's 3 s log, ``tests/test_fused.py``). Measured on the six-bar (fast phases of a machine whose speed
drifts by 30-80 %): about 29 us per call inside a compiled loop (the held model and its 20 RK4 steps 13 us, of
which the RK4 steps 7.7 us; Jacobian 3.5 us, covariance prediction 3.5 us, update 6 us), 2-3 us more from
Python (the arguments are one packed buffer instead of 46 arrays: 1.3-1.6 us to pass instead of 4.7 us),
33-46 us more when the step map is rebuilt. :func:`cached_run` loops over the samples of a whole log in
compiled code (``MultirateEKF.run``), which removes Python's 9 us per sample.

Python keeps what happens a few dozen times per run: the configuration evaluations, the measurement rows
per held configuration, and every case the kernel declines (it then returns a nonzero status before it has
changed the filter's state, and the filter takes its step-by-step path for that sample):

- ``RESCUE``: the held model broke down (NaN step; the step-by-step path evaluates the configuration);
- ``FAR``: the predicted q left the held configuration's measurement radius;
- ``INDEFINITE``: the innovation covariance is not positive definite (the step-by-step path's LU solve);
- ``REFRESH``: q left the held configuration's radius; the caller evaluates the configuration and calls
  again;
- ``JUMP``: the torque sample that ends the interval differs from the held one by more than their noise
  explains (the test of :meth:`~exuflex.observer.reduced.ReducedObserverModel.input_jump`, done here so that
  an ordinary sample costs no Python for it): the step-by-step path adds the jump's effect.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ._compiled import predict_cov, settle, update
from .held import (
    HAVE_NUMBA,
    _held_system,
    _jit,
    held_step_loops,
    map_lookahead,
    step_jacobian_loops,
    step_maps_held,
)

__all__ = ["DONE", "FAR", "INDEFINITE", "JUMP", "MISSING", "REFRESH", "RESCUE", "cached_run", "cached_sample",
           "warm_up"]

DONE, RESCUE, FAR, INDEFINITE, REFRESH, JUMP = 0, 1, 2, 3, 4, 5


def _secant_factor(dl, d, dd, has_old):  # pragma: no cover - compiled; twin of reduced._secant_factor
    if not has_old:
        return 0.0
    a = 0.0
    n2 = 0.0
    for i in range(dl.shape[0]):
        a += dl[i] * d[i]
        n2 += dl[i] * dl[i]
    if a * a < 0.49 * n2 * dd:
        return 0.0
    return a / dd


def _vec(pack, lay, i):  # pragma: no cover - compiled
    o = lay[4 * i]
    return pack[o : o + lay[4 * i + 1]]


def _mat(pack, lay, i):  # pragma: no cover - compiled
    o, a, b = lay[4 * i], lay[4 * i + 1], lay[4 * i + 2]
    return pack[o : o + a * b].reshape((a, b))


def _ten(pack, lay, i):  # pragma: no cover - compiled
    o, a, b, c = lay[4 * i], lay[4 * i + 1], lay[4 * i + 2], lay[4 * i + 3]
    return pack[o : o + a * b * c].reshape((a, b, c))


def _cached_sample(z, P, u, u_next, y, Rd, floor, x_out, r, S, P_out, P_pred, work, HP, pack, lay, fl, has_old,
                   nq, n):  # pragma: no cover - compiled
    """Predict over one interval and update with all channels of ``y``.

    Parameters
    ----------
    z, P : prior state and covariance at the previous sample (not written).
    u : input held over the interval; u_next : the input sample that ends it (for the jump test).
    y, Rd : measurement and its variances (all channels finite).
    floor : diagonal floor of the posterior covariance.
    x_out, r, S, P_out : out: posterior mean, innovation and its covariance, posterior covariance (``P_out``
        symmetrised and floored); P_pred, work, HP : scratch.
    pack, lay : every array that stays fixed while a configuration is held, in one buffer (one argument to
        pass instead of 33: numba unboxes each array argument of a call, about 0.1 us each), laid out as
        :data:`PACKED` says; ``lay[4 i : 4 i + 4]`` = offset and shape of item ``i``. The step map items
        (``q_map, Pn, SQM, L, Q``) are rebuilt in place when q has moved by ``remap_rad`` (a NaN ``q_map``
        forces the rebuild).
    fl : ``(rad, meas_rad, dd, remap_rad, beta, h, jump_threshold, ahead, horizon, jump_weights...)``: the
        held configuration's refresh radius (``REFRESH`` beyond it) and measurement radius, ``d . d`` of the
        secant direction ``d``, the step-map rebuild distance, the stiffness-proportional damping, the RK4
        step, the torque-jump test (``JUMP`` if ``sum w_i (u_next - u)_i^2 > threshold``; inf: no test) and
        how far ahead along the motion a step map is built (:func:`.held.map_lookahead`).
    has_old, nq, n : a secant partner exists; number of rigid coordinates; RK4 steps per interval.

    Returns
    -------
    status : int
        ``DONE`` or the reason the sample was declined (nothing but the map buffers written).
    nis : float
    remapped : bool
    finite : bool
        The posterior state and covariance are finite.
    """
    rad, meas_rad, dd, remap_rad, beta, h = fl[0], fl[1], fl[2], fl[3], fl[4], fl[5]
    jump = 0.0
    for i in range(u.shape[0]):
        e = u_next[i] - u[i]
        jump += e * e * fl[9 + i]
    if jump > fl[6]:
        return JUMP, math.nan, False, False
    q0, d = _vec(pack, lay, 0), _vec(pack, lay, 1)
    dl = z[:nq] - q0
    for i in range(nq):
        if abs(dl[i]) > rad:
            return REFRESH, math.nan, False, False
    s = _secant_factor(dl, d, dd, has_old)
    z_next, Mr, Kr, Cr, Gr = held_step_loops(
        z, u, dl, s, has_old, nq, beta, h, n, _mat(pack, lay, 2), _mat(pack, lay, 3), _mat(pack, lay, 4),
        _mat(pack, lay, 5), _mat(pack, lay, 6), _mat(pack, lay, 7), _vec(pack, lay, 8), _mat(pack, lay, 9),
        _mat(pack, lay, 10), _mat(pack, lay, 11), _mat(pack, lay, 12), _mat(pack, lay, 13), _mat(pack, lay, 14),
        _mat(pack, lay, 15), _vec(pack, lay, 16), _mat(pack, lay, 17), _mat(pack, lay, 18), _mat(pack, lay, 19))
    if not math.isfinite(z_next[0]) and (s != 0.0 or np.any(dl != 0.0)):
        return RESCUE, math.nan, False, False
    q_map = _vec(pack, lay, 22)
    Pn, SQM, L, Q = _mat(pack, lay, 23), _mat(pack, lay, 24), _mat(pack, lay, 25), _mat(pack, lay, 26)
    remapped = False
    for i in range(nq):
        if not abs(z[i] - q_map[i]) <= remap_rad:
            remapped = True
    if remapped:
        dla = dl + map_lookahead(z, nq, remap_rad, fl[7], fl[8])
        for i in range(nq):  # (not beyond the held model's measurement radius)
            dla[i] = min(max(dla[i], -meas_rad), meas_rad)
        sa = _secant_factor(dla, d, dd, has_old)
        Mr, Kr, Cr, Gr = _held_system(dla, sa, has_old, beta, _mat(pack, lay, 2), _mat(pack, lay, 3),
                                      _mat(pack, lay, 4), _mat(pack, lay, 5), _mat(pack, lay, 6), _mat(pack, lay, 7),
                                      _mat(pack, lay, 12), _mat(pack, lay, 13), _mat(pack, lay, 14),
                                      _mat(pack, lay, 15))
        Pn_new, SQM_new, L_new, Q_new = step_maps_held(Mr, Kr, Cr, Gr, h, n, _vec(pack, lay, 20))
        Pn[:] = Pn_new
        SQM[:] = SQM_new
        L[:] = L_new
        Q[:] = Q_new
        q_extra = _vec(pack, lay, 21)
        for i in range(q_extra.shape[0]):
            Q[i, i] += q_extra[i]
        q_map[:] = q0 + dla
    F = step_jacobian_loops(z, _ten(pack, lay, 27), _ten(pack, lay, 28), _ten(pack, lay, 29), Pn, SQM)
    dlp = z_next[:nq] - q0
    for i in range(nq):
        if abs(dlp[i]) > meas_rad:
            return FAR, math.nan, remapped, False
    predict_cov(F, P, Q, P_pred, work)
    H = _mat(pack, lay, 31)
    dH = _mat(pack, lay, 32)
    if dH.shape[0]:
        sm = _secant_factor(dlp, d, dd, has_old) * dd
        if sm != 0.0:
            H = H + sm * dH
    y_pred = _vec(pack, lay, 30) + H @ z_next
    nis, ok = update(z_next, P_pred, y, y_pred, H, Rd, HP, r, S, x_out, P_out)
    if not ok:
        return INDEFINITE, math.nan, remapped, False
    return DONE, nis, remapped, settle(x_out, P_out, floor)


#: Items of the packed arguments of :func:`cached_sample`, in order (see :func:`pack_arguments`).
PACKED = ("q0", "d", "Mr0", "Kr0", "Ca0", "Gr0", "dM2", "dK2", "fg", "T2", "V2", "C2", "oM2", "oK2", "oCa",
          "oGr", "ofg", "oT2", "oV2", "oC2", "torque_var", "q_extra", "q_map", "Pn", "SQM", "L", "Q", "Ts", "Vs",
          "C3", "c0", "Hm", "dH")


@functools.lru_cache(maxsize=16)
def _layout(shapes: tuple) -> tuple[np.ndarray, list[int]]:
    """The int64 layout of :func:`pack_arguments` for items of these shapes and every item's offset; a few
    signatures per observer (with and without a secant partner, per channel tuple), hence the small cache."""
    if len(shapes) != len(PACKED):
        raise ValueError(f"{len(shapes)} arrays to pack, expected {len(PACKED)}")
    lay = []
    offsets = []
    off = 0
    for name, shape in zip(PACKED, shapes):
        if len(shape) > 3:
            raise ValueError(f"{name} has {len(shape)} dimensions, at most 3 can be packed")
        lay += [off, *shape, *(0,) * (3 - len(shape))]
        offsets.append(off)
        off += math.prod(shape)
    return np.array(lay, dtype=np.int64), offsets


def pack_arguments(arrays, views=()) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """``(pack, lay, views)``: the float64 arrays (in :data:`PACKED` order) copied into one buffer, the int64
    layout (offset and up to three dimensions per item; shared by the packs of arrays of the same shapes, read
    only) and a view of the buffer, of the item's shape, for each item index in ``views`` (writing a view writes
    the buffer the kernel reads)."""
    lay, offsets = _layout(tuple([a.shape for a in arrays]))
    pack = np.concatenate(arrays, axis=None)
    if pack.dtype != np.float64:
        raise ValueError(f"packed arrays must be float64, got {pack.dtype}")
    out = [pack[offsets[i] : offsets[i] + arrays[i].size].reshape(arrays[i].shape) for i in views]
    return pack, lay, out


_secant_factor = _jit(_secant_factor)
_vec = _jit(_vec)
_mat = _jit(_mat)
_ten = _jit(_ten)
cached_sample = _jit(_cached_sample) if HAVE_NUMBA else None

#: :func:`cached_run` stopped at a sample with a missing or non-finite channel, or off the time grid.
MISSING = 6


def _cached_run(k0, U, Y, on_grid, jumps, x, P, P_alt, Rd, floor, r, S, P_pred, work, HP, pack, lay, fl, has_old,
                nq, n, X_out, Pd_out, Pf_out, R_out, S_out, nis_out):  # pragma: no cover - compiled
    """:func:`cached_sample` over the samples ``k0, k0 + 1, ...`` of a log while the kernel accepts them: the
    filter's sample loop compiled, for the offline run over a whole log (``MultirateEKF.run``).

    Sample ``k`` is predicted over the interval from ``k - 1`` with the input ``U[k - 1]`` held (``U[k]``
    ends it, for the jump test if ``jumps``) and updated with every channel of ``Y[k]``; its posterior mean,
    covariance diagonal (``Pd_out``, if it has rows) or whole covariance (``Pf_out``, likewise), innovation,
    innovation covariance and NIS go to row ``k`` of the outputs. ``x`` (in/out) holds the running mean;
    the covariance alternates between ``P`` and ``P_alt`` (a kernel never writes the covariance it reads).

    Returns
    -------
    k : int
        The first sample not done (``Y.shape[0]`` if all were).
    status : int
        Why the loop stopped at ``k``: ``DONE`` (the end, or the posterior of ``k - 1`` was not finite),
        a declined sample's status (nothing of sample ``k`` written but the step-map buffers), or
        ``MISSING`` (a channel without a finite sample, or ``t[k]`` off the grid: ``on_grid[k]`` False).
    in_alt : bool
        The latest covariance is in ``P_alt``.
    remaps : int
        Step maps rebuilt.
    finite : bool
        The last posterior is finite.
    """
    m = Y.shape[1]
    x_out = np.empty(x.shape[0])
    in_alt = False
    remaps = 0
    for k in range(k0, Y.shape[0]):
        y = Y[k]
        present = on_grid[k]
        for i in range(m):
            if not math.isfinite(y[i]):
                present = False
        if not present:
            return k, MISSING, in_alt, remaps, True
        u = U[k - 1]
        status, nis, remapped, finite = cached_sample(
            x, P_alt if in_alt else P, u, U[k] if jumps else u, y, Rd, floor, x_out, r, S, P if in_alt else P_alt,
            P_pred, work, HP, pack, lay, fl, has_old, nq, n)
        if remapped:
            remaps += 1
        if status != DONE:
            return k, status, in_alt, remaps, True
        in_alt = not in_alt
        Pk = P_alt if in_alt else P
        x[:] = x_out
        X_out[k] = x_out
        if Pd_out.shape[0]:
            for i in range(x.shape[0]):
                Pd_out[k, i] = Pk[i, i]
        if Pf_out.shape[0]:
            Pf_out[k] = Pk
        R_out[k] = r
        S_out[k] = S
        nis_out[k] = nis
        if not finite:
            return k + 1, DONE, in_alt, remaps, False
    return Y.shape[0], DONE, in_alt, remaps, True


cached_run = _jit(_cached_run) if HAVE_NUMBA else None


def warm_up() -> None:
    """Compile (or load from numba's cache) :func:`cached_sample` and :func:`cached_run` for the argument types the
    filter passes."""
    if not HAVE_NUMBA:
        return
    r, nq, m = 2, 1, 1
    nx = 2 * r
    z, u = np.zeros(nx), np.zeros(nq)
    M, g2, f = np.eye(r), np.zeros((nq, r * r)), np.zeros(r)
    T2, V2, C2 = np.zeros((r, r * r)), np.zeros((nq * r, r)), np.zeros((r * nq, r))
    G = np.zeros((r, nq))
    sq = np.empty((nx, nx))
    pack, lay, _ = pack_arguments(
        (u, u, M, M, M, G, g2, g2, f, T2, V2, C2, g2, g2, M, G, f, T2, V2, C2, np.ones(nq), np.zeros(0),
         np.full(nq, np.nan), sq, np.empty((nx, r)), np.empty((nx, nq)), sq, np.zeros((r, r, r)), np.zeros((nq, r, r)),
         np.zeros((r, nq, r)), np.zeros(m), np.zeros((m, nx)), np.zeros((0, nx))))
    fl = np.array([1.0, 1.0, 1.0, 1e-3, 0.0, 1e-4, np.inf, 1.0, 0.02, 1.0])
    cached_sample(z, np.eye(nx), u, u, np.zeros(m), np.ones(m), np.zeros(nx), np.empty(nx), np.empty(m),
                  np.empty((m, m)), sq.copy(), sq.copy(), sq.copy(), np.empty((m, nx)), pack, lay, fl, False, nq, 1)
    k = 2  # and the compiled sample loop, over two samples
    cached_run(1, np.zeros((k, nq)), np.zeros((k, m)), np.ones(k, dtype=np.bool_), True, z.copy(), np.eye(nx),
               sq.copy(), np.ones(m), np.zeros(nx), np.empty(m), np.empty((m, m)), sq.copy(), sq.copy(),
               np.empty((m, nx)), pack, lay, fl, False, nq, 1, np.empty((k, nx)), np.empty((k, nx)),
               np.empty((0, nx, nx)), np.empty((k, m)), np.empty((k, m, m)), np.empty(k))

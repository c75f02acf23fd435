"""The Kalman algebra of :class:`~exuflex.observer.ekf.MultirateEKF`, compiled with numba: the one implementation.

- :func:`predict_cov`: ``P = F P F' + Q`` (eq. 13);
- :func:`update`: innovation, its covariance, one Cholesky solve for the gain and ``S^-1 r``, the posterior mean
  and the Joseph-form covariance (eqs. 14-15);
- :func:`settle`: symmetrisation, a floor on the variances and the finiteness test that end every sample;
- :func:`predict_update`: the three in one call;
- :func:`condition_on`: :func:`update` and :func:`settle` on a subset of the channels (a sample with channels
  missing or gated); :func:`gate`: which channels the gate leaves out;
- :func:`predict`, :func:`condition`: the same algebra as pure steps on a :class:`~.base.Belief` (new arrays; the
  filter's driver calls the kernels on its own buffers).

At the observer's size (tens of states, a few channels) a NumPy call costs more in dispatch and temporaries
than in arithmetic, so the update's thin products are loops over contiguous rows (``row_i += a * row_k``, the
form LLVM vectorises without reassociating a sum); the covariance prediction keeps BLAS (two ``dgemm``). The
kernels are compiled without ``fastmath``: each entry is an ordinary evaluation of its formula. The tests
compare them with NumPy expressions and with filterpy's ``ExtendedKalmanFilter`` (independent oracles).

Calling convention: arrays are float64; results go to caller-owned ``out`` arrays where that saves numba
the cost of returning a new array (about half a microsecond each). An ``out`` argument is never read
before it is written and must not alias an input unless its docstring says so.

Without numba (a core dependency) the kernels run as plain, slow Python.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .base import Belief, Measurement, Prediction
from .stats import chi2_ppf

try:
    import numba
except ImportError:  # pragma: no cover - numba is a core dependency
    numba = None

__all__ = [
    "Innovation",
    "InputStepTest",
    "apply_gain",
    "condition",
    "condition_on",
    "fix_cov",
    "gate",
    "normalise",
    "predict",
    "predict_cov",
    "predict_update",
    "settle",
    "step_statistic",
    "update",
    "warm_up",
    "window_push",
    "window_seen",
]

if numba is not None:
    # error_model="numpy": a division by zero gives inf/nan, with no exception checks in the loops; no fastmath
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy", no_cfunc_wrapper=True)
    # the helpers below: inlined into the kernels that call them (numba IR), so that the kernels' loops compile as if
    # written out (called instead, the Joseph update took about a tenth longer)
    _inline = numba.njit(nogil=True, error_model="numpy", no_cfunc_wrapper=True, inline="always")
else:  # pragma: no cover

    def _jit(f):
        return f

    _inline = _jit


# --------------------------------------------------------------------------------------------- helpers
@_inline
def _substitute(row, u, rows, d):
    """One row of a triangular solve in place: ``row = (row - sum_k u[k] rows[k]) / d``, ``k`` ascending."""
    for k in range(u.shape[0]):
        uk = u[k]
        prev = rows[k]
        for j in range(row.shape[0]):
            row[j] -= uk * prev[j]
    for j in range(row.shape[0]):
        row[j] /= d


@_inline
def _less_combination(out, base, coef, col, rows, m, tmp):
    """``out = base - sum_i coef[i, col] rows[i, :len(tmp)]`` over ``i < m`` ascending, summed in the scratch
    ``tmp`` (``out`` may alias ``base``)."""
    tmp[:] = 0.0
    for i in range(m):
        c = coef[i, col]
        r = rows[i]
        for j in range(tmp.shape[0]):
            tmp[j] += c * r[j]
    for j in range(tmp.shape[0]):
        out[j] = base[j] - tmp[j]


@_jit
def _cholesky_solve(S, sol, U):
    """Solve ``S X = sol`` in place through the Cholesky factor ``S = U' U`` of the upper triangle of ``S``.

    The strict lower triangle of ``S`` is not read, as in LAPACK's ``dposv(uplo="U")``. Returns False (``sol`` partly overwritten) if a pivot is not positive or is NaN, the
    test of LAPACK's ``dpotrf``: ``S`` is not positive definite.
    """
    m = S.shape[0]
    for j in range(m):
        a = S[j, j]
        for k in range(j):
            a -= U[k, j] * U[k, j]
        if not a > 0.0:
            return False
        d = math.sqrt(a)
        U[j, j] = d
        for i in range(j + 1, m):
            s = S[j, i]
            for k in range(j):
                s -= U[k, j] * U[k, i]
            U[j, i] = s / d
    for i in range(m):  # U' Z = B
        _substitute(sol[i], U[:i, i], sol[:i], U[i, i])
    for i in range(m - 1, -1, -1):  # U X = Z
        _substitute(sol[i], U[i, i + 1 :], sol[i + 1 :], U[i, i])
    return True


# --------------------------------------------------------------------------------------------- kernels
@_jit
def predict_cov(F, P, Q, out, work):
    """``out = F P F' + Q`` (two BLAS products, then ``+ Q``).

    Parameters
    ----------
    F, P, Q : ndarray, shape (n, n)
    out : ndarray, shape (n, n)
        Result (must not alias ``F``, ``P`` or ``Q``).
    work : ndarray, shape (n, n)
        C-contiguous scratch.
    """
    np.dot(F, P, work)
    np.dot(work, F.T, out)
    n = out.shape[0]
    for i in range(n):
        row = out[i]
        q = Q[i]
        for j in range(n):
            row[j] += q[j]


@_jit
def apply_gain(x, P, H, HP, Rd, r, sol, x_out, P_out):
    """Posterior from the solved gain system: the part of :func:`update` after the solve.

    ``sol`` holds ``S^-1 [H P, r]`` (``K'`` in the first ``n`` columns, ``S^-1 r`` in the last). Writes
    ``x_out = x + K r`` and the Joseph form ``A - (A H' - K R) K'`` with ``A = P - K H P`` (valid for any
    gain) and returns the NIS ``r' S^-1 r``.

    The Joseph form is evaluated transposed, ``A' - K (H A' - R K')`` with ``A' = P - (H P)' K'`` (``P``
    symmetric, so ``H P = (P H')'``): every product then runs along contiguous rows. ``P_out`` is the
    unsymmetrised Joseph form transposed (up to rounding), which the end-of-sample symmetrisation removes.

    Parameters
    ----------
    x : ndarray, shape (n,)
    P : ndarray, shape (n, n)
        Symmetric prior covariance.
    H : ndarray, shape (m, n)
    HP : ndarray, shape (>= m, n)
        ``H P`` in its first ``m`` rows.
    Rd : ndarray, shape (m,)
        Diagonal of ``R``.
    r : ndarray, shape (m,)
        Innovation.
    sol : ndarray, shape (>= m, n + 1)
    x_out : ndarray, shape (n,)
        Posterior mean (may alias ``x``).
    P_out : ndarray, shape (n, n)
        Posterior covariance, not symmetrised (must not alias an input).

    Returns
    -------
    float
    """
    m, n = H.shape
    nis = 0.0
    for i in range(m):
        nis += r[i] * sol[i, n]
    tmp = np.zeros(n)
    for i in range(m):  # K r
        ri = r[i]
        k = sol[i]
        for j in range(n):
            tmp[j] += k[j] * ri
    for j in range(n):
        x_out[j] = x[j] + tmp[j]
    for l in range(n):  # A' = P - (H P)' K', kept in P_out
        _less_combination(P_out[l], P[l], HP, l, sol, m, tmp)
    Bt = np.zeros((m, n))
    for i in range(m):  # B' = H A' - R K'
        row = Bt[i]
        for l in range(n):
            h = H[i, l]
            if h != 0.0:  # (H's zeros, e.g. its velocity half, add nothing)
                a = P_out[l]
                for j in range(n):
                    row[j] += h * a[j]
        rd = Rd[i]
        k = sol[i]
        for j in range(n):
            row[j] -= k[j] * rd
    for l in range(n):  # A' - K B'
        _less_combination(P_out[l], P_out[l], sol, l, Bt, m, tmp)
    return nis


@_jit
def update(x, P, y, y_pred, H, Rd, HP, r, S, x_out, P_out):
    """Measurement update (eqs. 14-15), Joseph form.

    ``r = y - y_pred``, ``S = H P H' + diag(Rd)``, one Cholesky solve of ``S`` for ``[H P, r]`` (the gain
    ``K' = S^-1 H P`` and ``S^-1 r``), then :func:`apply_gain`.

    Parameters
    ----------
    x : ndarray, shape (n,)
        Prior mean.
    P : ndarray, shape (n, n)
        Prior covariance (symmetric).
    y, y_pred : ndarray, shape (m,)
        Measured and predicted channels.
    H : ndarray, shape (m, n)
        Measurement Jacobian.
    Rd : ndarray, shape (m,)
        Measurement variances.
    HP : ndarray, shape (>= m, n)
        Out: ``H P`` in the first ``m`` rows (what a fallback solve needs).
    r : ndarray, shape (m,)
        Out: innovation.
    S : ndarray, shape (m, m)
        Out: innovation covariance.
    x_out : ndarray, shape (n,)
        Out: posterior mean (may alias ``x``).
    P_out : ndarray, shape (n, n)
        Out: posterior covariance, not symmetrised (must not alias an input).

    Returns
    -------
    nis : float
        ``r' S^-1 r`` (NaN if not ``ok``).
    ok : bool
        False if ``S`` is not positive definite: ``x_out`` and ``P_out`` are then not written; the caller
        solves ``S`` otherwise and finishes with :func:`apply_gain`.
    """
    m, n = H.shape
    for i in range(m):
        r[i] = y[i] - y_pred[i]
    for i in range(m):  # H P
        row = HP[i]
        row[:] = 0.0
        for k in range(n):
            h = H[i, k]
            if h != 0.0:  # (sensors read positions: H's velocity half is zero)
                p = P[k]
                for j in range(n):
                    row[j] += h * p[j]
    for i in range(m):  # (H P) H' + R
        hp = HP[i]
        for j in range(m):
            h = H[j]
            s = 0.0
            for k in range(n):
                s += hp[k] * h[k]
            S[i, j] = s
        S[i, i] += Rd[i]
    sol = np.empty((m, n + 1))
    for i in range(m):  # element copies, not a slice assignment (whose shape check links numba's message code)
        for j in range(n):
            sol[i, j] = HP[i, j]
        sol[i, n] = r[i]
    if not _cholesky_solve(S, sol, np.empty((m, m))):
        return math.nan, False
    return apply_gain(x, P, H, HP, Rd, r, sol, x_out, P_out), True


@_jit
def fix_cov(P, floor):
    """Symmetrise ``P`` in place, ``(P + P') / 2``, and floor its diagonal at ``floor`` (shape (n,)).

    A NaN on the diagonal stays NaN (the finiteness test must see it).
    """
    n = P.shape[0]
    for i in range(n):
        d = (P[i, i] + P[i, i]) * 0.5
        if d < floor[i]:  # noqa: PLR1730 - not max(): a NaN must stay NaN
            d = floor[i]
        P[i, i] = d
        for j in range(i + 1, n):
            s = (P[i, j] + P[j, i]) * 0.5
            P[i, j] = s
            P[j, i] = s


@_jit
def settle(x, P, floor):
    """:func:`fix_cov` on ``P``, then the filter's end-of-sample test: is ``sum(x) + sum(P)`` finite?

    A NaN or inf anywhere makes the sum non-finite (a finite sum overflowing to inf fails the test too). Four partial sums keep the additions from waiting on each other.
    """
    fix_cov(P, floor)
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    n = P.shape[0]
    n4 = n - n % 4
    for i in range(n):
        row = P[i]
        for j in range(0, n4, 4):
            s0 += row[j]
            s1 += row[j + 1]
            s2 += row[j + 2]
            s3 += row[j + 3]
        for j in range(n4, n):
            s0 += row[j]
    for j in range(x.shape[0]):
        s1 += x[j]
    return math.isfinite((s0 + s1) + (s2 + s3))


@_jit
def normalise(r, S, gate, z):
    """The normalised innovations ``z_i = r_i / sqrt(S_ii)`` (standard normal for a consistent filter) into
    ``z``; returns how many exceed the gate, ``z_i**2 > gate``."""
    n_over = 0
    for i in range(r.shape[0]):
        z[i] = r[i] / math.sqrt(abs(S[i, i]))
        if z[i] * z[i] > gate:
            n_over += 1
    return n_over


@_jit
def predict_update(F, P, Q, x, y, y_pred, H, Rd, floor, scratch, out):
    """One whole sample: :func:`predict_cov` into ``P_pred``, :func:`update` from it, :func:`settle`.

    ``x`` is the predicted mean (the model's step); ``scratch`` is ``(P_pred, work, HP)`` (the predicted covariance
    and :func:`predict_cov`'s and :func:`update`'s scratch), ``out`` is ``(r, S, x_out, P_out)`` (:func:`update`'s
    outputs). Returns ``(nis, ok, finite)``; with ``ok`` False (``S`` not positive definite) nothing after the
    prediction is written and the caller finishes the update from ``P_pred``."""
    P_pred, work, HP = scratch
    r, S, x_out, P_out = out
    predict_cov(F, P, Q, P_pred, work)
    nis, ok = update(x, P_pred, y, y_pred, H, Rd, HP, r, S, x_out, P_out)
    if not ok:
        return nis, False, True
    return nis, True, settle(x_out, P_out, floor)


#: how :func:`condition_on` solved ``S``: by Cholesky; by LU (``S`` not positive definite: rounding, or a wrong
#: model; the filter warns); not at all (``S`` singular: nothing written)
CHOLESKY, LU, SINGULAR = 0, 1, 2


@_jit
def condition_on(keep, x, P, y, y_pred, H, Rd, floor, HP, x_out, P_out):
    """The update (:func:`update`) with the channels ``keep`` marks (the rows of ``y``, ``y_pred``, ``H``, ``Rd``
    where ``keep`` is True, in order), then :func:`settle`: ``(nis, how, finite, r, S)``, ``r`` and ``S`` of the
    kept channels. Where ``S`` is not positive definite the gain comes from an LU solve (:func:`apply_gain`;
    ``how`` :data:`LU`); where it is singular nothing is written (``how`` :data:`SINGULAR`)."""
    m, n = H.shape
    mk = 0
    for i in range(m):
        if keep[i]:
            mk += 1
    yk, ypk, Hk, Rk = y, y_pred, H, Rd
    if mk < m:  # the kept rows, copied element by element (no fancy indexing: its checks cost compile time)
        yk, ypk, Hk, Rk = np.empty(mk), np.empty(mk), np.empty((mk, n)), np.empty(mk)
        j = 0
        for i in range(m):
            if keep[i]:
                yk[j], ypk[j], Rk[j] = y[i], y_pred[i], Rd[i]
                for l in range(n):
                    Hk[j, l] = H[i, l]
                j += 1
    r, S = np.empty(mk), np.empty((mk, mk))
    nis, ok = update(x, P, yk, ypk, Hk, Rk, HP, r, S, x_out, P_out)
    how = CHOLESKY
    if not ok:  # S not positive definite: the gain system [H P, r] solved by LU
        rhs = np.empty((mk, n + 1))
        for i in range(mk):
            for j in range(n):
                rhs[i, j] = HP[i, j]
            rhs[i, n] = r[i]
        try:
            sol = np.linalg.solve(S, rhs)
        except Exception:  # noqa: BLE001 (numba catches no narrower class) S singular
            return math.nan, SINGULAR, False, r, S
        nis = apply_gain(x, P, Hk, HP[:mk], Rk, r, sol, x_out, P_out)
        how = LU
    return nis, how, settle(x_out, P_out, floor), r, S


@_jit
def gate(z, threshold, n_over, keep):
    """The gate's choice of channels (the filter's module notes), from the normalised innovations ``z`` of which
    ``n_over`` exceed ``threshold`` (:func:`normalise`; 0 within the hold-off after an input step: no gating): a
    channel stays in the update unless ``keep`` already leaves it out (the isolation of a faulty sensor) or its
    ``z_i**2`` exceeds ``threshold``; where none or most of the channels (at least half) would be left out, all
    stay (then the filter, not a sensor, is off: the NIS test sees it). Writes ``keep``, returns how many stay."""
    m = z.shape[0]
    n_out = 0
    for i in range(m):
        if not keep[i] or (n_over > 0 and z[i] * z[i] > threshold):
            keep[i] = False
            n_out += 1
    if n_out == 0 or 2 * n_out >= m:
        for i in range(m):
            keep[i] = True
        return m
    return m - n_out


@_jit
def window_push(Z, n, sm, sq, last_t, interval, t, idx, z, clip, k_mean, hi, lo, status):  # pragma: no cover
    """:meth:`.ekf.ChannelMonitor.push`'s arithmetic, compiled: the clipped ``z`` of channels ``idx`` into their
    moving windows ``Z`` (sums ``sm``, ``sq`` kept incrementally and recomputed exactly once per window), the
    channels' last sample times and intervals, and per entry of ``idx`` the verdict in ``status``: -1 window not
    full, 0 in band, 1 mean (offset), 2 scale above, 3 scale below (stuck). Returns the number of verdicts > 0."""
    W = Z.shape[0]
    n_bad = 0
    for j in range(idx.shape[0]):
        i = idx[j]
        if math.isfinite(last_t[i]):
            interval[i] = t - last_t[i]
        last_t[i] = t
        zc = min(max(z[j], -clip), clip)
        pos = n[i] % W
        old = Z[pos, i]
        Z[pos, i] = zc
        sm[i] += zc - old
        sq[i] += zc * zc - old * old
        n[i] += 1
        if pos == W - 1:  # once per window: exact sums (no drift)
            a = 0.0
            b = 0.0
            for k in range(W):
                a += Z[k, i]
                b += Z[k, i] * Z[k, i]
            sm[i] = a
            sq[i] = b
        if n[i] < W:
            status[j] = -1
        elif abs(sm[i]) > k_mean:
            status[j] = 1
        elif sq[i] > hi:
            status[j] = 2
        elif sq[i] < lo:
            status[j] = 3
        else:
            status[j] = 0
        if status[j] > 0:
            n_bad += 1
    return n_bad


@_jit
def window_seen(last_t, interval, t, idx):  # pragma: no cover
    """:meth:`.ekf.ChannelMonitor.seen`'s arithmetic: channels ``idx`` sampled at ``t`` (their innovations not
    tested): their last sample times and intervals."""
    for j in range(idx.shape[0]):
        i = idx[j]
        if math.isfinite(last_t[i]):
            interval[i] = t - last_t[i]
        last_t[i] = t


@_jit
def step_statistic(u0, u1, w):
    """``sum_i w_i (u1_i - u0_i)^2``: the test statistic of a step between two input samples (``w`` the inverse
    of twice each input's noise variance: chi-square with one degree of freedom per input for noise alone)."""
    s = 0.0
    for i in range(u0.shape[0]):
        e = u1[i] - u0[i]
        s += e * e * w[i]
    return s


class InputStepTest:
    """Is there a step between two successive input samples beyond what their noise explains?

    ``sum_i w_i (u1_i - u0_i)^2 > threshold`` (:func:`step_statistic`) with ``w_i = 1 / (2 var_i)`` (the
    difference of two samples has twice each sample's noise variance): for noise alone the sum is chi-square with
    one degree of freedom per input, and ``threshold`` is its ``1 - p`` quantile (false-alarm probability ``p``
    per interval; ``p`` None: never a step). The filter's hold-off after a planned torque step and the reduced
    model's torque-jump correction use it; the compiled sample loop reads ``weights`` and ``threshold``."""

    def __init__(self, var, p: float | None):
        self.weights = np.ascontiguousarray(0.5 / np.asarray(var, dtype=float).reshape(-1))
        self.threshold = math.inf if p is None else float(chi2_ppf(1.0 - p, len(self.weights)))

    def __call__(self, u0: np.ndarray, u1: np.ndarray) -> bool:
        return step_statistic(u0, u1, self.weights) > self.threshold


class Innovation(NamedTuple):
    """What a measurement update saw: the innovation ``r = y - g(x)``, its covariance ``S = H P H' + R`` and the
    normalised innovation squared ``r' S^-1 r`` (what the monitors test)."""

    r: np.ndarray
    S: np.ndarray
    nis: float


def predict(belief: Belief, interval: Prediction) -> Belief:
    """The belief carried over one interval (eqs. 10-13): the model's predicted mean ``interval.x`` and
    ``P = F P F' + Q`` (:func:`predict_cov`)."""
    n = len(belief.x)
    P = np.empty((n, n))
    predict_cov(np.ascontiguousarray(interval.F, float), np.ascontiguousarray(belief.P, float),
                np.ascontiguousarray(interval.Q, float), P, np.empty((n, n)))
    return Belief(np.array(interval.x, float), P)


def condition(belief: Belief, measurement: Measurement, y, R_diag, floor=0.0) -> tuple[Belief, Innovation]:
    """The belief conditioned on the measurement ``y`` of channels with the noise variances ``R_diag``
    (eqs. 14-15: the gain by a Cholesky solve of ``S``, the Joseph-form covariance; :func:`update`), settled
    (symmetrised, its variances floored at ``floor``: :func:`settle`); with what the update saw.

    Raises ``numpy.linalg.LinAlgError`` where ``S`` is not positive definite (the filter's driver finishes such an
    update by an LU solve, with a warning)."""
    x = np.ascontiguousarray(belief.x, float)
    P = np.ascontiguousarray(belief.P, float)
    H = np.ascontiguousarray(measurement.H, float)
    m, n = H.shape
    r, S, x_out, P_out = np.empty(m), np.empty((m, m)), np.empty(n), np.empty((n, n))
    nis, ok = update(x, P, np.ascontiguousarray(y, float), np.ascontiguousarray(measurement.y, float), H,
                     np.ascontiguousarray(R_diag, float), np.empty((m, n)), r, S, x_out, P_out)
    if not ok:
        raise np.linalg.LinAlgError("the innovation covariance is not positive definite")
    settle(x_out, P_out, np.ascontiguousarray(np.broadcast_to(np.asarray(floor, float), (n,))))
    return Belief(x_out, P_out), Innovation(r, S, nis)


def warm_up(python_steps: bool = True) -> None:
    """Compile (or load from numba's on-disk cache) the kernels for C-ordered float64 arrays, so that the
    first sample of a filter does not carry the compilation: every kernel, or without ``python_steps`` the one a
    filter whose samples go to the compiled loop calls from Python (the input-step test, :func:`step_statistic`)."""
    step_statistic(np.zeros(1), np.ones(1), np.ones(1))
    if not python_steps:
        return
    n, m = 3, 2
    P = np.eye(n)
    out = np.empty((n, n))
    predict_cov(np.eye(n), P, np.zeros((n, n)), out, np.empty((n, n)))
    H = np.ones((m, n))
    HP = np.empty((m, n))
    r = np.empty(m)
    x = np.zeros(n)
    update(x, P, np.ones(m), np.zeros(m), H, np.ones(m), HP, r, np.empty((m, m)), x, out)
    predict_update(np.eye(n), P, np.zeros((n, n)), x, np.ones(m), np.zeros(m), H, np.ones(m), np.zeros(n),
                   (np.empty((n, n)), np.empty((n, n)), HP), (r, np.empty((m, m)), np.empty(n), out))
    apply_gain(x, P, H, HP, np.ones(m), r, np.ones((m, n + 1)), x, out)
    settle(x, out, np.zeros(n))
    condition_on(np.ones(m, dtype=np.bool_), x, P, np.ones(m), np.zeros(m), H, np.ones(m), np.zeros(n), HP, x, out)
    gate(np.zeros(m), 1.0, 0, np.ones(m, dtype=np.bool_))
    normalise(r, np.eye(m), 1.0, np.empty(m))
    window_seen(np.zeros(m), np.zeros(m), 0.0, np.arange(m))
    window_push(np.zeros((2, m)), np.zeros(m, dtype=np.int64), np.zeros(m), np.zeros(m), np.zeros(m), np.zeros(m), 0.0,
                np.arange(m), np.zeros(m), 1.0, 1.0, 1.0, 0.0, np.zeros(m, dtype=np.int64))

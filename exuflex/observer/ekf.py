"""Multirate extended Kalman filter over a :class:`~exuflex.observer.base.DiscreteModel` (paper eqs. 10-15).

One call of :meth:`MultirateEKF.step` processes one measurement sample::

    predict  x_k|k-1 = f_d(x_k-1, u_k-1),   P_k|k-1 = F P_k-1 F' + Q          (eqs. 12-13)
    update   r = y_k - g(x_k|k-1),  S = H P H' + R,  K = P H' S^-1                (eqs. 14-15)
             x_k = x_k|k-1 + K r,   P_k = (I - K H) P (I - K H)' + K R K'      (Joseph form)

Multirate sensors are handled per sample: entries of ``y`` that are NaN are not available at this sample and
the update uses only the finite channels (``R`` restricted to them). An all-NaN sample (missing or late
packet) is a prediction only and is counted in ``n_missing``; so is every whole interval skipped in time
between two calls. At the end of every sample (after its prediction(s) and update) ``P`` is symmetrised and
its diagonal floored; a non-finite state or covariance never leaves silently (:class:`FilterDivergedError`,
or a flag).

Filter consistency is monitored with the normalised innovation squared (NIS): over a moving window of the
last ``nis_window`` updates, the summed NIS is chi-square with the summed number of channels for a
consistent filter. The filter is declared diverged when that sum exceeds the ``divergence_confidence``
(99.9 %) quantile in ``divergence_confirm`` consecutive *disjoint* windows (default 2: a single outlier cannot
trigger it, and the false-alarm rate of a consistent filter is ~1e-6 per window instead of 1e-3).

Three numerically equivalent back-ends share all bookkeeping: ``backend="numpy"`` (lean, the default),
``backend="filterpy"`` (the covariance algebra done by :class:`filterpy.kalman.ExtendedKalmanFilter`, whose
``update`` is in Joseph form; kept as the reference implementation) and ``backend="numba"`` (the numpy
back-end's algebra in compiled kernels, :mod:`._compiled`; at 26 states and 6 channels the filter's own
cost per sample is about a third of the numpy back-end's, for real-time use; needs the numba package). With the
numba back-end, a model that offers ``fused_sample`` (the cached reduced observer, :mod:`.fused`) does a whole
sample with every channel present (predict, update, settle) in one compiled call, with the same arithmetic as the
step-by-step path (``tests/test_fused.py``); other samples, and a sample the model declines, take the
step-by-step path. ``n_fused`` counts the fused samples. Over a whole log, :meth:`MultirateEKF.run` hands
the fused samples to the model's compiled sample loop (``fused_run``, with the zero-order hold and a NIS test
that flags rather than raises), bit-identical to calling :meth:`MultirateEKF.step` per sample.

Timing convention: ``x0``, ``P0`` are the *prior* at the first sample time. ``step(t_k, u_k, y_k)``
first predicts from the previous sample time to ``t_k`` with the input stored at the previous call
(zero-order hold, ``u_k-1`` drives ``x_k`` as in eq. 10), then updates with ``y_k``, stores ``u_k`` for the
next interval and returns the posterior estimate at ``t_k``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack
from scipy.stats import chi2

from ..erls.kinematics import KinematicsError
from . import _compiled
from .base import DiscreteModel, FilterDivergedError

__all__ = ["EstimationResult", "MultirateEKF", "NISMonitor"]

log = logging.getLogger(__name__)

_BACKENDS = ("numpy", "filterpy", "numba")


@dataclass
class EstimationResult:
    """Output of :meth:`MultirateEKF.run`.

    Attributes
    ----------
    t : ndarray, shape (n,)
        Sample times.
    x_hat : ndarray, shape (n, nx)
        Posterior state estimates (the prior where a sample was missing).
    P : ndarray or None
        Posterior covariance: diagonal, shape (n, nx) (``store_P="diag"``), full, shape (n, nx, nx)
        (``"full"``), or None (``"none"``).
    innovations : ndarray, shape (n, m)
        Innovation ``y - g(x_prior)`` per channel; NaN for channels not used at that sample.
    S : ndarray, shape (n, m, m)
        Innovation covariance; NaN rows/columns for channels not used.
    nis : ndarray, shape (n,)
        Normalised innovation squared ``r' S^-1 r``; NaN at samples without an update.
    nis_dof : ndarray of int, shape (n,)
        Number of channels used at each sample (the chi-square degrees of freedom of ``nis``).
    n_missing : int
        Prediction-only intervals: all-NaN samples plus whole intervals skipped between samples.
    n_updates : int
        Samples with at least one finite channel.
    diverged : bool
        NIS divergence test failed, or the filter went non-finite (in ``nonfinite="flag"`` mode).
    diverged_at : float or None
        Time of the first divergence detection.
    nonfinite : bool
        The filter produced a non-finite value (estimates from then on are NaN).
    wall_s : float
        Wall-clock time of the run (s).
    channels : tuple of str
        Channel order of the columns of ``innovations`` and ``S``.
    """

    t: np.ndarray
    x_hat: np.ndarray
    P: np.ndarray | None
    innovations: np.ndarray
    S: np.ndarray
    nis: np.ndarray
    nis_dof: np.ndarray
    n_missing: int
    n_updates: int
    diverged: bool
    diverged_at: float | None
    nonfinite: bool
    wall_s: float
    channels: tuple[str, ...] = ()

    @property
    def P_diag(self) -> np.ndarray | None:
        """Posterior variances, shape (n, nx), whatever ``P`` storage was chosen (None if not stored)."""
        if self.P is None:
            return None
        return self.P if self.P.ndim == 2 else np.diagonal(self.P, axis1=1, axis2=2)

    def mean_nis(self, burn_in: int = 0) -> tuple[float, float]:
        """Time-averaged NIS and its expected value (mean number of channels per update) after ``burn_in``
        samples."""
        sel = np.isfinite(self.nis)
        sel[:burn_in] = False
        if not sel.any():
            return float("nan"), float("nan")
        return float(self.nis[sel].mean()), float(self.nis_dof[sel].mean())

    def summary(self) -> dict:
        """Small dict of run-level figures (for logs and reports)."""
        mn, ex = self.mean_nis()
        n = len(self.t)
        return {
            "n_samples": n,
            "n_updates": self.n_updates,
            "n_missing": self.n_missing,
            "mean_nis": mn,
            "expected_nis": ex,
            "diverged": self.diverged,
            "diverged_at": self.diverged_at,
            "nonfinite": self.nonfinite,
            "wall_s": self.wall_s,
            "us_per_sample": 1e6 * self.wall_s / max(n, 1),
        }


class NISMonitor:
    """Moving-window chi-square test on the NIS sequence.

    Parameters
    ----------
    window : int
        Number of updates in a window.
    confidence : float
        One-sided chi-square quantile of the bound (0.999 = 99.9 %).
    confirm : int
        Number of consecutive disjoint windows that must all exceed the bound (>= 1).
    """

    def __init__(self, window: int = 100, confidence: float = 0.999, confirm: int = 2):
        if window < 1 or confirm < 1 or not 0 < confidence < 1:
            raise ValueError("need window >= 1, confirm >= 1 and 0 < confidence < 1")
        self.window = int(window)
        self.confidence = float(confidence)
        self.confirm = int(confirm)
        self._bounds: dict[int, float] = {}
        self.reset()

    def reset(self) -> None:
        self._nis = [0.0] * self.window
        self._dof = [0] * self.window
        self._sum = 0.0
        self._sdof = 0
        self._n = 0
        self._hist = [False] * ((self.confirm - 1) * self.window + 1)

    def bound(self, dof: int) -> float:
        """Chi-square ``confidence`` quantile for ``dof`` degrees of freedom (cached)."""
        b = self._bounds.get(dof)
        if b is None:
            b = float(chi2.ppf(self.confidence, dof))
            self._bounds[dof] = b
        return b

    def push(self, nis: float, dof: int) -> bool:
        """Add one update's NIS; return True if the divergence test fails at this update."""
        i = self._n % self.window
        self._sdof += dof - self._dof[i]
        self._sum += nis - self._nis[i]
        self._nis[i] = nis
        self._dof[i] = dof
        self._n += 1
        if i == self.window - 1:  # once per window: exact sum (no drift or cancellation after outliers)
            self._sum = math.fsum(self._nis)
        if self._n < self.window:
            return False
        exceed = self._sum > self.bound(self._sdof)
        h = self._hist
        j = (self._n - 1) % len(h)
        h[j] = exceed
        if not exceed:
            return False
        if self._n < self.confirm * self.window:
            return False
        for c in range(1, self.confirm):
            if not h[(j - c * self.window) % len(h)]:
                return False
        return True


def _make_filterpy_ekf(nx: int, m: int):
    from filterpy.kalman import ExtendedKalmanFilter

    class _ModelEKF(ExtendedKalmanFilter):
        """filterpy EKF whose state prediction is the model's step (set ``_x_next`` before ``predict``)."""

        def predict_x(self, u=0):
            self.x = self._x_next

    kf = _ModelEKF(dim_x=nx, dim_z=m)
    kf.x = np.zeros(nx)
    return kf


class MultirateEKF:
    """Multirate extended Kalman filter over a :class:`DiscreteModel`.

    Parameters
    ----------
    model : DiscreteModel
        Step map with Jacobian, measurement map with Jacobian, process noise.
    channels : sequence of str
        Names of the scalar sensor channels; the order of the columns of the measurement arrays.
    R_std : mapping str -> float
        Measurement-noise standard deviation of every channel (``R`` is diagonal).
    x0 : array_like, shape (nx,)
        Prior mean at the first sample time.
    P0 : array_like, shape (nx, nx) or (nx,)
        Prior covariance (a vector is taken as the diagonal).
    dt : float
        Measurement interval (s); samples must lie on a grid of this spacing (gaps allowed).
    backend : {"numpy", "filterpy", "numba"}
        Lean numpy algebra, filterpy's ``ExtendedKalmanFilter`` (reference), or the numpy algebra compiled
        (fastest; the first filter of a process compiles the kernels or loads them from numba's cache).
    store_P : {"diag", "full", "none"}
        What :meth:`run` records of the posterior covariance.
    nis_window, divergence_confidence, divergence_confirm
        NIS divergence test, see :class:`NISMonitor`. ``nis_window=0`` disables it.
    divergence_action : {"flag", "raise"}
        On a failed NIS test: record it and go on, or raise :class:`FilterDivergedError`.
    nonfinite : {"raise", "flag"}
        On a non-finite state/covariance: raise :class:`FilterDivergedError`, or flag the run as diverged and
        return NaN estimates from then on.
    p_floor : float or array_like
        Floor on the diagonal of ``P`` (in the state's squared units).
    time_tol : float
        Relative tolerance of the sample grid check.
    input_hold : {"zoh", "linear"}
        How the input behaves between two samples: held at the earlier sample's value (``"zoh"``), or
        varying linearly between the two (``"linear"``: the interval is predicted with their mean, which is
        the exact effect of a linear input on the held system to first order). ``"linear"`` adds no latency:
        the interval ending at a sample is predicted when that sample, and its input, arrive. With ``"zoh"``, a
        model with ``input_jump(u_old, u_new)`` (the increment if the two samples differ by more than their
        noise, else None) and ``input_jump_moments(d, dt)`` (the jump's effect at an unknown instant of the
        interval: mean and covariance) has that effect added to the interval (step-by-step path; counted in
        ``n_jumps``). Across missing
        samples the input is held. A model with a ``hold_interval(mean, renew)`` method
        (:class:`.hold.LinearHoldModel`, which keeps the input-sample noise as states) is told before each
        predicted interval whether it is driven by the mean and whether a new input sample ends it.
    """

    def __init__(
        self,
        model: DiscreteModel,
        channels: Sequence[str],
        R_std: Mapping[str, float],
        x0,
        P0,
        dt: float = 1 / 500,
        *,
        backend: str = "numpy",
        store_P: str = "diag",
        nis_window: int = 100,
        divergence_confidence: float = 0.999,
        divergence_confirm: int = 2,
        divergence_action: str = "flag",
        nonfinite: str = "raise",
        p_floor=1e-18,
        time_tol: float = 1e-6,
        input_hold: str = "zoh",
    ):
        if backend not in _BACKENDS:
            raise ValueError(f"backend must be one of {_BACKENDS}, got {backend!r}")
        if backend == "numba":
            _compiled.require()
        if store_P not in ("diag", "full", "none"):
            raise ValueError(f"store_P must be 'diag', 'full' or 'none', got {store_P!r}")
        if divergence_action not in ("flag", "raise"):
            raise ValueError(f"divergence_action must be 'flag' or 'raise', got {divergence_action!r}")
        if nonfinite not in ("flag", "raise"):
            raise ValueError(f"nonfinite must be 'flag' or 'raise', got {nonfinite!r}")
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        if input_hold not in ("zoh", "linear"):
            raise ValueError(f"input_hold must be 'zoh' or 'linear', got {input_hold!r}")
        self.input_hold = input_hold
        self.model = model
        self.nx = int(model.nx)
        self.channels = tuple(channels)
        if len(set(self.channels)) != len(self.channels):
            raise ValueError(f"duplicate channel names in {self.channels}")
        missing = [c for c in self.channels if c not in R_std]
        if missing:
            raise ValueError(f"R_std has no standard deviation for channel(s) {missing}")
        self.R_std = np.array([float(R_std[c]) for c in self.channels])
        if not np.all(self.R_std > 0):
            raise ValueError("all measurement standard deviations must be positive")
        self._Rdiag = self.R_std**2
        self.m = len(self.channels)
        self.dt = float(dt)
        self.backend = backend
        self.store_P = store_P
        self.divergence_action = divergence_action
        self.nonfinite_action = nonfinite
        self._scalar_floor = np.ndim(p_floor) == 0
        self.p_floor = float(p_floor) if self._scalar_floor else np.asarray(p_floor, float).reshape(-1)
        self.time_tol = float(time_tol)
        self.monitor = (
            NISMonitor(nis_window, divergence_confidence, divergence_confirm) if nis_window > 0 else None
        )

        self._x0 = np.array(x0, dtype=float).reshape(-1)
        if self._x0.shape != (self.nx,):
            raise ValueError(f"x0 has shape {self._x0.shape}, expected ({self.nx},)")
        P0 = np.array(P0, dtype=float)
        if P0.ndim == 1:
            P0 = np.diag(P0)
        if P0.shape != (self.nx, self.nx):
            raise ValueError(f"P0 has shape {P0.shape}, expected ({self.nx}, {self.nx})")
        self._P0 = 0.5 * (P0 + P0.T)

        y0, H0 = model.measure(self._x0, self.channels)
        if np.shape(y0) != (self.m,) or np.shape(H0) != (self.m, self.nx):
            raise ValueError(
                f"model.measure returned y {np.shape(y0)}, H {np.shape(H0)} for {self.m} channels; expected "
                f"({self.m},) and ({self.m}, {self.nx}) (every channel must be scalar)"
            )
        self._I = np.eye(self.nx)
        self._all = np.arange(self.m)
        self._Rfull = np.diag(self._Rdiag)
        self._subsets: dict[bytes, tuple] = {}
        self._kf = _make_filterpy_ekf(self.nx, self.m) if backend == "filterpy" else None
        self._compiled = backend == "numba"
        if self._compiled:
            n = self.nx
            self._sq = (n, n)
            # the floor per state (the kernels do not broadcast; a wrong length fails here, not in a kernel)
            if np.size(self.p_floor) not in (1, n):
                raise ValueError(f"p_floor has {np.size(self.p_floor)} entries, expected 1 or {n}")
            self._floor = np.ascontiguousarray(np.broadcast_to(self.p_floor, (n,)), dtype=float)
            # owned buffers: P alternates between _P and _Pspare (a kernel never writes the P it reads);
            # nothing outside the filter ever holds either
            self._Pspare = np.empty((n, n))
            self._work = np.empty((n, n))
            self._HP = np.empty((self.m, n))
            self._Ppred = np.empty((n, n))
            _compiled.warm_up()
        # a model that can do a whole sample in one compiled call (the cached reduced observer) is given the
        # chance to, with the numba back-end: see _fused_sample
        self._fused = getattr(model, "fused_sample", None) if self._compiled else None
        # a model with the input noise as states (:class:`.hold.LinearHoldModel`) is told how each interval
        # is driven: the mean of its two samples or the older one held, and whether a new sample ends it
        self._hold_hook = getattr(model, "hold_interval", None) if input_hold == "linear" else None
        # a model that tests two successive input samples for a jump between them (``input_jump``, with
        # ``input_jump_moments``; the reduced observer model) gets the jump's effect added to that interval
        self._jumps = getattr(model, "input_jump", None) if input_hold == "zoh" else None
        # step()'s short path: a fused model with the input held (the linear hold's interval mean and hook
        # take the general path)
        self._fast = self._fused is not None and input_hold == "zoh"
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self, x0=None, P0=None) -> None:
        """Restart from the prior (``x0``, ``P0`` of the constructor unless given) and clear all counters.

        A model with internal caches (e.g. held configuration-dependent matrices) is reset too, if it has a
        ``reset()`` method, so that a run never depends on what the model saw before.
        """
        if hasattr(self.model, "reset"):
            self.model.reset()
        self._x = self._x0.copy() if x0 is None else np.array(x0, dtype=float).reshape(self.nx)
        P = self._P0.copy() if P0 is None else np.array(P0, dtype=float)
        self._P = np.diag(P) if P.ndim == 1 else P
        if self._compiled:  # the kernels update P in place and index it without bounds checks
            if self._P.shape != self._sq:
                raise ValueError(f"P0 has shape {self._P.shape}, expected {self._sq}")
            self._P = np.ascontiguousarray(self._P)
        if self._kf is not None:
            self._kf.x = self._x
            self._kf.P = self._P
        self._t_prev: float | None = None
        self._u_prev = None
        self.n_missing = 0
        self.n_updates = 0
        self.n_fused = 0
        self.n_jumps = 0
        self.diverged = False
        self.diverged_at: float | None = None
        self.nonfinite = False
        self.last_idx = None
        self.last_innovation = None
        self.last_S = None
        self.last_nis = float("nan")
        self.last_dof = 0
        if self.monitor is not None:
            self.monitor.reset()

    @property
    def x(self) -> np.ndarray:
        """Current state estimate (a copy)."""
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        """Current covariance (a copy)."""
        return self._P.copy()

    @property
    def t(self) -> float | None:
        """Time of the current estimate (None before the first sample)."""
        return self._t_prev

    # ------------------------------------------------------------------ algebra
    def _fix_P(self, P: np.ndarray) -> np.ndarray:
        P = P + P.T
        P *= 0.5
        d = P.diagonal()
        if self._scalar_floor:
            if d.min() < self.p_floor:
                np.fill_diagonal(P, np.maximum(d, self.p_floor))
        else:
            low = d < self.p_floor
            if low.any():
                np.fill_diagonal(P, np.where(low, self.p_floor, d))
        return P

    def _settle_P(self) -> np.ndarray:
        if self._compiled:  # in place: _P is the filter's own buffer
            _compiled.fix_cov(self._P, self._floor)
            return self._P
        P = self._P = self._fix_P(self._P)
        if self._kf is not None:
            self._kf.x, self._kf.P = self._x, P
        return P

    def _predict(self, u, jump=None) -> None:
        x = self._x
        try:
            x_next, F = self.model.step(x, u, self.dt)
            Q = self.model.process_noise(x, u, self.dt)
            if jump is not None:  # the input jumped within the interval: its effect's mean and covariance
                dx, dQ = self.model.input_jump_moments(jump, self.dt)
                x_next = x_next + dx
                Q = Q + dQ
        except (ArithmeticError, np.linalg.LinAlgError, KinematicsError) as exc:
            # the model cannot be evaluated at the estimate (e.g. a runaway state where the mechanism's
            # loops no longer close): that is the filter diverging, not a bad model file
            n = self.nx
            x_next, F, Q = np.full(n, np.nan), np.eye(n), np.zeros((n, n))
            self._model_failure = f"{type(exc).__name__}: {exc}"
        if self._compiled:
            n = self.nx
            x_next = np.asarray(x_next, dtype=float)
            if x_next.shape != (n,):  # the kernels read without bounds checks: never a wrong shape
                raise ValueError(f"model.step returned a state of shape {x_next.shape}, expected ({n},)")
            sq = self._sq
            F = np.ascontiguousarray(F, dtype=float)  # for BLAS; no copy if it already is
            if F.shape != sq:
                raise ValueError(f"model.step returned a Jacobian F of shape {F.shape}, expected {sq}")
            Q = np.asarray(Q, dtype=float)
            if Q.shape != sq:
                raise ValueError(f"model.process_noise returned Q of shape {Q.shape}, expected {sq}")
            P = self._Pspare
            _compiled.predict_cov(F, self._P, Q, P, self._work)
            self._Pspare = self._P
        elif self._kf is None:
            P = F @ self._P @ F.T + Q
        else:
            kf = self._kf
            kf.F = F
            kf.Q = Q
            kf._x_next = np.asarray(x_next, dtype=float)
            kf.predict()
            x_next, P = kf.x, kf.P
        self._x = np.asarray(x_next, dtype=float)
        self._P = P  # symmetrised and floored once per sample, at the end of step()
        if self._kf is not None:
            self._kf.x, self._kf.P = self._x, self._P

    def _subset(self, mask: np.ndarray) -> tuple:
        key = mask.tobytes()
        s = self._subsets.get(key)
        if s is None:
            idx = np.flatnonzero(mask)
            chans = tuple(self.channels[i] for i in idx)
            Rd = self._Rdiag[idx]
            s = (idx, chans, Rd, np.diag(Rd))
            self._subsets[key] = s
        return s

    def _update(self, y: np.ndarray, idx: np.ndarray, chans: tuple, Rd: np.ndarray, R: np.ndarray) -> None:
        x, P = self._x, self._P
        try:
            y_pred, H = self.model.measure(x, chans)
        except (ArithmeticError, np.linalg.LinAlgError, KinematicsError) as exc:
            # cannot evaluate the sensors at a runaway estimate: the filter has diverged (see _predict)
            self._model_failure = f"{type(exc).__name__}: {exc}"
            self._x = np.full(self.nx, np.nan)
            return
        if self._compiled:
            m, nx = len(y), self.nx
            H = np.asarray(H, dtype=float)
            y_pred = np.asarray(y_pred, dtype=float)
            if H.shape != (m, nx) or y_pred.shape != (m,):  # the kernels read without bounds checks
                raise ValueError(
                    f"model.measure returned y {y_pred.shape}, H {H.shape} for {m} channels; expected "
                    f"({m},) and ({m}, {nx})"
                )
            y = np.ascontiguousarray(y)  # a row of a column-selected log is strided: one compiled variant
            # new arrays for what leaves the filter (last_innovation, last_S, the estimate); buffers else
            r = np.empty(m)
            S = np.empty((m, m))
            x_new = np.empty(nx)
            P_new = self._Pspare
            nis, ok = _compiled.update(x, P, y, y_pred, H, Rd, self._HP, r, S, x_new, P_new)
            if not ok:
                HP = self._HP[:m]
                rhs = np.empty((m, nx + 1))
                rhs[:, :nx] = HP
                rhs[:, nx] = r
                sol = np.ascontiguousarray(self._solve_indefinite(S, rhs))
                nis = _compiled.apply_gain(x, P, H, HP, Rd, r, sol, x_new, P_new)
            self._Pspare = P
            x, P = x_new, P_new
        elif self._kf is None:
            r = y - y_pred
            nx = self.nx
            HP = H @ P  # = (P H')' up to rounding (P symmetric)
            S = HP @ H.T
            S += R
            # one Cholesky solve gives both K' = S^-1 H P and S^-1 r
            rhs = np.empty((len(r), nx + 1))
            rhs[:, :nx] = HP
            rhs[:, nx] = r
            _, sol, info = lapack.dposv(S, rhs)
            if info != 0:
                sol = self._solve_indefinite(S, rhs)
            K = sol[:, :nx].T
            nis = float(r @ sol[:, nx])
            x = x + K @ r
            # Joseph form (I - K H) P (I - K H)' + K R K', factored without nx^3 products:
            # with A = (I - K H) P = P - K (H P) it equals A - (A H' - K R) K' (valid for any gain K)
            A = P - K @ HP
            P = A - (A @ H.T - K * Rd) @ K.T
        else:
            kf = self._kf
            kf.update(y, HJacobian=lambda _x: H, Hx=lambda _x: y_pred, R=R)
            r, S, x, P = kf.y, kf.S, kf.x, kf.P
            nis = float(r @ kf.SI @ r)
        self._x = x
        self._P = P
        self.last_idx = idx
        self.last_innovation = r
        self.last_S = S
        self.last_nis = nis
        self.last_dof = len(idx)

    def _fused_sample(self, u, y, u_next=None) -> bool:
        """One whole sample (predict one interval, update with every channel, settle) in the model's single
        compiled call, if the model offers one (``fused_sample``, the cached reduced observer) and every
        channel of ``y`` is present. Same arithmetic as the step-by-step path, to rounding; False (nothing
        changed) where it does not apply or the model declines, and the step-by-step path runs instead."""
        # a copy: contiguous and writable whatever the log's array was (a read-only row would make numba
        # compile the kernel once more, 0.1 s in a run's first sample)
        y = np.array(y, dtype=float)
        if y.shape != (self.m,) or not math.isfinite(sum(y.tolist())):
            return False
        try:
            out = self._fused(self._x, self._P, u, y, self.channels, self._Rdiag,
                              self._floor, self.dt, (self._Pspare, self._Ppred, self._work, self._HP),
                              None if u_next is None else np.ascontiguousarray(u_next, dtype=float))
        except (ArithmeticError, np.linalg.LinAlgError, KinematicsError):
            return False  # the step-by-step path meets the same failure and handles it (see _predict)
        if out is None:
            return False
        x, P, r, S, nis, self._fused_finite = out
        self._Pspare = self._P
        self._x, self._P = x, P
        self.last_idx = self._all
        self.last_innovation = r
        self.last_S = S
        self.last_nis = nis
        self.last_dof = self.m
        self.n_fused += 1
        return True

    def _solve_indefinite(self, S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        log.warning("innovation covariance not positive definite (t=%s); using an LU solve", self._t_prev)
        try:
            return np.linalg.solve(S, rhs)
        except np.linalg.LinAlgError as exc:
            raise FilterDivergedError(f"singular innovation covariance at t={self._t_prev}") from exc

    def _flag_divergence(self, t: float, why: str) -> None:
        if not self.diverged:
            self.diverged = True
            self.diverged_at = float(t)
            log.warning("EKF diverged at t=%.6g s: %s", t, why)

    # ------------------------------------------------------------------ public
    def step(self, t: float, u, y) -> np.ndarray:
        """Process one sample: predict to ``t`` (held input of the previous call), update with ``y``.

        Parameters
        ----------
        t : float
            Sample time; must lie on the ``dt`` grid after the previous sample. Skipped grid points are
            predicted through (input held) and counted as missing.
        u : array_like or None
            Input applied from ``t`` over the next interval (zero-order hold).
        y : array_like, shape (m,) or None
            Measurement in channel order; NaN entries are channels without a sample at ``t``. ``None`` or
            all-NaN: prediction only.

        Returns
        -------
        ndarray, shape (nx,)
            Posterior estimate at ``t`` (a new array).

        Raises
        ------
        FilterDivergedError
            Non-finite state/covariance (``nonfinite="raise"``) or failed NIS test
            (``divergence_action="raise"``).
        ValueError
            ``t`` not after the previous sample or off the grid.
        """
        t = float(t)
        if self._fast and y is not None and self._t_prev is not None and not self.nonfinite:
            # the common case in few lines: the next grid point, every channel in one compiled call
            k = (t - self._t_prev) / self.dt
            if abs(k - 1.0) <= self.time_tol * max(1.0, k):
                if not self._fused_sample(self._u_prev, y, u if self._jumps is not None else None):
                    return self._step(t, u, y, try_fused=False)  # declined (nothing changed): step by step
                self._t_prev = t
                self._u_prev = None if u is None else np.array(u, dtype=float)
                return self._close(t, self._fused_finite)
        return self._step(t, u, y)

    def _step(self, t: float, u, y, try_fused: bool = True) -> np.ndarray:
        """:meth:`step` in general (``try_fused``: offer a one-interval sample to the fused kernel)."""
        fused = False
        if self._t_prev is not None:
            k = (t - self._t_prev) / self.dt
            n = round(k)
            if n < 1 or abs(k - n) > self.time_tol * max(1.0, k):
                raise ValueError(
                    f"sample time {t!r} is not a positive multiple of dt={self.dt} after {self._t_prev!r}"
                )
            if not self.nonfinite:
                u_step = self._u_prev
                mean = False
                if self.input_hold == "linear" and n == 1 and u is not None and u_step is not None:
                    u_new = np.asarray(u, dtype=float)
                    if u_new.shape == u_step.shape and math.isfinite(sum(u_new.tolist())):
                        u_step = 0.5 * (u_step + u_new)  # the mean of the linear input over the interval
                        mean = True
                if n == 1 and try_fused and self._fused is not None and y is not None:
                    # (the kernel declines a sample whose input jumped: the model's test, done there)
                    fused = self._fused_sample(u_step, y, u if self._jumps is not None else None)
                if not fused:
                    jump = None
                    if self._jumps is not None and n == 1 and u is not None and u_step is not None:
                        jump = self._jumps(u_step, u)  # a torque jump within the interval (the model's test)
                        if jump is not None:
                            self.n_jumps += 1
                    hook = self._hold_hook
                    for i in range(n):
                        if hook is not None:  # the model keeps the input noise as states (.hold)
                            hook(mean and i == 0, i == n - 1 and u is not None)
                        self._predict(u_step if i == 0 else self._u_prev, jump)
                        if i < n - 1:  # a skipped sample: settle P exactly as for an all-NaN sample
                            self._settle_P()
            self.n_missing += n - 1
        self._t_prev = t
        self._u_prev = None if u is None else np.array(u, dtype=float)
        if fused:
            finite = self._fused_finite
        else:
            self.last_idx = None
            self.last_nis = math.nan
            self.last_dof = 0
            if self.nonfinite:
                self.n_missing += 1
                return np.full(self.nx, np.nan)

            if y is None:
                self.n_missing += 1
            else:
                y = np.asarray(y, dtype=float)
                if y.shape != (self.m,):
                    raise ValueError(f"measurement has shape {y.shape}, expected ({self.m},)")
                # every channel present (the common case): one sum, of a list (a numpy reduction of a few
                # entries costs five times as much); a NaN or inf anywhere makes it non-finite
                if math.isfinite(sum(y.tolist())):
                    self._update(y, self._all, self.channels, self._Rdiag, self._Rfull)
                else:
                    mask = np.isfinite(y)
                    if mask.any():
                        idx, chans, Rd, R = self._subset(mask)
                        self._update(y[idx], idx, chans, Rd, R)
                    else:
                        self.n_missing += 1

            if self._compiled:
                finite = _compiled.settle(self._x, self._P, self._floor)  # _settle_P and the same test, fused
            else:
                P = self._settle_P()
                # a NaN or inf anywhere makes a sum non-finite (finite overflow to inf is flagged too)
                finite = math.isfinite(self._x.sum() + P.sum())
        return self._close(t, finite)

    def _close(self, t: float, finite: bool) -> np.ndarray:
        """The end of a sample: the divergence tests, then a copy of the estimate (NaN once non-finite)."""
        if not finite:
            self._flag_divergence(t, "non-finite state or covariance")
            self.nonfinite = True
            if self.nonfinite_action == "raise":
                why = getattr(self, "_model_failure", None)
                raise FilterDivergedError(
                    f"non-finite state or covariance at t={t:.6g} s" + (f" (model step failed: {why})" if why else "")
                )
            return np.full(self.nx, np.nan)

        failed = self.last_idx is not None and self._count_update(t, self.last_nis, self.last_dof)
        if failed and self.divergence_action == "raise":
            raise FilterDivergedError(f"NIS divergence test failed at t={t:.6g} s")
        return self._x.copy()

    def _count_update(self, t: float, nis: float, dof: int) -> bool:
        """Count an update and push its NIS to the divergence test; True (and flagged) if the test fails."""
        self.n_updates += 1
        mon = self.monitor
        if mon is None or not mon.push(nis, dof):
            return False
        if not self.diverged:  # the test keeps failing after a divergence: format the reason once
            self._flag_divergence(t, f"NIS over {mon.window} updates above its {mon.confidence:.1%} bound")
        return True

    def _fused_log(self, t: np.ndarray, U, Y: np.ndarray) -> tuple | None:
        """``(U, Y, on_grid)`` for the model's compiled sample loop (``fused_run``) over a whole log, or None
        where it does not apply: no such model, the linear input hold, no inputs, or a NIS test that must
        raise at its sample (the loop runs ahead of the test)."""
        if not self._fast or U is None or self.divergence_action != "flag" or not hasattr(self.model, "fused_run"):
            return None
        U = np.ascontiguousarray(U, dtype=float)
        if U.ndim != 2 or len(t) < 2:
            return None
        k = np.diff(t) / self.dt
        on_grid = np.zeros(len(t), dtype=np.bool_)  # one interval after the previous sample, as step() tests
        on_grid[1:] = np.abs(k - 1.0) <= self.time_tol * np.maximum(1.0, k)
        return U, np.ascontiguousarray(Y, dtype=float), on_grid

    def _run_fused(self, k0: int, t: np.ndarray, log: tuple, outs: tuple, x_hat: np.ndarray, Pst, dof: np.ndarray) -> int:
        """Filter samples ``k0, k0 + 1, ...`` in the model's compiled loop (the same arithmetic as
        :meth:`step`'s fused samples, to the bit), then the end-of-sample tests of each in order. Returns the
        first sample not done, which :meth:`run` takes through :meth:`step`."""
        U, Y, on_grid = log
        m = self.m
        x = self._x.copy()
        P_alt = self._Pspare
        bufs = (np.empty(m), np.empty((m, m)), self._Ppred, self._work, self._HP)
        res = self.model.fused_run(k0, x, self._P, P_alt, U, Y, on_grid, self.channels, self._Rdiag, self._floor,
                                   self.dt, bufs, self._jumps is not None, outs)
        if res is None or res[0] == k0:
            return k0
        k, in_alt, finite = res
        if in_alt:
            self._P, self._Pspare = P_alt, self._P
        self._x = x
        self._t_prev = float(t[k - 1])
        self._u_prev = U[k - 1].copy()
        self.n_fused += k - k0
        dof[k0:k] = m
        self.last_idx = self._all
        self.last_dof = m
        self.last_innovation = outs[3][k - 1].copy()
        self.last_S = outs[4][k - 1].copy()
        nis = outs[5][k0:k].tolist()
        for j in range(k0, k - 1 if not finite else k):  # what step() does after each sample (see _close)
            self._count_update(t[j], nis[j - k0], m)  # (flags only: the loop runs with divergence_action "flag")
        self.last_nis = nis[-1]
        if not finite:
            x_hat[k - 1] = self._close(t[k - 1], False)  # non-finite: flagged, or raised
            if Pst is not None:
                Pst[k - 1] = np.nan
        return k

    def run(self, t, U, Y, *, reset: bool = True) -> EstimationResult:
        """Filter a whole record offline, through exactly the same code as :meth:`step`.

        Parameters
        ----------
        t : array_like, shape (n,)
            Sample times (on the ``dt`` grid).
        U : array_like, shape (n, nu) or (n,), or None
            Input at each sample time, held over the following interval.
        Y : array_like, shape (n, m)
            Measurements in channel order, NaN where a channel has no sample.
        reset : bool
            Restart from the prior first (default). With False the run continues from the current state.

        Returns
        -------
        EstimationResult
        """
        t = np.asarray(t, dtype=float).reshape(-1)
        Y = np.asarray(Y, dtype=float)
        n = len(t)
        if Y.shape != (n, self.m):
            raise ValueError(f"Y has shape {Y.shape}, expected ({n}, {self.m})")
        if U is not None:
            U = np.asarray(U, dtype=float)
            if len(U) != n:
                raise ValueError(f"U has {len(U)} rows, expected {n}")
        if reset:
            self.reset()
        nx, m = self.nx, self.m
        x_hat = np.empty((n, nx))
        Pst = {"diag": np.empty((n, nx)), "full": np.empty((n, nx, nx)), "none": None}[self.store_P]
        innov = np.full((n, m), np.nan)
        S_all = np.full((n, m, m), np.nan)
        nis = np.full(n, np.nan)
        dof = np.zeros(n, dtype=np.int64)
        step = self.step
        fused = self._fused_log(t, U, Y)
        outs = None
        if fused is not None:
            P_diag = Pst if self.store_P == "diag" else np.empty((0, nx))
            P_full = Pst if self.store_P == "full" else np.empty((0, nx, nx))
            outs = (x_hat, P_diag, P_full, innov, S_all, nis)
        t_start = time.perf_counter()
        k = 0
        while k < n:
            if fused is not None and self._t_prev is not None and not self.nonfinite:
                k = self._run_fused(k, t, fused, outs, x_hat, Pst, dof)  # the samples the compiled loop takes
                if k >= n:
                    break
            x_hat[k] = step(t[k], None if U is None else U[k], Y[k])
            if Pst is not None:
                if self.nonfinite:
                    Pst[k] = np.nan
                elif self.store_P == "diag":
                    Pst[k] = self._P.diagonal()
                else:
                    Pst[k] = self._P
            idx = self.last_idx
            if idx is not None:
                nis[k] = self.last_nis
                dof[k] = self.last_dof
                if len(idx) == m:
                    innov[k] = self.last_innovation
                    S_all[k] = self.last_S
                else:
                    innov[k, idx] = self.last_innovation
                    S_all[k][np.ix_(idx, idx)] = self.last_S
            k += 1
        wall = time.perf_counter() - t_start
        res = EstimationResult(
            t=t,
            x_hat=x_hat,
            P=Pst,
            innovations=innov,
            S=S_all,
            nis=nis,
            nis_dof=dof,
            n_missing=self.n_missing,
            n_updates=self.n_updates,
            diverged=self.diverged,
            diverged_at=self.diverged_at,
            nonfinite=self.nonfinite,
            wall_s=wall,
            channels=self.channels,
        )
        log.info("EKF run: %s", res.summary())
        return res

"""Consistency and accuracy statistics of state estimators.

- NEES ``e' P^-1 e`` (needs the true state) and NIS ``r' S^-1 r`` per step; for a consistent filter they are
  chi-square with ``nx`` resp. ``m`` degrees of freedom.
- Monte-Carlo averages over ``N`` runs: the per-step average over runs is ``chi2(N dof) / N``; the average
  over runs and steps is ``chi2(N n dof) / (N n)`` if the terms are independent (true for the NIS of an optimal
  filter, whose innovations are white; only approximate for the NEES, whose errors are time-correlated).
  Two-sided 95 % bands from :func:`chi2_band`.
- Error metrics (:func:`rms_error`, :func:`max_error`, the paper's eq. 21 statistics :func:`eq21_stats`) and an
  FFT peak finder (:func:`fft_peaks`) to compare the frequency content of estimated and true signals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ..observer.stats import chi2_ppf

__all__ = [
    "ConsistencyCheck",
    "chi2_band",
    "eq21_stats",
    "fft_peaks",
    "match_peaks",
    "max_error",
    "mc_consistency",
    "autocorrelation_time",
    "nees",
    "nis",
    "rms_error",
]


def nees(err, P) -> np.ndarray:
    """Normalised estimation error squared per step.

    Parameters
    ----------
    err : ndarray, shape (n, nx) or (nx,)
        Estimation errors ``x_true - x_hat``.
    P : ndarray
        Error covariances: shape (n, nx, nx) per step; (n, nx) per-step *diagonals* (correlations ignored;
        any 2-D ``P`` with the shape of a 2-D ``err`` is read this way); (nx, nx) one covariance for all steps
        (or for the single step of a 1-D ``err``).

    Returns
    -------
    ndarray, shape (n,), or float for a 1-D ``err``
    """
    err = np.asarray(err, float)
    P = np.asarray(P, float)
    single = err.ndim == 1
    e = np.atleast_2d(err)
    if P.ndim == 3:
        out = np.einsum("ij,ij->i", e, np.linalg.solve(P, e[..., None])[..., 0])
    elif P.ndim == 2 and not single and P.shape == e.shape:
        out = np.sum(e**2 / P, axis=1)
    elif P.ndim == 2:
        out = np.einsum("ij,ij->i", e, np.linalg.solve(P, e.T).T)
    else:
        raise ValueError(f"P of shape {P.shape} does not fit errors of shape {err.shape}")
    return float(out[0]) if single else out


def nis(innov, S) -> tuple[np.ndarray, np.ndarray]:
    """Normalised innovation squared per step, using only the finite channels of each step.

    Parameters
    ----------
    innov : ndarray, shape (n, m)
        Innovations, NaN for unused channels (as in :class:`~exuflex.observer.ekf.EstimationResult`).
    S : ndarray, shape (n, m, m)
        Innovation covariances (NaN rows/columns for unused channels).

    Returns
    -------
    values : ndarray, shape (n,)
        NIS, NaN where no channel was used.
    dof : ndarray of int, shape (n,)
        Channels used per step.
    """
    innov = np.atleast_2d(np.asarray(innov, float))
    S = np.asarray(S, float).reshape(len(innov), innov.shape[1], innov.shape[1])
    out = np.full(len(innov), np.nan)
    dof = np.isfinite(innov).sum(axis=1)
    for k in range(len(innov)):
        idx = np.flatnonzero(np.isfinite(innov[k]))
        if len(idx):
            r = innov[k, idx]
            out[k] = r @ np.linalg.solve(S[k][np.ix_(idx, idx)], r)
    return out, dof


def chi2_band(dof_total, n_avg, confidence: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided chi-square band of an average of ``n_avg`` chi-square terms with ``dof_total`` summed dof.

    Returns ``(chi2.ppf(a/2, dof_total) / n_avg, chi2.ppf(1 - a/2, dof_total) / n_avg)``, ``a = 1 - confidence``.
    """
    a = 1.0 - confidence
    dof_total = np.asarray(dof_total, float)
    return chi2_ppf(a / 2, dof_total) / n_avg, chi2_ppf(1 - a / 2, dof_total) / n_avg


@dataclass
class ConsistencyCheck:
    """Monte-Carlo consistency of a NEES or NIS sequence.

    Attributes
    ----------
    per_step, per_step_lo, per_step_hi : ndarray, shape (n,)
        Average over runs at each step and its band (NaN where no run has a value).
    fraction_inside : float
        Fraction of (valid) steps whose average lies in the band (expected ~ ``confidence``).
    time_avg, time_avg_lo, time_avg_hi : float
        Average over runs and steps, and its band (assuming independent terms).
    expected : float
        Expected value of ``time_avg`` (mean dof).
    confidence : float
    tau : float
        Integrated autocorrelation time of the sequence (steps; 1 for white terms such as the NIS of a
        consistent filter, tens of steps for a NEES: estimation errors are correlated in time).
    time_avg_lo_eff, time_avg_hi_eff : float
        The time-average band with ``n / tau`` independent terms per run instead of ``n``: the valid band
        for correlated terms (the independent-term band is then too narrow by ``sqrt(tau)``).
    """

    per_step: np.ndarray
    per_step_lo: np.ndarray
    per_step_hi: np.ndarray
    fraction_inside: float
    time_avg: float
    time_avg_lo: float
    time_avg_hi: float
    expected: float
    confidence: float
    tau: float = 1.0
    time_avg_lo_eff: float = float("nan")
    time_avg_hi_eff: float = float("nan")

    @property
    def time_avg_inside(self) -> bool:
        return bool(self.time_avg_lo <= self.time_avg <= self.time_avg_hi)


def mc_consistency(values, dof, confidence: float = 0.95, burn_in: int = 0) -> ConsistencyCheck:
    """Average NEES or NIS over Monte-Carlo runs and compare with chi-square bands.

    Parameters
    ----------
    values : ndarray, shape (N, n)
        NEES or NIS of ``N`` runs at ``n`` steps (NaN where undefined, e.g. NIS at a missing sample).
    dof : int or ndarray broadcastable to (N, n)
        Degrees of freedom of each term (``nx`` for NEES; channels used for NIS).
    confidence : float
        Two-sided confidence of the bands.
    burn_in : int
        Leading steps left out.

    Returns
    -------
    ConsistencyCheck
    """
    v = np.atleast_2d(np.asarray(values, float))[:, burn_in:]
    d = np.broadcast_to(np.asarray(dof, float), np.atleast_2d(np.asarray(values)).shape)[:, burn_in:]
    ok = np.isfinite(v)
    d = np.where(ok, d, 0.0)
    cnt = ok.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        per = np.where(cnt > 0, np.where(ok, v, 0.0).sum(axis=0) / cnt, np.nan)
        lo, hi = chi2_band(d.sum(axis=0), cnt, confidence)
    valid = cnt > 0
    inside = (per >= lo) & (per <= hi)
    frac = float(inside[valid].mean()) if valid.any() else float("nan")
    n_terms = ok.sum()
    tavg = float(v[ok].mean())
    tlo, thi = chi2_band(d.sum(), n_terms, confidence)
    tau = autocorrelation_time(v)
    elo, ehi = chi2_band(d.sum() / tau, n_terms / tau, confidence)
    return ConsistencyCheck(per_step=per, per_step_lo=lo, per_step_hi=hi, fraction_inside=frac, time_avg=tavg,
                            time_avg_lo=float(tlo), time_avg_hi=float(thi), expected=float(d.sum() / n_terms),
                            confidence=confidence, tau=tau, time_avg_lo_eff=float(elo), time_avg_hi_eff=float(ehi))


def autocorrelation_time(values, c: float = 5.0) -> float:
    """Integrated autocorrelation time ``1 + 2 sum_l rho(l)`` of sequences (N runs, n steps), with Sokal's
    automatic window (the sum stops at the first lag ``l >= c tau(l)``). NaN entries (missing terms) are
    replaced by the run's mean. At least 1."""
    v = np.atleast_2d(np.asarray(values, float))
    v = np.where(np.isfinite(v), v, np.nanmean(v, axis=1, keepdims=True))
    v = v - v.mean(axis=1, keepdims=True)
    n = v.shape[1]
    if n < 4:
        return 1.0
    f = np.fft.rfft(v, 2 * n, axis=1)
    acf = np.fft.irfft(f * np.conj(f), axis=1)[:, :n].sum(axis=0)
    if not acf[0] > 0:
        return 1.0
    rho = acf / acf[0]
    tau = 1.0
    for lag in range(1, n):
        tau += 2.0 * rho[lag]
        if lag >= c * tau:
            break
    return float(max(tau, 1.0))


def rms_error(x_true, x_hat, axis: int = 0) -> np.ndarray:
    """Root-mean-square of ``x_true - x_hat`` along ``axis`` (NaN samples ignored)."""
    e = np.asarray(x_true, float) - np.asarray(x_hat, float)
    return np.sqrt(np.nanmean(e**2, axis=axis))


def max_error(x_true, x_hat, axis: int = 0) -> np.ndarray:
    """Maximum absolute error along ``axis`` (NaN samples ignored)."""
    e = np.asarray(x_true, float) - np.asarray(x_hat, float)
    return np.nanmax(np.abs(e), axis=axis)


def eq21_stats(true_runs, est_runs) -> tuple[float, float]:
    """The paper's eq. 21 statistics of an estimated quantity over Monte-Carlo runs.

    Parameters
    ----------
    true_runs, est_runs : ndarray, shape (N, n_s)
        True and estimated quantity, ``N`` runs of ``n_s`` samples.

    Returns
    -------
    mu : float
        Mean over runs of the per-run mean absolute error.
    sigma : float
        Mean over runs of the per-run standard deviation (``ddof=1``) of the absolute error.
    """
    a = np.abs(np.atleast_2d(np.asarray(true_runs, float)) - np.atleast_2d(np.asarray(est_runs, float)))
    return float(a.mean(axis=1).mean()), float(a.std(axis=1, ddof=1).mean())


def fft_peaks(
    t,
    signal,
    fmax: float,
    n_peaks: int,
    *,
    fmin: float = 0.0,
    window: str = "hann",
    pad: int = 4,
    return_amplitudes: bool = False,
):
    """Frequencies of the strongest spectral peaks of a uniformly sampled signal.

    The signal is de-meaned, windowed (Hann by default), zero-padded to ``pad`` times its length (next power of
    two), and the local maxima of the magnitude spectrum in ``[fmin, fmax]`` are refined by parabolic
    interpolation of the log-magnitude over the three bins around each maximum.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Uniform sample times.
    signal : ndarray, shape (n,)
    fmax : float
        Highest frequency considered (Hz).
    n_peaks : int
        Number of peaks returned.
    fmin : float
        Lowest frequency considered (Hz).
    window : {"hann", "none"}
    pad : int
        Zero-padding factor.
    return_amplitudes : bool
        Also return the interpolated peak magnitudes.

    Returns
    -------
    freqs : ndarray, shape (<= n_peaks,)
        Peak frequencies (Hz), strongest first.
    amps : ndarray, optional
        Their magnitudes (window-normalised), if ``return_amplitudes``.
    """
    t = np.asarray(t, float)
    x = np.asarray(signal, float)
    n = len(x)
    if n < 4:
        raise ValueError("need at least 4 samples")
    dt = (t[-1] - t[0]) / (n - 1)
    if not np.allclose(np.diff(t), dt, rtol=1e-6, atol=1e-12):
        raise ValueError("fft_peaks needs uniformly sampled data")
    x = x - x.mean()
    if window == "hann":
        w = np.hanning(n)
    elif window == "none":
        w = np.ones(n)
    else:
        raise ValueError(f"unknown window {window!r}")
    nfft = 1 << int(np.ceil(np.log2(max(n * pad, n))))
    spec = np.abs(np.fft.rfft(x * w, nfft)) * (2.0 / w.sum())
    f = np.fft.rfftfreq(nfft, dt)
    df = f[1]
    lm = np.log(spec + 1e-300)
    i = np.arange(1, len(spec) - 1)
    is_peak = (spec[i] > spec[i - 1]) & (spec[i] >= spec[i + 1]) & (f[i] >= fmin) & (f[i] <= fmax)
    i = i[is_peak]
    a, b, c = lm[i - 1], lm[i], lm[i + 1]
    den = a - 2 * b + c
    with np.errstate(invalid="ignore", divide="ignore"):
        delta = np.where(den < 0, 0.5 * (a - c) / den, 0.0)
    fp = (i + delta) * df
    ap = np.exp(b - 0.25 * (a - c) * delta)
    order = np.argsort(-ap)[:n_peaks]
    if return_amplitudes:
        return fp[order], ap[order]
    return fp[order]


def match_peaks(f_ref, f_test) -> tuple[np.ndarray, np.ndarray]:
    """Match every reference peak to the nearest test peak.

    Returns
    -------
    matched : ndarray
        Nearest test frequency per reference frequency (NaN if ``f_test`` is empty).
    rel_err_pct : ndarray
        ``|f_ref - matched| / f_ref * 100`` (the paper's e_f of eq. 17).
    """
    f_ref = np.atleast_1d(np.asarray(f_ref, float))
    f_test = np.atleast_1d(np.asarray(f_test, float))
    if f_test.size == 0:
        m = np.full_like(f_ref, np.nan)
    else:
        m = f_test[np.argmin(np.abs(f_ref[:, None] - f_test[None, :]), axis=1)]
    return m, np.abs(f_ref - m) / np.abs(f_ref) * 100.0

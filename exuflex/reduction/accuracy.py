"""Accuracy indices of a reduced model (the paper's eqs. 16-17).

For every full-model mode ``phi`` below the band limit, the reduced mode ``phi_r`` that matches it
best is the one with the largest normalised cross-orthogonality

``NCO = (phi^T M H phi_r)^2 / ((phi^T M phi) (phi_r^T H^T M H phi_r))``  (1 = identical shapes),

and the frequency error is ``e_f = |f - f_r| / f * 100`` (%). Both are evaluated with the motors
free (torque-driven), the mechanism's zero-frequency modes dropped, like the paper's Table 2.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ..erls.modal import ModalResult, modal_analysis

__all__ = ["AccuracyResult", "accuracy_indices", "accuracy_along", "match_modes", "reduced_modes"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AccuracyResult:
    q: np.ndarray
    full_hz: np.ndarray  # full-model modes in the band
    reduced_hz: np.ndarray  # matched reduced modes, aligned with full_hz
    nco: np.ndarray
    freq_error_pct: np.ndarray

    def ok(self, nco_min: float, err_max_pct: float) -> bool:
        return bool(np.all(self.nco >= nco_min) and np.all(self.freq_error_pct <= err_max_pct))

    @property
    def worst_nco(self) -> float:
        return float(self.nco.min()) if self.nco.size else 1.0

    @property
    def worst_error_pct(self) -> float:
        return float(self.freq_error_pct.max()) if self.freq_error_pct.size else 0.0


def reduced_modes(cb, q) -> tuple[np.ndarray, np.ndarray, object]:
    """Elastic frequencies (Hz) and shapes (r, k) of the reduced model linearised at rest at q."""
    rc = cb.at(q)
    model = cb.model
    M = model.mass(rc.cfg)
    K = model.stiffness(rc.cfg)
    Mr = rc.H.T @ M @ rc.H
    Kr = rc.H.T @ K @ rc.H
    w2, V = sla.eigh(Kr, Mr)
    f = np.sqrt(np.clip(w2, 0, None)) / (2 * np.pi)
    return f[cb.nq :], V[:, cb.nq :], rc


def accuracy_indices(cb, q, full: ModalResult | None = None, band_hz: float | None = None) -> AccuracyResult:
    """NCO and frequency error of every full mode below ``band_hz`` (default: the basis' band) at q."""
    q = np.asarray(q, float)
    band_hz = cb.band_hz if band_hz is None else band_hz
    model = cb.model
    if full is None:
        full = modal_analysis(model, q)
    rc = cb.at(q)
    return match_modes(q, rc.H, model.mass(rc.cfg), model.stiffness(rc.cfg), full, cb.nq, band_hz)


def match_modes(q, H: np.ndarray, M: np.ndarray, K: np.ndarray, full: ModalResult, nq: int,
                band_hz: float) -> AccuracyResult:
    """NCO and frequency error of the full modes below ``band_hz`` against the modes of the basis ``H``
    (n, r) with the full mass and stiffness ``M``, ``K`` at q (the reduced model linearised at rest)."""
    w2, V = sla.eigh(H.T @ K @ H, H.T @ M @ H)
    fr = np.sqrt(np.clip(w2[nq:], 0, None)) / (2 * np.pi)
    Vr = V[:, nq:]
    sel = full.frequencies_hz <= band_hz
    Phi = full.shapes[:, sel]
    ff = full.frequencies_hz[sel]
    if Vr.shape[1] == 0:
        z = np.zeros(len(ff))
        return AccuracyResult(q, ff, np.full(len(ff), np.inf), z, np.full(len(ff), np.inf))
    HV = H @ Vr
    cross = Phi.T @ M @ HV
    n1 = np.einsum("ij,ik,kj->j", Phi, M, Phi)
    n2 = np.einsum("ij,ik,kj->j", HV, M, HV)
    nco = cross**2 / np.outer(n1, n2)
    best = np.argmax(nco, axis=1)
    fr_m = fr[best]
    return AccuracyResult(q, ff, fr_m, nco[np.arange(len(ff)), best], np.abs(ff - fr_m) / ff * 100.0)


def accuracy_along(cb, qs, warn: bool = True) -> list[AccuracyResult]:
    """Accuracy indices at each configuration of ``qs`` (n_cfg, nq), warning where a threshold fails."""
    out = []
    for q in np.atleast_2d(qs):
        acc = accuracy_indices(cb, q)
        if warn and not acc.ok(cb.nco_min, cb.freq_error_max_pct):
            msg = (
                f"reduced model below its accuracy thresholds at q = {np.round(q, 4).tolist()}: worst NCO "
                f"{acc.worst_nco:.4f} (min {cb.nco_min}), worst frequency error {acc.worst_error_pct:.2f} % "
                f"(max {cb.freq_error_max_pct} %)"
            )
            warnings.warn(msg, stacklevel=2)
            log.warning(msg)
        out.append(acc)
    return out

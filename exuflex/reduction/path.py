"""Interior modes chosen over the configurations a manoeuvre passes through, not at q* alone.

The basis ``H(q, q*)`` turns the interior modes of q* with their links and recomputes the Guyan shapes at q
(:mod:`.basis`), but the band's full modes change along a manoeuvre: a mode that lies above the band at q*
can enter it elsewhere, and the interior modes that carry a band mode's slave motion at q* need not be
those that carry it at another configuration (the four-bar with its tip's transverse master alone: the
interior modes ranked at q* miss band modes half a crank turn later, ``tests/test_reduction.py``). So the interior modes are chosen on sampled configurations of the planned
motion:

1. At every sample ``c`` (q* first, then the manoeuvre's configurations, :func:`manoeuvre_configurations`)
   the full band modes and the basis with every interior mode (``B(q_c)``, ``Psi(q_c, q*)``), reduced to
   ``H^T M H``, ``H^T K H`` and the band modes' ``Phi^T M H``: the NCO and frequency errors of any subset of
   interior modes then come from their rows and columns, without products with the full matrices.
2. Forward selection: starting from none, each step keeps the interior mode that makes the smallest margin
   to the thresholds (NCO >= ``nco_min`` and frequency error <= ``freq_error_max_pct`` for every full mode
   below the band limit, :func:`margin`) over all samples largest; ties go to the higher IMR score at q*.
   The count at which every sample meets the thresholds is the automatic ``n_interior``; a fixed count
   takes that many steps. The modes not selected follow by their largest IMR score over the samples
   (:func:`interior_mode_scores` with ``M_ss(q_c)``; the turned modes are M-orthonormal there up to the
   change of the mass matrix beyond a rotation). ``ranking="frequency"``: the lowest modes first.

With q* alone (``CraigBampton(..., path=False)``) the same selection is made at q* only.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from ..erls.modal import modal_analysis
from ..manoeuvre import plan
from ..mechanism import Mechanism
from .accuracy import AccuracyResult

__all__ = ["PathSamples", "interior_mode_scores", "manoeuvre_configurations", "margin"]


def interior_mode_scores(Phi_all: np.ndarray, M_ss: np.ndarray, band_shapes_s: np.ndarray, band_shapes_m: np.ndarray,
                         B: np.ndarray) -> np.ndarray:
    """IMR score of every interior mode (interior-mode ranking, :mod:`.basis`).

    Parameters
    ----------
    Phi_all : (s, n_int) all interior modes, M_ss-orthonormal.
    M_ss : (s, s) slave mass block.
    band_shapes_s, band_shapes_m : slave and elastic-master rows of the full band modes (s, n_band), (m_e, n_band).
    B : (s, m_e) Guyan shapes of the elastic masters.
    """
    r = band_shapes_s - B @ band_shapes_m
    c = Phi_all.T @ M_ss @ r  # (n_int, n_band)
    norms = np.einsum("ij,ik,kj->j", r, M_ss, r)
    norms = np.where(norms > 0, norms, 1.0)
    return (c**2 / norms).sum(axis=1)


def manoeuvre_configurations(mech: Mechanism, n: int = 16) -> np.ndarray | None:
    """``n`` configurations (n, nq) of the model's planned manoeuvre, equally spaced in time (``None``: the
    model has no manoeuvre)."""
    if mech.manoeuvre is None:
        return None
    return plan(mech, dt=mech.manoeuvre.duration / max(n - 1, 1)).q


def margin(acc: AccuracyResult, nco_min: float, err_max_pct: float) -> float:
    """The smallest relative margin of a configuration's modes to the thresholds: ``(NCO - nco_min) /
    (1 - nco_min)`` and ``(err_max - e_f) / err_max``; negative where a threshold fails."""
    if not acc.nco.size:
        return np.inf
    a = (acc.nco - nco_min) / max(1.0 - nco_min, 1e-12)
    b = (err_max_pct - acc.freq_error_pct) / err_max_pct
    return float(min(a.min(), b.min()))


class PathSamples:
    """The sampled configurations and what the interior-mode choice evaluates there.

    Parameters
    ----------
    cb : CraigBampton whose every interior mode is kept (``set_interior`` with all modes, in ascending order).
    qs : (n_c, nq) configurations.
    """

    def __init__(self, cb, qs: np.ndarray):
        model, nq = cb.model, cb.nq
        self.cb = cb
        self.qs = np.atleast_2d(np.asarray(qs, float))
        self.band_hz: list[np.ndarray] = []
        # per sample, with every interior mode: H^T M H, H^T K H and the band modes' cross products
        # Phi^T M H (the accuracy of a subset reads their rows and columns: no products with the full model)
        self.Mr, self.Kr, self.PMH, self.n1 = [], [], [], []
        scores = []
        s_ = cb.is_
        for q in self.qs:
            full = modal_analysis(model, q)
            rc = cb.at(q)
            M, K = model.mass(rc.cfg), model.stiffness(rc.cfg)
            qc, qsn = cb._frame_cs(rc.cfg)
            Mw = cb._congruence(M[nq:, nq:], qc, qsn)
            band = full.frequencies_hz <= cb.band_hz
            shapes = cb._to_frame(full.shapes[nq:, band], qc, qsn)
            scores.append(interior_mode_scores(rc.Psi, Mw[np.ix_(s_, s_)], shapes[s_], shapes[cb.im], rc.B))
            Phi = full.shapes[:, band]
            H = rc.H
            self.band_hz.append(full.frequencies_hz[band])
            self.Mr.append(H.T @ M @ H)
            self.Kr.append(H.T @ K @ H)
            self.PMH.append(Phi.T @ M @ H)
            self.n1.append(np.einsum("ij,ik,kj->j", Phi, M, Phi))
        self.scores = np.array(scores)  # (n_c, n_interior modes)

    def evaluate(self, kept) -> list[AccuracyResult]:
        """The accuracy indices (:func:`~.accuracy.match_modes`) at every sample with the interior modes ``kept``
        (indices into all of them)."""
        cb = self.cb
        nq = cb.nq
        cols = np.r_[np.arange(cb.n_m), cb.n_m + np.sort(np.asarray(kept, int))]
        ix = np.ix_(cols, cols)
        out = []
        for q, Mr, Kr, PMH, n1, ff in zip(self.qs, self.Mr, self.Kr, self.PMH, self.n1, self.band_hz):
            w2, V = sla.eigh(Kr[ix], Mr[ix])
            fr = np.sqrt(np.clip(w2[nq:], 0, None)) / (2 * np.pi)
            Vr = V[:, nq:]
            if not Vr.shape[1]:
                z = np.zeros(len(ff))
                out.append(AccuracyResult(q, ff, np.full(len(ff), np.inf), z, np.full(len(ff), np.inf)))
                continue
            n2 = np.einsum("ij,ik,kj->j", Vr, Mr[ix], Vr)
            nco = (PMH[:, cols] @ Vr) ** 2 / np.outer(n1, n2)
            best = np.argmax(nco, axis=1)
            fr_m = fr[best]
            out.append(AccuracyResult(q, ff, fr_m, nco[np.arange(len(ff)), best], np.abs(ff - fr_m) / ff * 100.0))
        return out

    def choose(self, ranking: str, n_max: int | None = None) -> tuple[np.ndarray, int, list[AccuracyResult]]:
        """``(order, n_needed, accuracy)``: the interior modes in the order they are kept, how many the
        thresholds need at every sample (module docstring) and the samples' indices with that many.

        ``ranking="imr"``: forward selection; each step keeps the mode that makes the smallest margin over
        the samples largest (ties: the higher score at q*), up to ``n_max`` modes (default: until every
        sample meets the thresholds), then the others by their largest score over the samples.
        ``"frequency"``: the lowest modes first. Where no count meets the thresholds at every sample
        (:attr:`reachable` False; e.g. a global master that becomes a link's axial direction), the smallest count
        meeting them wherever some count does."""
        n_all = self.scores.shape[1]
        self.reachable = True
        if ranking == "frequency":
            order = np.arange(n_all)
            for k in range(n_all + 1):
                accs = self.evaluate(order[:k])
                if self.worst_margin(accs) >= 0:
                    return order, k, accs
            k = self._need(order)
            return order, k, self.evaluate(order[:k])
        tie = np.argsort(-self.scores[0], kind="stable")  # q*'s IMR order
        seq: list[int] = []
        accs = self.evaluate(seq)
        n_needed = None
        while len(seq) < n_all:
            if self.worst_margin(accs) >= 0 and n_needed is None:
                n_needed = len(seq)
            if (n_needed is not None and n_max is None) or (n_max is not None and len(seq) >= n_max):
                break
            best, best_m, best_accs = -1, -np.inf, None
            for i in tie:
                if i in seq:
                    continue
                a = self.evaluate(seq + [int(i)])
                m = self.worst_margin(a)
                if m > best_m:
                    best, best_m, best_accs = int(i), m, a
            seq.append(best)
            accs = best_accs
        rest = np.argsort(-self.scores.max(axis=0), kind="stable")
        order = np.array(seq + [int(i) for i in rest if i not in set(seq)], int)
        if n_needed is None:  # a fixed count below the need, or every mode: the need by the order's prefixes
            n_needed = self._need(order)
        return order, n_needed, self.evaluate(order[:n_needed])

    def _need(self, order: np.ndarray) -> int:
        """The smallest prefix of ``order`` meeting the thresholds at every sample where some prefix does
        (:attr:`reachable` False if that is not every sample)."""
        cb = self.cb
        m = np.array([[margin(a, cb.nco_min, cb.freq_error_max_pct) for a in self.evaluate(order[:k])]
                      for k in range(len(order) + 1)])  # (prefix, sample)
        can = (m >= 0).any(axis=0)
        self.reachable = bool(can.all())
        return next(k for k in range(len(order) + 1) if np.all(m[k, can] >= 0))

    def worst_margin(self, accs: list[AccuracyResult]) -> float:
        """The smallest :func:`margin` over the samples."""
        return min(margin(a, self.cb.nco_min, self.cb.freq_error_max_pct) for a in accs)

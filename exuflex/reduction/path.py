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

Modes the sensors see
---------------------
The band's limit is the user's statement of the dynamics of interest, but the observer's channels see every
mode the manoeuvre's torques excite above their noise. A mode just above the band that rings visibly in a
strain gauge after a torque step, and that the reduced model represents only by a spurious mode at another
frequency, is read by the filter as motion of its own modes: the single link's third mode (225 Hz, band 180
Hz) rings at about its gauge's noise level after each step of its trapezoid, and the reduced model without it
has a mode near 360 Hz instead; its estimation errors after the steps then exceed the filter's own bound
(``docs/gallery.md`` shows the figures). So at every sample the accuracy requirement also covers the full modes
*visible* in the channels (:class:`Excitation`, :meth:`Excitation.snr`): below the Nyquist frequency of the
sample rate and with a peak dynamic response to the manoeuvre's torques of at least ``visibility`` times a
channel's noise std. The default :data:`VISIBILITY` = sqrt(0.2) = 0.45: a ringing of amplitude ``a`` has mean
square ``a^2 / 2``, so a mode below it raises no channel's innovation variance by more than 10 %, the tolerance
of the observer's NIS test.

A visible mode counts as followed when the part of its ringing the reduced model cannot follow
(:meth:`PathSamples._unexplained`: its shape outside the matched reduced mode, or the dephasing of a frequency
error over the ringing's decay) times its response stays below ``visibility``. Modes that mix along the
manoeuvre (the four-bar's pairs near 450 and 490 Hz) cannot all be followed by a few interior modes; the
automatic count adds at most one interior mode per visible mode (:meth:`PathSamples._visible_cap`) and says so.
Modes above the Nyquist frequency are left to the band limit: the samples see them only aliased, and the count
would grow with them (the six-bar at 500 Hz would take its 487 and 558 Hz modes); a model that needs one fixes
``n_interior`` (the slider-crank keeps its 895 Hz mode so).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ..erls.modal import ModalResult, modal_analysis
from ..erls.sensing import channel_matrix
from ..manoeuvre import open_loop_torque, plan
from ..mechanism import Mechanism
from ..sensors import default_channels
from .accuracy import AccuracyResult

__all__ = ["VISIBILITY", "Excitation", "PathSamples", "interior_mode_scores", "manoeuvre_configurations", "margin"]

log = logging.getLogger(__name__)

#: a full mode whose response in a channel reaches this multiple of the channel's noise std is part of the band
#: (module docstring: a ringing below it raises the channel's innovation variance by at most 10 %)
VISIBILITY = float(np.sqrt(0.2))


@dataclass(frozen=True)
class Excitation:
    """What the observer's channels see of the full modes under the model's manoeuvre.

    ``du`` (n_t, n_motors): the increments of the open-loop torques on a grid of ``dt`` (half the sample
    interval: it resolves every frequency below the sample rate's Nyquist frequency), from rest before the
    manoeuvre to rest after it; ``channels`` and their noise std ``noise``; ``nyquist_hz``, half the model's
    sample rate.
    """

    du: np.ndarray
    dt: float
    channels: tuple[str, ...]
    noise: np.ndarray
    nyquist_hz: float

    @classmethod
    def of(cls, mech: Mechanism, channels: Sequence[str] | None = None) -> Excitation | None:
        """The excitation of ``mech``'s manoeuvre seen by ``channels`` (default: the sensors with a stated noise
        except tip positions, :func:`exuflex.sensors.default_channels`); None without a manoeuvre or channels."""
        if mech.manoeuvre is None or not mech.motors:
            return None
        channels = tuple(default_channels(mech) if channels is None else channels)
        sensors = {s.name: s for s in mech.sensors}
        channels = tuple(c for c in channels if c in sensors and sensors[c].noise_std > 0)
        if not channels:
            return None
        dt = 0.5 / mech.sample_rate_hz
        try:
            tau = open_loop_torque(mech, plan(mech, dt=dt, t_end=mech.manoeuvre.duration))
        except Exception as exc:  # noqa: BLE001 - no torques (e.g. a coordinate without a motor): the band alone
            log.info("%s: no open-loop torques for the modes the channels see (%s); the band limit alone",
                     mech.source or mech.name, exc)
            return None
        zero = np.zeros((1, tau.shape[1]))
        du = np.diff(np.vstack([zero, tau, zero]), axis=0)
        return cls(du, dt, channels, np.array([sensors[c].noise_std for c in channels]), 0.5 * mech.sample_rate_hz)

    def snr(self, model, q, full: ModalResult) -> np.ndarray:
        """Per full mode below the Nyquist frequency (others: 0), the peak of its dynamic response to the torques
        in any channel, in units of that channel's noise std.

        A mode of mass-normalised shape ``phi`` and frequency ``w`` (Rayleigh damping ratio ``zeta``) driven by
        torques ``u(t)`` moves as ``eta = (b . u) / w^2 - (1 / w^2) integral cos(w_d (t - s)) e^(-zeta w (t - s))
        b . du(s)`` (integration by parts of the oscillator's response), ``b = phi^T G`` its modal input. The
        first term is the quasi-static part, which the Craig-Bampton shapes carry; the second rings at the
        mode's frequency after each change of the torques. Its peak is bounded by ``sum_m |b_m| max_t |S_m(t)|
        / w^2`` with ``S_m(t) = sum_k exp((i w_d - zeta w)(t - t_k)) du_m(t_k)``, and a channel of row ``c``
        reads it times ``|c . phi|``."""
        cfg = model.configuration(np.asarray(q, float))
        f = full.frequencies_hz
        out = np.zeros(len(f))
        sel = np.flatnonzero((f > 0) & (f < self.nyquist_hz))
        if not sel.size:
            return out
        phi = full.shapes[:, sel]
        b = np.abs(phi.T @ model.input_matrix(cfg))  # (modes, motors)
        read = np.abs(channel_matrix(model, cfg, model.mech, self.channels) @ phi) / self.noise[:, None]
        w = 2 * np.pi * f[sel]
        zeta = model.alpha / (2 * w) + model.beta * w / 2
        wd = w * np.sqrt(np.clip(1 - zeta**2, 0, None))
        poles = np.exp((1j * wd - zeta * w) * self.dt)
        from scipy.signal import lfilter  # here, not at import: scipy.signal is a large import

        peak = np.zeros_like(b)
        for j, a in enumerate(poles):
            s = lfilter([1.0], [1.0, -a], self.du.astype(complex), axis=0)
            peak[j] = np.abs(s).max(axis=0)
        out[sel] = read.max(axis=0) * (b * peak).sum(axis=1) / w**2
        return out


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
    excitation : what the channels see (:class:`Excitation`); with it the band at each sample also holds the
        full modes visible there (``visibility``, module docstring), listed per sample in :attr:`visible_hz`.
    """

    def __init__(self, cb, qs: np.ndarray, excitation: Excitation | None = None, visibility: float = VISIBILITY):
        model, nq = cb.model, cb.nq
        self.cb = cb
        self.qs = np.atleast_2d(np.asarray(qs, float))
        self.visibility = float(visibility)
        self.band_hz: list[np.ndarray] = []
        self.visible_hz: list[np.ndarray] = []  # full modes above the band limit that the channels see
        self.visible_snr: list[np.ndarray] = []  # their peak response / noise std (:meth:`Excitation.snr`)
        # per sample, with every interior mode: H^T M H, H^T K H and the cross products Phi^T M H of the band's and
        # the visible full modes (the accuracy of a subset reads their rows and columns: no products with the
        # full model)
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
            seen = np.zeros_like(band)
            if excitation is not None and self.visibility > 0:
                snr = excitation.snr(model, q, full)
                seen = (snr >= self.visibility) & ~band
                self.visible_snr.append(snr[seen])
            else:
                self.visible_snr.append(np.zeros(0))
            self.visible_hz.append(full.frequencies_hz[seen])
            shapes = cb._to_frame(full.shapes[nq:, band], qc, qsn)
            scores.append(interior_mode_scores(rc.Psi, Mw[np.ix_(s_, s_)], shapes[s_], shapes[cb.im], rc.B))
            Phi = np.hstack([full.shapes[:, band], full.shapes[:, seen]])  # the band's modes, then the visible ones
            H = rc.H
            self.band_hz.append(full.frequencies_hz[band])
            self.Mr.append(H.T @ M @ H)
            self.Kr.append(H.T @ K @ H)
            self.PMH.append(Phi.T @ M @ H)
            self.n1.append(np.einsum("ij,ik,kj->j", Phi, M, Phi))
        self.scores = np.array(scores)  # (n_c, n_interior modes)
        self.reachable = True  # every sample's band thresholds met by some count (:meth:`choose`)
        self.visible_met = True  # the visible modes' requirement met within :meth:`_visible_cap`

    def _match(self, kept) -> list[AccuracyResult]:
        """The accuracy indices (:func:`~.accuracy.match_modes`) of the band's and the visible full modes (in
        that order) at every sample with the interior modes ``kept`` (indices into all of them)."""
        cb = self.cb
        nq = cb.nq
        cols = np.r_[np.arange(cb.n_m), cb.n_m + np.sort(np.asarray(kept, int))]
        ix = np.ix_(cols, cols)
        out = []
        for q, Mr, Kr, PMH, n1, fb, fv in zip(self.qs, self.Mr, self.Kr, self.PMH, self.n1, self.band_hz,
                                              self.visible_hz):
            ff = np.r_[fb, fv]
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

    def evaluate(self, kept) -> list[AccuracyResult]:
        """The accuracy indices of the band's full modes at every sample with the interior modes ``kept``."""
        out = []
        for a, fb in zip(self._match(kept), self.band_hz):
            k = len(fb)
            out.append(AccuracyResult(a.q, a.full_hz[:k], a.reduced_hz[:k], a.nco[:k], a.freq_error_pct[:k]))
        return out

    def margins(self, kept, visible: bool = True) -> np.ndarray:
        """Per sample, the smallest margin to the requirements with the interior modes ``kept``: the thresholds
        on the band's modes (:func:`margin`), and on each visible mode the part of its ringing the reduced model
        cannot follow, ``snr * u`` (:meth:`_unexplained`), against ``visibility``: ``(visibility - unexplained) / visibility``; ``visible=False``: the
        band's thresholds alone."""
        cb = self.cb
        out = []
        for a, fb, snr in zip(self._match(kept), self.band_hz, self.visible_snr):
            k = len(fb)
            band = AccuracyResult(a.q, a.full_hz[:k], a.reduced_hz[:k], a.nco[:k], a.freq_error_pct[:k])
            m = margin(band, cb.nco_min, cb.freq_error_max_pct)
            if visible and len(snr):
                m = min(m, float(((self.visibility - snr * self._unexplained(a, k)) / self.visibility).min()))
            out.append(m)
        return np.array(out)

    def _unexplained(self, a: AccuracyResult, k: int) -> np.ndarray:
        """The fraction ``u`` of each visible mode's ringing (entries ``k:`` of ``a``) that the reduced model cannot
        follow: the larger of the shape's part outside the matched reduced mode, ``sqrt(1 - NCO)``, and the
        dephasing of a ringing followed at a frequency off by the relative error ``e``: over its decay a ringing
        ``exp(-zeta w t) sin(w t)`` and the same at ``w (1 + e)`` differ by ``e / (sqrt(2) zeta)`` of its RMS
        (to first order in ``e``; at most 1)."""
        model = self.cb.model
        w = 2 * np.pi * a.full_hz[k:]
        zeta = model.alpha / (2 * w) + model.beta * w / 2
        phase = np.minimum(1.0, a.freq_error_pct[k:] / 100.0 / (np.sqrt(2.0) * np.maximum(zeta, 1e-12)))
        return np.maximum(np.sqrt(np.clip(1.0 - a.nco[k:], 0.0, 1.0)), phase)

    def _visible_cap(self, band_need: int) -> int:
        """The most interior modes the visible modes may add to the band's need: one per visible mode of the sample
        that has most (a mode the reduced model cannot follow with that many is reported, not chased)."""
        return band_need + max((len(v) for v in self.visible_snr), default=0)

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
            k = self._need(order)
            return order, k, self.evaluate(order[:k])
        tie = np.argsort(-self.scores[0], kind="stable")  # q*'s IMR order
        seq: list[int] = []
        worst = self.margins(seq).min()
        n_needed, band_need = None, None
        self.visible_met = True
        while len(seq) < n_all:
            if band_need is None and self.margins(seq, visible=False).min() >= 0:
                band_need = len(seq)
            if worst >= 0 and n_needed is None:
                n_needed = len(seq)
            if n_needed is None and band_need is not None and len(seq) >= self._visible_cap(band_need):
                n_needed, self.visible_met = len(seq), False  # the visible modes' best effort
            if (n_needed is not None and n_max is None) or (n_max is not None and len(seq) >= n_max):
                break
            best, best_m = -1, -np.inf
            for i in tie:
                if i in seq:
                    continue
                m = self.margins(seq + [int(i)]).min()
                if m > best_m:
                    best, best_m = int(i), m
            seq.append(best)
            worst = best_m
        rest = np.argsort(-self.scores.max(axis=0), kind="stable")
        order = np.array(seq + [int(i) for i in rest if i not in set(seq)], int)
        if n_needed is None:  # a fixed count below the need, or every mode: the need by the order's prefixes
            n_needed = self._need(order)
        return order, n_needed, self.evaluate(order[:n_needed])

    def _need(self, order: np.ndarray) -> int:
        """The smallest prefix of ``order`` meeting the thresholds at every sample where some prefix does
        (:attr:`reachable` False if that is not every sample)."""
        mb = np.array([self.margins(order[:k], visible=False) for k in range(len(order) + 1)])  # (prefix, sample)
        can = (mb >= 0).any(axis=0)
        self.reachable = bool(can.all())
        band_need = next(k for k in range(len(order) + 1) if np.all(mb[k, can] >= 0))
        cap = min(self._visible_cap(band_need), len(order))
        for k in range(band_need, cap + 1):
            if np.all(self.margins(order[:k])[can] >= 0):
                self.visible_met = True
                return k
        self.visible_met = False
        return cap

    def worst_margin(self, kept) -> float:
        """The smallest of :meth:`margins` over the samples."""
        return float(self.margins(kept).min())

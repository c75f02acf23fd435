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

What the filter needs
---------------------
The band's limit is the user's statement of the dynamics of interest, but the observer's channels read every
part of the motion the manoeuvre excites: the quasi-static deflection of the slaves under the motion's inertial
loads and the ringing of modes above the band after every torque step. What no reduced state can represent, the
filter explains with its own states (a bias) or leaves in its innovations. So the automatic count also meets the
truncation requirement of :mod:`.truncation`: at every sample, the mean square of the truncated modes' output in
the observer's channels under the planned motion, in units of each channel's noise variance and summed over the
channels, ``rho``, at most ``rho_max`` (default :data:`.truncation.TRUNCATION_MAX`). The forward selection then
maximises the smaller of the two margins, the band thresholds' and ``(rho_max - rho) / rho_max``.

A mode whose ringing decays within one sample interval (``zeta w > f_s``, the sample rate) acts on the samples
only through its quasi-static part; keeping it would make the reduced model stiff without following any dynamics
the filter sees (a master dof is the remedy for a static shape). The truncation requirement adds only modes
that ring for longer; where those cannot meet it, the count stops when the next mode raises the worst margin by
less than 0.01 (``rho`` by 1 % of ``rho_max``), and says so (:attr:`PathSamples.truncation_met`).

Last, the filter requirement (:mod:`.truncation`, "What the filter makes of it"): the steady filter's error on the
linearised full model under the manoeuvre, per estimated quantity over the bound's variance, ``b <= bias_max``
(:meth:`PathSamples.bias`) and the steady filter's whitened innovations at most ``INNOVATION_MAX`` summed over the
channels (:meth:`PathSamples.innovation`); modes are added until both hold (:meth:`PathSamples.extend_for_bias`,
:attr:`PathSamples.bias_met`). :class:`.basis.CraigBampton` judges every requirement again on the final basis, after
the static corrections (:mod:`.static`), and adds modes among every re-based one until they hold
(:meth:`PathSamples.requirement_excess` at most 1).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ..erls.modal import ModalResult, modal_analysis
from ..manoeuvre import plan
from ..mechanism import Mechanism
from .accuracy import AccuracyResult
from .truncation import (BIAS_MAX, INNOVATION_MAX, TRUNCATION_MAX, WINDOW_SAMPLES, FilterSample, PlannedInput, modal_response,
                         quantity_columns, truncation_sample, window_mean_square)

__all__ = ["PathSamples", "interior_mode_scores", "manoeuvre_configurations", "margin"]

log = logging.getLogger(__name__)

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


def _key(kept) -> tuple[int, ...]:
    """A set of interior modes as a cache key: their indices, sorted."""
    return tuple(sorted(int(i) for i in kept))


class PathSamples:
    """The sampled configurations and what the interior-mode choice evaluates there.

    Parameters
    ----------
    cb : CraigBampton whose every interior mode is kept (``set_interior`` with all modes, in ascending order).
    qs : (n_c, nq) configurations.
    planned : the manoeuvre's planned input and the channels (:class:`.truncation.PlannedInput`); with it, the
        truncation requirement at every sample (:mod:`.truncation`, module docstring), in :attr:`truncation`.
    rho_max : the truncation requirement's limit (0: the band's thresholds alone).
    quantity_max : the largest RMS of the truncated part allowed per estimated tip quantity (a mapping from its
        name, :attr:`.truncation.PlannedInput.quantities`, to m or m/s; the observer sets it from its bound); None:
        the channels' requirement alone.
    bias_max : the filter requirement's limit (0: off), :data:`.truncation.BIAS_MAX` by default; its figures need
        ``planned`` and ``rho_max > 0``.
    """

    def __init__(self, cb, qs: np.ndarray, planned: PlannedInput | None = None, rho_max: float = TRUNCATION_MAX,
                 quantity_max=None, bias_max: float = BIAS_MAX):
        model, nq = cb.model, cb.nq
        self.quantity_max = None
        if quantity_max is not None and planned is not None and planned.quantities:
            self.quantity_max = np.array([quantity_max.get(k, np.inf) for k in planned.quantities], float)
        self.cb = cb
        self.qs = np.atleast_2d(np.asarray(qs, float))
        self.rho_max = float(rho_max)
        self.bias_max = float(bias_max)
        self.filters: list[FilterSample] = []  # per truncation sample, the observer's linear model (.truncation)
        self.band_hz: list[np.ndarray] = []
        self.truncation = []  # per sample, :class:`.truncation.TruncationSample` (empty without a planned input)
        self._locked = []  # per sample, for :meth:`_ringing`
        self._tix = []  # the samples with a truncation figure
        self._cache: dict = {}
        # per sample, with every interior mode: H^T M H, H^T K H and the band's full modes' cross products Phi^T M H
        # (the accuracy of a subset reads their rows and columns: no products with the full model)
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
            if planned is not None and self.rho_max > 0 and len(self.band_hz) % 2 == 1:  # q* and every other sample
                locked = modal_analysis(model, q, locked=True, hold_readings=False)  # the interior's constraint
                t = truncation_sample(cb, rc, locked, planned)
                self.truncation.append(t)
                self._tix.append(len(self.band_hz) - 1)
                # q held: the reduced model's elastic block and the full modes' cross products with it
                He = H[nq:, nq:]
                self._locked.append((self.Mr[-1][nq:, nq:], self.Kr[-1][nq:, nq:], locked.shapes[nq:].T @ M[nq:, nq:] @ He, He))
                if self.bias_max > 0:
                    self.filters.append(FilterSample(model, rc, planned))
        self.scores = np.array(scores)  # (n_c, n_interior modes)
        self._tpos = {c: j for j, c in enumerate(self._tix)}  # sample -> its index in :attr:`truncation`
        # the interior modes that ring for at least a sample interval (zeta w <= f_s): the truncation requirement's
        # candidates (module docstring)
        w = 2 * np.pi * cb.interior_frequencies_hz
        zeta = model.alpha / (2 * np.maximum(w, 1e-12)) + model.beta * w / 2
        self.dynamic = zeta * w <= model.mech.sample_rate_hz
        self.reachable = True  # every sample's band thresholds met by some count (:meth:`choose`)
        self.truncation_met = True  # the truncation requirement met by the count chosen
        self.bias_met = True  # the filter requirement met by the count chosen
        self.bias_tried: list[int] = []  # the modes the filter requirement tried, in order (:meth:`extend_for_bias`)

    def bias(self, kept) -> np.ndarray:
        """Per estimated quantity (:attr:`.truncation.PlannedInput.quantities`), the filter requirement's figure with
        the interior modes ``kept``: the mean square of the steady filter's error made of the truncated motion, over
        the sampled configurations, in units of the bound's variance there (its mean over them) (:mod:`.truncation`,
        "What the filter makes of it"); empty without a planned input or with ``bias_max`` 0."""
        if not self.filters:
            return np.zeros(0)
        key = ("b", _key(kept))
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        cb = self.cb
        cols = np.r_[np.arange(cb.n_m), cb.n_m + np.sort(np.asarray(kept, int))].astype(int)
        ms, var, nu = [], [], []
        for fs in self.filters:
            a, b, c = fs.bias(cols)
            ms.append(a)
            var.append(b)
            nu.append(c.sum())
        v = np.mean(var, axis=0)
        v = np.where(v > 0, v, np.inf)
        out = np.mean(ms, axis=0) / v
        self._cache[key] = out
        self._cache[("bv", key)] = (np.array(ms) / v, v, np.array(nu))
        return out

    def innovation(self, kept) -> float:
        """The filter requirement's innovation figure with the interior modes ``kept``: the mean square of the steady
        filter's whitened innovations on the linearised full model, summed over the channels, averaged over the
        sampled configurations (:mod:`.truncation`, "What the filter makes of it"); 0 without filter samples."""
        if not self.filters:
            return 0.0
        self.bias(kept)
        return float(self._cache[("bv", ("b", _key(kept)))][2].mean())

    def _excess(self, per: np.ndarray, nu: np.ndarray) -> np.ndarray:
        """Per configuration, the filter requirement's figures over their limits, the largest: ``b`` over
        ``bias_max`` (``per``: configurations x quantities) and the innovations over :data:`INNOVATION_MAX`."""
        return np.maximum(per.max(axis=1) / self.bias_max, np.asarray(nu) / INNOVATION_MAX)

    def filter_excess(self, kept) -> float:
        """The filter requirement with ``kept``, its figures over their limits, the largest (met at most 1): every
        quantity's ``b`` over ``bias_max`` and the innovations over :data:`INNOVATION_MAX`."""
        if not self.filters:
            return 0.0
        return max(float(self.bias(kept).max()) / self.bias_max, self.innovation(kept) / INNOVATION_MAX)

    def bias_of_basis(self, basis) -> np.ndarray:
        """:meth:`bias` for the basis ``basis(q)`` (a callable giving the full-coordinate basis ``H`` (n, r) at a
        configuration ``q``, e.g. a :class:`.basis.CraigBampton`'s with its static corrections, ``lambda q:
        cb.at(q).H``) at the same configurations, in the same units: the mean over them of the mean-square error
        over the mean of the bound's variance."""
        if not self.filters:
            return np.zeros(0)
        ms, var = [], []
        for t, fs in zip(self.truncation, self.filters):
            a, b, _ = fs.bias_of(basis(t.q))
            ms.append(a)
            var.append(b)
        v = np.mean(var, axis=0)
        return np.mean(ms, axis=0) / np.where(v > 0, v, np.inf)

    def requirement_excess(self, kept, truncation: bool = True) -> float:
        """The requirements with the interior modes ``kept``, their figures over their limits, the largest (every
        requirement met where at most 1): the filter requirement's (:meth:`filter_excess`: ``b`` and the
        innovations, averaged over the configurations as the requirement states them), ``rho`` over ``rho_max`` at
        the worst configuration and, with :attr:`quantity_max`, each estimated tip quantity's truncated RMS over its
        limit at the worst; 0 without a planned input."""
        out = self.filter_excess(kept)
        if truncation and self.truncation and self.rho_max > 0:
            out = max(out, float(self.rho(kept).max()) / self.rho_max)
            if self.quantity_max is not None and self.quantity_max.size:
                out = max(out, float((self.quantities_rms(kept) / self.quantity_max).max()))
        return out

    def excess(self, kept, truncation: bool = True) -> np.ndarray:
        """Per configuration with a truncation figure, the requirements' figures there over their limits, the
        largest: the configuration's share of the filter requirement (its mean square over the mean of the bound's
        variance, its innovations; :meth:`_excess`), its ``rho`` and tip quantities over their limits. Empty without
        a planned input. The search (:meth:`extend_for_bias`) works on the configuration where it is largest."""
        if not self.truncation:
            return np.zeros(0)
        return np.array([self._excess_at(c, kept, None, truncation) for c in range(len(self.truncation))])

    def _excess_at(self, c: int, kept, v: np.ndarray | None = None, truncation: bool = True) -> float:
        """:meth:`excess` at the ``c``-th configuration with a truncation figure; with ``v`` (the bound's variance
        averaged over the configurations, per quantity) only that configuration's filter is run (a candidate's
        score: the mean variance barely moves with one more mode)."""
        out = 0.0
        if self.filters:
            if v is None:
                self.bias(kept)
                per, _, nu = self._cache[("bv", ("b", _key(kept)))]
                out = float(self._excess(per[c][None, :], [nu[c]])[0])
            else:
                cols = np.r_[np.arange(self.cb.n_m), self.cb.n_m + np.sort(np.asarray(kept, int))].astype(int)
                a, _, nu = self.filters[c].bias(cols)
                out = float(self._excess((a / v)[None, :], [nu.sum()])[0])
        if truncation and self.rho_max > 0:
            out = max(out, float(self._windowed_at(c, kept, False)[0].sum()) / self.rho_max)
            if self.quantity_max is not None and self.quantity_max.size:
                out = max(out, float((self._windowed_at(c, kept, True)[1] / self.quantity_max).max()))
        return out

    def extend_for_bias(self, seq: list[int], until_met: bool = False, every_mode: bool = False) -> int:
        """Interior modes added to ``seq`` until every requirement holds at every configuration: the filter
        requirement's (``max bias <= bias_max``, :meth:`bias`; the innovations' figure at most
        :data:`INNOVATION_MAX`, :meth:`innovation`) and the truncation requirement's (``rho <= rho_max`` and the
        estimated tip quantities' limits): :meth:`excess` at most 1. Returns the count.

        The candidates are every interior mode not in ``seq``, judged by their figures on the linearised full model,
        not by frequency: a mode that decays within a sample interval still carries the slaves' quasi-static motion
        and the coordinates' recoil from it, which the channels read (a single link shaken in 50 ms strokes meets the
        filter requirement only with a mode at twice the sample rate, ``docs/reduction.md``). Each step keeps the
        mode that makes the largest figure over its limit smallest at the configuration where it is largest now
        (ties: the IMR order at q*), whether or not it lowers it there: the figures are not monotone in the modes
        kept (a mode whose partner is missing rings at a frequency the truth does not have). With every interior
        mode the basis spans the elastic coordinates and every figure is zero, so continued to the end the search
        always meets the requirements; it stops at the first count that does. Then each mode it added, the last
        first, is dropped where the requirements hold without it: no single added mode can be left out.

        ``until_met`` False (the dynamic modes' stage, before the static corrections, :class:`.basis.CraigBampton`):
        the filter requirement alone, among the modes that ring for a sample interval (:attr:`dynamic`; ``every_mode``:
        every mode); the search also stops where no mode lowers the figure at that configuration by 1 % of its limit
        or three modes in a row lower the largest figure over every configuration by less, and then leaves ``seq``
        as it was (the static corrections may meet the requirements with fewer columns; :attr:`bias_met` False).
        ``until_met`` True (the final basis): every requirement, every mode, no such stop.
        :attr:`bias_tried`: the modes added, in order, before the outcome."""
        tie = np.argsort(-self.scores[0], kind="stable")  # q*'s IMR order
        n0 = len(seq)
        self.bias_tried = []
        if not self.truncation:
            return len(seq)
        best_n, best_b = len(seq), self.requirement_excess(seq, until_met)
        stall = 0
        while best_b > 1.0 and (until_met or stall < 3):
            cands = [int(i) for i in tie if i not in seq and (until_met or every_mode or self.dynamic[i])]
            if not cands:
                break
            j = int(np.argmax(self.excess(seq, until_met)))
            v = self._cache[("bv", ("b", _key(seq)))][1] if self.filters else None
            scores = [self._excess_at(j, seq + [i], v, until_met) for i in cands]
            if not until_met and min(scores) > self._excess_at(j, seq, None, False) - 0.01:
                break  # no mode lowers the figure where it is largest
            seq.append(cands[int(np.argmin(scores))])
            b = self.requirement_excess(seq, until_met)
            if b < best_b - 0.01:
                best_n, best_b, stall = len(seq), b, 0
            else:
                stall += 1
            if b <= 1.0:
                best_n, best_b = len(seq), b
        self.bias_tried = list(seq[n0:])
        self.bias_met = best_b <= 1.0
        del seq[best_n if self.bias_met else n0:]
        if self.bias_met:  # the modes added, the last first, dropped where the requirements hold without them
            for i in reversed(seq[n0:]):
                rest = [k for k in seq if k != i]
                if self.requirement_excess(rest, until_met) <= 1.0:
                    seq.remove(i)
        return len(seq)

    def _match(self, kept) -> list[AccuracyResult]:
        """The accuracy indices (:func:`~.accuracy.match_modes`) of the band's full modes at every sample with the
        interior modes ``kept`` (indices into all of them)."""
        key = _key(kept)
        return [self._match_at(c, key) for c in range(len(self.qs))]

    def _match_at(self, c: int, key: tuple[int, ...]) -> AccuracyResult:
        """:meth:`_match` at sample ``c`` with the interior modes ``key`` (sorted; kept per sample: the forward
        selection asks for the same subsets again)."""
        hit = self._cache.get(("m", c, key))
        if hit is not None:
            return hit
        cb = self.cb
        nq = cb.nq
        q, Mr, Kr, PMH, n1, ff = self.qs[c], self.Mr[c], self.Kr[c], self.PMH[c], self.n1[c], self.band_hz[c]
        cols = np.r_[np.arange(cb.n_m), cb.n_m + np.asarray(key, int)]
        ix = np.ix_(cols, cols)
        try:
            w2, V = sla.eigh(Kr[ix], Mr[ix])
        except np.linalg.LinAlgError:  # a degenerate partition (a global master turned axial): no match
            w2, V = np.zeros(nq), np.zeros((len(cols), nq))
        fr = np.sqrt(np.clip(w2[nq:], 0, None)) / (2 * np.pi)
        Vr = V[:, nq:]
        if not Vr.shape[1]:
            z = np.zeros(len(ff))
            out = AccuracyResult(q, ff, np.full(len(ff), np.inf), z, np.full(len(ff), np.inf))
        else:
            n2 = np.einsum("ij,ik,kj->j", Vr, Mr[ix], Vr)
            nco = (PMH[:, cols] @ Vr) ** 2 / np.outer(n1, n2)
            best = np.argmax(nco, axis=1)
            fr_m = fr[best]
            out = AccuracyResult(q, ff, fr_m, nco[np.arange(len(ff)), best], np.abs(ff - fr_m) / ff * 100.0)
        self._cache[("m", c, key)] = out
        return out

    def evaluate(self, kept) -> list[AccuracyResult]:
        """The accuracy indices of the band's full modes at every sample with the interior modes ``kept``."""
        return self._match(kept)

    def _ringing(self, c: int, kept) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """At sample ``c`` with the interior modes ``kept`` (q held): ``(unfollowed, ms_channels, ms_quantities)``.

        ``unfollowed`` (n_full_modes): the fraction of each full mode's ringing the reduced model does not follow,
        the larger of the shape's part outside its best-matching reduced mode, ``sqrt(1 - NCO)``, and the dephasing
        of a ringing followed at a frequency off by the relative error ``e``: over its decay a ringing
        ``exp(-zeta w t) sin(w t)`` and the same at ``w (1 + e)`` differ by ``e / (sqrt(2) zeta)`` of its RMS (to
        first order in ``e``; at most 1). The reduced model's own modes above the band ring too under the planned
        loads; the part of that ringing no full mode matches (the same fraction, from the reduced mode's side) is
        a response the truth does not have: its series in the channels (whitened, n_t x n_ch) and in the estimated tip
        quantities (n_t x 4) are ``ms_channels``, ``ms_quantities``, subtracted from the truth's side's."""
        key = ("r", c, _key(kept))
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        cb = self.cb
        t = self.truncation[c]
        Mr, Kr, PMH, He = self._locked[c]
        me = cb.n_m - cb.nq
        cols = np.r_[np.arange(me), me + np.sort(np.asarray(kept, int))].astype(int)
        n_ch = t.C_el.shape[0]
        n_qu = 2 * t.tip_el.shape[0]
        n_t = len(t.S)
        if not len(cols):
            out = (np.ones(len(t.frequencies_hz)), np.zeros((n_t, n_ch)), np.zeros((n_t, n_qu)))
            self._cache[key] = out
            return out
        ix = np.ix_(cols, cols)
        try:
            w2, V = sla.eigh(Kr[ix], Mr[ix])
        except np.linalg.LinAlgError:  # a degenerate partition (a global master turned axial): nothing followed
            out = (np.ones(len(t.frequencies_hz)), np.zeros((n_t, n_ch)), np.zeros((n_t, n_qu)))
            self._cache[key] = out
            return out
        fr = np.sqrt(np.clip(w2, 0, None)) / (2 * np.pi)
        nco = (PMH[:, cols] @ V) ** 2 / np.maximum(np.einsum("ij,ik,kj->j", V, Mr[ix], V), 1e-300)[None, :]
        best = np.argmax(nco, axis=1)
        n = nco[np.arange(len(best)), best]
        e = np.abs(fr[best] - t.frequencies_hz) / t.frequencies_hz
        unf = np.maximum(np.sqrt(np.clip(1.0 - n, 0.0, 1.0)), np.minimum(1.0, e / (np.sqrt(2.0) * t.zeta)))
        # the reduced modes above the band, by the same measure from their side
        model = cb.model
        ms_ch, ms_qu = np.zeros((n_t, n_ch)), np.zeros((n_t, n_qu))
        wr = 2 * np.pi * fr
        zr = np.clip(model.alpha / (2 * np.maximum(wr, 1e-12)) + model.beta * wr / 2, 1e-9, 0.999)
        # the reduced modes above the band that ring for at least a sample interval (as :attr:`dynamic`)
        sel = np.flatnonzero((fr > cb.band_hz) & (zr * wr <= model.mech.sample_rate_hz))
        if sel.size:
            jb = np.argmax(nco[:, sel], axis=0)
            wr, zr = wr[sel], zr[sel]
            er = np.abs(t.frequencies_hz[jb] - fr[sel]) / fr[sel]
            v = np.maximum(np.sqrt(np.clip(1.0 - nco[jb, sel], 0.0, 1.0)), np.minimum(1.0, er / (np.sqrt(2.0) * zr)))
            shapes = He[:, cols] @ V[:, sel]  # (ne, k) the reduced modes in the elastic coordinates
            f = t.loads[::2] @ shapes  # the loads held over each sample interval: the sample times, as the truth's side
            eta, eta_d = modal_response(f, wr, zr, 2 * t.dt, rates=True)
            ring = (eta - f / wr**2) * v
            ms_ch = -(ring @ (t.C_el @ shapes).T)  # a response the truth does not have: the truth minus it
            A = t.tip_el @ shapes
            ms_qu = -quantity_columns(ring @ A.T, (eta_d * v) @ A.T, t.n_q)
        out = (unf, ms_ch, ms_qu)
        self._cache[key] = out
        return out

    def _windowed(self, kept, quantities: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per sample, ``(rho_channels, quantities_rms)`` at the worst window (:data:`.truncation.WINDOW_SAMPLES`
        samples): the channels' whitened mean squares in the window where their sum is largest, and (with
        ``quantities``, else empty) each tip quantity's largest RMS over the windows."""
        return [self._windowed_at(c, kept, quantities) for c in range(len(self.truncation))]

    def _windowed_at(self, c: int, kept, quantities: bool) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_windowed` at the ``c``-th sample with a truncation figure."""
        key = ("w", c, quantities, _key(kept))
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        t = self.truncation[c]
        unf, y_ch, y_qu = self._ringing(c, kept)
        n = WINDOW_SAMPLES
        ms = window_mean_square(t.channel_series(kept, unf) + y_ch, n)
        zq = t.quantity_series(kept, unf) if quantities else np.zeros((0, 0))
        qu = np.sqrt(window_mean_square(zq + y_qu, n).max(axis=0)) if zq.shape[1] else np.zeros(0)
        out = (ms[int(np.argmax(ms.sum(axis=1)))], qu)
        self._cache[key] = out
        return out

    def rho(self, kept) -> np.ndarray:
        """Per sample, the truncation figure ``rho`` with the interior modes ``kept``: the whitened mean square of
        the truncated output summed over the channels, in the worst window (empty without a planned input)."""
        return self.rho_channels(kept).sum(axis=1) if self.truncation else np.zeros(0)

    def rho_channels(self, kept) -> np.ndarray:
        """(samples, channels): :meth:`rho` per channel."""
        return np.array([w[0] for w in self._windowed(kept)])

    def quantities_rms(self, kept) -> np.ndarray:
        """(samples, 4): the largest windowed RMS of the truncated part of the estimated tip deflection and rate
        (:meth:`.truncation.TruncationSample.quantity_series`, less the reduced model's unmatched ringing; no
        columns without a tip)."""
        return np.array([w[1] for w in self._windowed(kept, quantities=True)])

    def margins(self, kept, truncation: bool = True) -> np.ndarray:
        """Per sample, the smallest margin to the requirements with the interior modes ``kept``: the thresholds on
        the band's modes (:func:`margin`), ``(rho_max - rho) / rho_max`` and, with :attr:`quantity_max`, the
        estimated tip quantities' ``(max - rms) / max``; ``truncation=False``: the band's thresholds alone."""
        return np.array([self._margin_at(c, kept, truncation) for c in range(len(self.qs))])

    def _margin_at(self, c: int, kept, truncation: bool, above: float = -np.inf) -> float:
        """:meth:`margins` at sample ``c``; once the band's margin is at most ``above``, that margin (the
        truncation's can only lower it: :meth:`_least_margin`)."""
        cb = self.cb
        m = margin(self._match_at(c, _key(kept)), cb.nco_min, cb.freq_error_max_pct)
        j = self._tpos.get(c) if truncation and m > above else None
        if j is not None:
            m = np.minimum(m, (self.rho_max - self._windowed_at(j, kept, False)[0].sum()) / self.rho_max)
            if self.quantity_max is not None and self.quantity_max.size:
                rms = self._windowed_at(j, kept, True)[1]
                m = np.minimum(m, ((self.quantity_max - rms) / self.quantity_max).min())
        return float(m)

    def _least_margin(self, kept, truncation: bool, samples, above: float) -> float:
        """The smallest of :meth:`margins` over ``samples``, or, once the running minimum is at most ``above``,
        that running minimum: a bound the forward selection's candidate cannot beat (the minimum over every sample
        is no larger), so the remaining samples are not evaluated. The selection is the same as with every
        sample's margin; the worst samples first make the bound bite early."""
        least = np.inf
        for c in samples:
            least = np.minimum(least, self._margin_at(c, kept, truncation, above))
            if not least > above:
                break
        return float(least)

    def choose(self, ranking: str, n_max: int | None = None, truncation: bool = True
               ) -> tuple[np.ndarray, int, list[AccuracyResult]]:
        """``(order, n_needed, accuracy)``: the interior modes in the order they are kept, how many the
        requirements need at every sample (module docstring) and the samples' indices with that many.

        ``ranking="imr"``: forward selection; each step keeps the mode that makes the smallest margin over
        the samples largest (ties: the higher score at q*), up to ``n_max`` modes (default: until every
        sample meets the requirements), then the others by their largest score over the samples. Once the band's
        thresholds hold, only modes that ring for a sample interval are candidates (:attr:`dynamic`); the
        automatic count stops where the next raises the worst margin by less than 0.01 (1 % of ``rho_max``)
        (:attr:`truncation_met` False); ``truncation=False``: the band's thresholds alone (a fixed count keeps the
        modes the band needs, as the paper's); the automatic count then adds the filter requirement's modes
        (:meth:`extend_for_bias`). ``"frequency"``: the lowest modes first. Where no count meets the
        band's thresholds at every sample (:attr:`reachable` False; e.g. a global master that becomes a link's
        axial direction), the smallest count meeting them wherever some count does."""
        n_all = self.scores.shape[1]
        self.reachable = True
        self.truncation_met = True
        use = truncation and bool(self.truncation)
        if ranking == "frequency":
            order = np.arange(n_all)
            k = self._need(order, use)
            return order, k, self.evaluate(order[:k])
        tie = np.argsort(-self.scores[0], kind="stable")  # q*'s IMR order
        seq: list[int] = []
        n_needed = None
        band_met = False
        while len(seq) < n_all:
            m = self.margins(seq, use)
            band_met = band_met or bool(self.margins(seq, truncation=False).min() >= 0)
            if n_needed is None and m.min() >= 0:
                n_needed = len(seq)
            if (n_needed is not None and n_max is None) or (n_max is not None and len(seq) >= n_max):
                break
            cands = [int(i) for i in tie if i not in seq and (not band_met or self.dynamic[i] or n_max is not None)]
            if not cands:
                if n_needed is None:
                    n_needed, self.truncation_met = len(seq), False
                if n_max is None:
                    break
                cands = [int(i) for i in tie if i not in seq]
            best, best_m = -1, -np.inf
            worst_first = np.argsort(m, kind="stable")
            for i in cands:
                mi = self._least_margin(seq + [i], use, worst_first, best_m)
                if mi > best_m:
                    best, best_m = i, mi
            if n_needed is None and band_met and use and best_m - m.min() < 0.01:
                n_needed, self.truncation_met = len(seq), False  # the next mode no longer helps: best effort
                if n_max is None:
                    break
            seq.append(best)
        if n_max is None and n_needed is None and len(seq) == n_all and self.margins(seq, use).min() >= 0:
            n_needed = len(seq)  # met only with every mode in
        if n_max is None and n_needed is not None and n_needed == len(seq) > 1 and self.truncation_met:
            # a mode added early can be left out once later ones are in (two modes that meet a requirement only
            # together are added last, after every mode that helps alone): each, the last first, is dropped where
            # every sample still meets the requirements without it
            for i in list(reversed(seq)):
                rest = [k for k in seq if k != i]
                if self.margins(rest, use).min() >= 0:
                    seq.remove(i)
            n_needed = len(seq)
        if use and n_max is None and n_needed is not None and self.filters:
            n_needed = self.extend_for_bias(seq)
        rest = np.argsort(-self.scores.max(axis=0), kind="stable")
        order = np.array(seq + [int(i) for i in rest if i not in set(seq)], int)
        if n_needed is None:  # a fixed count below the need, or every mode: the need by the order's prefixes
            n_needed = self._need(order, use)
        return order, n_needed, self.evaluate(order[:n_needed])

    def _need(self, order: np.ndarray, truncation: bool = True) -> int:
        """The smallest prefix of ``order`` meeting the band's thresholds at every sample where some prefix does
        (:attr:`reachable` False if that is not every sample), and the truncation requirement where a prefix
        does (else the band's need: :attr:`truncation_met` False)."""
        mb = np.array([self.margins(order[:k], truncation=False) for k in range(len(order) + 1)])  # (prefix, sample)
        can = (mb >= 0).any(axis=0)
        self.reachable = bool(can.all())
        band_need = next(k for k in range(len(order) + 1) if np.all(mb[k, can] >= 0))
        if not truncation:
            return band_need
        for k in range(band_need, len(order) + 1):
            if np.all(self.margins(order[:k])[can] >= 0):
                self.truncation_met = True
                return k
        self.truncation_met = False
        return band_need

    def worst_margin(self, kept) -> float:
        """The smallest of :meth:`margins` over the samples."""
        return float(self.margins(kept).min())

"""Configuration-dependent modified Craig-Bampton reduction (the paper's eqs. 4-7).

The full coordinates ``x = [q; u]`` are split into masters ``x_m = [q; u_m]`` (every ERLS
coordinate plus chosen elastic dofs) and slaves ``u_s``. The reduced coordinates are
``p = [q; u_m; eta]`` and

``x = H(q, q*) p``,  ``H = [[I, 0], [B(q), Psi(q, q*)]]``,  ``Psi = R(q, q*) Phi(q*)``

- ``B(q) = -K_ss(q)^-1 K_sm(q)``: the Guyan (static) shapes, recomputed from the stiffness at the
  current configuration. ``K`` has no ``q`` rows, so the columns of ``B`` for the ``q`` masters are zero.
- ``Phi(q*)``: interior (fixed-master) modes of the slave subsystem at the equilibrium ``q*``
  (``K_ss v = w^2 M_ss v``), mass-normalised; a subset of them is kept, chosen by the interior-mode
  ranking (:func:`interior_mode_scores`) or by frequency.
- Masters named in a link's frame (``node5.transverse``, ``node5.axial``; :mod:`exuflex.mechanism.dofs`) are
  components of a node's translation along and across its link at the current q. The partition is then made
  in the coordinates ``w = Q(q)^T u``, where ``Q(q)`` turns the translation pair of every node carrying such a
  master by its link's ERLS angle ``phi(q)`` (every other pair: the identity). The Guyan shapes come from the
  stiffness in those coordinates, ``K_w = Q^T K_uu Q``, the interior modes from ``K_w`` and ``M_w`` at q*, and
  the basis in the global elastic coordinates is ``H_u = Q(q) H_w(q)``: a transverse master stays transverse
  however far its link turns (a global ``node5.y`` master becomes the stiff axial direction after a quarter
  turn). Global names keep ``Q = I`` and the original formulas.
- ``R(q, q*)``: the elastic dofs are global-frame nodal displacements, so an interior mode computed at
  ``q*`` must follow its links: the (x, y) pair of every node is rotated by the change of its link's
  angle, ``theta_link(q) - theta_link(q*)`` (rotations are frame-independent in the plane). A node
  shared by several links (a joint) follows the link that owns its dofs in the numbering; the
  interior modes barely move joint nodes, so the choice does not matter (checked: 0.918-0.920 %
  frequency error over all choices on the six-bar). A pair in a link frame turns with that link; it
  always does (its interior-mode components are constant in ``w``).

Interior-mode ranking (IMR)
---------------------------
Each full-model mode ``j`` in the band of interest, restricted to the slaves, is split into its Guyan
part ``B phi_m,j`` and the remainder ``r_j = phi_s,j - B phi_m,j``, which only interior modes can
represent. Since the interior modes are ``M_ss``-orthonormal, ``c_ij = psi_i^T M_ss r_j`` are the exact
expansion coefficients of ``r_j``; the score of interior mode ``i`` is the fraction of the band modes'
remainders it carries, summed over the band:

``score_i = sum_j c_ij^2 / (r_j^T M_ss r_j)``.

Plain frequency truncation keeps the lowest interior modes instead; it ignores that a low interior mode
can be irrelevant to the band (e.g. a local mode of a link the band modes do not bend) while a higher
one carries most of a band mode's slave motion. On the six-bar at q* the ranked choice of 5 modes
lowers the worst frequency error from 0.92 % to 0.47 % (``benchmarks/reduction_table.py``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ..erls.model import Configuration, ErlsModel
from . import _compiled
from .masters import automatic_masters, reading_masters
from .path import PathSamples, interior_mode_scores, manoeuvre_configurations
from .static import STATIC_MAX, static_corrections
from .truncation import BIAS_MAX, INNOVATION_MAX, TRUNCATION_MAX, PlannedInput

__all__ = ["CraigBampton", "ReducedConfiguration", "interior_mode_scores"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReducedConfiguration:
    """The full configuration at q plus the reduction basis there."""

    cfg: Configuration
    B: np.ndarray  # (s, n_m_elastic) Guyan shapes of the elastic masters (slave rows of w = Q^T u)
    Psi: np.ndarray  # (s, k) rotated interior modes (slave rows of w)
    H: np.ndarray  # (n, r)
    Kuu: np.ndarray | None = None  # (ne, ne) elastic stiffness at q
    Kss_inv: np.ndarray | None = None  # inverse of the slave stiffness block (s, s)

    @property
    def q(self) -> np.ndarray:
        return self.cfg.q


def _truncation_report(samples: PathSamples, planned, kept, rho_max: float) -> dict | None:
    """The truncation requirement's figures with the interior modes ``kept`` at the worst sample
    (:mod:`.truncation`): ``rho`` (the whitened mean-square truncated output summed over the channels), its share per
    channel, the RMS of the tip deflection's truncated part (m), where (q), the limit; the filter requirement's
    ``bias`` per estimated quantity (the steady filter's mean-square error on the linearised full model over the
    bound's variance, "What the filter makes of it"), its limit ``bias_max`` and its value without interior modes,
    ``innovation`` (the steady filter's whitened innovations' mean square summed over the channels) and its limit,
    ``bias_met`` both within their limits;
    ``met``: both requirements hold. None without a planned input. :class:`CraigBampton` reports these of the final
    basis (its static corrections in) and adds ``dynamic``: ``rho``, ``rho_channels``, ``bias``, ``q`` and
    ``n_interior`` of the dynamic modes alone."""
    if not samples.truncation:
        return None
    rho = samples.rho(kept)
    i = int(np.argmax(rho))
    zr = samples.quantities_rms(kept)
    quantities = {k: float(v) for k, v in zip(planned.quantities, zr.max(axis=0))} if zr.size else {}
    met = bool(rho[i] <= rho_max)
    if samples.quantity_max is not None and zr.size:
        met = met and bool(np.all(zr.max(axis=0) <= samples.quantity_max))
    b = samples.bias(kept)
    bias = {k: float(v) for k, v in zip(planned.quantities, b)} if b.size else {}
    nu = samples.innovation(kept) if b.size else None
    bias_met = bool(samples.filter_excess(kept) <= 1.0) if b.size else True
    return {"rho": float(rho[i]), "rho_max": rho_max, "met": met and bias_met,
            "bias": bias, "bias_max": samples.bias_max, "bias_met": bias_met,
            "innovation": nu, "innovation_max": INNOVATION_MAX,
            "bias_without_interior": float(samples.bias([]).max()) if b.size else None,
            "rho_channels": dict(zip(planned.channels, map(float, samples.rho_channels(kept)[i]))),
            "q": samples.truncation[i].q.tolist(), "rho_without_interior": float(samples.rho([]).max()),
            "quantities_rms": quantities,
            "quantity_max": (None if samples.quantity_max is None else
                             {k: float(v) for k, v in zip(planned.quantities, samples.quantity_max)})}


class CraigBampton:
    """The modified Craig-Bampton basis ``H(q, q*)`` of an ERLS model.

    Parameters
    ----------
    model : ErlsModel
    masters : elastic master dof names (e.g. ``("x14", "y15", "theta24", "x25", "y26")`` or
        ``("node9.transverse",)``); the ERLS coordinates are always masters. Default: the model file's
        ``[reduction] masters``, else (and for ``"auto"``) the transverse dofs at the joints and tips
        (:mod:`.masters`); the elastic rotations the coordinates' encoders read are added to either
        (:func:`.masters.reading_masters`).
    q_star : configuration of the interior modes. Default: the model file's ``q_star`` or ``q_ref``.
    n_interior : number of interior modes, or ``"auto"`` (the smallest set meeting ``nco_min`` and
        ``freq_error_max_pct`` for every full mode below ``band_hz``, and the truncation requirement
        ``rho <= truncation_max``, at q* and at every configuration of ``path``, then the filter requirement
        ``bias_max``), or ``None`` (the model file's value, else ``"auto"``).
    ranking : ``"imr"`` (interior-mode ranking) or ``"frequency"`` (lowest modes).
    path : configurations (n, nq) the interior modes are chosen over besides q* (:mod:`.path`); default
        (``None``): ``path_samples`` configurations of the model's manoeuvre; ``False``: q* only.
    channels : the observer's sensor channels (default: :func:`exuflex.sensors.default_channels`): those the
        truncation requirement reads (:mod:`.truncation`: the truncated modes' output under the manoeuvre's planned
        motion, against each channel's noise). The automatic count meets it; a fixed count is kept as given, its
        modes chosen by the band's thresholds alone, and the figure is reported (:attr:`truncation`).
    truncation_max : the requirement's limit on ``rho`` (default :data:`.truncation.TRUNCATION_MAX`; 0: the band
        limit alone).
    quantity_max : the largest RMS of the truncated part of each estimated tip quantity (name -> m or m/s), as
        the observer sets it from its bound (:func:`exuflex.observer.session.make_observer`); None: the channels'
        requirement alone.
    bias_max : the filter requirement's limit (default :data:`.truncation.BIAS_MAX`; 0: off): the automatic count
        also keeps interior modes until the steady filter's mean-square error on the linearised full model under the
        manoeuvre is at most ``bias_max`` times its bound's variance in every estimated quantity (:mod:`.truncation`,
        "What the filter makes of it").
    static_max : the static corrections' limit (default :data:`.static.STATIC_MAX`; 0: none): with the automatic
        count, the interior modes not kept are re-based so that their first vectors are the slaves' quasi-static
        response to the loads the motion can produce, and kept until the largest reading of the rest is at most
        ``static_max`` noise sd in every channel (:mod:`.static`); figures in :attr:`static`.
    """

    def __init__(
        self,
        model: ErlsModel,
        masters=None,
        q_star=None,
        n_interior: int | str | None = None,
        ranking: str = "imr",
        band_hz: float | None = None,
        nco_min: float | None = None,
        freq_error_max_pct: float | None = None,
        path=None,
        path_samples: int = 16,
        channels=None,
        truncation_max: float | None = None,
        quantity_max: dict[str, float] | None = None,
        bias_max: float | None = None,
        static_max: float | None = None,
    ):
        t0 = time.perf_counter()
        spec = model.mech.reduction
        self.model = model
        src = model.mech.source or model.mech.name
        self.nq = model.nq
        qs = q_star if q_star is not None else (spec.q_star or model.mech.q_ref)
        self.q_star = np.asarray(qs, float)
        if self.q_star.shape != (self.nq,):
            raise ValueError(f"{src}: q_star must have {self.nq} entries, got {self.q_star.shape}")
        # the configurations the interior modes (and automatic masters) are chosen over (.path)
        if path is None:
            path = manoeuvre_configurations(model.mech, path_samples)
        elif path is False:
            path = None
        q_samples = self.q_star[None, :]
        if path is not None:
            path = np.atleast_2d(np.asarray(path, float))
            if path.shape[1:] != (self.nq,):
                raise ValueError(f"{src}: path configurations must have {self.nq} entries each, got {path.shape}")
            q_samples = np.vstack([q_samples, path])
        masters = tuple(spec.masters if masters is None else ([masters] if isinstance(masters, str) else masters))
        if masters == ("auto",):
            masters = ()
        # none named (or "auto"): the transverse dofs at the joints and tips (.masters)
        self.automatic_masters = not masters
        if not masters:
            masters = automatic_masters(model, q_samples)
            if not masters:
                raise ValueError(f"{src}: no elastic master dofs given (model file [reduction] masters or --masters) "
                                 "and no joint off the ground or free tip to choose them at")
        try:
            refs = [model.dofs.locate(m) for m in masters]
        except KeyError as e:
            raise KeyError(f"{src}: reduction master: {e.args[0]}") from None
        im = [r.index for r in refs]
        if len(set(im)) != len(im):
            raise ValueError(f"{src}: reduction masters repeat a dof: {list(masters)}")
        # the elastic rotations the coordinates' encoders read are masters whatever was named (.masters)
        extra = [model.dofs.locate(m) for m in reading_masters(model)]
        refs += [r for r in extra if r.index not in set(im)]
        masters = tuple(masters) + tuple(r.name for r in extra if r.index not in set(im))
        im = [r.index for r in refs]
        self.masters = masters
        self.im = np.array(im, int)
        self.is_ = np.array([k for k in range(model.ne) if k not in set(im)], int)
        self._ix_ss, self._ix_sm = np.ix_(self.is_, self.is_), np.ix_(self.is_, self.im)  # slave blocks of K_w
        # slave rows of T^T times the element scatter map: dK_N/dq w projected on the slaves (basis_derivative)
        TtS = model.T.T @ model.scatter
        self._TtS_s = np.ascontiguousarray(TtS[self.is_])
        self._TtS = np.ascontiguousarray(TtS)
        # basis_derivative in one compiled call (:mod:`._compiled`) where numba is installed; False: NumPy
        self.compiled = _compiled.HAVE_NUMBA
        # R(q, q*): the interior modes turn with their nodes (the paper's modification); False keeps Phi(q*)
        # fixed in the global frame (to show what the rotation buys)
        self.rotate = True
        self.n_m = self.nq + len(im)
        self.band_hz = float(spec.band_hz if band_hz is None else band_hz)
        self.nco_min = float(spec.nco_min if nco_min is None else nco_min)
        self.freq_error_max_pct = float(spec.freq_error_max_pct if freq_error_max_pct is None else freq_error_max_pct)
        if ranking not in ("imr", "frequency"):
            raise ValueError(f"ranking must be 'imr' or 'frequency', got {ranking!r}")
        self.ranking = ranking
        self._pairs_setup(refs)
        # interior modes at q*, in the partition's coordinates w = Q(q*)^T u
        self.cfg_star = model.configuration(self.q_star)
        M = model.mass(self.cfg_star)
        K = model.stiffness(self.cfg_star)
        nq = self.nq
        qc, qs = self._frame_cs(self.cfg_star)
        Muu = self._congruence(M[nq:, nq:], qc, qs)
        Kuu = self._congruence(K[nq:, nq:], qc, qs)
        s_ = self.is_
        w2, Phi = sla.eigh(Kuu[np.ix_(s_, s_)], Muu[np.ix_(s_, s_)])
        self.interior_frequencies_hz = np.sqrt(np.clip(w2, 0, None)) / (2 * np.pi)
        self.Phi_all = Phi  # (s, s), M_ss-orthonormal, ascending frequency
        self._theta_star = self.cfg_star.pose.r[2::3].copy()
        # the interior modes' order and count, chosen at q* and along the path (.path)
        self.order = np.arange(Phi.shape[1])
        self.set_interior(Phi.shape[1])
        if n_interior is None:
            n_interior = spec.n_interior if spec.n_interior is not None else "auto"
        # the truncation requirement (.truncation): what the filter needs of the manoeuvre's motion; the automatic
        # count meets it, a fixed count is the user's (its figure is reported)
        self.truncation_max = TRUNCATION_MAX if truncation_max is None else float(truncation_max)
        auto = n_interior == "auto"
        # a fixed count's figure is computed when asked for (:attr:`truncation`)
        planned = PlannedInput.of(model.mech, channels) if self.truncation_max > 0 and auto else None
        self.bias_max = BIAS_MAX if bias_max is None else float(bias_max)
        samples = PathSamples(self, q_samples, planned, self.truncation_max, quantity_max, self.bias_max)
        self._truncation_args = (q_samples, channels, quantity_max)
        self.scores = samples.scores[0]  # IMR scores at q*
        self.order, n_needed, _ = samples.choose(ranking, None if n_interior == "auto" else int(n_interior),
                                                 truncation=n_interior == "auto")
        self.path_q = q_samples  # q* and the path's configurations the choice was made on
        if n_interior is None:
            n_interior = spec.n_interior if spec.n_interior is not None else "auto"
        if n_interior == "auto":
            n_interior = n_needed
        n_interior = int(n_interior)
        if not 0 <= n_interior <= Phi.shape[1]:
            raise ValueError(f"{src}: n_interior must be in 0..{Phi.shape[1]} (number of slaves), got {n_interior}")
        self.set_interior(n_interior)
        self.path_accuracy = samples.evaluate(self.kept)  # at q* and every path configuration
        self._truncation = _truncation_report(samples, planned, self.kept, self.truncation_max) if auto else False
        missed = [a for a in self.path_accuracy if not a.ok(self.nco_min, self.freq_error_max_pct)]
        if missed:
            a = min(missed, key=lambda a: a.worst_nco)
            hint = (f"'auto' would keep {n_needed}" if samples.reachable else
                    "no choice of interior modes meets them there (global masters such as node5.y turn into a "
                    "link's axial direction; link-frame masters such as node5.transverse do not)")
            log.warning("%s: %d interior modes miss the accuracy thresholds at %d of %d sampled configurations "
                        "(worst NCO %.4f at q = %s); %s", src, n_interior, len(missed), len(self.path_accuracy),
                        a.worst_nco, np.round(a.q, 4).tolist(), hint)
        # the static corrections (.static): the modes not kept re-based on the slaves' quasi-static response to the
        # motion's loads, the count by their largest reading at the channels
        self.static_max = STATIC_MAX if static_max is None else float(static_max)
        self.static = None
        self.n_static = 0
        self.bias_tried: list[int] = []  # the modes the requirements' search tried (.path.PathSamples.extend_for_bias)
        args = (samples, q_samples, planned, quantity_max)
        n_interior_dynamic = n_interior
        first = self._state()
        if auto:
            n_interior = self._finish(n_interior, *args)
        if auto and samples.filters and not samples.bias_met and self.static_max > 0:
            # the dynamic modes that ring for a sample interval did not meet the filter requirement, so the static
            # corrections were left to: the same search over every interior mode (.path.PathSamples.extend_for_bias)
            # may meet it with the dynamic modes; of the two final bases the one with fewer columns is kept
            kept = self._state()
            self._restore(first)
            seq = [int(i) for i in self.order[:n_interior_dynamic]]
            samples.extend_for_bias(seq, every_mode=True)
            # the static corrections and the final search only add columns: a dynamic count already at the first
            # basis' count cannot give fewer
            if samples.bias_met and n_interior_dynamic < len(seq) < n_interior:
                self.order = np.array(seq + [int(i) for i in self.order if int(i) not in set(seq)], int)
                self.set_interior(len(seq))
                self._truncation = _truncation_report(samples, planned, self.kept, self.truncation_max)
                n_alt = self._finish(len(seq), *args)
                if n_alt < n_interior:
                    n_interior = n_alt
                else:
                    self._restore(kept)
            else:
                self._restore(kept)
        if auto and isinstance(self._truncation, dict):
            tr = self._truncation
            if not missed and not tr["met"]:
                bad = [f"rho = {tr['rho']:.3g} (limit {tr['rho_max']:.3g}; "
                       + ", ".join(f"{c} {v:.2g}" for c, v in tr["rho_channels"].items()) + ") in the channels"
                       ] if tr["rho"] > tr["rho_max"] else []
                if not tr["bias_met"]:
                    worst = max(tr["bias"], key=tr["bias"].get)
                    bad.append(f"a steady filter's mean-square error of {tr['bias'][worst]:.3g} x its bound's "
                               f"variance in {worst} (limit {tr['bias_max']:.3g}) and whitened innovations of mean "
                               f"square {tr['innovation']:.3g} over the channels (limit {tr['innovation_max']:.3g}) "
                               "on the linearised full model")
                log.warning("%s: %d interior modes (%d of them static corrections) leave %s under the manoeuvre "
                            "(.truncation) although their search ran to every interior mode (the figures are "
                            "linearised estimates, zero with every mode to roundoff)",
                            src, n_interior, self.n_static, " and ".join(bad))
        if self.static is not None and not self.static.met:
            st = self.static
            log.warning("%s: %d static corrections leave a quasi-static reading of %.3g noise sd in %s (limit %.3g) "
                        "under the loads the inputs can produce (.static); no further correction lowers it", src,
                        st.n, st.figure[st.n], st.worst[st.n][0], st.limit)
        self.build_seconds = time.perf_counter() - t0
        log.info("Craig-Bampton basis: %d masters + %d interior modes (%s; %d of them static corrections), built in "
                 "%.3f s", self.n_m, n_interior, ranking, self.n_static, self.build_seconds)

    def _state(self) -> dict:
        """The interior basis' state the automatic count sets (:meth:`_finish`), to try another count."""
        keys = ("Phi_all", "interior_frequencies_hz", "order", "static", "n_static", "bias_tried", "_truncation",
                "path_accuracy", "n_interior")
        return {k: getattr(self, k) for k in keys}

    def _restore(self, state: dict) -> None:
        """Back to a :meth:`_state`."""
        for k, v in state.items():
            setattr(self, k, v)
        self.set_interior(state["n_interior"])

    def _finish(self, n_interior: int, samples: PathSamples, q_samples, planned, quantity_max):
        """The automatic count's last steps on the dynamic modes ``self.kept`` (``n_interior`` of them): the static
        corrections (:mod:`.static`), then the requirements on the final basis, modes added among the re-based ones
        until they hold (:meth:`.path.PathSamples.extend_for_bias`). Sets the basis; returns the count."""
        n_dynamic = n_interior
        if planned is not None and self.static_max > 0:
            self.static = static_corrections(self, self.kept, q_samples, planned, quantity_max, self.static_max)
        if self.static is not None and self.static.n:
            st = self.static
            self.Phi_all = st.Phi
            self.interior_frequencies_hz = np.sqrt(np.clip(st.w2, 0, None)) / (2 * np.pi)
            new = [int(i) for i in st.rest[: st.n]]
            self.order = np.array([int(i) for i in self.order[:n_interior]] + new
                                  + [int(i) for i in self.order[n_interior:] if int(i) not in set(new)], int)
            self.n_static = st.n
            n_interior += st.n
            self.set_interior(n_interior)
        dynamic = self._truncation
        final = samples
        if isinstance(dynamic, dict):
            # the requirements on the basis the observer uses: the static corrections carry quasi-static slave motion
            # the dynamic modes leave out (a relative motor's reaction on the other link's node) and enter the
            # filter's model as every other column does. Where the requirements are still not met there, modes are
            # added among every re-based mode until they are (.path.PathSamples.extend_for_bias)
            if self.n_static:
                self.set_interior(len(self.order))  # every interior mode, ascending (as PathSamples wants)
                final = PathSamples(self, q_samples, planned, self.truncation_max, quantity_max, self.bias_max)
            seq = [int(i) for i in self.order[:n_interior]]
            self.bias_tried = list(samples.bias_tried)
            if final.filters:
                final.extend_for_bias(seq, until_met=True)
                self.bias_tried += final.bias_tried
            self.order = np.array(seq + [int(i) for i in self.order if int(i) not in set(seq)], int)
            if len(seq) != n_interior or self.n_static:
                n_interior = len(seq)
                self.set_interior(n_interior)
                self.path_accuracy = final.evaluate(self.kept)
            self._truncation = tr = _truncation_report(final, planned, self.kept, self.truncation_max)
            tr["dynamic"] = {k: dynamic[k] for k in ("rho", "rho_channels", "bias", "innovation", "q")}
            tr["dynamic"]["n_interior"] = n_dynamic
        return n_interior

    @property
    def truncation(self) -> dict | None:
        """The truncation requirement's figures with the kept interior modes (:func:`_truncation_report`; None
        without a manoeuvre, computable torques or noisy channels, or with ``truncation_max`` 0)."""
        if self._truncation is False:
            q_samples, channels, quantity_max = self._truncation_args
            planned = PlannedInput.of(self.model.mech, channels) if self.truncation_max > 0 else None
            n = self.n_interior
            self.set_interior(len(self.order))  # every interior mode, ascending (as :class:`.path.PathSamples` wants)
            try:
                samples = PathSamples(self, q_samples, planned, self.truncation_max, quantity_max, self.bias_max)
            finally:
                self.set_interior(n)
            self._truncation = _truncation_report(samples, planned, self.kept, self.truncation_max)
        return self._truncation

    # ------------------------------------------------------------------ setup
    def _pairs_setup(self, refs):
        """(x, y) pairs of elastic dofs owned by one node: rotated together by R(q, q*), and by Q(q) where a
        master names the pair in a link frame (the pair then turns with that node's link)."""
        model = self.model
        src = model.mech.source or model.mech.name
        by_node: dict[int, dict[str, int]] = {}
        for k, (node, comp) in enumerate(model.dofs.free):
            by_node.setdefault(node, {})[comp] = k
        node_pos = {n: i for i, n in enumerate(model.mech.node_ids)}
        frame: dict[int, tuple[int | None, str]] = {}  # pair x index -> (frame node, the master naming it)
        for r in refs:
            if r.pair is None:
                continue
            prev = frame.get(r.pair[0])
            if prev is not None and prev[0] != r.frame_node:
                raise ValueError(f"{src}: reduction masters {prev[1]!r} and {r.name!r} name the same nodal "
                                 "translation in different frames; name both in one frame (x/y, or "
                                 "axial/transverse of one node)")
            frame[r.pair[0]] = (r.frame_node, r.name)
        px, py, pn, loc = [], [], [], []
        for node, comps in by_node.items():
            if "x" in comps and "y" in comps:
                fn = frame.get(comps["x"], (None, ""))[0]
                px.append(comps["x"])
                py.append(comps["y"])
                pn.append(node_pos[node if fn is None else fn])
                loc.append(fn is not None)
        self._px, self._py, self._pnode = np.array(px, int), np.array(py, int), np.array(pn, int)
        self._plocal = np.array(loc, bool)
        self.has_local = bool(self._plocal.any())
        # rows whose interior-mode rotation enters H: the slaves, and both components of a link-frame pair
        keep = np.zeros(model.ne, bool)
        keep[self.is_] = True
        keep[self._px[self._plocal]] = keep[self._py[self._plocal]] = True
        self._keep = keep

    def _frame_cs(self, cfg: Configuration) -> tuple[np.ndarray, np.ndarray]:
        """Cosine and sine of Q(q) per node pair: the link angle of a link-frame pair, 0 for the others."""
        phi = np.where(self._plocal, cfg.pose.r[2::3][self._pnode], 0.0)
        return np.where(self._plocal, np.cos(phi), 1.0), np.where(self._plocal, np.sin(phi), 0.0)

    def _to_frame(self, X: np.ndarray, c: np.ndarray, s: np.ndarray, inverse: bool = False) -> np.ndarray:
        """``Q^T X`` (``inverse``: ``Q X``) for elastic-coordinate rows ``X`` (ne, ...)."""
        if not self.has_local:
            return X
        X = np.array(X, float)
        px, py = self._px, self._py
        sh = (-1,) + (1,) * (X.ndim - 1)
        c, s = c.reshape(sh), (-s if inverse else s).reshape(sh)
        A, Bm = X[px].copy(), X[py].copy()
        X[px] = c * A + s * Bm
        X[py] = -s * A + c * Bm
        return X

    def _congruence(self, A: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        """``Q^T A Q`` for a symmetric elastic-coordinate matrix ``A`` (``A`` itself without link-frame pairs)."""
        if not self.has_local:
            return A
        return np.ascontiguousarray(self._to_frame(self._to_frame(A, c, s).T, c, s))

    def frame_rotation(self, q_or_cfg) -> np.ndarray:
        """Q(q) as a (ne, ne) matrix: ``u = Q w`` from the partition's coordinates ``w`` (link-frame pairs
        along and across their links) to the global elastic coordinates ``u``."""
        cfg = q_or_cfg if isinstance(q_or_cfg, Configuration) else self.model.configuration(q_or_cfg)
        c, s = self._frame_cs(cfg)
        return self._to_frame(np.eye(self.model.ne), c, s, inverse=True) if self.has_local else np.eye(self.model.ne)

    def master_values(self, q_or_cfg, u: np.ndarray) -> np.ndarray:
        """The elastic master coordinates of global elastic displacements ``u`` (ne,) at a configuration:
        ``(Q(q)^T u)[masters]``."""
        cfg = q_or_cfg if isinstance(q_or_cfg, Configuration) else self.model.configuration(q_or_cfg)
        c, s = self._frame_cs(cfg)
        return self._to_frame(np.asarray(u, float), c, s)[self.im]

    def set_interior(self, k: int) -> None:
        """Keep the first ``k`` interior modes in ranking order."""
        self.kept = np.sort(self.order[:k])
        self.Phi = self.Phi_all[:, self.kept]
        self.n_interior = k
        self.r = self.n_m + k
        # Phi expanded to u = Q(q*) w (zeros at masters), used by the rotation
        Pu = np.zeros((self.model.ne, k))
        Pu[self.is_] = self.Phi
        self._Phi_u = np.ascontiguousarray(self._to_frame(Pu, *self._frame_cs(self.cfg_star), inverse=True))

    # ------------------------------------------------------------------ basis
    def _guyan(self, Kuu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Guyan shapes ``B = -K_ss^-1 K_sm`` and ``K_ss^-1`` (kept for :meth:`basis_derivative`). The slave block
        is small (22 x 22 on the six-bar) and well conditioned (condition number 6e5 there): an explicit inverse
        costs less than an LU factorisation's call overhead and is reused as two matrix products."""
        Kinv = np.linalg.inv(Kuu[self._ix_ss])
        return -(Kinv @ Kuu[self._ix_sm]), Kinv

    def _pair_angles(self, cfg: Configuration) -> np.ndarray:
        """Rotation of each interior-mode node pair from q* (zero with ``rotate`` off, except link-frame pairs,
        which always turn with their link)."""
        dth = cfg.pose.r[2::3][self._pnode] - self._theta_star[self._pnode]
        return dth if self.rotate else np.where(self._plocal, dth, 0.0)

    def _pair_rates(self, cfg: Configuration) -> np.ndarray:
        """``d theta / dq`` (pairs, nq) of the pairs that turn (zero rows for those that do not)."""
        Sn = cfg.pose.S[2::3][self._pnode]
        return Sn if self.rotate else np.where(self._plocal[:, None], Sn, 0.0)

    def rotation(self, cfg: Configuration) -> np.ndarray:
        """R(q, q*) as a (ne, ne) matrix acting on global-frame elastic displacement vectors."""
        ne = self.model.ne
        Rm = np.eye(ne)
        dth = self._pair_angles(cfg)
        c, s = np.cos(dth), np.sin(dth)
        px, py = self._px, self._py
        Rm[px, px], Rm[px, py], Rm[py, px], Rm[py, py] = c, -s, s, c
        return Rm

    def rotated_modes(self, cfg: Configuration) -> np.ndarray:
        """Psi(q, q*) = Q(q)^T R(q, q*) Phi(q*), slave rows of w (s, k)."""
        dth = self._pair_angles(cfg)
        c, s = np.cos(dth)[:, None], np.sin(dth)[:, None]
        P = self._Phi_u.copy()
        X, Y = self._Phi_u[self._px], self._Phi_u[self._py]
        P[self._px] = c * X - s * Y
        P[self._py] = s * X + c * Y
        return self._to_frame(P, *self._frame_cs(cfg))[self.is_]

    def at(self, q_or_cfg, z0=None) -> ReducedConfiguration:
        """The basis H(q, q*) at a configuration (``q`` array or a full-model Configuration)."""
        cfg = q_or_cfg if isinstance(q_or_cfg, Configuration) else self.model.configuration(q_or_cfg, z0)
        nq, ne = self.nq, self.model.ne
        T = self.model.T
        qc, qs = self._frame_cs(cfg)
        if self.compiled:
            dth = self._pair_angles(cfg)
            Kuu, B, Kinv, Psi, H = _compiled.basis_at(cfg.K_N, self.model.t_index, ne, nq, self.im, self.is_,
                                                      self._Phi_u, self._px, self._py, np.cos(dth), np.sin(dth),
                                                      qc, qs, self.has_local)
            return ReducedConfiguration(cfg, B, Psi, H, Kuu, Kinv)
        Kuu = T.T @ cfg.K_N @ T
        B, Kinv = self._guyan(self._congruence(Kuu, qc, qs))  # K_w = Q^T K_uu Q
        Psi = self.rotated_modes(cfg)
        H = np.zeros((nq + ne, self.r))
        H[:nq, :nq] = np.eye(nq)
        me = len(self.im)
        H[nq + self.im, nq : nq + me] = np.eye(me)
        H[nq + self.is_, nq : nq + me] = B
        H[nq + self.is_, nq + me :] = Psi
        H[nq:] = self._to_frame(H[nq:], qc, qs, inverse=True)  # H_u = Q H_w
        return ReducedConfiguration(cfg, B, Psi, H, Kuu, Kinv)

    def basis_derivative(self, rc: ReducedConfiguration, V: np.ndarray) -> np.ndarray:
        """``d(H(q) v)/dq`` for each column ``v`` of ``V`` (r, k): array (k, n, nq), exact.

        Only the slave rows depend on q: ``d(B u_m)/dq_i = -K_ss^-1 (dK_uu/dq_i w)_s`` with ``w`` the Guyan
        field ``[u_m; B u_m]`` (``dK_N/dtheta_e = R (G K - K G) R^T`` per element), and
        ``d(Psi eta)/dq_i = G2 (Psi eta)`` per node pair, times ``d theta_node / dq_i``.
        """
        model = self.model
        cfg = rc.cfg
        nq, ne, me = self.nq, model.ne, len(self.im)
        V = np.atleast_2d(np.asarray(V, float).T).T
        qc, qs = self._frame_cs(cfg)
        if self.compiled:
            dth = self._pair_angles(cfg)
            Sn = np.ascontiguousarray(self._pair_rates(cfg))
            return _compiled.basis_derivative(
                np.ascontiguousarray(V), nq, ne, self.im, self.is_, np.ascontiguousarray(rc.B), model.t_index,
                model.el_dofs, cfg.R, model.KGl, np.ascontiguousarray(cfg.pose.Sz[2::3][model.el_link]),
                np.asfortranarray(rc.Kss_inv), np.cos(dth), np.sin(dth), self._Phi_u, self._px, self._py,
                Sn, rc.Kuu, qc, qs, self._plocal, self._keep, self.has_local)
        k = V.shape[1]
        T = model.T
        # Guyan fields, w (ne, k) in the partition's coordinates, then u = Q w
        W = np.zeros((ne, k))
        W[self.im] = V[nq : nq + me]
        W[self.is_] = rc.B @ V[nq : nq + me]
        W = self._to_frame(W, qc, qs, inverse=True)
        d = T @ W  # nodal (N, k)
        R = cfg.R
        Rt = np.swapaxes(R, 1, 2)
        dl = Rt @ d[model.el_dofs]  # (n_el, 6, k)
        ye = R @ (model.KGl @ dl)  # (n_el, 6, k)
        S_th = cfg.pose.Sz[2::3][model.el_link]  # (n_el, nq)
        C = (ye[:, :, :, None] * S_th[:, None, None, :]).reshape(-1, k * nq)  # (n_el*6, k*nq)
        out = np.zeros((k, nq + ne, nq))
        if not self.has_local:
            # slave rows of T^T (dK_N/dq_i w), column kk*nq + i: the element vectors scattered to the nodes and
            # projected on the slave dofs in one product (T_s^T S, built once)
            rhs = self._TtS_s @ C
            dB = -(rc.Kss_inv @ rhs).reshape(-1, k, nq)  # (s, k, nq)
            out[:, nq + self.is_, :] = dB.transpose(1, 0, 2)
        else:
            # d(Q w_G)/dq_i = D_i u_G + Q (0; dB_w/dq_i w_m) with D_i = dQ/dq_i Q^T (G2 on each link-frame pair
            # times its link's angle rate), and dK_w/dq_i = Q^T (dK_uu/dq_i + K_uu D_i - D_i K_uu) Q
            Sq = np.where(self._plocal[:, None], cfg.pose.S[2::3][self._pnode], 0.0)  # (pairs, nq)
            DW = self._turn(W, Sq).reshape(ne, k * nq)  # D_i u_G, column kk*nq + i
            rhs = self._TtS @ C + rc.Kuu @ DW - self._turn(rc.Kuu @ W, Sq).reshape(ne, k * nq)
            dB = -(rc.Kss_inv @ self._to_frame(rhs, qc, qs)[self.is_])  # (s, k nq)
            dW = np.zeros((ne, k * nq))
            dW[self.is_] = dB
            dW = self._to_frame(dW, qc, qs, inverse=True) + DW
            out[:, nq:, :] = dW.reshape(ne, k, nq).transpose(1, 0, 2)
        # rotated interior modes
        if self.n_interior and (self.rotate or self.has_local):
            dth = self._pair_angles(cfg)
            c, s_ = np.cos(dth)[:, None], np.sin(dth)[:, None]
            Wu = self._Phi_u @ V[nq + me :]  # (ne, k) unrotated
            X, Y = Wu[self._px], Wu[self._py]
            RX, RY = c * X - s_ * Y, s_ * X + c * Y  # rotated
            Sn = self._pair_rates(cfg)  # (n_pairs, nq) d theta_node / dq
            dU = np.zeros((ne, k, nq))
            dU[self._px] = -RY[:, :, None] * Sn[:, None, :]  # G2 applied: (x, y) -> (-y, x)
            dU[self._py] = RX[:, :, None] * Sn[:, None, :]
            rows = np.flatnonzero(self._keep)  # the slaves (and link-frame pairs)
            out[:, nq + rows, :] += dU[rows].transpose(1, 0, 2)
        return out

    def _turn(self, X: np.ndarray, Sq: np.ndarray) -> np.ndarray:
        """``D_i X`` for every q_i (ne, k, nq): G2 = [[0, -1], [1, 0]] applied to each pair of ``X`` (ne, k), times
        the pair's angle rate ``Sq`` (pairs, nq)."""
        out = np.zeros(X.shape + (Sq.shape[1],))
        out[self._px] = -X[self._py][:, :, None] * Sq[:, None, :]
        out[self._py] = X[self._px][:, :, None] * Sq[:, None, :]
        return out

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the reduced coordinates p: q names, elastic masters, eta1..etak."""
        return tuple(self.model.mech.coordinate_names) + self.masters + tuple(f"eta{i + 1}" for i in range(self.n_interior))

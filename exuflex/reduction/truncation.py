"""What the reduced model leaves out of the manoeuvre's own motion, as the observer's channels read it.

The interior modes are kept for the filter's sake: a part of the true motion that no reduced state can represent
reaches the sensors as a signal the filter must explain with its own states (biasing them) or leave in its
innovations (raising the NIS). This module measures that part along the planned manoeuvre and states the
requirement the automatic interior-mode count meets (:mod:`.path`); ``docs/reduction.md`` gives the derivation
with the gallery's figures.

The truncated part of a motion
------------------------------
At a configuration ``q`` the Craig-Bampton coordinates of a full elastic displacement ``u`` (in the partition's
coordinates ``w = Q^T u``, :mod:`.basis`) are exact for the masters, and the slaves split as

``w_s = B w_m + Psi zeta``,  ``zeta = Psi^-1 (w_s - B w_m)``,

with ``Psi`` (s, s) *every* interior mode turned to ``q`` (:meth:`.basis.CraigBampton.rotated_modes`): the interior
modes span the slave space, so ``zeta`` is unique. A basis keeping the set ``K`` of interior modes represents
``u`` up to ``sum_{i not in K} psi_i zeta_i``; the ERLS coordinates ``q`` and the masters are represented
exactly. A Galerkin reduced model reproduces any motion that lies in its basis, so the part outside it is the
truncation error of the motion, to first order in it.

The motion: the manoeuvre's own input
-------------------------------------
At a sampled configuration ``q_c`` of the manoeuvre the full model with its coordinates q held (the plan's q(t)
is what the encoders read) is driven by the planned motion's loads on the elastic coordinates,

``F(t) = G_u u(t) - M_uq(q_c) q''(t) - h_u(q_c, q'(t))`` (:func:`elastic_loads`),

the motor torques ``u(t)`` (:func:`exuflex.manoeuvre.open_loop_torque`), the inertial load of the planned
acceleration and the velocity forces (centrifugal, quadratic in q'), held over a grid of half the sample
interval from rest at ``t = 0``: the trapezoid's steps included. Each elastic mode ``phi_j`` (q held,
mass-normalised, frequency ``w_j``, the model file's Rayleigh ratio ``zeta_j = alpha / (2 w_j) + beta w_j / 2``)
moves as ``eta_j'' + 2 zeta_j w_j eta_j' + w_j^2 eta_j = phi_j^T F(t)``, exactly for a staircase with steps
``df_k`` at ``t_k`` (the oscillator's step response summed, :func:`modal_response`):

``eta_j(t_n) = f_j(t_n) / w_j^2 - Re[(1 - i zeta_j w_j / w_dj) S_n] / w_j^2``,
``S_n = sum_{k <= n} df_k exp((i w_dj - zeta_j w_j)(t_n - t_k))`` (a first-order recursion).

``eta_j = f_j / w_j^2 + r_j``: a quasi-static part and the ringing ``r_j`` after every step.

What the reduced model misses
-----------------------------
- **The quasi-static part's interior content.** ``zeta_qs(t) = sum_j Psi^-1 (phi_j,s - B phi_j,m) f_j(t) /
  w_j^2``, of every full mode: the slaves' deflection ``d = Psi zeta_qs`` between the masters under the motion's
  loads. A Galerkin model's static response to a load is the stiffness-weighted projection of the full one on its
  basis (the Guyan columns are ``K``-orthogonal to every slave-only vector, so the slaves condense apart), so the
  basis keeping ``K`` leaves ``d - V (V' K_ss V)^-1 V' K_ss d`` (``V`` the kept columns of ``Psi``, ``K_ss`` the
  slaves' stiffness at the configuration): for modes that are ``K_ss``-orthogonal, ``sum_{i not in K} psi_i
  zeta_qs,i(t)``; for the static corrections' Ritz vectors (:mod:`.static`), which are not, the projection.
- **Ringing it does not follow.** A full mode above the band rings after each step; the reduced model follows a
  fraction of it: a full mode whose shape lies outside its best-matching reduced mode (NCO), or whose frequency is
  off by ``e`` (its ringing dephases: over its decay a ringing ``exp(-zeta w t) sin(w t)`` and the same at
  ``w (1 + e)`` differ by ``e / (sqrt(2) zeta)`` of its RMS), leaves ``u_j = max(sqrt(1 - NCO), e / (sqrt(2)
  zeta))`` (at most 1) of ``r_j(t)``. The band's modes are the band thresholds' (NCO, frequency error): the filter
  follows their phase through its measurements.
- **Ringing the truth does not have.** The reduced model's own modes above the band ring too under the same
  loads; a reduced mode matching no full mode (a spurious mode between the band and the kept interior modes)
  rings at a frequency the truth has not, the same fraction from the reduced mode's side.

In a channel of row ``c`` (noise std ``sigma``) the three add to ``e(t)``; in the estimated quantities likewise.
The motors are torque-driven, so an elastic motion ``u`` also moves the coordinates by its recoil, ``dq = -M_qq^-1
M_qu u`` (the q rows' momentum balance under unchanged torques), which the encoders read: a channel's row on the
elastic coordinates is ``c_u - c_q M_qq^-1 M_qu``. The estimated quantities are what the observer reports and is
scored on (:func:`quantity_rows`): each coordinate as its encoder reads it, ``q + G u`` (a relative angle's reading
adds the other link's elastic rotation at the joint to the ERLS coordinate,
:meth:`~exuflex.erls.model.ErlsModel.coordinate_reading_rows`), and the tip's elastic displacement from the rigid
tip at the readings, ``A u - J G u``, with their rates.

The requirement
---------------
The figure is the whitened mean square of ``e`` summed over the channels, in the worst window of
:data:`WINDOW_SAMPLES` samples (the observer's NIS test window):

``rho = max_windows sum_channels mean_window (e(t) / sigma)^2``.

A signal of mean square ``rho_k sigma_k^2`` left unexplained raises channel ``k``'s NIS by at most ``rho_k`` over
the window (its innovation variance is at least ``sigma_k^2``); explained, it moves an update's estimate by ``dx =
P C^T S^-1 e`` with ``dx^T P^-1 dx <= e^T R^-1 e`` (the update is an R^-1-weighted projection). :data:`TRUNCATION_MAX`
= 0.1 keeps the windowed NIS within 0.1 of its expectation in all (the observer's test allows 10 % of the channel
count) and a bias of ``b`` posterior standard deviations adds to a consistent filter's error as ``sqrt(1 +
b^2)``, about 1.05x at ``b^2 = 0.1``. A window rather than the whole manoeuvre: the ringing after a step lasts a
few tens of milliseconds, and averaged over a whole manoeuvre it would vanish while the filter meets it at once.
The requirement holds at q* and at every other sampled configuration of the manoeuvre, the worst counting; the
estimated tip quantities' truncated part is reported beside it (``docs/reduction.md``).

What the filter makes of it
---------------------------
The figure above bounds what one update makes of the truncated output; the filter meets it at every sample and
integrates it over its own memory, and the motion above holds the coordinates at the plan while the motors are
torque-driven: the elastic motion the reduced model misses also moves the coordinates, and the filter's error
in them feeds back through its prediction. A two-link arm with a slender steel forearm
(``benchmarks/models/steel_arm.toml``) meets ``rho <= 0.1`` with two interior modes while its observer's error
on a noiseless log of the full model is above its bound (``docs/filter_requirement.md``). So the automatic count
also meets a requirement on what the filter's estimates become:

- **The truth's side.** At each sampled configuration with a truncation figure, the full model linearised at rest
  with its coordinates free, ``M x'' + D x' + K x = G u``, is driven from rest by the torques that give the rigid
  mechanism the planned acceleration there, ``u(t) = G_q^+ M_qq q''(t)`` (``G_q`` the input matrix's coordinate
  rows, ``+`` the least-squares inverse), each held over a sample interval: the trapezoid's steps included, the
  velocity forces left out with the linearisation at rest. The plan's own torques at a frozen configuration would
  give an acceleration the mechanism never has where its inertia changes along the manoeuvre (the slider-crank).
  Discretised exactly (``expm``), its channels ``y = C x`` and estimated quantities ``z`` (the readings, the tip's
  elastic displacement from the rigid tip at the readings, their rates; :func:`quantity_rows`) follow.
- **The filter's side.** The reduced model on the same configuration (``x = H p``: ``H' M H``, ``H' D H``, ``H' K H``,
  ``H' G``, ``C H``), discretised the same way, with the observer's steady Kalman gain (:func:`steady_gain`: the stated
  torque noise held over the interval as process noise, the channels' noise; as the observer's own tuning and the
  bound's) reads ``y`` with the same torques from the same rest state. Its error ``e(t) = Z H p(t) - z(t)`` is what
  the reduction costs the estimates; with every interior mode it is zero (``H`` spans the elastic coordinates).
- **The figure.** On a log with noise, the filter's error is ``e(t)`` plus the noise-driven error, whose variance is
  the bound's ``s^2``; the two are uncorrelated, so an RMS error over the bound becomes ``sqrt(1 + b)`` with ``b =
  mean(e^2) / s^2``. Per estimated quantity, ``b`` is the mean square of ``e`` over the manoeuvre averaged over the
  configurations, over the steady posterior variance ``s^2`` averaged over them (the bound's RMS over poses, as
  the quick estimate of the bound). :data:`BIAS_MAX` ``= 0.1`` keeps every ratio within ``sqrt(1.1) = 1.049`` of the
  filter's on the reduced model itself, a fifth of the ERLS truth's acceptance margin (1.25) and below the
  scatter of a single run's ratio.
- **The innovations.** The same filter's innovations, the channels less its prediction from the last estimate,
  whitened by the channels' noise: on a log with noise they add their mean square to the NIS (the noise-driven
  innovations are uncorrelated with them), so its mean square summed over the channels, averaged over the
  configurations, is what the reduction adds to the NIS summed over the channels. :data:`INNOVATION_MAX` ``=
  TRUNCATION_MAX = 0.1`` keeps the NIS per channel within ``0.1 / n_channels`` of its expectation, against the
  observer's test's 10 %. ``rho`` above is the open-loop part of it, with the coordinates held at the plan; closed
  loop, the filter's own error in the coordinates feeds back through its prediction and the channels read it: on
  ``benchmarks/models/long_two_link.toml`` a basis meeting ``rho`` and ``b`` leaves innovations whose share of the
  observer's NIS on a noiseless log of the full model is what this figure predicts, and one more mode removes
  both (``docs/filter_requirement.md``).

The basis: the requirements are the figures of the basis the observer uses, the dynamic modes and the static
corrections that follow them (:mod:`.static`; :class:`.basis.CraigBampton`): a relative motor's reaction on the
other link's node is a load concentrated at a slave rotation, whose quasi-static response the dynamic modes carry
only in part and the corrections carry (the steel-forearm arm's ``b`` in q1 is above the limit with its dynamic
modes alone, ``docs/reduction.md``). The truncated output's quasi-static part is then the stiffness-weighted
projection's residual (above), which for a modal basis is the modes not kept.

The count: after the band's thresholds and ``rho``, interior modes are added one at a time, each the mode (among
the modes that ring for a sample interval) that makes the largest figure over its limit (every ``b`` over
:data:`BIAS_MAX`, the innovations over :data:`INNOVATION_MAX`) smallest at the configuration where it is largest,
until none is above its limit; where no such mode lowers it by 1 % of its limit the dynamic modes are left to the
static corrections. Then the static corrections, and the requirements on the final basis (``b``, the innovations,
``rho`` and the estimated quantities' limits): modes are added the same way among *every* re-based mode not kept,
whether or not one step lowers the figure, until they hold, and each mode so added is dropped again where the
requirements hold without it. The candidates there are judged by these figures of the linearised full model, not by
frequency: a mode that decays within a sample interval still carries quasi-static slave motion and the
coordinates' recoil from it, which the channels read (a single link shaken in 50 ms strokes,
``benchmarks/models/shaken_link.toml``, meets the filter requirement only with an interior mode at twice its sample
rate). With every interior mode every figure is zero (the basis spans the elastic coordinates), so this search
always ends with the requirements met: the guarantee is that whenever some basis among the candidates meets them
(every one of them does), the count meets them, and no mode the final search added can be left out. Where the
ringing modes did not meet the filter requirement before the static corrections, the same is also tried with every
interior mode as a dynamic-mode candidate, and of the two final bases the one with fewer columns is kept (a modal
mode may replace static corrections whose Ritz vectors ring at frequencies of their own). A mode the input, the
loads and the channels do not couple to changes no figure and is never kept. The search is greedy: it does not
prove that no smaller set exists (``docs/reduction.md`` lists the counts). ``exuflex modes MODEL --reduced`` prints ``b`` per quantity and the innovations' figure (``--json``:
``truncation.bias``, ``truncation.innovation``; the dynamic modes' own in ``truncation.dynamic``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from ..erls.modal import ModalResult
from ..erls.sensing import channel_matrix
from ..manoeuvre import open_loop_torque, plan
from ..mechanism import Mechanism
from ..sensors import default_channels, tip_dof_names, tip_point

__all__ = ["BIAS_MAX", "INNOVATION_MAX", "TRUNCATION_MAX", "WINDOW_SAMPLES", "FilterSample", "PlannedInput", "TruncationSample",
           "elastic_loads", "modal_response", "steady_gain", "truncation_sample", "window_mean_square"]

log = logging.getLogger(__name__)

#: the whitened mean-square truncated output the automatic count allows, summed over the channels (module docstring)
TRUNCATION_MAX = 0.1
#: the largest mean-square bias of an estimated quantity the filter makes of the truncated motion, in units of its
#: bound's mean variance (module docstring, "What the filter makes of it")
BIAS_MAX = 0.1
#: the largest mean square of the steady filter's whitened innovations the truncated motion may leave, summed over
#: the channels (module docstring, "What the filter makes of it"): the NIS per channel rises by it over the channels
INNOVATION_MAX = TRUNCATION_MAX
#: the window (samples) of the mean square: the observer's NIS test window (:class:`exuflex.observer.ekf.NISMonitor`)
WINDOW_SAMPLES = 100


@dataclass(frozen=True)
class PlannedInput:
    """The manoeuvre's open-loop torques and the channels that read the motion.

    ``u`` (n_t, n_motors): the torques on the grid ``t_k = k dt`` (``dt`` half the sample interval), each held over
    its interval, from rest at ``t = 0`` to the manoeuvre's end; ``channels``, their noise std ``noise`` (the
    observer's default channels with a stated noise); ``tip``: the (link, station) of the tip whose elastic
    deflection and rate the observer estimates (:func:`exuflex.sensors.tip_point`), if the model has one;
    ``quantities``: the names of the estimated quantities (:func:`exuflex.sensors.truth_names`: q, q', the tip's).
    """

    u: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    dt: float
    channels: tuple[str, ...]
    noise: np.ndarray
    tip: tuple[str, float] | None = None
    quantities: tuple[str, ...] = ()

    @classmethod
    def of(cls, mech: Mechanism, channels: Sequence[str] | None = None) -> PlannedInput | None:
        """The planned input of ``mech``'s manoeuvre (None without a manoeuvre, motors, noisy channels or
        computable torques)."""
        if mech.manoeuvre is None or not mech.motors:
            return None
        channels = tuple(default_channels(mech) if channels is None else channels)
        sensors = {s.name: s for s in mech.sensors}
        channels = tuple(c for c in channels if c in sensors and sensors[c].noise_std > 0)
        if not channels:
            return None
        dt = 0.5 / mech.sample_rate_hz
        try:
            p = plan(mech, dt=dt, t_end=mech.manoeuvre.duration)
            tau = open_loop_torque(mech, p)
        except Exception as exc:  # noqa: BLE001 - no torques (e.g. a coordinate without a motor): the band alone
            log.info("%s: no open-loop torques for the truncation requirement (%s); the band limit alone",
                     mech.source or mech.name, exc)
            return None
        tip = tip_point(mech)
        qn = tuple(mech.coordinate_names)
        names = qn + tuple("d" + n for n in qn)
        if tip is not None:
            ex, ey = tip_dof_names(mech)
            names += (ex, ey, "d" + ex, "d" + ey)
        return cls(np.asarray(tau, float), p.qd, p.qdd, dt, channels, np.array([sensors[c].noise_std for c in channels]),
                   tip, names)


def modal_response(f: np.ndarray, w: np.ndarray, zeta: np.ndarray, dt: float, rates: bool = False):
    """``eta`` (n_t, modes): the exact response from rest of ``eta'' + 2 zeta w eta' + w^2 eta = f(t)`` to the
    staircase forces ``f`` (n_t, modes), ``f[k]`` held over ``[k dt, (k + 1) dt)``, at ``t_n = n dt`` just after the
    step there (module docstring); ``w`` > 0 (rad/s), ``0 <= zeta < 1``. ``rates``: also ``eta'``, ``(eta, eta')``
    (the step response's rate is ``exp(-zeta w t) sin(w_d t) / w_d``, so ``eta'_n = Im S_n / w_d``)."""
    from scipy.signal import lfilter  # here, not at import: scipy.signal is a large import

    f = np.atleast_2d(np.asarray(f, float))
    df = np.diff(np.vstack([np.zeros((1, f.shape[1])), f]), axis=0)
    wd = w * np.sqrt(1.0 - zeta**2)
    a = np.exp((1j * wd - zeta * w) * dt)
    out = np.empty_like(f)
    rate = np.empty_like(f)
    for j in range(f.shape[1]):
        S = lfilter([1.0], [1.0, -a[j]], df[:, j].astype(complex))
        out[:, j] = (f[:, j] - np.real((1.0 - 1j * zeta[j] * w[j] / wd[j]) * S)) / w[j] ** 2
        rate[:, j] = np.imag(S) / wd[j]
    return (out, rate) if rates else out


def quantity_columns(disp: np.ndarray, rate: np.ndarray, n_q: int) -> np.ndarray:
    """The estimated quantities' columns (q, q', tip deflection, its rate) from displacement-type rows (the
    coordinates' first ``n_q``, then the tip's) and their rates."""
    return np.hstack([disp[:, :n_q], rate[:, :n_q], disp[:, n_q:], rate[:, n_q:]])


def window_mean_square(E: np.ndarray, n: int) -> np.ndarray:
    """(n_t - n + 1, k): the mean of ``E**2`` (n_t, k) over every window of ``n`` consecutive rows (all of them
    when there are fewer)."""
    n = max(1, min(int(n), len(E)))
    c = np.vstack([np.zeros((1, E.shape[1])), np.cumsum(E**2, axis=0)])
    return (c[n:] - c[:-n]) / n


@dataclass(frozen=True)
class TruncationSample:
    """The truncation series at one configuration, for any set of interior modes.

    ``S`` (n_t, n_int + 2 n_modes): the quasi-static interior content (every interior mode, in the basis'
    ascending order), the ringing of every full elastic mode (q held) and its rate; ``Y`` (n_ch, n_int) and ``G``
    (n_ch, n_modes): the channels' rows of the interior modes and of the full modes, divided by the noise std;
    ``Y_tip``, ``G_tip`` (k, ...) the same for the estimated quantities' displacement rows (``tip_el``: the
    coordinates' recoil ``-M_qq^-1 M_qu`` and, with a tip, its elastic deflection), whose rates are the other
    estimated quantities (``n_q`` coordinates);
    ``frequencies_hz``, ``zeta``: the full modes' and their damping ratios; ``ringing_counted``: the modes above the
    band, whose ringing counts where the reduced model does not follow it; ``loads``, ``C_el``, ``tip_el``: the
    planned loads and the rows on the elastic coordinates, for the reduced model's own response
    (:class:`.path.PathSamples`).
    """

    q: np.ndarray
    S: np.ndarray
    Y: np.ndarray
    G: np.ndarray
    Y_tip: np.ndarray | None
    G_tip: np.ndarray | None
    frequencies_hz: np.ndarray
    zeta: np.ndarray
    ringing_counted: np.ndarray
    loads: np.ndarray
    dt: float
    C_el: np.ndarray
    tip_el: np.ndarray | None
    n_q: int = 0
    Kz: np.ndarray | None = None

    def _weights(self, kept, unfollowed) -> tuple[np.ndarray, np.ndarray]:
        """``(W, f)``: the map ``W`` (n_int, n_int) from the interior content ``zeta`` to what the basis keeping
        ``kept`` leaves out of it quasi-statically, ``zeta - P zeta`` with ``P`` the ``Kz``-orthogonal projection on
        the kept coordinates (a Galerkin model's static response is the stiffness-weighted projection; for modes
        that are ``Kz``-orthogonal, the modes not kept: ``W = diag(not kept)``), and the ringing fractions ``f``."""
        n_i = self.Y.shape[1]
        k = np.asarray(kept, int)
        W = np.eye(n_i)
        if k.size == n_i:  # every interior mode: nothing left out
            W[:] = 0.0
        elif k.size and self.Kz is not None:
            W -= np.eye(n_i)[:, k] @ np.linalg.solve(self.Kz[np.ix_(k, k)], self.Kz[k])
        elif k.size:
            W[k, k] = 0.0
        f = np.zeros(self.G.shape[1]) if unfollowed is None else np.where(self.ringing_counted, unfollowed, 0.0)
        return W, f

    def channel_series(self, kept, unfollowed=None) -> np.ndarray:
        """(n_t, n_ch) the truncated output ``e(t) / sigma`` in every channel with the interior modes ``kept``
        (indices) and the fractions ``unfollowed`` (n_modes) of the full modes' ringing the reduced model does not
        follow (None: all followed)."""
        W, f = self._weights(kept, unfollowed)
        n_i, n_m = self.Y.shape[1], self.G.shape[1]
        return self.S[:, :n_i] @ (self.Y @ W).T + self.S[:, n_i : n_i + n_m] @ (self.G * f).T

    def quantity_series(self, kept, unfollowed=None) -> np.ndarray:
        """(n_t, n_quantities) the truncated part of the estimated quantities in :attr:`PlannedInput.quantities`'
        order: the coordinates' recoil (rad, m) and its rate, the tip's elastic deflection (x, y; m) and its rate
        (the rates: the ringing's, the quasi-static part's rate left out)."""
        W, f = self._weights(kept, unfollowed)
        n_i, n_m = self.Y.shape[1], self.G.shape[1]
        ring = self.S[:, n_i : n_i + n_m] * f
        disp = self.S[:, :n_i] @ (self.Y_tip @ W).T + ring @ self.G_tip.T
        rate = (self.S[:, n_i + n_m :] * f) @ self.G_tip.T
        return quantity_columns(disp, rate, self.n_q)


def elastic_loads(model, cfg, inp: PlannedInput) -> np.ndarray:
    """(n_t, ne) the elastic rows of the loads of the planned motion on the mechanism held at ``cfg``'s
    configuration with its elastic coordinates at rest: ``G_u u(t) - M_uq q''(t) - h_u(q'(t))``; ``h_u`` is
    quadratic in ``q'`` and is evaluated from its ``nq (nq + 1) / 2`` coefficient vectors."""
    nq, n = model.nq, model.n
    M = model.mass(cfg)
    F = inp.u @ model.input_matrix(cfg)[nq:].T - inp.qdd @ M[nq:, :nq].T
    x = np.zeros(n)
    x[:nq] = cfg.q

    def h(qd):
        v = np.zeros(n)
        v[:nq] = qd
        return model.velocity_forces(cfg, x, v)[nq:]

    e = np.eye(nq)
    hd = [h(e[i]) for i in range(nq)]
    for i in range(nq):
        F -= inp.qd[:, i : i + 1] ** 2 * hd[i][None, :]
        for j in range(i + 1, nq):
            F -= (inp.qd[:, i] * inp.qd[:, j])[:, None] * (h(e[i] + e[j]) - hd[i] - hd[j])[None, :]
    return F


def quantity_rows(model, cfg, tip) -> tuple[np.ndarray, np.ndarray | None]:
    """``(Zq, Zt)``: the estimated quantities' rows on the elastic coordinates u at ``cfg`` beyond the ERLS
    coordinates (first order): the coordinates as their encoders read them, ``q + G u`` (``Zq = G``,
    :meth:`~exuflex.erls.model.ErlsModel.coordinate_reading_rows`), and the tip's elastic displacement from the rigid
    tip at that reading, ``A u - J G u`` (``Zt``, 2 x ne: ``A`` the tip's displacement rows, ``J`` the rigid tip's
    q-Jacobian; None without a tip) -- what the observer reports (:meth:`exuflex.observer.session.Observer.physical`)."""
    G = model.coordinate_reading_rows()
    if tip is None:
        return G, None
    A = model.point_displacement_rows(cfg, *tip)
    if np.any(G):
        A = A - model.kin.point(cfg.pose, *tip)[1] @ G
    return G, A


def truncation_sample(cb, rc, full: ModalResult, inp: PlannedInput) -> TruncationSample:
    """The :class:`TruncationSample` at ``rc`` (the basis of ``cb`` with every interior mode, at a configuration)
    with the full modes ``full`` there (q held: ``modal_analysis(..., locked=True, hold_readings=False)``), under
    the planned motion ``inp`` (its loads: :func:`elastic_loads`)."""
    model, nq = cb.model, cb.nq
    cfg = rc.cfg
    n_int = rc.Psi.shape[1]
    f_hz = full.frequencies_hz
    phi = full.shapes
    w = 2 * np.pi * f_hz
    zeta = np.clip(model.alpha / (2 * w) + model.beta * w / 2, 0.0, 0.999)
    F = elastic_loads(model, cfg, inp)
    f = F @ phi[nq:]  # (n_t, modes) modal forces
    eta, eta_d = modal_response(f, w, zeta, inp.dt, rates=True)
    quasi = f / w**2
    qc, qs = cb._frame_cs(cfg)
    sh = cb._to_frame(phi[nq:], qc, qs)  # w-frame elastic rows
    r = sh[cb.is_] - rc.B @ sh[cb.im]
    coef = np.linalg.solve(rc.Psi, r)  # (n_int, modes): interior content of each full mode
    # quasi-static interior content, each mode's ringing and its rate (the staircase's quasi-static part is constant
    # over each interval: the ringing's rate is eta')
    S = np.hstack([quasi @ coef.T, eta - quasi, eta_d])
    # the interior modes as full-coordinate vectors (q and master rows zero), u = Q(q) w
    W = np.zeros((model.ne, n_int))
    W[cb.is_] = rc.Psi
    X = np.zeros((model.n, n_int))
    X[nq:] = cb._to_frame(W, qc, qs, inverse=True)
    C = channel_matrix(model, cfg, model.mech, inp.channels) / inp.noise[:, None]
    # the motors are torque-driven: an elastic motion u moves q by its recoil, M_qq dq = -M_qu u (the momentum
    # balance of the q rows under unchanged torques), which the encoders read
    M = model.mass(cfg)
    recoil = -np.linalg.solve(M[:nq, :nq], M[:nq, nq:])  # (nq, ne)
    C_el = C[:, nq:] + C[:, :nq] @ recoil
    # the estimated quantities' displacement rows: the coordinates' recoil and readings and the tip's elastic
    # deflection
    Zq, Zt = quantity_rows(model, cfg, inp.tip)
    Z = recoil + Zq if Zt is None else np.vstack([recoil + Zq, Zt])
    # the series at the sample times (every other point of the grid): what the filter reads
    # the slaves' stiffness in the interior coordinates (the Guyan columns are K-orthogonal to slave-only vectors:
    # a Galerkin model's static response in the slaves is the Kz-weighted projection of zeta)
    Kw = cb._congruence(model.stiffness(cfg)[nq:, nq:], qc, qs)
    Kz = rc.Psi.T @ Kw[np.ix_(cb.is_, cb.is_)] @ rc.Psi
    return TruncationSample(np.asarray(cfg.q, float).copy(), np.ascontiguousarray(S[::2]), C_el @ X[nq:],
                            C_el @ phi[nq:], Z @ X[nq:], Z @ phi[nq:], f_hz, zeta, f_hz > cb.band_hz, F, inp.dt, C_el,
                            Z, nq, 0.5 * (Kz + Kz.T))


def steady_gain(A: np.ndarray, C: np.ndarray, Q: np.ndarray, R: np.ndarray, tol: float = 1e-12,
                max_doublings: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """``(P, K)``: the stationary prior covariance of the Kalman filter of ``x+ = A x + w``, ``y = C x + v`` (``w ~
    N(0, Q)``, ``v ~ N(0, R)``), ``P = A P A' - A P C' (C P C' + R)^-1 C P A' + Q``, and its gain ``K = P C' (C P C'
    + R)^-1``.

    Solved by structure-preserving doubling (Chu, Fan, Lin and Wang 2004, the dual of the control equation): with
    ``A_0 = A'``, ``G_0 = C' R^-1 C``, ``H_0 = Q`` and ``W_k = I + G_k H_k``,
    ``A_k+1 = A_k W_k^-1 A_k``, ``G_k+1 = G_k + A_k W_k^-1 G_k A_k'``, ``H_k+1 = H_k + A_k' H_k W_k^-1 A_k``; ``H_k``
    is the Riccati recursion's covariance after ``2^k`` steps from zero and converges quadratically to ``P``. The
    Schur method (``scipy.linalg.solve_discrete_are``) fails on the reduced models' fast, heavily damped modes
    (eigenvalues of ``A`` near 0); the doubling does not need ``A`` invertible."""
    n = A.shape[0]
    Ak = np.array(A.T, float)
    G = C.T @ np.linalg.solve(R, C)
    H = np.array(Q, float)
    eye = np.eye(n)
    for _ in range(max_doublings):
        W = eye + G @ H
        WA = np.linalg.solve(W, Ak)
        WG = np.linalg.solve(W, G)
        Hn = H + Ak.T @ H @ WA
        G = G + Ak @ WG @ Ak.T
        Ak = Ak @ WA
        done = np.linalg.norm(Hn - H) <= tol * max(np.linalg.norm(Hn), 1e-300)
        H = Hn
        if done:
            break
    P = 0.5 * (H + H.T)
    S = C @ P @ C.T + R
    return P, np.linalg.solve(S, C @ P).T



def _discrete(M, D, K, G, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``(A, B)``: ``M x'' + D x' + K x = G u`` over one interval ``dt`` with ``u`` held, exactly (the matrix
    exponential of the system with its input appended), on the state ``[x; x']``."""
    import scipy.linalg as sla

    n, nu = M.shape[0], G.shape[1]
    Mi = np.linalg.inv(M)
    X = np.zeros((2 * n + nu, 2 * n + nu))
    X[:n, n : 2 * n] = np.eye(n)
    X[n : 2 * n, :n] = -Mi @ K
    X[n : 2 * n, n : 2 * n] = -Mi @ D
    X[n : 2 * n, 2 * n :] = Mi @ G
    E = sla.expm(X * dt)
    return E[: 2 * n, : 2 * n], E[: 2 * n, 2 * n :]


class FilterSample:
    """The steady filter's error on the linearised full model at one configuration (module docstring, "What the
    filter makes of it").

    At ``rc``'s configuration the full model linearised at rest with its coordinates free (torque-driven), ``M x'' +
    D x' + K x = G u``, is driven from rest by the planned torques ``u(t)`` held over each sample interval; its
    channels ``y = C x`` and estimated quantities ``z`` (the coordinates, the tip's elastic deflection, and their
    rates) are computed once. :meth:`bias` runs the reduced model on the coordinates ``cols`` of ``rc.H`` (``x = H
    p``: ``H' M H``, ``H' D H``, ``H' K H``, ``H' G``, ``C H``) as the observer does: its steady Kalman filter (the
    stated torque noise as process noise, the channels' noise) reading ``y`` with the same torques, from the same
    rest state."""

    def __init__(self, model, rc, planned: PlannedInput):
        nq, n, cfg = model.nq, model.n, rc.cfg
        mech = model.mech
        self.dt = 1.0 / mech.sample_rate_hz
        self.H = rc.H
        self.M, self.D, self.K, self.G = model.mass(cfg), model.damping(cfg), model.stiffness(cfg), model.input_matrix(cfg)
        self.C = channel_matrix(model, cfg, mech, planned.channels)
        Zq, Zt = quantity_rows(model, cfg, planned.tip)
        Z = np.hstack([np.eye(nq), Zq])
        if Zt is not None:
            Z = np.vstack([Z, np.hstack([np.zeros((2, nq)), Zt])])
        self.Z = Z
        self.n_q = nq
        self.noise = planned.noise
        self.torque_var = np.array([m.noise_std for m in mech.motors], float) ** 2
        # the torques that give the rigid mechanism the planned acceleration at this configuration, held over each
        # sample interval (least squares where the motors do not span the coordinates)
        step = max(1, round(self.dt / planned.dt))
        self.u = np.linalg.lstsq(self.G[:nq], self.M[:nq, :nq] @ planned.qdd[::step].T, rcond=None)[0].T
        A, B = _discrete(self.M, self.D, self.K, self.G, self.dt)
        x = np.zeros(2 * n)
        Bu = self.u @ B.T
        X = np.empty((len(self.u), 2 * n))
        for k in range(len(self.u)):  # x_k at t_k, then held u_k over [t_k, t_k+1)
            X[k] = x
            x = A @ x + Bu[k]
        self.A, self.B, self.X = A, B, X  # the exact discretisation and the response (the gauge rule reuses them)
        self.y = X[:, :n] @ self.C.T
        self.z = np.hstack([X[:, :n] @ Z.T, X[:, n:] @ Z.T])

    def bias(self, cols) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(ms, var)`` per estimated quantity in :attr:`PlannedInput.quantities`' order: the mean square over the
        manoeuvre of the steady filter's error (its estimate ``Z H p`` minus the full model's ``z``) on the reduced
        coordinates ``cols`` (indices into ``rc.H``'s columns), the filter's steady posterior variance there (the
        bound at this configuration, :func:`steady_gain`), and per channel the mean square of its innovations (the
        full model's channels less the reduced filter's prediction) over the channel's noise variance."""
        return self.bias_of(self.H[:, np.asarray(cols, int)])

    def bias_of(self, Hc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`bias` for any basis ``Hc`` (n, r) at this configuration (full coordinates, the ERLS coordinates
        its first columns), e.g. one with static corrections (:mod:`.static`)."""
        r = Hc.shape[1]
        A, B = _discrete(Hc.T @ self.M @ Hc, Hc.T @ self.D @ Hc, Hc.T @ self.K @ Hc, Hc.T @ self.G, self.dt)
        C = np.hstack([self.C @ Hc, np.zeros((len(self.C), r))])
        Q = (B * self.torque_var) @ B.T
        P, K = steady_gain(A, C, 0.5 * (Q + Q.T), np.diag(self.noise**2))
        ZH = self.Z @ Hc
        k = len(ZH)
        Zr = np.zeros((2 * k, 2 * r))
        Zr[:k, :r] = ZH
        Zr[k:, r:] = ZH
        var = np.einsum("ij,jk,ik->i", Zr, P - K @ C @ P, Zr)
        # the filter: predict with the held torque, update with the full model's channels
        F = (np.eye(2 * r) - K @ C) @ A
        W = self.y @ K.T  # x_j = F x_j-1 + (I - K C) B u_j-1 + K y_j, x_0 = K y_0 (the rest state updated)
        W[1:] += (self.u[:-1] @ B.T) @ (np.eye(2 * r) - K @ C).T
        est = np.empty_like(W)
        x = est[0] = W[0]
        with np.errstate(over="ignore", invalid="ignore"):  # a degenerate partition: no stable filter, figure inf
            for j in range(1, len(W)):
                x = est[j] = F @ x + W[j]
            err = est @ Zr.T - self.z
            ms = (err**2).mean(axis=0)
            # the innovations: the channels less the prediction from the last estimate with its held torque
            prior = np.zeros_like(est)
            prior[1:] = est[:-1] @ A.T + self.u[:-1] @ B.T
            nu = ((self.y - prior @ C.T) / self.noise) ** 2
            nu = nu.mean(axis=0)
        nq = self.n_q
        order = np.r_[np.arange(nq), k + np.arange(nq), np.arange(nq, k), k + np.arange(nq, k)]
        return (np.where(np.isfinite(ms), ms, np.inf)[order], np.clip(var, 0.0, None)[order],
                np.where(np.isfinite(nu), nu, np.inf))


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
At a sampled configuration ``q_c`` of the manoeuvre the linearised full model (motors free, the model file's
Rayleigh damping ratio ``zeta_j = alpha / (2 w_j) + beta w_j / 2`` per mode) is driven by the planned open-loop
torques ``u(t)`` (:func:`exuflex.manoeuvre.open_loop_torque`), held over a grid of half the sample interval and
applied from rest at ``t = 0``, torque steps included. Each elastic mode ``phi_j`` (mass-normalised, frequency
``w_j``) moves as

``eta_j'' + 2 zeta_j w_j eta_j' + w_j^2 eta_j = f_j(t)``,  ``f_j = phi_j^T G(q_c) u(t)``,

exactly, for a staircase ``f_j`` with steps ``df_k`` at ``t_k`` (the step response of the oscillator summed):

``eta_j(t_n) = f_j(t_n) / w_j^2 - Re[(1 - i zeta_j w_j / w_dj) S_n] / w_j^2``,
``S_n = sum_{k <= n} df_k exp((i w_dj - zeta_j w_j)(t_n - t_k))`` (a first-order recursion).

The mechanism's zero-frequency modes are the q directions (``K`` has no q rows), which every basis holds: they
move alike in the full and the reduced model and carry no truncation error. The interior content of the motion
is ``zeta(t) = sum_j Psi^-1 (phi_j,s - B phi_j,m) eta_j(t)``: the quasi-static part (the inertial loads of the
rigid motion deflect the slaves between the masters) and the ringing after every torque step, of *every* full
mode, above the band and above the Nyquist frequency alike (the samples read those aliased).

The requirement
---------------
A channel of row ``c`` (noise std ``sigma``) reads the truncated part as ``e(t) = sum_{i not in K} (c . psi_i)
zeta_i(t)``. The figure is its mean square over the manoeuvre in units of the channel's noise variance, summed over
the channels:

``rho(K) = sum_channels mean_t (e(t) / sigma)^2 = 1_U^T A 1_U``,  ``A = Gamma o (C_w^T C_w)``,

with ``U`` the truncated modes, ``Gamma = mean_t zeta zeta^T`` and ``C_w`` the channels' rows of the interior
modes divided by their noise std (``o``: the element-wise product), so that any set of interior modes is scored
from one small matrix per configuration. Two consequences bound what ``rho`` does to the filter:

- the innovations: a signal of mean square ``rho_k sigma_k^2`` left unexplained raises channel ``k``'s NIS by at
  most ``rho_k`` (its innovation variance is at least ``sigma_k^2``), the total by at most ``rho``;
- the states: an update moves the estimate by ``dx = P C^T S^-1 e``, whose size in the posterior's own metric obeys
  ``dx^T P^-1 dx <= e^T R^-1 e`` (the update is an R^-1-weighted projection); a bias of ``b`` standard deviations
  adds to a consistent filter's error as ``sqrt(1 + b^2)``.

:data:`TRUNCATION_MAX` = 0.1 therefore keeps the NIS within 0.1 of its expectation in all (the observer's NIS test
allows 10 % of the channel count) and an update's bias within sqrt(0.1) = 0.32 standard deviations, an error within
about 1.05x the filter's bound. The requirement holds at every sampled configuration (q* and the manoeuvre's, the
worst counts). The estimated tip deflection's truncated part (``tip`` rows, metres) is reported beside it
(:class:`TruncationSample`): the observer's bound is the filter's, outside the reduction.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from ..erls.modal import ModalResult
from ..erls.sensing import channel_matrix
from ..manoeuvre import open_loop_torque, plan
from ..mechanism import Mechanism
from ..sensors import default_channels

__all__ = ["TRUNCATION_MAX", "PlannedInput", "TruncationSample", "modal_response", "truncation_sample"]

log = logging.getLogger(__name__)

#: the whitened mean-square truncated output the automatic count allows, summed over the channels (module docstring)
TRUNCATION_MAX = 0.1


@dataclass(frozen=True)
class PlannedInput:
    """The manoeuvre's open-loop torques and the channels that read the motion.

    ``u`` (n_t, n_motors): the torques on the grid ``t_k = k dt`` (``dt`` half the sample interval), each held over
    its interval, from rest at ``t = 0`` to the manoeuvre's end; ``channels``, their noise std ``noise`` (the
    observer's default channels with a stated noise); ``tip``: the tip_x and tip_y sensors (the estimated tip
    deflection), if the model has them.
    """

    u: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    dt: float
    channels: tuple[str, ...]
    noise: np.ndarray
    tip: tuple[str, ...] = ()

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
        tip = tuple(s.name for s in mech.sensors if s.kind in ("tip_x", "tip_y"))
        return cls(np.asarray(tau, float), p.qd, p.qdd, dt, channels, np.array([sensors[c].noise_std for c in channels]), tip)


def modal_response(f: np.ndarray, w: np.ndarray, zeta: np.ndarray, dt: float) -> np.ndarray:
    """``eta`` (n_t, modes): the exact response from rest of ``eta'' + 2 zeta w eta' + w^2 eta = f(t)`` to the
    staircase forces ``f`` (n_t, modes), ``f[k]`` held over ``[k dt, (k + 1) dt)``, at ``t_n = n dt`` just after the
    step there (module docstring); ``w`` > 0 (rad/s), ``0 <= zeta < 1``."""
    f = np.atleast_2d(np.asarray(f, float))
    df = np.diff(np.vstack([np.zeros((1, f.shape[1])), f]), axis=0)
    wd = w * np.sqrt(1.0 - zeta**2)
    a = np.exp((1j * wd - zeta * w) * dt)
    out = np.empty_like(f)
    for j in range(f.shape[1]):
        S = lfilter([1.0], [1.0, -a[j]], df[:, j].astype(complex))
        out[:, j] = (f[:, j] - np.real((1.0 - 1j * zeta[j] * w[j] / wd[j]) * S)) / w[j] ** 2
    return out


@dataclass(frozen=True)
class TruncationSample:
    """The truncation figures at one configuration for every set of interior modes.

    ``A`` (n_int, n_int): ``rho(K) = 1_U^T A 1_U`` (module docstring), interior modes in the basis' ascending
    order; ``A_tip`` the same for the tip deflection's two components in m^2 (None without tip sensors);
    ``A_channel`` (n_ch, n_int, n_int) per channel.
    """

    q: np.ndarray
    A: np.ndarray
    A_channel: np.ndarray
    A_tip: np.ndarray | None

    def rho(self, kept) -> float:
        """``rho`` with the interior modes ``kept`` (indices): the whitened mean-square truncated output, summed
        over the channels."""
        u = self._unkept(kept)
        return float(u @ self.A @ u)

    def rho_channels(self, kept) -> np.ndarray:
        """Per channel, its share of :meth:`rho`."""
        u = self._unkept(kept)
        return np.einsum("i,kij,j->k", u, self.A_channel, u)

    def tip_rms(self, kept) -> float:
        """RMS (m) over the manoeuvre of the tip deflection's truncated part (NaN without tip sensors)."""
        if self.A_tip is None:
            return float("nan")
        u = self._unkept(kept)
        return float(np.sqrt(max(u @ self.A_tip @ u, 0.0)))

    def _unkept(self, kept) -> np.ndarray:
        u = np.ones(self.A.shape[0])
        u[np.asarray(kept, int)] = 0.0
        return u


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


def truncation_sample(cb, rc, full: ModalResult, inp: PlannedInput) -> TruncationSample:
    """The :class:`TruncationSample` at ``rc`` (the basis of ``cb`` with every interior mode, at a configuration)
    with the full modes ``full`` there, under the planned input ``inp``."""
    model, nq = cb.model, cb.nq
    cfg = rc.cfg
    n_int = rc.Psi.shape[1]
    f_hz = full.frequencies_hz
    sel = f_hz > 0
    phi = full.shapes[:, sel]
    w = 2 * np.pi * f_hz[sel]
    zeta = np.clip(model.alpha / (2 * w) + model.beta * w / 2, 0.0, 0.999)
    if full.locked:
        F = elastic_loads(model, cfg, inp)  # (n_t, ne)
        eta = modal_response(F @ phi[nq:], w, zeta, inp.dt)
    else:
        eta = modal_response(inp.u @ (model.input_matrix(cfg).T @ phi), w, zeta, inp.dt)  # (n_t, modes)
    qc, qs = cb._frame_cs(cfg)
    sh = cb._to_frame(phi[nq:], qc, qs)  # w-frame elastic rows
    r = sh[cb.is_] - rc.B @ sh[cb.im]
    coef = np.linalg.solve(rc.Psi, r)  # (n_int, modes): interior content of each full mode
    z = eta @ coef.T  # (n_t, n_int)
    gamma = z.T @ z / len(z)
    # the interior modes as full-coordinate vectors (q and master rows zero), u = Q(q) w
    W = np.zeros((model.ne, n_int))
    W[cb.is_] = rc.Psi
    X = np.zeros((model.n, n_int))
    X[nq:] = cb._to_frame(W, qc, qs, inverse=True)
    Cw = channel_matrix(model, cfg, model.mech, inp.channels) @ X / inp.noise[:, None]  # (n_ch, n_int)
    A_ch = gamma[None] * Cw[:, :, None] * Cw[:, None, :]
    A_tip = None
    if inp.tip:
        Ct = channel_matrix(model, cfg, model.mech, inp.tip) @ X
        A_tip = gamma * (Ct.T @ Ct)
    return TruncationSample(np.asarray(cfg.q, float).copy(), A_ch.sum(axis=0), A_ch, A_tip)

"""Measured channels: sampling, white noise and ADC quantisation of clean signals.

The paper (Sec. 4.1, Table 3) corrupts every measured signal, the three motor torques (the observer's
inputs) and the encoder and strain-gauge outputs, with zero-mean white Gaussian noise, and digitises
them with a 24-bit ADC (+-10 V). Here each channel carries

- ``noise_std``: the white-noise standard deviation in the channel's unit
  (:class:`~exuflex.mechanism.Sensor` / :class:`~exuflex.mechanism.Motor`; a manoeuvre's
  ``torque_noise`` overrides a motor's);
- ``full_scale``: the channel value mapped to the ADC's +-10 V. The reading is rounded to the
  quantum ``2 full_scale / 2**24`` and clipped to ``[-full_scale, full_scale - quantum]`` (a
  saturation is logged as a warning). ``None``: no quantisation;
- ``rate_hz``: the sample rate (``None``: the mechanism's ``sample_rate_hz``, 500 Hz for the six-bar).

Time grid
---------
All channels share one *base grid* ``t_k = k / f_base`` with ``f_base`` the mechanism's sample rate
(or the ``rate_hz`` argument), over the span of the clean record (from its first to ``t_end``). A channel with a lower rate ``r`` is sampled at the base-grid instants
nearest to ``m / r`` (m = 0, 1, ...) and holds NaN at the other rows; a rate above the base rate is
an error. Clean channels are linearly interpolated onto the grid (exact when the engine's output grid
contains it); torques are read as the zero-order hold the simulation applied (the table value in
force at ``t_k``).

Randomness: one ``numpy.random.Generator(PCG64(seed))`` draws a standard-normal array
``(n_t, n_channels)`` in column order; the seed is returned with the result so a run can be repeated.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from .mechanism import Mechanism
from .sensors import Signals

__all__ = ["ADC_BITS", "Measurement", "measure", "new_seed", "quantise"]

log = logging.getLogger(__name__)

ADC_BITS = 24  # paper Sec. 4.1: 24-bit ADC


@dataclass(frozen=True)
class Measurement:
    """Measured channels (torques first, then sensors) with the seed and settings that made them."""

    signals: Signals
    seed: int
    settings: dict = field(default_factory=dict)


def new_seed() -> int:
    """A fresh random seed (entropy of a new SeedSequence)."""
    return int(np.random.SeedSequence().entropy)


def quantise(y: np.ndarray, full_scale: float | None, bits: int = ADC_BITS, *, name: str = "") -> np.ndarray:
    """Round ``y`` to the ADC quantum ``2 full_scale / 2**bits``, clipping at the range ends.

    ``full_scale=None`` returns ``y`` unchanged. NaN (not sampled) stays NaN.
    """
    if full_scale is None:
        return y
    if not full_scale > 0:
        raise ValueError(f"channel {name!r}: ADC full_scale must be positive, got {full_scale}")
    step = 2.0 * full_scale / 2**bits
    out = np.round(y / step) * step
    lo, hi = -full_scale, full_scale - step
    with np.errstate(invalid="ignore"):
        n_sat = int(np.sum((out < lo) | (out > hi)))
    if n_sat:
        log.warning("channel %r saturates the ADC (|y| > %g) at %d samples", name, full_scale, n_sat)
    return np.clip(out, lo, hi)


def _sample_mask(t: np.ndarray, base: float, rate: float, name: str) -> np.ndarray:
    if rate > base * (1 + 1e-9):
        raise ValueError(f"channel {name!r}: rate_hz = {rate:g} exceeds the base sample rate {base:g} Hz")
    if abs(rate - base) <= 1e-9 * base:
        return np.ones(len(t), bool)
    inst = np.arange(0.0, t[-1] + 0.5 / base, 1.0 / rate)
    idx = np.clip(np.round(inst * base).astype(int), 0, len(t) - 1)
    mask = np.zeros(len(t), bool)
    mask[idx] = True
    return mask


def measure(
    mech: Mechanism,
    clean: Signals,
    torque_t: np.ndarray,
    torques: np.ndarray,
    *,
    seed: int | None = None,
    noise: bool = True,
    quantisation: bool = True,
    rate_hz: float | None = None,
    t_end: float | None = None,
) -> Measurement:
    """Sample, corrupt and quantise torques and sensor channels.

    Parameters
    ----------
    mech : Mechanism
        Supplies motors, sensors (noise_std, full_scale, rate_hz) and ``sample_rate_hz``.
    clean : Signals
        Clean sensor channels (:func:`exuflex.sensors.sensor_channels`); every sensor of ``mech``.
    torque_t, torques : (n,), (n, n_motors) arrays
        Applied motor torques, held constant from each ``torque_t[i]`` to the next (zero-order hold).
    seed : int, optional
        Seed of the noise generator; a fresh one is drawn (and returned) if None.
    noise, quantisation : bool
        Switch the white noise / the ADC rounding off (for clean logs and tests).
    rate_hz : float, optional
        Base sample rate; defaults to ``mech.sample_rate_hz``.
    t_end : float, optional
        Last sample time; defaults to the last clean time.

    Returns
    -------
    Measurement
        ``signals`` has the columns ``mech.motor_names + sensor names`` on the base grid.
    """
    base = float(rate_hz if rate_hz is not None else mech.sample_rate_hz)
    if not base > 0:
        raise ValueError(f"{mech.source or mech.name}: sample rate must be positive, got {base}")
    t_end = float(clean.t[-1] if t_end is None else t_end)
    if t_end > clean.t[-1] + 1e-9 * max(1.0, t_end):
        raise ValueError(
            f"measure: t_end = {t_end} s is past the last clean sample at {float(clean.t[-1])} s"
        )
    k0 = int(np.ceil(clean.t[0] * base - 1e-6))  # first base-grid instant the engine recorded
    t = np.arange(k0, int(np.floor(t_end * base + 1e-6)) + 1) / base
    torque_t = np.asarray(torque_t, float)
    torques = np.asarray(torques, float).reshape(len(torque_t), -1)
    if torques.shape[1] != len(mech.motors):
        raise ValueError(
            f"{mech.source or mech.name}: {torques.shape[1]} torque columns for motors {list(mech.motor_names)}"
        )
    seed = new_seed() if seed is None else int(seed)
    rng = np.random.Generator(np.random.PCG64(seed))
    n_ch = len(mech.motors) + len(mech.sensors)
    white = rng.standard_normal((len(t), n_ch))
    # zero-order hold of the torque table (tolerance: a sample exactly on a table time reads that entry)
    dt_tab = np.min(np.diff(torque_t)) if len(torque_t) > 1 else 1.0
    i_hold = np.clip(np.searchsorted(torque_t, t + 1e-6 * dt_tab, side="right") - 1, 0, len(torque_t) - 1)
    override = dict(mech.manoeuvre.torque_noise) if mech.manoeuvre is not None else {}
    cols, names, units = [], [], []
    for j, m in enumerate(mech.motors):
        y = torques[i_hold, j].copy()
        std = override.get(m.name, m.noise_std)
        if noise and std:
            y += std * white[:, j]
        if quantisation:
            y = quantise(y, m.full_scale, name=m.name)
        cols.append(y)
        names.append(m.name)
        units.append("N m")
    for i, s in enumerate(mech.sensors):
        if s.name not in clean:
            raise KeyError(f"clean signals lack sensor channel {s.name!r}; they have {list(clean.names)}")
        y = np.interp(t, clean.t, clean[s.name])
        if noise and s.noise_std:
            y = y + s.noise_std * white[:, len(mech.motors) + i]
        if quantisation:
            y = quantise(y, s.full_scale, name=s.name)
        mask = _sample_mask(t, base, float(s.rate_hz or base), s.name)
        y = np.where(mask, y, np.nan)
        cols.append(y)
        names.append(s.name)
        units.append(clean.unit(s.name))
    settings = {"sample_rate_hz": base, "noise": noise, "quantisation": quantisation, "adc_bits": ADC_BITS}
    return Measurement(Signals(t, tuple(names), np.column_stack(cols), tuple(units)), seed, settings)

"""The validity guard (:mod:`exuflex.erls.validity`): links turning fast against their own first clamped frequency.

Oracles: the Euler-Bernoulli cantilever frequency, the spin-up benchmark's measured departure ratio and error
table in ``docs/validity.md`` (the guard's constant and square law must agree with them), the spin-up law's own
rate (when it crosses each threshold).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pytest

from exuflex.erls.validity import (
    DEPARTURE_NRMS,
    DEPARTURE_RATIO,
    WARN_NRMS,
    check_link_rates,
    clamped_frequencies,
    link_rates,
    rate_warnings,
    signal_warnings,
)
from exuflex.mechanism import load_mechanism
from exuflex.sensors import Signals

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
PAGE = (ROOT / "docs" / "validity.md").read_text()


def _spin_law(omega, ts, t):
    """The spin-up benchmark's hub law (benchmarks/spin_up.py): angle and rate at times t."""
    w = 2 * np.pi / ts
    up = t < ts
    th = np.where(up, omega / ts * (t * t / 2 + (np.cos(w * t) - 1) / w**2), omega * (t - ts / 2))
    thd = np.where(up, omega / ts * (t - np.sin(w * t) / w), omega)
    return th, thd


@pytest.fixture(scope="module")
def spin():
    return load_mechanism(MODELS / "spin_up.toml")


def test_departure_ratio_is_the_documented_one():
    """The constant is the benchmark's measured ratio on docs/validity.md, for both forms."""
    m = re.search(r"departure / that: `lagrange` ([0-9.]+), `eq2` ([0-9.]+)", PAGE)
    assert m, "docs/validity.md lost the spin-up departure ratio"
    assert float(m.group(1)) == pytest.approx(DEPARTURE_RATIO, abs=0.005)
    assert float(m.group(2)) == pytest.approx(DEPARTURE_RATIO, abs=0.005)


def test_clamped_frequency_of_the_spin_up_beam(spin):
    """omega_c = 1.8751^2 sqrt(EI / (rho A L^4)) (Euler-Bernoulli cantilever), 10 cubic elements: within 1e-4;
    and the value the page quotes."""
    lk = spin.links[0]
    EI, rhoA = lk.material.E * lk.section.I, lk.material.rho * lk.section.A
    analytic = 1.875104068711961**2 * np.sqrt(EI / (rhoA * lk.length**4))
    wc = clamped_frequencies(spin)["beam"]
    assert wc == pytest.approx(analytic, rel=1e-4)
    m = re.search(r"first clamped-free frequency of the ERLS beam \(hub locked\): ([0-9.]+) rad/s", PAGE)
    assert m and float(m.group(1)) == pytest.approx(wc, abs=0.005)


def test_clamped_frequency_with_a_tip_mass_and_both_ends():
    """A cantilever with a tip mass m_t: the Rayleigh-quotient bound with the static deflection shape,
    omega^2 <= 3 EI / (L^3 (m_t + 33/140 rho A L)), is met from above within 2 %; a link with joints at both ends is
    clamped at each and the lower frequency kept (the tip mass at the free end, not at the clamp)."""
    mech = load_mechanism(MODELS / "single_link.toml")
    lk = mech.links[0]
    EI, rhoA, L = lk.material.E * lk.section.I, lk.material.rho * lk.section.A, lk.length
    mt = mech.payload.mass
    approx = np.sqrt(3 * EI / (L**3 * (mt + 33 / 140 * rhoA * L)))
    wc = clamped_frequencies(mech)["arm"]
    assert approx * 0.98 <= wc <= approx * 1.001


@pytest.mark.parametrize("omega, level", [(0.5, None), (1.0, "approaching"), (1.5, "departed"), (4.0, "unstable")])
def test_spin_up_warns_by_level_naming_the_link_and_time(spin, omega, level, caplog):
    """The benchmark's law (15 s spin-up to omega, 20 s): no warning at 0.5 rad/s (estimated 0.9 %), 'approaching'
    from 0.83 rad/s, 'departed' past 1.18 rad/s (the page's departure), 'unstable' at the clamped frequency; the
    warning's time is when the law's own rate first reaches the threshold (to the sampling step)."""
    t = np.arange(0.0, 20.0 + 1e-9, 0.01)
    th, thd = _spin_law(omega, 15.0, t)
    with caplog.at_level(logging.WARNING, logger="exuflex.erls.validity"):
        ws = rate_warnings(spin, t, th[:, None], thd[:, None])
    if level is None:
        assert ws == [] and not caplog.records
        return
    (w,) = ws
    assert w.link == "beam" and w.level == level
    wc = clamped_frequencies(spin)["beam"]
    threshold = {"approaching": np.sqrt(WARN_NRMS / DEPARTURE_NRMS) * DEPARTURE_RATIO * wc,
                 "departed": DEPARTURE_RATIO * wc, "unstable": wc}[level]
    crossing = t[np.flatnonzero(thd >= threshold)[0]]
    assert w.time_s == pytest.approx(crossing, abs=0.011)
    assert w.peak_rate_rad_s == pytest.approx(omega, rel=1e-9)
    assert "'beam'" in w.message and f"t = {w.peak_time_s:.3g} s" in w.message
    assert any("'beam'" in r.getMessage() for r in caplog.records)
    d = w.as_dict()
    assert d["link"] == "beam" and d["level"] == level and d["message"] == w.message


def test_square_law_follows_the_measured_table(spin):
    """The guard's estimate DEPARTURE_NRMS (Omega / Omega_dep)^2 against the spin-up table on the page (lagrange
    column), speeds below the departure: within 15 % of each measured NRMS."""
    block = PAGE[PAGE.index("<!-- spin_up.py: begin -->"):PAGE.index("<!-- spin_up.py: end -->")]
    rows = re.findall(r"^\| ([0-9.]+) \| ([0-9.]+) \| ([0-9.]+) \|", block, flags=re.MULTILINE)
    wc = clamped_frequencies(spin)["beam"]
    checked = 0
    for speed, lagrange, _ in rows:
        speed, nrms = float(speed), float(lagrange) / 100
        if speed >= DEPARTURE_RATIO * wc:
            continue
        est = check_link_rates(spin, np.array([0.0]), np.array([[speed]]), {"beam": wc})
        estimate = est[0].estimated_nrms if est else DEPARTURE_NRMS * (speed / (DEPARTURE_RATIO * wc)) ** 2
        assert estimate == pytest.approx(nrms, rel=0.15), speed
        checked += 1
    assert checked >= 3


def test_link_rates_are_the_links_absolute_rates():
    """Serial arm: the upper link turns at q1', the forearm (relative coordinate q2) at q1' + q2'."""
    mech = load_mechanism(MODELS / "serial_arm.toml")
    q = np.array([[0.1, 1.45], [0.4, 0.9]])
    qd = np.array([[0.7, -0.2], [-1.1, 2.5]])
    np.testing.assert_allclose(link_rates(mech, q, qd), np.column_stack([qd[:, 0], qd.sum(axis=1)]), atol=1e-12)


def test_signal_warnings_read_the_named_columns(spin):
    t = np.linspace(0.0, 1.0, 11)
    sig = Signals(t, ("q1", "dq1"), np.column_stack([2.0 * t, np.full(11, 2.0)]))
    (w,) = signal_warnings(spin, sig)
    assert w.level == "departed" and w.time_s == 0.0
    assert signal_warnings(spin, Signals(t, ("q1",), t[:, None])) == []


@pytest.mark.parametrize("name", ["fivebar", "fourbar", "serial_arm", "single_link", "sixbar", "slider_crank"])
def test_gallery_manoeuvres_stay_inside(name):
    """The gallery's own manoeuvres (their plans): no warning. Their fastest link against its departure rate
    is at most 0.15 (the slider-crank's rod: estimated error 0.1 %)."""
    from exuflex.manoeuvre import plan

    mech = load_mechanism(MODELS / f"{name}.toml")
    p = plan(mech, dt=2e-3, t_end=mech.manoeuvre.duration)
    assert rate_warnings(mech, p.t, p.q, p.qd) == []
    wc = clamped_frequencies(mech)
    peak = np.abs(link_rates(mech, p.q, p.qd)).max(axis=0)
    assert max(r / (DEPARTURE_RATIO * wc[lk.name]) for r, lk in zip(peak, mech.links)) < 0.16


@pytest.mark.slow
def test_simulate_and_observe_carry_the_warnings(tmp_path, caplog):
    """A soft arm written for the test (the single link at twice the length and half the diameter: omega_c
    7.9 rad/s) turned 5 rad in 1.5 s: the ERLS run logs the warning and writes it to meta.json; the observer's
    summary (result.json) carries it too."""
    from exuflex.scoring.run import observe_run
    from exuflex.runs import read_run
    from exuflex.truth import simulate_run

    text = (MODELS / "single_link.toml").read_text()
    for a, b in (('name = "single_link"', 'name = "soft_arm"'), ("length = 1.0\n", "length = 2.0\n"),
                 ("diameter = 0.02\n", "diameter = 0.01\n"), ("station = 1.0\n", "station = 2.0\n"),
                 ("station = 0.25\n", "station = 0.5\n"), ("end = 1.5707963267948966", "end = 5.0")):
        assert a in text
        text = text.replace(a, b)
    model = tmp_path / "soft_arm.toml"
    model.write_text(text)
    mech = load_mechanism(model)
    assert clamped_frequencies(mech)["arm"] == pytest.approx(7.94, abs=0.01)
    with caplog.at_level(logging.WARNING, logger="exuflex.erls.validity"):
        out = simulate_run(model, tmp_path / "run", engine="erls", seed=1)
    run = read_run(out)
    (w,) = run.meta["validity"]
    assert w["link"] == "arm" and w["level"] == "departed" and w["peak_rate_rad_s"] > 4.0
    assert any("'arm'" in r.getMessage() for r in caplog.records)
    summary = observe_run(mech, run, keep="summary").summary
    assert [v["link"] for v in summary["validity"]] == ["arm"]

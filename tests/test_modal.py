"""Modal analysis: Euler-Bernoulli beam frequencies (with fitted h^4 convergence) and the paper's Table 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _beam import beam_frequencies

from exuflex.data import paper_reference
from exuflex.erls.modal import modal_analysis
from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism, refine_mechanism

MODELS = Path(__file__).resolve().parents[1] / "models"


def _single_link(hub: bool = True, tip: bool = True):
    mech = load_mechanism(MODELS / "single_link.toml")
    return mech.replace(masses=mech.masses if hub else (), payload=mech.payload if tip else None)


def _bending(res, n: int = 3) -> np.ndarray:
    """The first n modes whose motion is mostly transverse (the arm lies along x at q = 0)."""
    sh = res.nodal_shapes
    lateral = np.sum(sh[1::3] ** 2, axis=0) / np.sum(sh[0::3] ** 2 + sh[1::3] ** 2, axis=0)
    return res.frequencies_hz[lateral > 0.5][:n]


def _analytic(mech, locked: bool) -> np.ndarray:
    lk = mech.links[0]
    EI, rhoA = lk.material.E * lk.section.I, lk.material.rho * lk.section.A
    J_h = sum(m.inertia for m in mech.masses)
    m_t = mech.payload.mass if mech.payload is not None else 0.0
    J_t = mech.payload.inertia if mech.payload is not None else 0.0
    return beam_frequencies(EI, rhoA, lk.length, hub="clamped" if locked else J_h, m_t=m_t, J_t=J_t, n=3)


CASES = [  # (hub inertia, tip mass, motor locked): the analytic problem
    (True, True, True),  # clamped-free with a tip mass
    (True, True, False),  # beam pinned to a free hub of inertia J_h, tip mass
    (False, False, True),  # clamped-free: beta L = 1.8751, 4.6941, 7.8548
    (False, False, False),  # pinned-free: beta L = 3.9266, 7.0686, 10.2102
]


@pytest.mark.parametrize("hub,tip,locked", CASES)
def test_single_link_matches_euler_bernoulli(hub, tip, locked):
    mech = _single_link(hub, tip)
    exact = _analytic(mech, locked)
    factors = (1, 2, 4, 8)
    errs = []
    for k in factors:
        f = _bending(modal_analysis(ErlsModel(refine_mechanism(mech, k)), locked=locked))
        errs.append(f / exact - 1)
        if k == 2:
            f2 = f
    errs = np.abs(np.array(errs))
    h = mech.links[0].length / (mech.links[0].n_elements * np.array(factors))
    rates = [np.polyfit(np.log(h), np.log(errs[:, i]), 1)[0] for i in range(3)]
    label = f"hub={'J_h' if hub else 0}, tip={'m_t' if tip else 0}, {'locked' if locked else 'free'}"
    print(f"\n{label}: analytic {np.round(exact, 4)} Hz; 8 elements {np.round(f2, 4)} Hz; "
          f"rel. errors {np.array2string(errs[1], precision=2)}; fitted rates {np.round(rates, 2)}")
    assert np.all(errs[1] < 0.005)  # refined twice (8 elements): within 0.5 %
    assert np.all(errs[-1] < 1e-5)
    assert all(3.6 < r < 4.4 for r in rates)  # cubic Hermite, consistent mass: O(h^4) in frequency


def test_single_link_frequencies_do_not_depend_on_q():
    model = ErlsModel(_single_link())
    a = modal_analysis(model, [0.0]).frequencies_hz
    b = modal_analysis(model, [2.3]).frequencies_hz
    np.testing.assert_allclose(a, b, rtol=1e-10)


def test_sixbar_matches_table2():
    ref = paper_reference()["table2_reduced_model_accuracy"]["frequencies_hz"]
    model = ErlsModel(load_mechanism(MODELS / "sixbar.toml"))
    assert (model.n, model.ne) == (30, 27)
    res = modal_analysis(model)
    np.testing.assert_allclose(res.rigid_frequencies_hz, 0.0, atol=1e-3)
    f = res.below(180.0)
    assert len(f) == 6
    dev = 100 * (f / np.array(ref) - 1)
    rms = float(np.sqrt(np.mean(dev**2)))
    print("\nmode  Table 2 (Hz)  ERLS (Hz)  dev (%)")
    for i, (a, b, d) in enumerate(zip(ref, f, dev)):
        print(f"{i + 1:>4}  {a:>12.2f}  {b:>9.2f}  {d:>+7.2f}")
    print(f"RMS deviation {rms:.2f} %")
    assert rms <= 7.0



def test_paper_reference_data():
    """Package data: every entry names its source; Table 2 is complete; the reduced frequencies follow eq. 17."""
    ref = paper_reference()
    for key, entry in ref.items():
        if key.startswith("_"):
            continue
        entries = entry.values() if key == "exuflex_reference" else [entry]
        assert all("source" in e for e in entries), key
    t2 = ref["table2_reduced_model_accuracy"]
    assert len(t2["frequencies_hz"]) == len(t2["nco"]) == len(t2["frequency_error_pct"]) == 6
    err = 100 * np.abs(np.array(t2["reduced_frequencies_hz"]) / t2["frequencies_hz"] - 1)
    np.testing.assert_allclose(err, t2["frequency_error_pct"], atol=1e-3)
    assert ref["model_sizes"]["full"]["ndof"] == 30 and ref["table3_noise_std"]["values"]["T2"] == 0.4
    ref["model_sizes"]["full"]["ndof"] = 0  # callers get a copy
    assert paper_reference()["model_sizes"]["full"]["ndof"] == 30

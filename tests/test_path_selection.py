"""The interior-mode selection along the path (reduction/path.py) stops evaluating a candidate's samples once it
cannot beat the best so far, and keeps each sample's accuracy per subset of modes: the selection must be the one
every sample's margin gives. Oracles: the margins assembled from the per-sample quantities at once (the band's
thresholds, ``rho`` and the tip quantities' RMS), and the forward selection with every candidate's minimum over
every sample, on every model of the gallery and on a mechanism written here."""

import tomllib
from pathlib import Path

import numpy as np
import pytest
from _toml import dumps

from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism
from exuflex.observer.session import ObserverConfig
from exuflex.reduction import CraigBampton, PathSamples
from exuflex.reduction.path import margin

MODELS = sorted((Path(__file__).resolve().parents[1] / "models").glob("*.toml"))

def _basis(mech) -> CraigBampton:
    config = ObserverConfig.for_model(mech)
    return CraigBampton(ErlsModel(mech), masters=config.masters, q_star=config.q_star, n_interior=config.n_interior,
                        ranking=config.ranking, channels=config.channels)


def _all_margins(ps: PathSamples, kept, truncation: bool = True) -> np.ndarray:
    """The margins as one array per requirement, combined at once (the oracle of :meth:`PathSamples.margins`)."""
    cb = ps.cb
    m = np.array([margin(a, cb.nco_min, cb.freq_error_max_pct) for a in ps.evaluate(kept)])
    if truncation and ps.truncation:
        ix = ps._tix
        m[ix] = np.minimum(m[ix], (ps.rho_max - ps.rho_channels(kept).sum(axis=1)) / ps.rho_max)
        if ps.quantity_max is not None and ps.quantity_max.size:
            q = ((ps.quantity_max - ps.quantities_rms(kept)) / ps.quantity_max).min(axis=1)
            m[ix] = np.minimum(m[ix], q)
    return m


def _fresh(tmp_path) -> Path:
    """A mechanism not in the gallery: the four-bar's chain in steel with a slender coupler and a faster rocker
    sampled at 800 Hz (no setting taken from a gallery result)."""
    doc = tomllib.loads((MODELS[0].parent / "fourbar.toml").read_text())
    doc["model"].update(name="fourbar_steel", sample_rate_hz=800.0)
    doc["materials"] = [{"name": "aluminium", "E": 200.0e9, "rho": 7850.0}]
    for lk in doc["links"]:
        if lk["name"] == "coupler":
            lk["diameter"] = 0.009
    path = tmp_path / "fourbar_steel.toml"
    path.write_text(dumps(doc))
    return path


@pytest.mark.parametrize("path", MODELS + ["fresh"], ids=[p.stem for p in MODELS] + ["fresh"])
def test_selection_equals_every_sample(path, monkeypatch, tmp_path):
    mech = load_mechanism(_fresh(tmp_path) if path == "fresh" else path)
    cb = _basis(mech)
    chosen = (cb.order.copy(), cb.n_interior, cb.truncation)
    seen = []

    def least(self, kept, truncation, samples, above):  # every sample, no bound
        full = self.margins(kept, truncation)
        oracle = _all_margins(self, kept, truncation)
        assert np.array_equal(full, oracle, equal_nan=True)
        seen.append(len(kept))
        return full.min()

    monkeypatch.setattr(PathSamples, "_least_margin", least)
    ref = _basis(mech)
    assert np.array_equal(chosen[0], ref.order)
    assert chosen[1] == ref.n_interior
    if chosen[2]:
        assert chosen[2]["rho"] == ref.truncation["rho"]
        assert chosen[2]["rho_channels"] == ref.truncation["rho_channels"]
    assert np.array_equal(cb.at(cb.q_star).H, ref.at(ref.q_star).H)
    # the forward selection ran where it kept a dynamic mode of its own: the kept dynamic modes (before the static
    # corrections) less those the filter requirement added (PathSamples.extend_for_bias, which needs no selection)
    dynamic = cb.truncation.get("dynamic", {}) if isinstance(cb.truncation, dict) else {}
    kept_dynamic = [int(i) for i in cb.order[: dynamic.get("n_interior", cb.n_interior)]]
    if cb.ranking == "imr" and set(kept_dynamic) - set(cb.bias_tried):
        assert seen  # the forward selection ran

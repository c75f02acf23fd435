"""The filter requirement's figure of the final basis (static corrections included, ``truncation.bias_final``):
the same quantity as :meth:`exuflex.reduction.PathSamples.bias` (:mod:`exuflex.reduction.truncation`, "What the
filter makes of it"), computed on the basis the observer uses."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from exuflex.erls.model import ErlsModel
from exuflex.mechanism import load_mechanism
from exuflex.reduction import CraigBampton
from exuflex.reduction.truncation import FilterSample, PlannedInput

MODELS = Path(__file__).resolve().parents[1] / "models"


def test_final_figure_is_the_filter_requirement_on_the_observers_basis():
    """The slider-crank (4 interior modes and 5 static corrections): ``bias_final`` equals the figure rebuilt from
    fresh :class:`FilterSample` objects on the final basis at the same configurations (mean over them of the
    mean-square error over the mean variance, every column of ``cb.at(q).H``); the static corrections lower the
    largest figure (they span quasi-static slave motion the dynamic modes leave out); with none, it is ``bias``."""
    mech = load_mechanism(MODELS / "slider_crank.toml")
    model = ErlsModel(mech)
    cb = CraigBampton(model)
    tr = cb.truncation
    assert cb.n_static > 0 and list(tr["bias_final"]) == list(tr["bias"])
    planned = PlannedInput.of(mech)
    qs = cb.path_q[::2]  # the configurations with a truncation figure: q* and every other path sample
    ms, var = [], []
    for q in qs:
        rc = cb.at(q)
        a, b = FilterSample(model, rc, planned).bias(np.arange(rc.H.shape[1]))
        ms.append(a)
        var.append(b)
    ref = np.mean(ms, axis=0) / np.mean(var, axis=0)
    np.testing.assert_allclose(list(tr["bias_final"].values()), ref, rtol=1e-6, atol=0)  # the Riccati doubling stops at 1e-12
    assert max(tr["bias_final"].values()) < max(tr["bias"].values())
    assert tr["bias_final_met"] == (max(ref) <= cb.bias_max)
    plain = CraigBampton(model, static_max=0).truncation
    assert plain["bias_final"] == plain["bias"]

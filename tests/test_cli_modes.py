"""``exuflex modes``: JSON shape, table output, options and one-line errors."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from exuflex.cli import main

MODELS = Path(__file__).resolve().parents[1] / "models"
SIXBAR = str(MODELS / "sixbar.toml")


def _json(capsys, *argv) -> dict:
    assert main(["modes", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_sixbar_json(capsys):
    rep = _json(capsys, SIXBAR)
    assert rep["model"] == "sixbar"
    assert rep["q"] == [1.0821, 2.6354, 4.7123]
    assert rep["full"]["ndof"] == 30 and rep["full"]["n_elastic"] == 27
    f = rep["full"]["frequencies_hz"]
    assert len(f) == 6 and f == sorted(f) and 12 < f[0] < 14 and f[-1] <= 180.0


def test_options(capsys):
    base = _json(capsys, SIXBAR)["full"]["frequencies_hz"]
    locked = _json(capsys, SIXBAR, "--locked")
    assert locked["locked"] and locked["full"]["frequencies_hz"][0] < 10.0  # link 2 as a cantilever (sixbar.md)
    assert len(_json(capsys, SIXBAR, "--fmax", "50")["full"]["frequencies_hz"]) == 2
    moved = _json(capsys, SIXBAR, "--q", "0.75,2.6,4.8")
    assert moved["q"] == [0.75, 2.6, 4.8] and moved["full"]["frequencies_hz"] != base
    fine = _json(capsys, SIXBAR, "--refine", "2")
    assert fine["full"]["n_elastic"] > 27 and abs(fine["full"]["frequencies_hz"][0] - base[0]) < 0.05


@pytest.mark.parametrize("name", ["single_link", "fourbar"])
def test_other_models(capsys, name):
    rep = _json(capsys, str(MODELS / f"{name}.toml"))
    assert rep["model"] == name and rep["full"]["frequencies_hz"]


def test_table(capsys):
    assert main(["modes", SIXBAR]) == 0
    out = capsys.readouterr().out
    assert "30 dofs (27 elastic)" in out and "12.89" in out and "motors free" in out


@pytest.mark.parametrize(
    "argv,message",
    [
        (["nope.toml"], r"nope\.toml: \(file\): expected an existing TOML model file"),
        ([SIXBAR, "--q", "1,2"], r"--q: expected 3 values \(q1, q2, q3\), got 2"),
    ],
)
def test_errors_are_one_line(capsys, argv, message):
    assert main(["modes", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("exuflex modes: error: ") and err.count("\n") == 1
    assert re.search(message, err)


def test_bad_argument_syntax(capsys):
    assert main(["modes", SIXBAR, "--q", "a,b,c"]) == 2
    assert "comma-separated numbers" in capsys.readouterr().err


def test_reduced(capsys):
    pytest.importorskip("exuflex.reduction")
    rep = _json(capsys, SIXBAR, "--reduced")
    red = rep["reduced"]
    assert red["ndof"] == 13 and len(red["frequencies_hz"]) == len(rep["full"]["frequencies_hz"])
    rep = _json(capsys, SIXBAR, "--reduced", "--masters", "x14,y15", "--n-interior", "3", "--qstar", "1.0821,2.6354,4.7123")
    assert rep["reduced"]["ndof"] == 3 + 2 + 3


def test_reduced_reports_the_worst_along_the_manoeuvre(capsys):
    """``--reduced`` evaluates the basis on configurations of the manoeuvre: the worst NCO and frequency error
    there are each the worst of :func:`~exuflex.reduction.accuracy_along` over the same configurations."""
    from exuflex.erls.model import ErlsModel
    from exuflex.manoeuvre import plan
    from exuflex.mechanism import load_mechanism
    from exuflex.reduction import CraigBampton, accuracy_along

    fourbar = str(MODELS / "fourbar.toml")
    rep = _json(capsys, fourbar, "--reduced", "--masters", "node9.transverse", "--along", "11")
    al = rep["reduced"]["along"]
    mech = load_mechanism(fourbar)
    accs = accuracy_along(CraigBampton(ErlsModel(mech), masters=["node9.transverse"]),
                          plan(mech, dt=mech.manoeuvre.duration / 10).q, warn=False)
    assert al["configurations"] == 11 and al["ok"]
    assert al["worst_nco"] == pytest.approx(min(a.worst_nco for a in accs), abs=1e-10)
    assert al["worst_freq_error_pct"] == pytest.approx(max(a.worst_error_pct for a in accs), abs=1e-8)
    assert main(["modes", fourbar, "--reduced", "--along", "5"]) == 0
    assert "along the manoeuvre (5 configurations): worst NCO" in capsys.readouterr().out


def test_exudyn(capsys):
    pytest.importorskip("exudyn")
    rep = _json(capsys, SIXBAR, "--exudyn")
    fe, fx = rep["exudyn"]["frequencies_hz"], rep["full"]["frequencies_hz"]
    # the same (paper) mesh in both: cubic bending in both, the same modes (seen within 0.002 %)
    assert rep["exudyn"]["n_elements"] == 9 and rep["exudyn"]["elements_per_link"] == "file"
    assert len(fe) == len(fx) and all(abs(a - b) / b < 1e-3 for a, b in zip(fe, fx))


def test_subprocess():
    """The installed entry point path: python -m exuflex modes ... --json."""
    out = subprocess.run([sys.executable, "-m", "exuflex", "modes", str(MODELS / "fourbar.toml"), "--json"],
                         capture_output=True, text=True, check=True).stdout
    assert json.loads(out)["full"]["ndof"] == 31


def test_reduced_reports_the_filter_requirement(capsys):
    """``--reduced`` reports the filter requirement's figure per estimated quantity (``truncation.bias``, the same
    numbers as :meth:`PathSamples.bias` on the final basis, its static corrections in), its limit and whether the
    count meets it, and the dynamic modes' figures alone (``truncation.dynamic``); the text names them. The fresh
    steel-forearm arm: the dynamic modes alone miss it in q1 (the elbow motor's reaction on the upper arm's node, a
    load they carry only partly: reduction.static); with the static corrections the count meets it."""
    from exuflex.erls.model import ErlsModel
    from exuflex.mechanism import load_mechanism
    from exuflex.reduction import CraigBampton, PathSamples
    from exuflex.reduction.truncation import BIAS_MAX, PlannedInput

    steel = str(MODELS.parent / "benchmarks" / "models" / "steel_arm.toml")
    tr = _json(capsys, steel, "--reduced", "--along", "0")["reduced"]["truncation"]
    mech = load_mechanism(steel)
    model = ErlsModel(mech)
    cb = CraigBampton(model, static_max=0)  # the dynamic modes the default keeps before its static corrections
    every = CraigBampton(model, n_interior=0, truncation_max=0)
    every.set_interior(len(every.order))
    planned = PlannedInput.of(mech)
    b = PathSamples(every, cb.path_q, planned).bias(cb.kept)
    dyn = tr["dynamic"]
    assert dyn["n_interior"] == cb.n_interior
    assert list(tr["bias"]) == list(dyn["bias"]) == list(planned.quantities)
    assert np.allclose(list(dyn["bias"].values()), b, rtol=1e-9, atol=0)
    assert max(b) > BIAS_MAX and max(b) < tr["bias_without_interior"]
    assert tr["bias_max"] == BIAS_MAX and tr["bias_met"] and max(tr["bias"].values()) <= BIAS_MAX
    assert main(["modes", steel, "--reduced", "--along", "0"]) == 0
    out = capsys.readouterr().out
    assert "filter (docs/reduction.md): the steady filter's mean-square error" in out
    assert f"its {cb.n_interior} dynamic modes alone" in out

"""The beam-theory (slenderness) study: its levels, the observer following each level's model, the runs scored
against their bound, and the command line's errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from exuflex.errors import UsageError
from exuflex.mechanism import load_mechanism
from exuflex.study import StudySpec, apply_overrides, run_study, slenderness_levels

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "single_link.toml"


def test_levels_set_the_diameter_and_keep_the_beam_dynamics():
    """``keep="dynamics"``: d = L / ratio, and EI and rho A of the link equal the nominal ones (relative 1e-12);
    ``keep="material"``: E and rho unchanged, so EI grows with d^4 and rho A with d^2; the mesh size follows d."""
    mech = load_mechanism(MODEL)
    lk = mech.link("arm")
    EI0, rA0 = lk.material.E * lk.section.I, lk.material.rho * lk.section.A
    for lv in slenderness_levels(mech, "arm", [50, 10, 5.5], mesh_scale=2.0):
        m = apply_overrides(mech, lv.overrides).link("arm")
        d = lk.length / lv.value
        assert m.section.diameter == pytest.approx(d, rel=1e-12)
        assert m.section.I == pytest.approx(math.pi * d**4 / 64, rel=1e-12)
        assert m.material.E * m.section.I == pytest.approx(EI0, rel=1e-12)
        assert m.material.rho * m.section.A == pytest.approx(rA0, rel=1e-12)
        assert m.mesh_size == pytest.approx(2.0 * d, rel=1e-12)
    (lv,) = slenderness_levels(mech, "arm", ["25"], keep="material")
    m = apply_overrides(mech, lv.overrides).link("arm")
    assert (m.material.E, m.material.rho) == (lk.material.E, lk.material.rho)
    assert m.material.E * m.section.I == pytest.approx(EI0 * 16, rel=1e-12)


@pytest.mark.parametrize("args, words", [
    (("nope", [10]), r"link \(--link\): 'nope' is not a link of single_link; expected one of arm"),
    (("arm", [10, 10.0]), r"the level L/d = 10 is given twice"),
    (("arm", ["x"]), r"expected slenderness ratios L/d, got 'x'"),
    (("arm", [1.0]), r"slenderness L/d 1; expected a finite ratio above 1"),
    (("arm", []), r"expected at least one slenderness ratio"),
])
def test_level_errors_name_the_argument(args, words):
    """Each bad argument gets one error naming it; a level whose scaled material the model file's checks refuse
    says so with the way out."""
    with pytest.raises(UsageError, match=words):
        slenderness_levels(load_mechanism(MODEL), *args)
    with pytest.raises(UsageError, match=r"keep \(--keep\): expected one of dynamics, material, got 'shape'"):
        slenderness_levels(load_mechanism(MODEL), "arm", [10], keep="shape")
    with pytest.raises(UsageError, match=r"L/d = 3 on link 'arm': .*rho.* choose ratios nearer it, or --keep material"):
        slenderness_levels(load_mechanism(MODEL), "arm", [3])


def test_observer_follows_the_level_and_runs_are_scored_against_their_bound(tmp_path):
    """On truths from the observer's own reduced model (``engine="reduced"``), a link twice as thick (EI 16x, rho A
    4x): with the level's model as the observer's, every run stays near its bound (worst ratio below 3); with the
    nominal model it is far off (above 10). Each run's ratio is its RMS error over its bound, quantity by
    quantity, and the level's worst ratio the runs' largest ones."""
    mech = load_mechanism(MODEL)
    levels = slenderness_levels(mech, "arm", [25], keep="material")
    worst = {}
    for follow in ("level", "nominal"):
        spec = StudySpec(model=str(MODEL), levels=levels, runs=2, duration=0.4, engine="reduced", kind="slenderness",
                         observer_model=follow, with_bound=True)
        res = run_study(spec, tmp_path / follow)
        lv = res.summary["levels"][0]
        for r in res.rows:
            for q, ratio in r["ratio_to_bound"].items():
                assert ratio == pytest.approx(r["rms"][q] / r["bound_rms"][q], rel=1e-12)
        per_run = [max(r["ratio_to_bound"].values()) for r in res.rows]
        assert lv["worst_ratio"]["mean"] == pytest.approx(np.mean(per_run), rel=1e-12)
        assert lv["worst_ratio"]["max"] == pytest.approx(max(per_run), rel=1e-12)
        worst[follow] = lv["worst_ratio"]["mean"]
    assert worst["level"] < 3.0, worst
    assert worst["nominal"] > 10.0, worst


def test_cli_errors(tmp_path, capsys):
    from exuflex.cli import main

    base = ["study", "slenderness", str(MODEL), "--out", str(tmp_path / "s")]
    assert main(base + ["--link", "crank"]) == 2
    assert "link (--link): 'crank' is not a link of single_link" in capsys.readouterr().err
    assert main(base + ["--link", "arm", "--levels", "50,,3"]) == 2
    assert "--levels '50,,3': expected comma-separated slenderness ratios" in capsys.readouterr().err
    assert main(base + ["--link", "arm", "--beam", "shell"]) == 2
    assert "--beam 'shell': expected one of" in capsys.readouterr().err


@pytest.mark.slow
def test_quick_cli_study_on_ffrf_truths(tmp_path, monkeypatch, capsys):
    """``exuflex study slenderness --quick`` on FFRF truths (coarse solid meshes): three levels of two runs, each
    scored against its bound, the summary's levels in the order given, the figure written; a second call resumes
    every run."""
    pytest.importorskip("ngsolve")
    from exuflex.cli import main

    monkeypatch.setenv("EXUFLEX_CACHE", str(tmp_path / "cache"))
    args = ["study", "slenderness", str(MODEL), "--link", "arm", "--quick", "--mesh-scale", "2", "--no-progress",
            "--out", str(tmp_path / "s")]
    assert main(args) == 0
    import json

    summary = json.loads((tmp_path / "s" / "summary.json").read_text())
    assert [lv["value"] for lv in summary["levels"]] == [50.0, 10.0, 5.5]
    assert summary["settings"]["beam"] == "ffrf" and summary["settings"]["kind"] == "slenderness"
    assert all(lv["n_runs"] == 2 and np.isfinite(lv["worst_ratio"]["mean"]) for lv in summary["levels"])
    assert (tmp_path / "s" / "fig_slenderness.png").exists()
    assert main(args) == 0
    assert "0 run(s) computed, 6 reused" in capsys.readouterr().out

"""A study's overrides pass through the model file loader's checks (:func:`exuflex.mechanism.writer.revalidate`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from exuflex.cli import main
from exuflex.mechanism import load_mechanism, parse_mechanism
from exuflex.mechanism.writer import mechanism_document, revalidate
from exuflex.study import OverrideError, apply_overrides

MODELS = Path(__file__).resolve().parents[1] / "models"
SIXBAR = MODELS / "sixbar.toml"


@pytest.mark.parametrize("path", sorted(MODELS.glob("*.toml")), ids=lambda p: p.stem)
def test_written_document_loads_back_to_the_same_mechanism(path):
    mech = load_mechanism(path)
    again = parse_mechanism(mechanism_document(mech), mech.source)
    assert again.replace(manoeuvre=mech.manoeuvre) == mech
    assert revalidate(mech) == mech


def test_a_link_with_its_own_modulus_gets_its_own_material():
    mech = apply_overrides(load_mechanism(SIXBAR), {"links.L3.E": 70e9})
    doc = mechanism_document(mech)
    assert [m["name"] for m in doc["materials"]] == ["aluminium", "aluminium@L3"]
    again = revalidate(mech)
    assert again.link("L3").material.E == 70e9 and again.link("L2").material.E == 69e9


# (override, the loader's field, a phrase of the loader's message): what the model file would be refused for
CASES = [
    ("links.L4.diameter", 24, "links[3].diameter", "mm by mistake"),
    ("materials.aluminium.E", 69.0, "materials[0].E", "[1e+06, 1e+13] Pa"),
    ("links.L3.rho", 2.7, "materials[1].rho", "kg/m^3"),
    ("links.L1.A", 0.5, "links[0].A", "much smaller than length^2"),
    ("damping.beta", 1e12, "damping", "damping ratio"),
    ("sensors.q1.noise_std", -1.0, "sensors[0].noise_std", ">= 0"),
    ("motors.T1.full_scale", 0.0, "motors[0].full_scale", "positive"),
    ("sample_rate_hz", 0, "model.sample_rate_hz", "positive"),
    ("reduction.nco_min", 2.0, "reduction.nco_min", "[0, 1]"),
    ("masses.12.inertia", -0.1, "masses[9].inertia", ">= 0"),
]


@pytest.mark.parametrize("path,value,field,phrase", CASES, ids=[c[0] for c in CASES])
def test_override_refused_by_the_loaders_check(path, value, field, phrase):
    with pytest.raises(OverrideError) as ei:
        apply_overrides(load_mechanism(SIXBAR), {path: value})
    msg = str(ei.value)
    assert msg.startswith(f"override {path}={value!r}: the model file's check refuses it: {field}: expected"), msg
    assert phrase in msg and "\n" not in msg


def test_in_range_overrides_still_apply():
    m = apply_overrides(load_mechanism(SIXBAR), {"links.L4.diameter": 0.025, "damping.beta": 2e-5,
                                                 "materials.aluminium.E": 70e9})
    assert m.link("L4").section.diameter == 0.025 and m.damping.beta == 2e-5


def test_length_override_keeps_every_point_at_its_fraction():
    nominal = load_mechanism(SIXBAR)
    m = apply_overrides(nominal, {"links.L5.length": 0.3, "links.L2.length": 0.9})
    f2, f5 = 0.9 / 0.85, 0.3 / 0.282
    for jn, jo in zip(m.joints, nominal.joints, strict=True):
        for p, po in zip(jn.points, jo.points, strict=True):
            assert p.station == pytest.approx(po.station * {"L2": f2, "L5": f5}.get(p.link, 1.0))
    for s, so in zip(m.sensors, nominal.sensors, strict=True):
        if so.station is not None:
            assert s.station == pytest.approx(so.station * {"L2": f2, "L5": f5}.get(s.link, 1.0))
    assert m.manoeuvre.tip.station == pytest.approx(0.3)
    assert m.link("L2").stations == pytest.approx((0.0, 0.45, 0.9))
    assert dataclasses.replace(m.manoeuvre, tip=nominal.manoeuvre.tip) == nominal.manoeuvre


def test_cli_sweep_in_the_wrong_unit_is_one_line_before_any_work(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["study", "sweep", str(SIXBAR), "--out", str(out), "--set", "links.L4.diameter=0.024,24",
                 "--quick"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "override links.L4.diameter=24: " in err and "mm by mistake" in err
    assert not (out / "study.json").exists() and not (out / "runs").exists()


def test_cli_sweep_level_whose_loop_cannot_close(tmp_path, capsys):
    """Link 3 (A -> B) 0.1 m long cannot reach from A to B: the level is refused as its model file would be."""
    out = tmp_path / "s"
    assert main(["study", "sweep", str(SIXBAR), "--out", str(out), "--set", "links.L3.length=0.1",
                 "--quick"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "level links.L3.length=0.1: the model file's check refuses it: model.q_ref" in err
    assert not (out / "study.json").exists()

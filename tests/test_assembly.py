"""The branch the closure assembles at the reference configuration, checked against the links' angle guesses
(:func:`exuflex.validate.assembly`, :func:`exuflex.validate.check_configurations`)."""

from __future__ import annotations

import json
import logging
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import _toml  # noqa: E402

from exuflex.cli import main  # noqa: E402
from exuflex.mechanism import load_mechanism, parse_mechanism  # noqa: E402
from exuflex.validate import ANGLE_GUESS_TOL, assembly, check_configurations  # noqa: E402

MODELS = Path(__file__).resolve().parents[1] / "models"


def _sixbar(**guesses) -> dict:
    with open(MODELS / "sixbar.toml", "rb") as fh:
        doc = tomllib.load(fh)
    for lk in doc["links"]:
        if lk["name"] in guesses:
            lk["angle_guess"] = guesses[lk["name"]]
    return doc


def _unit(a: float) -> np.ndarray:
    return np.array([np.cos(a), np.sin(a)])


def _branches(q1: float, q2: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """Angles (L3, L4) of the six-bar's loop O-A-B-C in closed form: A = 0.5 e(q1), C = 0.85 e(q2), B at 0.85
    from A and 0.5 from C. The open branch is the parallelogram B = A + C; the other intersection of the two
    circles is its mirror image in the line AC (the crossed branch). L3 points A -> B, L4 points B -> C."""
    A, C = 0.5 * _unit(q1), 0.85 * _unit(q2)
    out = []
    for B in (A + C, None):
        if B is None:
            u = (C - A) / np.linalg.norm(C - A)
            d = C  # the parallelogram's B = A + C, relative to A
            B = A + 2 * (d @ u) * u - d  # A + C mirrored in the line through A and C
        out.append((np.arctan2(*(B - A)[::-1]), np.arctan2(*(C - B)[::-1])))
    return out[0], out[1]


def _same_angle(a: float, b: float) -> bool:
    return abs((a - b + np.pi) % (2 * np.pi) - np.pi) < 1e-9


@pytest.mark.parametrize("path", sorted(MODELS.glob("*.toml")), ids=lambda p: p.stem)
def test_gallery_assembles_on_its_guesses(path, caplog):
    with caplog.at_level(logging.WARNING):
        asm = check_configurations(load_mechanism(path))
    assert asm is not None and asm.mismatched == () and not caplog.records
    assert "every guessed link within" in asm.summary()


def test_sixbar_open_branch_is_the_parallelogram():
    asm = assembly(load_mechanism(MODELS / "sixbar.toml"))
    q1, q2, _ = asm.q
    (l3, l4), _crossed = _branches(q1, q2)
    ang = dict(zip(asm.links, asm.angles))
    assert _same_angle(ang["L3"], l3) and _same_angle(ang["L4"], l4)
    assert _same_angle(ang["L3"], q2) and _same_angle(ang["L4"], q1 + np.pi)  # L3 parallel to L2, L4 to L1


@pytest.mark.parametrize("flip", [{"L4": 1.0821}, {"L3": 5.7770}], ids=["L4", "L3"])
def test_flipped_guess_assembles_the_crossed_branch_and_is_warned(flip, caplog):
    mech = parse_mechanism(_sixbar(**flip), "flipped.toml")
    with caplog.at_level(logging.WARNING):
        asm = check_configurations(mech)
    q1, q2, _ = asm.q
    _open, (l3, l4) = _branches(q1, q2)
    ang = dict(zip(asm.links, asm.angles))
    assert _same_angle(ang["L3"], l3) and _same_angle(ang["L4"], l4)  # the closed-form crossed branch
    assert asm.mismatched == ("L3", "L4")
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 2
    for i, name in ((2, "L3"), (3, "L4")):
        (m,) = [m for m in msgs if f"links[{i}].angle_guess: link {name} " in m]
        assert m.startswith("flipped.toml: ") and "another branch" in m and f"{ANGLE_GUESS_TOL:.3f} rad" in m
        assert abs(asm.deviation(name)) > ANGLE_GUESS_TOL


def test_guess_of_a_link_set_by_a_coordinate_is_called_wrong(caplog):
    mech = parse_mechanism(_sixbar(L5=1.5708), "l5.toml")
    with caplog.at_level(logging.WARNING):
        asm = check_configurations(mech)
    assert asm.mismatched == ("L5",)
    (m,) = [r.getMessage() for r in caplog.records]
    assert "links[4].angle_guess: link L5" in m and "set by coordinate q3" in m


def test_modes_reports_the_branch_and_its_other_frequencies(tmp_path, capsys, caplog):
    """The crossed parallelogram is another mechanism: its first mode differs from the open one's."""
    path = tmp_path / "flipped.toml"
    path.write_text(_toml.dumps(_sixbar(L4=1.0821)))
    freqs = {}
    for name, p in (("open", MODELS / "sixbar.toml"), ("crossed", path)):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            assert main(["modes", str(p), "--json"]) == 0
        cap = capsys.readouterr()
        err = " ".join(r.getMessage() for r in caplog.records)
        rep = json.loads(cap.out)
        freqs[name] = rep["full"]["frequencies_hz"][0]
        asm = rep["assembly"]
        assert asm["field"] == "model.q_ref"
        if name == "open":
            assert asm["mismatched"] == [] and "angle_guess" not in err
        else:
            assert asm["mismatched"] == ["L3", "L4"] and "links[3].angle_guess: link L4" in err
    assert abs(freqs["open"] - 12.89) < 0.01  # models/README.md
    assert abs(freqs["crossed"] - freqs["open"]) > 1.0
    assert main(["modes", str(path)]) == 0
    assert "L3, L4 more than" in capsys.readouterr().out

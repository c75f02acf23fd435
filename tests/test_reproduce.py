"""``exuflex reproduce --quick``: every artefact is written and the report cites them."""

from __future__ import annotations

import json
from pathlib import Path

from exuflex.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_reproduce_quick(tmp_path):
    out = tmp_path / "r"
    assert main(["reproduce", "--quick", "--model", str(ROOT / "models" / "sixbar.toml"), "--out", str(out)]) == 0
    report = (out / "report.md").read_text()
    for f in ("table2.json", "run/truth.csv", "observer/result.json", "observer/fig_tip_errors.png",
              "payload_study/summary.json", "payload_study/results.csv", "payload_study/fig_payload.png"):
        assert (out / f).exists(), f
    for ref in ("observer/fig_tip_errors.png", "payload_study/fig_payload.png", "observer/fig_fft.png"):
        assert f"]({ref})" in report
    if (out / "manoeuvre.gif").exists():
        assert "](manoeuvre.gif)" in report
    t2 = json.loads((out / "table2.json").read_text())
    assert t2["ndof"] == 13 and len(t2["rows"]) >= 6
    assert "13.28" in report and "Table 2" in report and "versions" in report
    s = json.loads((out / "payload_study" / "summary.json").read_text())
    assert [lv["value"] for lv in s["levels"]] == [0.0, 100.0]

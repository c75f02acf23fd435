"""Acceptance on lab-style logs (slow: a 3 s full-order ERLS truth recorded every 0.1 ms, per seed): the six-bar
with +-0.2 ms uniform time-stamp jitter and a clock 500 ppm fast, renamed columns and a time column in ms,
observed through the command line. Per quantity, the RMS error over the bound averaged over three noise seeds
stays within 1.5 (one seed alone scatters: seed 1 gives q3 1.74 with or without the jitter and drift, seeds 2
and 3 give 1.03 and 0.94).

    python -m pytest -m slow tests/test_lab_acceptance.py -s
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from exuflex.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _lablog import lab_log  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_jittered_drifting_lab_logs_within_1_5_of_the_bound(tmp_path, capsys):
    ratios = []
    for seed in (1, 2, 3):
        d = tmp_path / f"seed{seed}"
        info = lab_log(d, jitter_s=0.2e-3, drift_ppm=500.0, duration=3.0, seed=seed)
        rc = main(["observe", str(ROOT / "models" / "sixbar.toml"), str(d / "lab.csv"), "--map", info["map"],
                   "--time-column", "Time_ms", "--time-scale", "1e-3", "--truth", str(d / "truth.csv"), "--json"])
        assert rc == 0
        s = json.loads(capsys.readouterr().out)
        assert 400 < s["log_check"]["clock_drift_ppm"] < 600
        assert s["log_check"]["jitter_max_s"] < 0.25e-3
        assert not s["diverged"]
        ratios.append(s["ratio_to_bound"])
    names = list(ratios[0])
    mean = {k: float(np.mean([r[k] for r in ratios])) for k in names}
    with capsys.disabled():
        for seed, r in zip((1, 2, 3), ratios, strict=True):
            print(f"\nseed {seed}: " + ", ".join(f"{k} {v:.2f}" for k, v in r.items()))
        print("mean: " + ", ".join(f"{k} {v:.2f}" for k, v in mean.items()))
    assert max(mean.values()) < 1.5, mean

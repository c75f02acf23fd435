"""
The paper's reproduction, in brief
==================================

``exuflex reproduce`` regenerates Palomba, Richiedei and Trevisani (2018) on the six-bar: Table 2 (the
full-order frequencies at q* and the 13-dof reduced model's accuracy, eqs. 16-17), Figs 3-10 (the
manoeuvre, the torques, the measurements and the observer's estimates and errors on one run) and Fig. 11 (the
payload-mismatch study, eq. 21), with a ``report.md`` beside the figures. Here it runs with its quick settings
(0.6 s runs and a payload study of two levels and two runs), so its numbers are not the paper's; the full
reproduction is::

    exuflex reproduce --out results        # a few minutes; results/report.md

and its figures, with the commands behind each, are on :doc:`/results/index`.
"""

import json
import tempfile
from pathlib import Path

from exuflex.cli.reproduce import reproduce

# the model files, from the repository's root or from examples/
MODELS = Path("models") if Path("models").is_dir() else Path("../models")
OUT = Path(tempfile.mkdtemp(prefix="exuflex_reproduce_"))

report = reproduce(MODELS / "sixbar.toml", OUT, quick=True)

# %%
# Table 2: the full-order model's frequencies at q* against the paper's, and the reduced model's normalised
# cross-orthogonality (NCO, eq. 16) and frequency error (eq. 17).
table2 = json.loads((OUT / "table2.json").read_text())
print("mode  full Hz  paper Hz     NCO  paper NCO   err %  paper err %")
for r in table2["rows"]:
    print(f"{r['mode']:4d} {r['full_hz']:8.2f} {r['paper_full_hz']:9.2f} {r['nco']:7.4f} "
          f"{r['paper_nco']:10.4f} {r['freq_error_pct']:7.3f} {r['paper_freq_error_pct']:12.3f}")

# %%
# Figs 3 and 6-7: the tip's path, truth and estimate, and the joint errors against the observer's bound.
FIGURES = [OUT / "observer" / "fig_trajectory.png", OUT / "observer" / "fig_joint_errors.png"]

# %%
# Fig. 10: the spectra of the tip's elastic displacement, true and estimated.
FIGURES = [OUT / "observer" / "fig_fft.png"]

# %%
# Fig. 11 (two levels, two runs: the quick form): eq. 21's mean absolute error against the payload increase.
FIGURES = [OUT / "payload_study" / "fig_payload.png"]
print("the report:", report)

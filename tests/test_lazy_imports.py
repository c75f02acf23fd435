"""What a user waits for before the filter runs: importing the package, the command line and the observer does not
import the large scipy subpackages (``scipy.signal``, ``scipy.stats``, ``scipy.optimize``, ``scipy.integrate``),
filterpy or matplotlib; the few functions that need them import them where they are called. The distribution
quantiles the filter needs at run time (chi-square, normal) come from ``scipy.special`` and equal scipy.stats'
bit for bit; the UKF's Merwe weights equal filterpy's."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("scipy.signal", "scipy.stats", "scipy.optimize", "scipy.integrate", "scipy.interpolate", "filterpy",
         "matplotlib", "exudyn")


def _loaded_after(code: str, names=HEAVY) -> list[str]:
    """The modules of ``names`` (default the heavy ones) in ``sys.modules`` after running ``code`` in a fresh
    interpreter (this checkout first on the path)."""
    probe = code + f"\nimport sys, json\nprint(json.dumps([m for m in {list(names)!r} if m in sys.modules]))\n"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, cwd=ROOT,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_package_cli_and_observer_imports_stay_light():
    code = ("import exuflex, exuflex.observer, exuflex.observer.session, exuflex.cli, exuflex.cli.observe, "
            "exuflex.runs, exuflex.validate, exuflex.scoring.output, exuflex.scoring.run, exuflex._compile\n"
            "from exuflex.cli import _build_parser\n_build_parser()")
    assert _loaded_after(code) == []


def test_a_command_line_imports_its_own_command_only():
    """``exuflex observe ...`` builds the parser of ``observe`` alone: the other commands' modules, and what they
    import (the truth engines' registry, the plots), stay unimported; ``exuflex --help`` still lists them all."""
    from exuflex.cli import COMMANDS, _build_parser

    others = [f"exuflex.cli.{c}" for c in COMMANDS if c != "observe"] + ["exuflex.truth", "exuflex.plots"]
    assert _loaded_after("from exuflex.cli import _build_parser\n_build_parser('observe')", others) == []
    assert set(_loaded_after("from exuflex.cli import _build_parser\n_build_parser()", others)) >= \
        {f"exuflex.cli.{c}" for c in COMMANDS if c != "observe"}
    helps = _build_parser().format_help()
    assert all(c in helps for c in COMMANDS)
    assert _build_parser("observe").parse_args(["observe", "m.toml", "run"]).run_dir == "run"


@pytest.mark.slow
def test_observe_command_stays_light():
    """The whole ``observe`` command on a log (kernels loaded from numba's cache or compiled)."""
    code = ("import io, contextlib\nfrom exuflex import cli\n"
            "with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):\n"
            "    assert cli.main(['observe', 'models/sixbar.toml', 'tests/data/sixbar_erls_3s']) == 0")
    assert _loaded_after(code) == []


def test_quantiles_equal_scipy_stats():
    from scipy.stats import chi2, norm

    from exuflex.observer.stats import chi2_ppf, norm_ppf

    for dof in (1, 2, 3, 6, 13, 40):
        for q in (0.0, 1e-9, 0.01, 0.025, 0.5, 0.95, 0.975, 0.99, 1 - 1e-9, 1.0):
            assert chi2_ppf(q, dof) == chi2.ppf(q, dof)
    dofs = np.array([1.0, 5.0, 120.0])
    np.testing.assert_array_equal(chi2_ppf(0.025, dofs), chi2.ppf(0.025, dofs))
    for q in (1e-6, 0.025, 0.5, 0.975):
        assert norm_ppf(q) == norm.ppf(q)


@pytest.mark.parametrize("n, alpha, beta, kappa", [(4, 1e-3, 2.0, 0.0), (13, 0.5, 2.0, 1.0), (7, 1.0, 0.0, 3.0)])
def test_ukf_weights_equal_filterpy(n, alpha, beta, kappa):
    from filterpy.kalman import MerweScaledSigmaPoints

    from exuflex.observer.base import LinearDiscreteModel
    from exuflex.observer.ukf import UnscentedKF

    pts = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)
    model = LinearDiscreteModel(np.eye(n), None, {"y0": np.eye(1, n)[0]}, np.eye(n))
    ukf = UnscentedKF(model, ["y0"], {"y0": 1.0}, np.zeros(n), np.eye(n), dt=0.01, alpha=alpha, beta=beta,
                      kappa=kappa)
    np.testing.assert_array_equal(ukf.Wm, pts.Wm)
    np.testing.assert_array_equal(ukf.Wc, pts.Wc)

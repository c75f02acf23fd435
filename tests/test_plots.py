"""Figures and animation from small synthetic signals (no observer run, no simulation, nothing shown)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from exuflex import plots
from exuflex.erls.modal import ModalResult
from exuflex.mechanism import load_mechanism
from exuflex.observer.ekf import EstimationResult
from exuflex.observer.session import Estimate
from exuflex.scoring.run import Outcome
from exuflex.runs import Run
from exuflex.sensors import Signals

MODEL = Path(__file__).resolve().parents[1] / "models" / "sixbar.toml"
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(autouse=True)
def _low_dpi(monkeypatch):
    monkeypatch.setattr(plots, "DPI", 50)  # faster tests; the files are still real PNGs


@pytest.fixture(scope="module")
def mech():
    return load_mechanism(MODEL)


def _is_png(p: Path) -> bool:
    return p.exists() and p.stat().st_size > 500 and p.read_bytes()[:8] == PNG


def _truth(mech, t, phase=0.0, noise=0.0, rng=None):
    """Physical-state table: q near q_ref with a slow swing, a 13 Hz tip vibration."""
    qn = mech.coordinate_names
    q0 = np.asarray(mech.q_ref, float)
    w = 2 * np.pi * 2.0
    Q = q0 + 0.02 * np.sin(w * t + phase)[:, None] * np.array([1.0, -0.5, 1.5])
    Qd = 0.02 * w * np.cos(w * t + phase)[:, None] * np.array([1.0, -0.5, 1.5])
    f = 2 * np.pi * 13.0
    E = np.column_stack([1e-3 * np.sin(f * t), 2e-3 * np.cos(f * t)])
    Ed = np.column_stack([1e-3 * f * np.cos(f * t), -2e-3 * f * np.sin(f * t)])
    data = np.hstack([Q, Qd, E, Ed])
    if noise and rng is not None:
        data = data + noise * rng.standard_normal(data.shape) * np.abs(data).max(axis=0)
    names = qn + tuple("d" + n for n in qn) + ("x25", "y26", "dx25", "dy26")
    units = ("rad",) * 3 + ("rad/s",) * 3 + ("m", "m", "m/s", "m/s")
    return Signals(t, names, data, units)


@pytest.fixture(scope="module")
def fake(mech):
    rng = np.random.default_rng(0)
    t = np.arange(0, 0.3, 0.002)
    truth = _truth(mech, t)
    est = _truth(mech, t, noise=1e-3, rng=rng)
    n, nx = len(t), 26
    sens_names = ("T1", "T2", "T3", "q1", "q2", "q3", "c1", "c2", "c4")
    sens = np.column_stack([rng.standard_normal((n, 3)), truth.data[:, :3], 1e-3 * rng.standard_normal((n, 3))])
    sensors = Signals(t, sens_names, sens, ("N m",) * 3 + ("rad",) * 3 + ("1/m",) * 3)
    run = Run(Path("/nonexistent"), sensors, truth, {"motors": ["T1", "T2", "T3"], "sensors": list(sens_names[3:])})
    nis = rng.chisquare(6, n)
    res = EstimationResult(t=t, x_hat=np.zeros((n, nx)), P=np.ones((n, nx)), innovations=np.zeros((n, 6)),
                           S=np.zeros((n, 6, 6)), nis=nis, nis_dof=np.full(n, 6), n_missing=0, n_updates=n,
                           diverged=False, diverged_at=None, nonfinite=False, wall_s=0.1,
                           channels=("q1", "q2", "q3", "c1", "c2", "c4"))
    bound = {name: 1e-4 for name in est.names}
    out = Outcome(Estimate(res, est, 0.1, 3.0), None, bound, {"config": {"start_up": 0.05}})
    return run, out


def test_observer_figures_with_truth(mech, fake, tmp_path):
    run, out = fake
    files = plots.observer_figures(tmp_path, mech, run, out)
    names = {f.name for f in files}
    for n in ("fig_trajectory.png", "fig_torques.png", "fig_joint_errors.png", "fig_tip_displacement.png",
              "fig_tip_errors.png", "fig_fft.png", "fig_nis.png", "fig_joint_states.png", "fig_measurements.png"):
        assert n in names, n
    assert all(_is_png(f) for f in files)
    assert not list(tmp_path.glob(".*tmp*")), "temporary files left behind"


def test_observer_figures_without_truth(mech, fake, tmp_path, monkeypatch):
    run, out = fake
    monkeypatch.setattr(plots, "clean_torques", lambda *a, **k: None)  # tested above; keep this test fast
    lab = Run(run.path, run.sensors, None, run.meta)
    files = plots.observer_figures(tmp_path, mech, lab, out)
    names = {f.name for f in files}
    assert {"fig_torques.png", "fig_nis.png", "fig_tip_displacement.png"} <= names
    assert not names & {"fig_joint_errors.png", "fig_tip_errors.png", "fig_fft.png"}
    assert all(_is_png(f) for f in files)


def test_tip_path_adds_elastic_displacement(mech, fake):
    run, _ = fake
    _t, p = plots.tip_path(mech, run.truth)
    rigid = run.truth.select(mech.coordinate_names)
    _t0, p0 = plots.tip_path(mech, rigid)
    assert np.allclose(p - p0, run.truth.select(("x25", "y26")).data, atol=1e-12)


def test_spectrum_peak_amplitude():
    t = np.arange(0, 2.0, 0.002)
    f, a = plots.spectrum(t, 3e-4 * np.sin(2 * np.pi * 40.0 * t))
    k = np.argmax(a)
    assert abs(f[k] - 40.0) < 0.3 and abs(a[k] - 3e-4) < 3e-5


def test_payload_study_figure(tmp_path):
    rows = [{"level": lv, "quantity": q, "mu": 1e-5 * (1 + lv / 100) * (i + 1), "sigma": 3e-6}
            for lv in (0, 25, 50, 75, 100) for i, q in enumerate(("x25", "y26", "dx25", "dy26"))]
    p = plots.payload_study_figure(rows, tmp_path / "fig11.png")
    assert _is_png(p)
    rows = [dict(r, title=f"{r['quantity']}: tip position (rigid + elastic)") for r in rows]
    assert _is_png(plots.payload_study_figure(rows, tmp_path / "fig11_titles.png"))


def test_animation_gif(mech, fake, tmp_path):
    run, out = fake
    p = plots.animate_manoeuvre(mech, run.truth, out.estimate.physical, tmp_path / "anim.gif", max_frames=8)
    assert p.suffix == ".gif" and p.read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    from PIL import Image

    with Image.open(p) as im:
        assert im.n_frames == 8


def test_animation_full_elastic_state(mech, fake, tmp_path):
    """With every ERLS elastic dof in the table, every link is drawn deformed."""
    from exuflex.erls.model import ErlsModel

    run, _ = fake
    model = ErlsModel(mech)
    tr = run.truth
    extra = tuple(n for n in model.dofs.names if n not in tr)
    u = 1e-3 * np.sin(2 * np.pi * 13 * tr.t)[:, None] * np.ones(len(extra))
    full = tr.hstack(Signals(tr.t, extra, u, ("m",) * len(extra)))
    assert plots._full_elastic(model, full)
    p = plots.animate_manoeuvre(mech, full, None, tmp_path / "anim_full.mp4", max_frames=4, magnify=10)
    assert p.exists() and p.stat().st_size > 0


def test_modes_figure(mech, tmp_path):
    nn = len(mech.node_ids)
    rng = np.random.default_rng(1)
    shapes = rng.standard_normal((3 * nn, 3)) * 1e-2
    mr = ModalResult(np.asarray(mech.q_ref), False, np.array([13.0, 43.0, 65.0]), np.zeros((1, 3)), shapes,
                     np.zeros(3), ())
    p = plots.modes_figure(mech, mr, tmp_path / "modes.png", n=6)
    assert _is_png(p)

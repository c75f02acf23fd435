"""Figures in the style of Palomba, Richiedei, Trevisani (Shock and Vibration 2018), and an animation.

Every function draws on its own :class:`matplotlib.figure.Figure` with an Agg canvas (no pyplot state,
nothing is ever shown) and writes a file, returning its path.

Paper figure → function (file written by :func:`observer_figures`):

- Fig. 3, end-effector trajectory → :func:`trajectory_figure` (``fig_trajectory.png``)
- Fig. 4, actuator torques → :func:`torques_figure` (``fig_torques.png``)
- Fig. 5, measured outputs → :func:`measurements_figure` (``fig_measurements.png``)
- Figs 6-7, joint angles/rates and their errors → :func:`joint_states_figure` (``fig_joint_states.png``),
  :func:`joint_errors_figure` (``fig_joint_errors.png``)
- Figs 8-9, tip elastic displacements/velocities and errors → :func:`tip_displacement_figure`
  (``fig_tip_displacement.png``), :func:`tip_errors_figure` (``fig_tip_errors.png``)
- Fig. 10, FFT of the tip elastic displacements → :func:`fft_figure` (``fig_fft.png``)
- Fig. 11, payload sensitivity (eq. 21) → :func:`payload_study_figure`; a parameter sweep → :func:`sweep_figure`;
  either from a study's summary → :func:`study_figure`
- not in the paper: filter consistency → :func:`nis_figure` (``fig_nis.png``); mode shapes at q* →
  :func:`modes_figure`; animation of the manoeuvre → :func:`animate_manoeuvre`.

Colours follow the paper: truth ("Simulator") red, estimate ("Observer") blue.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

if "matplotlib.pyplot" not in sys.modules:  # never switch the backend of a session already using pyplot
    matplotlib.use("Agg")

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .erls.kinematics import Kinematics, KinematicsError
from .sensors import Signals, tip_dof_names, tip_point

__all__ = [
    "ESTIMATE_COLOUR",
    "TRUTH_COLOUR",
    "animate_manoeuvre",
    "clean_torques",
    "fft_figure",
    "joint_errors_figure",
    "joint_states_figure",
    "measurements_figure",
    "mode_probability_figure",
    "modes_figure",
    "nis_figure",
    "observer_figures",
    "payload_study_figure",
    "spectrum",
    "study_figure",
    "sweep_figure",
    "tip_displacement_figure",
    "tip_errors_figure",
    "tip_path",
    "torques_figure",
    "trajectory_figure",
]

log = logging.getLogger(__name__)

TRUTH_COLOUR = "tab:red"
ESTIMATE_COLOUR = "tab:blue"
MEASURED_COLOUR = "0.55"
BOUND_COLOUR = "tab:green"
DPI = 110



# ------------------------------------------------------------------------------------------ helpers
PAPER_MODELS = ("sixbar",)
"""Mechanisms whose figures name the paper's (Palomba et al. 2018's six-bar); others get plain captions."""


def _cf(paper, figs: str, extra: str = "") -> str:
    """`` (cf. paper Fig. N)`` when ``paper`` is true or a mechanism of :data:`PAPER_MODELS`; else only ``extra``."""
    if paper is not None and not isinstance(paper, bool):
        paper = getattr(paper, "name", None) in PAPER_MODELS
    inner = "; ".join(x for x in ((f"cf. paper {figs}" if paper else ""), extra) if x)
    return f" ({inner})" if inner else ""


def _figure(nrows: int = 1, ncols: int = 1, size=(8.0, 5.0), **kw):
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    return fig, axes


def _save(fig: Figure, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    fig.savefig(tmp, dpi=DPI)
    os.replace(tmp, path)
    return path


def _unit(sig: Signals | None, name: str, default: str = "") -> str:
    if sig is not None and name in sig and sig.units:
        return sig.unit(name)
    return default


def _guess_unit(name: str, nq_names: Sequence[str] = ()) -> str:
    """Unit of a physical quantity from its name (q*/dq* angles, others lengths)."""
    rate = name.startswith("d")
    base = name[1:] if rate else name
    angle = base in nq_names or (base.startswith("q") and base[1:].isdigit())
    if angle:
        return "rad/s" if rate else "rad"
    return "m/s" if rate else "m"


def _label(name: str) -> str:
    """Axis label of a quantity: ``dq1`` → ``dq1/dt``."""
    if name.startswith("d") and len(name) > 1 and not name.startswith("dt"):
        return f"d{name[1:]}/dt"
    return name


def _on(t_dst: np.ndarray, sig: Signals, name: str) -> np.ndarray:
    """Channel ``name`` of ``sig`` linearly interpolated onto ``t_dst`` (NaN outside its span)."""
    y = sig[name]
    ok = np.isfinite(y)
    if ok.sum() < 2:
        return np.full(len(t_dst), np.nan)
    out = np.interp(t_dst, sig.t[ok], y[ok], left=np.nan, right=np.nan)
    return out


def _start_up(outcome) -> float:
    try:
        return float(outcome.summary.get("config", {}).get("start_up", 0.0))
    except AttributeError:
        return 0.0


def _shade_start_up(ax, t0: float, start_up: float) -> None:
    if start_up > 0:
        ax.axvspan(t0, t0 + start_up, color="0.92", zorder=0, lw=0)


def _finite_rows(sig: Signals) -> np.ndarray:
    return np.all(np.isfinite(sig.data), axis=1)


# ------------------------------------------------------------------------------------------ tip path
def tip_path(mech, states: Signals, *, max_points: int | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Absolute tip position from q (rigid ERLS kinematics) plus the tip elastic displacement columns.

    Parameters
    ----------
    mech : Mechanism
    states : Signals
        Must hold the coordinate columns; the tip elastic columns (e.g. ``x25``, ``y26``) are added if present.
    max_points : int, optional
        Evaluate at most this many (evenly spaced) samples.

    Returns
    -------
    (t, p) : ndarray (k,), ndarray (k, 2)
        Times and tip positions (m); None if the mechanism has no tip or the columns are missing.
    """
    tp = tip_point(mech)
    qn = mech.coordinate_names
    if tp is None or any(n not in states for n in qn):
        return None
    ex, ey = tip_dof_names(mech)
    Q = states.select(qn).data
    has_e = ex in states and ey in states
    E = states.select((ex, ey)).data if has_e else np.zeros((len(states.t), 2))
    ok = np.all(np.isfinite(Q), axis=1) & np.all(np.isfinite(E), axis=1)
    idx = np.flatnonzero(ok)
    if max_points is not None and len(idx) > max_points:
        idx = idx[np.linspace(0, len(idx) - 1, max_points).round().astype(int)]
    kin = Kinematics(mech)
    p = np.full((len(idx), 2), np.nan)
    z = None
    for k, i in enumerate(idx):
        try:
            pose = kin.pose(Q[i], z)
        except KinematicsError:
            z = None
            continue
        z = pose.z
        p[k] = kin.point(pose, *tp)[0] + E[i]
    return states.t[idx], p


def _planned_arc(mech) -> np.ndarray | None:
    man = mech.manoeuvre
    if man is None or man.kind != "tip_arc" or man.centre is None:
        return None
    phi = np.linspace(man.phi_start, man.phi_end, 200)
    return np.column_stack([man.centre[0] + man.radius * np.cos(phi), man.centre[1] + man.radius * np.sin(phi)])


def trajectory_figure(mech, truth: Signals | None, estimate: Signals | None, path,
                      sensors: Signals | None = None) -> Path:
    """End-effector trajectory in the plane (the paper's Fig. 3) and the tip position error.

    The actual path is the run's ``tip_x``/``tip_y`` sensor channels if present, else the truth's q through
    the rigid kinematics plus its tip elastic displacement; the estimated path is the same construction
    from the estimate. The planned arc is drawn dashed.

    Parameters
    ----------
    mech : Mechanism
    truth, estimate : Signals or None
        Physical states (q, dq, tip elastic displacement and rate).
    path : path-like
        PNG file written.
    sensors : Signals, optional
        Measured channels; ``tip_x``/``tip_y`` give the actual tip path when present.

    Returns
    -------
    Path
    """
    actual = None
    if sensors is not None and "tip_x" in sensors and "tip_y" in sensors:
        ok = np.isfinite(sensors["tip_x"]) & np.isfinite(sensors["tip_y"])
        actual = sensors.t[ok], np.column_stack([sensors["tip_x"][ok], sensors["tip_y"][ok]])
    elif truth is not None:
        actual = tip_path(mech, truth, max_points=800)
    est = tip_path(mech, estimate, max_points=800) if estimate is not None else None
    with_err = actual is not None and est is not None
    fig, axes = _figure(1, 2 if with_err else 1, size=(11.0, 5.0) if with_err else (6.0, 5.5))
    ax = axes[0, 0]
    arc = _planned_arc(mech)
    if arc is not None:
        ax.plot(arc[:, 0], arc[:, 1], "k--", lw=0.8, label="planned path")
    if actual is not None:
        ax.plot(actual[1][:, 0], actual[1][:, 1], color=TRUTH_COLOUR, lw=1.6, label="Simulator (actual)")
    if est is not None:
        ax.plot(est[1][:, 0], est[1][:, 1], color=ESTIMATE_COLOUR, lw=1.0, label="Observer (estimated)")
    ax.set_xlabel("x end effector (m)")
    ax.set_ylabel("y end effector (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("End-effector trajectory" + _cf(mech, "Fig. 3"))
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=8)
    if with_err:
        ta, pa = actual
        te, pe = est
        px = np.interp(te, ta, pa[:, 0], left=np.nan, right=np.nan)
        py = np.interp(te, ta, pa[:, 1], left=np.nan, right=np.nan)
        err = np.hypot(pe[:, 0] - px, pe[:, 1] - py)
        ax2 = axes[0, 1]
        ax2.semilogy(te, np.where(err > 0, err, np.nan), color=ESTIMATE_COLOUR, lw=0.8)
        ax2.set_xlabel("t (s)")
        ax2.set_ylabel("|tip position error| (m)")
        ax2.set_title("Estimated minus actual tip position")
        ax2.grid(True, which="both", lw=0.3)
    return _save(fig, path)


# ------------------------------------------------------------------------------------------ torques
def clean_torques(mech, t: np.ndarray, max_points: int = 400) -> Signals | None:
    """The open-loop computed torques of the nominal rigid model on (a subsample of) the times ``t``.

    Returns None when the mechanism has no manoeuvre or the plan fails.
    """
    if mech.manoeuvre is None or len(t) < 2:
        return None
    from .manoeuvre import computed_torque, plan

    t0, t1 = float(t[0]), float(t[-1])
    dt = max((t1 - t0) / max_points, float(np.median(np.diff(t))))
    try:
        p = plan(mech, dt=dt, t_end=t1)
        tau = computed_torque(mech, p)
    except Exception as exc:  # noqa: BLE001 - a figure must not break the run
        log.warning("could not compute the clean computed torques (%s); plotting the measured ones only", exc)
        return None
    sel = p.t >= t0 - 1e-12
    return Signals(p.t[sel], mech.motor_names, np.asarray(tau)[sel], ("N m",) * len(mech.motor_names))


def torques_figure(measured: Signals, motors: Sequence[str], path, clean: Signals | None = None,
                   paper: bool = False) -> Path:
    """Actuator torques (the paper's Fig. 4): the measured (noisy) inputs and the clean computed torques.

    Parameters
    ----------
    measured : Signals
        Sensor table holding the motor columns.
    motors : sequence of str
        Motor column names.
    path : path-like
    clean : Signals, optional
        Clean computed torques (e.g. :func:`clean_torques`).

    Returns
    -------
    Path
    """
    n = max(len(motors), 1)
    fig, axes = _figure(n, 1, size=(8.0, 2.2 * n + 0.6), sharex=True)
    for j, m in enumerate(motors):
        ax = axes[j, 0]
        if m in measured:
            ax.plot(measured.t, measured[m], color=MEASURED_COLOUR, lw=0.5, label="measured (noisy)")
        if clean is not None and m in clean:
            ax.plot(clean.t, clean[m], color="k", lw=1.2, label="computed torque (rigid model)")
        ax.set_ylabel(f"{m} ({_unit(measured, m, 'N m') or 'N m'})")
        ax.grid(True, lw=0.3)
        if j == 0:
            ax.legend(fontsize=8, loc="best")
    axes[-1, 0].set_xlabel("t (s)")
    fig.suptitle("Actuator torques" + _cf(paper, "Fig. 4"))
    return _save(fig, path)


def measurements_figure(measured: Signals, channels: Sequence[str], path, paper: bool = False) -> Path:
    """Measured outputs used by the observer (the paper's Fig. 5): one panel per channel, each on its own axis
    (encoders in rad, gauges in 1/m: a shared axis would hide their noise and motion)."""
    channels = [c for c in channels if c in measured]
    n = max(len(channels), 1)
    ncols = 1 if n <= 3 else 2
    nrows = -(-n // ncols)
    fig, axes = _figure(nrows, ncols, size=(8.0 if ncols == 1 else 11.0, 1.9 * nrows + 0.8), sharex=True)
    for i, c in enumerate(channels):
        ax = axes[i % nrows, i // nrows]
        y = measured[c]
        ok = np.isfinite(y)
        ax.plot(measured.t[ok], y[ok], lw=0.6, color=MEASURED_COLOUR)
        ax.set_ylabel(f"{c} ({_unit(measured, c, '') or '-'})")
        ax.grid(True, lw=0.3)
    for j in range(len(channels), nrows * ncols):
        axes[j % nrows, j // nrows].set_visible(False)
    for col in range(ncols):
        last = min(nrows, len(channels) - col * nrows) - 1
        if last >= 0:
            axes[last, col].set_xlabel("t (s)")
            axes[last, col].xaxis.set_tick_params(labelbottom=True)
    fig.suptitle("Measured outputs" + _cf(paper, "Fig. 5"))
    return _save(fig, path)


# ------------------------------------------------------------------------------------------ states
def _limits_after(t, y, t_from: float, other=None, margin: float = 0.08):
    """y-limits from the samples after ``t_from`` (the start-up spike, often orders of magnitude larger than the
    motion, would flatten everything else), ``other`` (times, values) included; None if nothing to go by."""
    parts = [np.asarray(y)[np.asarray(t) >= t_from]]
    if other is not None:
        parts.append(np.asarray(other[1])[np.asarray(other[0]) >= t_from])
    v = np.concatenate(parts)
    v = v[np.isfinite(v)]
    if v.size < 2 or t_from <= t[0]:
        return None
    lo, hi = float(v.min()), float(v.max())
    pad = margin * (hi - lo) if hi > lo else max(abs(hi), 1e-12) * margin
    return lo - pad, hi + pad


def _state_grid(names: Sequence[str], truth: Signals | None, estimate: Signals, path, title: str,
                ncols: int, start_up: float = 0.0, errors: bool = False,
                bound: Mapping[str, float] | None = None, size=None) -> Path:
    names = [n for n in names if n in estimate and (not errors or (truth is not None and n in truth))]
    nrows = max(int(np.ceil(len(names) / ncols)), 1)
    fig, axes = _figure(nrows, ncols, size=size or (5.0 * ncols, 2.4 * nrows + 0.8), sharex=True)
    t = estimate.t
    for k, n in enumerate(names):
        ax = axes[k // ncols, k % ncols]
        unit = _unit(estimate, n, _guess_unit(n))
        _shade_start_up(ax, t[0], start_up)
        if errors:
            e = estimate[n] - _on(t, truth, n)
            ax.plot(t, e, color=ESTIMATE_COLOUR, lw=0.6, label="estimation error")
            b = None if bound is None else bound.get(n)
            if b is not None and np.isfinite(b) and b > 0:
                for s, ls in ((1, "-"), (3, "--")):
                    ax.axhline(s * b, color=BOUND_COLOUR, lw=0.9, ls=ls, label=f"±{s}× RMS bound")
                    ax.axhline(-s * b, color=BOUND_COLOUR, lw=0.9, ls=ls)
            sel = t >= t[0] + start_up
            ef = e[sel][np.isfinite(e[sel])]
            if ef.size:
                rms = float(np.sqrt(np.mean(ef**2)))
                ax.text(0.01, 0.97, f"RMS {rms:.3g} {unit}" + (f" (bound {b:.3g})" if b else ""),
                        transform=ax.transAxes, va="top", fontsize=7,
                        bbox={"fc": "white", "ec": "none", "alpha": 0.7})
                lim = 1.3 * max(np.max(np.abs(ef)), 3 * b if b else 0.0)
                if lim > 0:
                    ax.set_ylim(-lim, lim)
            ax.set_ylabel(f"{_label(n)} error ({unit})")
        else:
            if truth is not None and n in truth:
                ax.plot(truth.t, truth[n], color=TRUTH_COLOUR, lw=1.4, label="Simulator")
            ax.plot(t, estimate[n], color=ESTIMATE_COLOUR, lw=0.7, label="Observer")
            ax.set_ylabel(f"{_label(n)} ({unit})")
            lim = _limits_after(t, estimate[n], t[0] + start_up,
                                (truth.t, truth[n]) if truth is not None and n in truth else None)
            if lim is not None:
                ax.set_ylim(*lim)
        ax.grid(True, lw=0.3)
        if k == 0:
            ax.legend(fontsize=7, loc="lower right")
    for k in range(len(names), nrows * ncols):
        axes[k // ncols, k % ncols].set_visible(False)
    for c in range(ncols):
        axes[-1, c].set_xlabel("t (s)")
    fig.suptitle(title)
    return _save(fig, path)


def joint_states_figure(mech, truth: Signals | None, estimate: Signals, path, start_up: float = 0.0) -> Path:
    """Estimated vs true joint angles and rates (the paper's Figs 6a, 7a): columns q_j, rows angle/rate."""
    qn = mech.coordinate_names
    names = list(qn) + ["d" + n for n in qn]
    return _state_grid(names, truth, estimate, path, "Actuated-link angles and rates" + _cf(mech, "Figs 6a, 7a"),
                       ncols=len(qn), start_up=start_up)


def joint_errors_figure(mech, truth: Signals, estimate: Signals, path, bound: Mapping[str, float] | None = None,
                        start_up: float = 0.0) -> Path:
    """Estimation errors of the joint angles and rates (the paper's Figs 6b, 7b) with ±1, ±3 × the RMS bound."""
    qn = mech.coordinate_names
    names = list(qn) + ["d" + n for n in qn]
    return _state_grid(names, truth, estimate, path,
                       "Joint estimation errors" + _cf(mech, "Figs 6b, 7b", "grey: start-up excluded from RMS"),
                       ncols=len(qn), start_up=start_up, errors=True, bound=bound)


def _tip_names(mech) -> list[str]:
    if tip_point(mech) is None:
        return []
    ex, ey = tip_dof_names(mech)
    return [ex, ey, "d" + ex, "d" + ey]


def tip_displacement_figure(mech, truth: Signals | None, estimate: Signals, path, start_up: float = 0.0) -> Path:
    """True vs estimated tip elastic displacements and velocities (the paper's Figs 8a, 9a)."""
    return _state_grid(_tip_names(mech), truth, estimate, path,
                       "Tip elastic displacements and velocities" + _cf(mech, "Figs 8a, 9a"), ncols=2,
                       start_up=start_up)


def tip_errors_figure(mech, truth: Signals, estimate: Signals, path, bound: Mapping[str, float] | None = None,
                      start_up: float = 0.0) -> Path:
    """Estimation errors of the tip elastic displacements and velocities (the paper's Figs 8b, 9b)."""
    return _state_grid(_tip_names(mech), truth, estimate, path,
                       "Tip elastic estimation errors" + _cf(mech, "Figs 8b, 9b"), ncols=2, start_up=start_up,
                       errors=True, bound=bound)


# ------------------------------------------------------------------------------------------ FFT
def spectrum(t, x, pad: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """One-sided magnitude spectrum (Hann window, de-meaned, zero-padded), normalised like
    :func:`exuflex.scoring.stats.fft_peaks` (a sinusoid of amplitude A shows a peak of about A).

    Non-uniform or gappy samples are first interpolated onto a uniform grid.
    """
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    ok = np.isfinite(x)
    t, x = t[ok], x[ok]
    n = len(x)
    if n < 4:
        return np.zeros(0), np.zeros(0)
    dt = (t[-1] - t[0]) / (n - 1)
    if not np.allclose(np.diff(t), dt, rtol=1e-6, atol=1e-12):
        tu = np.linspace(t[0], t[-1], n)
        x = np.interp(tu, t, x)
    x = x - x.mean()
    w = np.hanning(n)
    nfft = 1 << int(np.ceil(np.log2(n * pad)))
    return np.fft.rfftfreq(nfft, dt), np.abs(np.fft.rfft(x * w, nfft)) * (2.0 / w.sum())


def fft_figure(mech, truth: Signals | None, estimate: Signals, path, fmax: float = 180.0, n_peaks: int = 4,
               start: float = 0.0, peak_floor: float = 0.05) -> Path:
    """FFT magnitude of the true and estimated tip elastic displacements over ``fmin``-``fmax`` Hz (``fmin`` =
    max(5 Hz, 4 / record length): the 0 Hz bin and the manoeuvre's slow content left out), each curve normalised
    to its strongest peak there, peaks marked and labelled once (the paper's Fig. 10).

    Parameters
    ----------
    mech : Mechanism
    truth : Signals or None
    estimate : Signals
    path : path-like
    fmax : float
        Upper frequency shown (Hz); the paper's reduced model is tuned for 0-180 Hz.
    n_peaks : int
        Peaks marked per curve (by :func:`exuflex.scoring.stats.fft_peaks`), searched above
        ``max(5 Hz, 4 / record length)`` (below that is the manoeuvre's own rigid-motion content).
    peak_floor : float
        Peaks weaker than this fraction of the curve's strongest peak are not marked.
    start : float
        Samples before ``t0 + start`` are left out (e.g. the filter's start-up).

    Returns
    -------
    Path
    """
    from .scoring.stats import fft_peaks

    names = _tip_names(mech)[:2]
    fig, axes = _figure(1, max(len(names), 1), size=(11.0, 4.2))
    t = estimate.t
    sel = t >= t[0] + start
    for k, n in enumerate(names):
        ax = axes[0, k]
        curves = []
        if truth is not None and n in truth:
            curves.append(("Simulator", TRUTH_COLOUR, 1.6, _on(t, truth, n)))
        if n in estimate:
            curves.append(("Observer", ESTIMATE_COLOUR, 0.9, estimate[n]))
        labelled: list[float] = []
        for lab, col, lw, x in curves:
            xs, ts = x[sel], t[sel]
            ok = np.isfinite(xs)
            f, a = spectrum(ts[ok], xs[ok])
            if f.size == 0:
                continue
            span = float(ts[ok][-1] - ts[ok][0])
            fmin = max(5.0, 4.0 / span) if span > 0 else 5.0  # leave the manoeuvre's own low-frequency content
            # from fmin: the 0 Hz bin and the manoeuvre's own slow content (which would dwarf the modes) left out
            band = (f >= fmin) & (f <= fmax)
            ref = a[band]
            scale = float(ref.max()) if ref.size and ref.max() > 0 else 1.0  # normalised to the strongest peak
            ax.plot(f[band], a[band] / scale, color=col, lw=lw, label=f"{lab} (max {scale:.2g} m)")
            try:
                fp, ap = fft_peaks(np.linspace(ts[ok][0], ts[ok][-1], ok.sum()), xs[ok], fmax=fmax,
                                   n_peaks=n_peaks, fmin=fmin, return_amplitudes=True)
            except ValueError:
                fp, ap = np.zeros(0), np.zeros(0)
            keep = ap >= peak_floor * (ap.max() if ap.size else 0.0)
            fp, ap = fp[keep], ap[keep] / scale
            marker = "v" if lab == "Simulator" else "^"
            ax.plot(fp, ap, marker, color=col, ms=6, mfc="none", ls="none")
            if lab == "Observer" and len(curves) > 1:
                continue  # the simulator's peaks are labelled; the observer's are marked
            for i, (f0, a0) in enumerate(sorted(zip(fp, ap, strict=True))):
                if any(abs(f0 - g) < 0.03 * fmax for g in labelled):
                    continue  # the same peak of the other curve is labelled already
                labelled.append(f0)
                ax.annotate(f"{f0:.1f} Hz", (f0, a0), textcoords="offset points", xytext=(4, 6 + 9 * (i % 2)),
                            fontsize=7, color=col)
        ax.set_xlim(0, fmax)
        ax.set_ylim(0, 1.25)
        ax.set_xlabel("Frequency (Hz)")
        ax.set_ylabel(f"|{n.upper()}| normalised")
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"FFT of the tip elastic displacements up to {fmax:g} Hz" + _cf(mech, "Fig. 10"))
    return _save(fig, path)


# ------------------------------------------------------------------------------------------ NIS
def nis_figure(result, path, window: int = 50, confidence: float = 0.95, start_up: float = 0.0) -> Path:
    """Normalised innovation squared vs time with chi-square bands.

    Points: the NIS of each update with its two-sided ``confidence`` band (dof = channels used); line: the
    moving average over ``window`` updates with its (much narrower) band. A consistent filter keeps the
    moving average inside its band.

    Parameters
    ----------
    result : EstimationResult
    path : path-like
    window : int
        Moving-average length (updates).
    confidence : float
    start_up : float
        Seconds shaded as the filter's start-up.

    Returns
    -------
    Path
    """
    from .scoring.stats import chi2_band

    t = np.asarray(result.t, float)
    v = np.asarray(result.nis, float)
    d = np.asarray(result.nis_dof, float)
    ok = np.isfinite(v) & (d > 0)
    fig, axes = _figure(1, 1, size=(9.0, 4.2))
    ax = axes[0, 0]
    if ok.any():
        _shade_start_up(ax, t[0], start_up)
        tt, vv, dd = t[ok], v[ok], d[ok]
        _lo, hi = chi2_band(dd, 1, confidence)
        ax.plot(tt, vv, ".", color=MEASURED_COLOUR, ms=1.5, label="NIS per update")
        ax.plot(tt, hi, color=MEASURED_COLOUR, lw=0.6, ls=":", label=f"{confidence:.0%} band per update")
        w = int(min(max(window, 1), len(vv)))
        ker = np.ones(w)
        ma = np.convolve(vv, ker, "valid") / w
        mdof = np.convolve(dd, ker, "valid")
        tm = tt[w - 1:]
        mlo, mhi = chi2_band(mdof, w, confidence)
        ax.plot(tm, ma, color=ESTIMATE_COLOUR, lw=1.0, label=f"moving mean ({w} updates)")
        ax.fill_between(tm, mlo, mhi, color=BOUND_COLOUR, alpha=0.25, lw=0,
                        label=f"{confidence:.0%} band of the moving mean")
        ax.plot(tm, mdof / w, color=BOUND_COLOUR, lw=0.8, ls="--", label="expected (mean dof)")
        mean, expected = float(vv.mean()), float(dd.mean())
        ax.set_title(f"Normalised innovation squared: mean {mean:.3g}, expected {expected:.3g}")
        top = max(np.nanpercentile(vv, 99.5), np.nanmax(hi), np.nanmax(ma)) * 1.1
        ax.set_ylim(0, top)
        ax.legend(fontsize=7, loc="upper right", ncol=2)
    else:
        ax.text(0.5, 0.5, "no updates", ha="center", va="center", transform=ax.transAxes)
        ax.set_title("Normalised innovation squared")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("NIS (-)")
    ax.grid(True, lw=0.3)
    return _save(fig, path)


def mode_probability_figure(result, path, start_up: float = 0.0) -> Path:
    """The posterior probability of the nominal payload vs time (the IMM's nominal mode, or the payload EKF's
    model average) and of the payload-scale hypothesis, ``1 - p``."""
    t = np.asarray(result.t, float)
    p = np.asarray(result.nominal_p, float)
    fig, axes = _figure(1, 1, size=(9.0, 3.6))
    ax = axes[0, 0]
    _shade_start_up(ax, t[0], start_up)
    ax.plot(t, p, color=ESTIMATE_COLOUR, lw=1.0, label="nominal payload")
    ax.plot(t, 1.0 - p, color=MEASURED_COLOUR, lw=1.0, ls="--", label="payload scale estimated")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("probability (-)")
    ax.legend(loc="best", fontsize=8)
    ax.grid(True, lw=0.3)
    return _save(fig, path)


# ------------------------------------------------------------------------------------------ all
def observer_figures(out_dir, mech, run, outcome) -> list[Path]:
    """All observer figures of one run into ``out_dir`` (truth-dependent ones only when the run has a truth).

    Files: ``fig_trajectory.png``, ``fig_torques.png``, ``fig_measurements.png``, ``fig_joint_states.png``,
    ``fig_tip_displacement.png``, ``fig_nis.png``, and with a truth ``fig_joint_errors.png``,
    ``fig_tip_errors.png``, ``fig_fft.png``; ``fig_payload_probability.png`` where the estimator reports the
    nominal payload's probability (:func:`mode_probability_figure`). A figure that fails is logged and skipped.

    Parameters
    ----------
    out_dir : path-like
    mech : Mechanism
    run : exuflex.runs.Run
    outcome : exuflex.scoring.run.Outcome

    Returns
    -------
    list of Path
        The files written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    est = outcome.estimate.physical
    res = outcome.estimate.result
    truth = run.truth
    bound = outcome.bound
    su = _start_up(outcome)
    motors = tuple(run.motors or mech.motor_names)
    channels = tuple(getattr(res, "channels", ()) or ()) or tuple(
        n for n in run.sensor_names if n not in ("tip_x", "tip_y"))
    jobs = [
        ("fig_trajectory.png", lambda p: trajectory_figure(mech, truth, est, p, sensors=run.sensors)),
        ("fig_torques.png", lambda p: torques_figure(run.sensors, motors, p, clean_torques(mech, run.sensors.t),
                                                     paper=mech.name in PAPER_MODELS)),
        ("fig_measurements.png", lambda p: measurements_figure(run.sensors, channels, p,
                                                               paper=mech.name in PAPER_MODELS)),
        ("fig_joint_states.png", lambda p: joint_states_figure(mech, truth, est, p, su)),
        ("fig_tip_displacement.png", lambda p: tip_displacement_figure(mech, truth, est, p, su)),
        ("fig_nis.png", lambda p: nis_figure(res, p, start_up=su)),
    ]
    if getattr(res, "nominal_p", None) is not None:
        jobs.append(("fig_payload_probability.png", lambda p: mode_probability_figure(res, p, start_up=su)))
    if truth is not None:
        jobs += [
            ("fig_joint_errors.png", lambda p: joint_errors_figure(mech, truth, est, p, bound, su)),
            ("fig_tip_errors.png", lambda p: tip_errors_figure(mech, truth, est, p, bound, su)),
            ("fig_fft.png", lambda p: fft_figure(mech, truth, est, p)),
        ]
    if tip_point(mech) is None:
        jobs = [j for j in jobs if j[0] not in ("fig_tip_displacement.png", "fig_tip_errors.png", "fig_fft.png")]
    written = []
    for name, job in jobs:
        try:
            written.append(job(out / name))
        except Exception as exc:  # noqa: BLE001 - one broken figure must not lose the others or the results
            log.warning("figure %s failed: %s: %s", name, type(exc).__name__, exc)
    return written


# ------------------------------------------------------------------------------------------ Fig. 11
def paper_payload_quantities(quantities: Sequence[str]) -> list[str]:
    """The four quantities of the paper's Fig. 11 panels among a study's: the tip coordinates' displacements and
    velocities, absolute (``tip_x tip_y dtip_x dtip_y``) where the study has them, else elastic (the two tip
    elastic dofs and their rates, e.g. ``x25 y26 dx25 dy26``); empty if neither set is complete."""
    qs = list(quantities)
    if all(q in qs for q in ("tip_x", "tip_y", "dtip_x", "dtip_y")):
        return ["tip_x", "tip_y", "dtip_x", "dtip_y"]
    elastic = [q for q in qs if not q.startswith("d") and not q.startswith("q") and not q.startswith("tip_")]
    if len(elastic) >= 2 and all("d" + q in qs for q in elastic[:2]):
        return [elastic[0], elastic[1], "d" + elastic[0], "d" + elastic[1]]
    return []


def payload_study_figure(table_rows: Sequence[Mapping], path, units: Mapping[str, str] | None = None,
                         paper: bool = False) -> Path:
    """Payload-mismatch sensitivity (the paper's Fig. 11): mean absolute error mu (markers) and its spread
    sigma (error bars) of each estimated quantity vs the payload increase (%), eq. 21.

    Parameters
    ----------
    table_rows : sequence of dict
        ``{"level": float (%), "quantity": str, "mu": float, "sigma": float}``, optionally ``"title"``: the
        panel's title (default the quantity's name; :func:`exuflex.study.figure_rows` names the tip panels
        "tip elastic displacement" or "tip position (rigid + elastic)"), and ``"series"``: the estimator
        (several series are drawn side by side in each panel, with a legend). Panels follow the rows' order of
        quantities, two per row of the figure.
    path : path-like
    units : dict, optional
        Unit per quantity; default guessed from the name (``q*`` rad, ``dq*`` rad/s, others m, ``d*`` m/s).

    Returns
    -------
    Path
    """
    quantities: list[str] = []
    titles: dict[str, str] = {}
    for r in table_rows:
        if r["quantity"] not in quantities:
            quantities.append(r["quantity"])
        if r.get("title"):
            titles.setdefault(r["quantity"], str(r["title"]))
    n = max(len(quantities), 1)
    ncols = 2 if n > 1 else 1
    nrows = int(np.ceil(n / ncols))
    fig, axes = _figure(nrows, ncols, size=(5.0 * ncols, 2.8 * nrows + 0.7))
    for k, qname in enumerate(quantities):
        ax = axes[k // ncols, k % ncols]
        rows = sorted((r for r in table_rows if r["quantity"] == qname), key=lambda r: float(r["level"]))
        lv = np.array([float(r["level"]) for r in rows])
        mu = np.array([float(r["mu"]) for r in rows])
        sg = np.array([float(r["sigma"]) for r in rows])
        unit = (units or {}).get(qname) or _guess_unit(qname)
        series = list(dict.fromkeys(r.get("series") for r in rows))
        step = np.min(np.diff(np.unique(lv))) if np.unique(lv).size > 1 else 10.0
        for j, name in enumerate(series):
            sel = np.array([r.get("series") == name for r in rows])
            dx = (j - (len(series) - 1) / 2) * 0.05 * step if len(series) > 1 else 0.0
            ax.errorbar(lv[sel] + dx, mu[sel], yerr=sg[sel], fmt="o",
                        color=ESTIMATE_COLOUR if name is None else f"C{j}", ecolor="k", elinewidth=1.0, capsize=4,
                        label="mean μ ± std σ of |error|" if name is None else f"{name}: μ ± σ")
        ax.set_xlabel("payload increase (%)")
        ax.set_ylabel(f"|{_label(qname)} error| ({unit})")
        ax.set_title(titles.get(qname, _label(qname)), fontsize=10)
        ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 2))
        if lv.size:
            span = max(lv.max() - lv.min(), 1.0)
            pad = 0.08 * span + 0.05 * step * (len(series) - 1) / 2
            ax.set_xlim(lv.min() - pad, lv.max() + pad)
            ax.set_xticks(np.unique(lv))
        ax.set_ylim(bottom=min(0.0, float(np.nanmin(mu - sg)) if mu.size else 0.0))
        ax.grid(True, lw=0.3)
        if k == 0:
            ax.legend(fontsize=7)
    for k in range(len(quantities), nrows * ncols):
        axes[k // ncols, k % ncols].set_visible(False)
    fig.suptitle("Sensitivity to the tip payload mismatch, eq. 21" + _cf(paper, "Fig. 11"))
    return _save(fig, path)


# ------------------------------------------------------------------------------------------ drawing links
def _link_segments(kin: Kinematics, pose, mech) -> list[np.ndarray]:
    """Rigid polyline (2 points) of every link at ``pose``."""
    out = []
    for i, lk in enumerate(mech.links):
        x, y, th = pose.z[3 * i: 3 * i + 3]
        out.append(np.array([[x, y], [x + lk.length * np.cos(th), y + lk.length * np.sin(th)]]))
    return out


def _hermite_links(mech, node_ids: Sequence[int], r: np.ndarray, d: np.ndarray, scale: float,
                   n_sub: int = 8) -> list[np.ndarray]:
    """Deformed polyline of every link: ERLS nodal rigid coordinates ``r`` (3 N) plus ``scale`` × nodal
    displacements ``d`` (3 N: x, y, theta in the global frame), cubic Hermite transverse and linear axial
    interpolation inside each element."""
    idx = {n: k for k, n in enumerate(node_ids)}
    xi = np.linspace(0.0, 1.0, n_sub + 1)
    h1, h2 = 1 - 3 * xi**2 + 2 * xi**3, xi - 2 * xi**2 + xi**3
    h3, h4 = 3 * xi**2 - 2 * xi**3, -(xi**2) + xi**3
    out = []
    for lk in mech.links:
        pts = []
        for a in range(lk.n_elements):
            ia, ib = idx[lk.node_ids[a]], idx[lk.node_ids[a + 1]]
            pa, pb = r[3 * ia: 3 * ia + 2], r[3 * ib: 3 * ib + 2]
            L = float(np.hypot(*(pb - pa)))
            if L <= 0:
                continue
            ex = (pb - pa) / L
            ey = np.array([-ex[1], ex[0]])
            da, db = scale * d[3 * ia: 3 * ia + 3], scale * d[3 * ib: 3 * ib + 3]
            ua, ub = da[:2] @ ex, db[:2] @ ex
            va, vb = da[:2] @ ey, db[:2] @ ey
            axial = (1 - xi) * ua + xi * ub
            trans = h1 * va + h2 * L * da[2] + h3 * vb + h4 * L * db[2]
            seg = pa[None, :] + np.outer(xi * L + axial, ex) + np.outer(trans, ey)
            pts.append(seg if not pts else seg[1:])
        out.append(np.vstack(pts) if pts else np.zeros((0, 2)))
    return out


def _bent_tip_link(kin: Kinematics, pose, mech, tip, e: np.ndarray, n_sub: int = 12) -> np.ndarray:
    """Polyline of the tip's link with only its tip displaced by ``e`` (already magnified), blended along the
    link with the cantilever shape ``(s/L)^2 (3 - s/L) / 2`` from the link's start."""
    link, station = tip
    i = kin.link_names.index(link)
    x, y, th = pose.z[3 * i: 3 * i + 3]
    s = np.linspace(0.0, station, n_sub + 1)
    p = np.column_stack([x + s * np.cos(th), y + s * np.sin(th)])
    xi = s / station if station > 0 else np.ones_like(s)
    return p + np.outer(xi**2 * (3 - xi) / 2, e)


def _full_elastic(model, sig: Signals) -> bool:
    return all(n in sig for n in model.dofs.names)


def animate_manoeuvre(mech, truth: Signals, estimate: Signals | None, path, magnify: float = 50.0,
                      fps: int = 25, max_frames: int = 150, dpi: int = 80) -> Path:
    """Animation of the manoeuvre: the mechanism's links at each frame, truth and estimate overlaid.

    Each frame draws the rigid ERLS pose from the frame's q (:class:`Kinematics`) with the elastic
    deformation magnified by ``magnify``:

    - when the table holds every ERLS elastic dof (``model.dofs.names``, e.g. a full-state record), every
      link is drawn deformed (cubic Hermite between nodes);
    - otherwise only the tip elastic displacement (``x25``, ``y26``) is known: the tip's link is drawn bent so
      that its tip sits at the magnified displaced position, the other links rigid.

    Truth red, estimate blue (dashed); the tip's path so far is traced.

    Parameters
    ----------
    mech : Mechanism
    truth : Signals
        Must hold the coordinate columns (``q1`` ...).
    estimate : Signals or None
        Same columns; interpolated onto the truth's frame times.
    path : path-like
        ``.gif`` (Pillow) or ``.mp4`` (only if ``ffmpeg`` is on the PATH; otherwise a ``.gif`` is written
        next to it and that path returned).
    magnify : float
        Elastic deformation scale.
    fps : int
    max_frames : int
        Frames are evenly spaced in time, at most this many.
    dpi : int

    Returns
    -------
    Path
        The file written.
    """
    from .erls.model import ErlsModel

    path = Path(path)
    if path.suffix.lower() == ".mp4" and shutil.which("ffmpeg") is None:
        log.warning("ffmpeg not found; writing a GIF instead of %s", path)
        path = path.with_suffix(".gif")
    qn = mech.coordinate_names
    ok = np.all(np.isfinite(truth.select(qn).data), axis=1)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        raise ValueError("animate_manoeuvre: the truth has no finite coordinate sample")
    if len(idx) > max_frames:
        idx = idx[np.linspace(0, len(idx) - 1, max_frames).round().astype(int)]
    tf = truth.t[idx]
    kin = Kinematics(mech)
    tp = tip_point(mech)
    tipn = tip_dof_names(mech)[:2] if tp is not None else None
    model = ErlsModel(mech)
    if not _full_elastic(model, truth):
        model = None  # only the tip elastic displacement is known

    def frames_of(sig: Signals, on_truth: bool):
        if on_truth:
            Q = sig.select(qn).data[idx]
            get = lambda n: sig[n][idx]
        else:
            Q = np.column_stack([_on(tf, sig, n) for n in qn])
            get = lambda n: _on(tf, sig, n)
        full = model is not None and _full_elastic(model, sig)
        U = np.column_stack([get(n) for n in model.dofs.names]) if full else None
        E = None
        if tipn is not None and all(n in sig for n in tipn):
            E = np.column_stack([get(tipn[0]), get(tipn[1])])
        polys, tips = [], []
        z = None
        for k in range(len(tf)):
            if not np.all(np.isfinite(Q[k])):
                polys.append(None)
                tips.append(np.full(2, np.nan))
                continue
            try:
                pose = kin.pose(Q[k], z)
            except KinematicsError:
                polys.append(None)
                tips.append(np.full(2, np.nan))
                z = None
                continue
            z = pose.z
            if full and np.all(np.isfinite(U[k])):
                d = model.nodal_displacements(U[k])
                lines = _hermite_links(mech, kin.node_ids, pose.r, d, magnify)
                tip = kin.point(pose, *tp)[0] + magnify * (E[k] if E is not None else 0.0) if tp else None
            else:
                lines = _link_segments(kin, pose, mech)
                tip = None
                if tp is not None:
                    e = magnify * E[k] if E is not None and np.all(np.isfinite(E[k])) else np.zeros(2)
                    li = kin.link_names.index(tp[0])
                    bent = _bent_tip_link(kin, pose, mech, tp, e)
                    lk = mech.links[li]
                    if tp[1] < lk.length:  # the link goes on past the tip: keep the rest rigid
                        bent = np.vstack([bent, lines[li][1:]])
                    lines[li] = bent
                    tip = bent[-1] if tp[1] >= lk.length else kin.point(pose, *tp)[0] + e
            polys.append(lines)
            tips.append(np.asarray(tip, float) if tip is not None else np.full(2, np.nan))
        return polys, np.array(tips)

    tr_polys, tr_tips = frames_of(truth, True)
    es = frames_of(estimate, False) if estimate is not None and all(n in estimate for n in qn) else None

    allpts = np.vstack([np.vstack(p) for p in tr_polys if p is not None])
    lo, hi = np.nanmin(allpts, axis=0), np.nanmax(allpts, axis=0)
    pad = 0.08 * float(np.max(hi - lo))
    fig = Figure(figsize=(5.6, 5.0), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, lw=0.3)
    arc = _planned_arc(mech)
    if arc is not None:
        ax.plot(arc[:, 0], arc[:, 1], "k:", lw=0.7, label="planned tip path")
    for j in mech.joints:
        _draw_ground(ax, j, lo, hi, pad, 8)
    n_links = len(mech.links)
    tr_lines = [ax.plot([], [], "-o", color=TRUTH_COLOUR, lw=2.2, ms=2.5,
                        label="truth" if i == 0 else None)[0] for i in range(n_links)]
    tr_trace, = ax.plot([], [], color=TRUTH_COLOUR, lw=0.8, alpha=0.6)
    es_lines, es_trace = [], None
    if es is not None:
        es_lines = [ax.plot([], [], "--", color=ESTIMATE_COLOUR, lw=1.4,
                            label="estimate" if i == 0 else None)[0] for i in range(n_links)]
        es_trace, = ax.plot([], [], color=ESTIMATE_COLOUR, lw=0.8, alpha=0.6, ls="--")
    ax.legend(fontsize=7, loc="upper right")
    what = "all links" if model is not None else "tip only"
    ax.set_title(f"Manoeuvre (elastic deformation ×{magnify:g}, {what})", fontsize=9)
    stamp = ax.text(0.02, 0.97, "", transform=ax.transAxes, va="top", fontsize=9)
    dynamic = [*tr_lines, tr_trace, *es_lines, *([es_trace] if es_trace is not None else []), stamp]
    for a in dynamic:
        a.set_animated(True)
    # blitting: the static background (axes, ticks, labels, legend) is drawn once
    fig.set_dpi(dpi)
    canvas = fig.canvas
    canvas.draw()
    fig.set_layout_engine("none")
    background = canvas.copy_from_bbox(fig.bbox)
    frames = []
    for k in range(len(tf)):
        for lines, polys in ((tr_lines, tr_polys),) + (((es_lines, es[0]),) if es is not None else ()):
            p = polys[k]
            for i, ln in enumerate(lines):
                if p is None:
                    ln.set_data([], [])
                else:
                    ln.set_data(p[i][:, 0], p[i][:, 1])
        tr_trace.set_data(tr_tips[: k + 1, 0], tr_tips[: k + 1, 1])
        if es_trace is not None:
            es_trace.set_data(es[1][: k + 1, 0], es[1][: k + 1, 1])
        stamp.set_text(f"t = {tf[k]:.3f} s")
        canvas.restore_region(background)
        for a in dynamic:
            ax.draw_artist(a)
        frames.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
    return _write_movie(frames, path, fps)


def _draw_ground(ax, j, lo, hi, pad: float, ms: float) -> None:
    """A ground pin as a triangle; a prismatic joint's axis as a dash-dotted line across the view."""
    if j.ground is None:
        return
    if j.kind != "prismatic":
        ax.plot(*j.ground, "k^", ms=ms)
        return
    g, d = np.asarray(j.ground, float), np.asarray(j.axis, float)
    span = float(np.hypot(*(np.asarray(hi) - np.asarray(lo)))) + 2 * pad
    s = np.array([-span, span]) + float(d @ (0.5 * (np.asarray(lo) + np.asarray(hi)) - g))
    ax.plot(g[0] + s * d[0], g[1] + s * d[1], "k-.", lw=0.8)


def _write_movie(frames: list[np.ndarray], path: Path, fps: int) -> Path:
    """Write RGB frames as a GIF (Pillow, as :class:`matplotlib.animation.PillowWriter` does) or an MP4
    (``ffmpeg`` raw-video pipe)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    if path.suffix.lower() == ".mp4":
        import subprocess

        h, w = frames[0].shape[:2]
        cmd = [shutil.which("ffmpeg") or "ffmpeg", "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
               "-s", f"{w}x{h}", "-r", str(fps), "-i", "-", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2",
               "-pix_fmt", "yuv420p", "-vcodec", "libx264", os.fspath(tmp)]
        subprocess.run(cmd, input=b"".join(f.tobytes() for f in frames), check=True)
    else:
        from PIL import Image

        # one palette (from the first and last frames) for all: fast, and no palette flicker
        ref = Image.fromarray(np.vstack([frames[0], frames[-1]])).quantize(colors=64, method=Image.Quantize.MEDIANCUT)
        ims = [Image.fromarray(f).quantize(palette=ref, dither=Image.Dither.NONE) for f in frames]
        ims[0].save(tmp, format="GIF", save_all=True, append_images=ims[1:], duration=round(1000 / fps),
                    loop=0, optimize=False)
    os.replace(tmp, path)
    return path


# ------------------------------------------------------------------------------------------ modes
def modes_figure(mech, modal_result, path, n: int = 6, amplitude: float = 0.12) -> Path:
    """Mode shapes of the linearised mechanism at ``modal_result.q`` drawn on its links.

    Parameters
    ----------
    mech : Mechanism
    modal_result : exuflex.erls.modal.ModalResult
        ``nodal_shapes`` (3 N, n_modes): x, y, theta of every node (``mech.node_ids`` order).
    path : path-like
    n : int
        Number of modes drawn (the lowest).
    amplitude : float
        Largest nodal translation of every drawn shape, as a fraction of the mechanism's size.

    Returns
    -------
    Path
    """
    kin = Kinematics(mech)
    pose = kin.pose(np.asarray(modal_result.q, float))
    rigid = _link_segments(kin, pose, mech)
    allpts = np.vstack(rigid)
    size = float(np.max(np.ptp(allpts, axis=0)))
    shapes = np.asarray(modal_result.nodal_shapes, float)
    freqs = np.asarray(modal_result.frequencies_hz, float)
    n = int(min(n, shapes.shape[1]))
    ncols = 3 if n > 2 else max(n, 1)
    nrows = max(int(np.ceil(n / ncols)), 1)
    fig, axes = _figure(nrows, ncols, size=(4.2 * ncols, 3.8 * nrows + 0.5))
    lo, hi = allpts.min(axis=0), allpts.max(axis=0)
    pad = (amplitude + 0.05) * size
    for k in range(n):
        ax = axes[k // ncols, k % ncols]
        d = shapes[:, k]
        tmax = float(np.max(np.hypot(d[0::3], d[1::3])))
        scale = amplitude * size / tmax if tmax > 0 else 0.0
        for seg in rigid:
            ax.plot(seg[:, 0], seg[:, 1], color="0.7", lw=1.5)
        for lk_line in _hermite_links(mech, kin.node_ids, pose.r, d, scale):
            ax.plot(lk_line[:, 0], lk_line[:, 1], color=ESTIMATE_COLOUR, lw=1.6)
        xy = pose.r.reshape(-1, 3)[:, :2] + scale * d.reshape(-1, 3)[:, :2]
        ax.plot(xy[:, 0], xy[:, 1], "o", color=ESTIMATE_COLOUR, ms=2.5)
        for j in mech.joints:
            _draw_ground(ax, j, lo, hi, pad, 7)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal")
        ax.set_title(f"mode {k + 1}: {freqs[k]:.2f} Hz", fontsize=10)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.grid(True, lw=0.3)
    for k in range(n, nrows * ncols):
        axes[k // ncols, k % ncols].set_visible(False)
    state = "motors locked" if getattr(modal_result, "locked", False) else "motors free"
    q = ", ".join(f"{v:.4f}" for v in np.asarray(modal_result.q, float))
    fig.suptitle(f"Mode shapes at q = [{q}] rad ({state}; grey: undeformed ERLS)")
    return _save(fig, path)


def sweep_figure(summary: Mapping, path, quantities=None) -> Path:
    """eq. 21 mu (markers) +- sigma (bars) of each quantity per sweep level (levels on the x axis).

    Default quantities: the tip ones, elastic (``x25 y26 dx25 dy26``) beside absolute (``tip_x tip_y dtip_x
    dtip_y``), else every quantity of the summary.
    """
    from .study.runner import ABS_TIP_QUANTITIES, TIP_QUANTITIES, ordered_quantities, quantity_title

    tips = [q for q in TIP_QUANTITIES + ABS_TIP_QUANTITIES if q in summary["quantities"]]
    qs = ordered_quantities(summary, quantities or tips or summary["quantities"])
    levels = summary["levels"]
    numeric = all(isinstance(lv["value"], (int, float)) and not isinstance(lv["value"], bool) for lv in levels)
    x = np.array([lv["value"] for lv in levels], float) if numeric else np.arange(len(levels), dtype=float)
    ncols = 2 if len(qs) > 1 else 1
    nrows = int(np.ceil(len(qs) / ncols))
    fig, axes = _figure(nrows, ncols, size=(5.0 * ncols, 2.8 * nrows + 0.9))
    for k, q in enumerate(qs):
        ax = axes[k // ncols, k % ncols]
        mu = np.array([lv["eq21"][q]["mu"] for lv in levels])
        sg = np.array([lv["eq21"][q]["sigma"] for lv in levels])
        ax.errorbar(x, mu, yerr=sg, fmt="o", capsize=4, ecolor="k")
        ax.set_title(quantity_title(q, summary), fontsize=10)
        ax.set_ylabel(f"|{q} error|")
        ax.grid(True, lw=0.3)
        ax.set_xticks(x)
        ax.set_xticklabels([str(lv["value"]) if numeric else lv["label"] for lv in levels],
                           rotation=0 if numeric else 30, fontsize=7)
        ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 2))
    for k in range(len(qs), nrows * ncols):
        axes[k // ncols, k % ncols].set_visible(False)
    fields = sorted({o[0] for lv in levels for o in lv["overrides"]})
    fig.suptitle(f"Truth-model mismatch sweep: {', '.join(fields)} (eq. 21 mu +- sigma)")
    return _save(fig, path)


def slenderness_figure(summary: Mapping, path, departure: Mapping[str, Mapping[float, float]] | None = None,
                       limit: float = 1.5, reference: Mapping | None = None) -> Path:
    """A slenderness study (observer scored against its bound): the worst quantity's ratio RMS error / bound per
    level (mean over the runs, bars from the smallest to the largest run), each quantity's mean ratio (thin lines)
    and the acceptance ``limit``; x: the link's L/d on a log axis, stubby links to the right. ``departure``
    (a label -> {L/d: percent}, e.g. the beam model's first- and second-mode errors against the solid truth): on a
    second axis. ``reference``: another study's summary on the same levels (e.g. on the observer's own beam
    formulation as the truth), its worst ratio drawn in grey."""
    from matplotlib.ticker import NullFormatter

    levels = sorted(summary["levels"], key=lambda lv: -float(lv["value"]))
    x = np.array([float(lv["value"]) for lv in levels])
    fig, axes = _figure(1, 1, size=(6.4, 4.0))
    ax = axes[0, 0]
    w = [lv.get("worst_ratio") or {} for lv in levels]
    mean = np.array([v.get("mean", np.nan) for v in w])
    lo, hi = np.array([v.get("min", np.nan) for v in w]), np.array([v.get("max", np.nan) for v in w])
    qs = sorted({q for lv in levels for q in (lv.get("ratio_to_bound_mean") or {})})
    for q in qs:
        ax.plot(x, [(lv.get("ratio_to_bound_mean") or {}).get(q, np.nan) for lv in levels], lw=0.6, alpha=0.5)
    ax.errorbar(x, mean, yerr=[mean - lo, hi - mean], fmt="o-", color="k", capsize=4,
                label=f"worst quantity, {summary['settings'].get('beam', 'ancf')} truth")
    if reference is not None:
        ref = {float(lv["value"]): (lv.get("worst_ratio") or {}).get("mean", np.nan) for lv in reference["levels"]}
        ax.plot(x, [ref.get(v, np.nan) for v in x], "o--", color="0.5",
                label=f"worst quantity, {reference['settings'].get('engine', 'reference')} truth")
    ax.axhline(limit, color="r", ls="--", lw=1, label=f"{limit:g}x the bound")
    ax.set_xscale("log")
    ax.invert_xaxis()
    ax.set_xticks(x)
    ax.set_xticklabels([f"{v:g}" for v in x])
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("L/d of the swept link (stubby to the right)")
    ax.set_ylabel("RMS error / bound")
    ax.grid(True, lw=0.3)
    if departure:
        ax2 = ax.twinx()
        for (label, dep), mk in zip(departure.items(), "s^vd"):
            xs = sorted(dep, reverse=True)
            ax2.plot(xs, [dep[v] for v in xs], mk + ":", color="tab:blue", label=label)
        ax2.set_ylabel("beam model's mode error against the solid (%)", color="tab:blue")
        ax2.xaxis.set_minor_formatter(NullFormatter())
        ax2.legend(loc="upper center", fontsize=8)
    ax.legend(loc="upper left", fontsize=8)
    fig.suptitle(f"Beam observer on solid (FFRF) truths: {summary['model']['name']}")
    return _save(fig, path)


def study_figure(summary: Mapping, out_dir) -> Path:
    """The figure of a study's summary in ``out_dir``. A payload study: Fig. 11 (``fig_payload.png``,
    :func:`payload_study_figure`), the paper's four panels (the tip coordinates' displacements and velocities) when
    the study has them, with every quantity in ``fig_payload_all.png``; a sweep: :func:`sweep_figure`
    (``fig_sweep.png``); a slenderness study: :func:`slenderness_figure` (``fig_slenderness.png``)."""
    from .study.runner import figure_rows

    out_dir = Path(out_dir)
    if summary["settings"]["kind"] == "slenderness":
        return slenderness_figure(summary, out_dir / "fig_slenderness.png")
    if summary["settings"]["kind"] != "payload":
        return sweep_figure(summary, out_dir / "fig_sweep.png")
    paper = (summary.get("model") or {}).get("name") in PAPER_MODELS
    rows = figure_rows(summary)
    four = paper_payload_quantities([r["quantity"] for r in rows])
    if four:
        payload_study_figure([r for r in rows if r["quantity"] in four], out_dir / "fig_payload.png", paper=paper)
        payload_study_figure(rows, out_dir / "fig_payload_all.png", paper=paper)
        return out_dir / "fig_payload.png"
    return payload_study_figure(rows, out_dir / "fig_payload.png", paper=paper)

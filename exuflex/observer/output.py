"""Writing an observer outcome: estimates, result summary (with provenance) and figures."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np

from ..runs import atomic_write_text, package_versions, write_signals_csv
from ..sensors import Signals

__all__ = ["estimates_table", "summary_table", "write_outcome"]

log = logging.getLogger(__name__)


def estimates_table(mech, outcome, observer=None) -> Signals:
    """The physical estimates with their standard deviations and the absolute tip position.

    Columns: the physical quantities (q, dq/dt, tip elastic displacement and rate; :func:`.session.physical_names`),
    the absolute tip position and velocity ``tip_x tip_y dtip_x dtip_y`` (rigid + elastic,
    :func:`exuflex.sensors.absolute_tip`), then ``std_<name>`` for every quantity whose standard deviation the
    filter's covariance gives to first order: q and dq/dt from the posterior variances; with the full covariance
    (``store_P="full"``, :meth:`.session.Observer.physical_covariance`) also the tip elastic columns and the
    absolute tip position, ``J_q P_qq J_q' + J_q P_qe + P_eq J_q' + P_ee`` with ``J_q`` the rigid tip point's
    sensitivity to q. The absolute tip velocity's standard deviation would need the second derivative of the
    kinematics and is not given."""
    from ..sensors import ABSOLUTE_TIP_NAMES, absolute_tip, tip_point

    phys = outcome.estimate.physical
    res = outcome.estimate.result
    names, cols, units = list(phys.names), [phys.data], list(phys.units or ("",) * len(phys.names))
    tp = tip_point(mech)
    if tp is not None:
        tip = absolute_tip(mech, phys, on_error="nan")
        names += list(ABSOLUTE_TIP_NAMES)
        cols.append(tip.data)
        units += list(tip.units or ("m", "m", "m/s", "m/s"))
    nq = len(mech.coordinates)
    P = res.P
    std_names, std_cols = [], []
    if P is not None and P.ndim == 3 and observer is not None:
        C = observer.physical_covariance(res.x_hat, P)
        sd = np.sqrt(np.clip(np.diagonal(C, axis1=1, axis2=2), 0, None))
        std_names += [f"std_{n}" for n in phys.names[: sd.shape[1]]]
        std_cols.append(sd)
        if tp is not None:
            from ..erls.kinematics import Kinematics, KinematicsError

            kin = Kinematics(mech)
            sdt = np.full((len(res.t), 2), np.nan)
            q = phys.data[:, :nq]
            z = None
            for k in range(len(res.t)):
                if not np.all(np.isfinite(q[k])):
                    continue
                try:
                    pose = kin.pose(q[k], z)
                except KinematicsError:
                    continue
                z = pose.z
                _, J = kin.point(pose, *tp)
                G = np.zeros((2, C.shape[1]))
                G[:, :nq] = J
                G[:, 2 * nq : 2 * nq + 2] = np.eye(2)
                sdt[k] = np.sqrt(np.clip(np.diag(G @ C[k] @ G.T), 0, None))
            std_names += ["std_tip_x", "std_tip_y"]
            std_cols.append(sdt)
    elif P is not None and observer is not None:
        Pd = res.P_diag
        r = observer.model.r
        std_names += [f"std_{n}" for n in phys.names[: 2 * nq]]
        std_cols.append(np.sqrt(np.clip(np.hstack([Pd[:, :nq], Pd[:, r : r + nq]]), 0, None)))
    if std_cols:
        names += std_names
        cols += std_cols
        units += [units[names.index(n[4:])] for n in std_names]
    return Signals(phys.t, tuple(names), np.hstack(cols), tuple(units))


def write_outcome(out_dir, mech, run, outcome, plots: bool = True, observer=None) -> Path:
    """Write ``estimates.csv`` (physical estimates, absolute tip, standard deviations: :func:`estimates_table`),
    ``result.json`` (metrics, settings, versions) and the figures (``fig_*.png``) into ``out_dir``; every file is
    written atomically, readable by everyone (0644)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_signals_csv(out / "estimates.csv", estimates_table(mech, outcome, observer))
    summary = dict(outcome.summary)
    summary["versions"] = package_versions()
    summary["run_meta"] = {k: run.meta.get(k) for k in ("engine", "seed", "model", "settings") if k in run.meta}
    atomic_write_text(out / "result.json", json.dumps(summary, indent=1, default=float))
    if plots:
        from ..plots import observer_figures

        for f in observer_figures(out, mech, run, outcome):
            log.info("wrote %s", os.fspath(f))
    return out


_UNITS = {"rad": "rad", "rad/s": "rad/s", "m": "m", "m/s": "m/s"}


def summary_table(mech, outcome, bound: bool = True) -> str:
    """The result as text: a header (samples, model, channels, NIS), then one row per physical quantity with its
    unit, RMS and max error against the truth (if any), the bound for this log and their ratio."""
    s = outcome.summary
    res = outcome.estimate.result
    phys = outcome.estimate.physical
    lines = [f"{mech.name}: {len(res.t)} samples, reduced model {s['reduced_ndof']} dofs, channels "
             f"{' '.join(s.get('channels_used') or s['channels'])}",
             f"wall {s['wall_s']:.2f} s, real-time factor {s['real_time_factor']:.2f}, mean NIS {s['nis_mean']:.2f} "
             f"(expected {s['nis_expected']:.1f})"]
    if s.get("diverged"):
        lines.append(f"DIVERGED: the estimates became non-finite at t = {s['diverged_at']} s")
    elif s.get("nis_inconsistent"):
        lines.append(f"NIS inconsistent from t = {s['nis_flagged_at']} s (the innovations exceed what the filter's "
                     "covariance explains: model mismatch or noise settings; the estimates stay finite)")
    units = dict(zip(phys.names, phys.units or ("",) * len(phys.names), strict=True))
    met = outcome.metrics
    bnd = outcome.bound or {}
    if met:
        lines.append(f"{'quantity':10s} {'unit':>6s} {'RMS error':>11s} {'max error':>11s} {'bound':>11s} "
                     f"{'ratio':>6s}")
        for k, v in met["rms_error"].items():
            b = bnd.get(k)
            ratio = f"{v / b:6.2f}" if b else "     -"
            bs = f"{b:11.3g}" if b else "          -"
            lines.append(f"{k:10s} {units.get(k, ''):>6s} {v:11.3g} {met['max_error'][k]:11.3g} {bs} {ratio}")
    elif bound and bnd:
        lines.append(f"{'quantity':10s} {'unit':>6s} {'bound':>11s}")
        for k, b in bnd.items():
            lines.append(f"{k:10s} {units.get(k, ''):>6s} {b:11.3g}")
    return "\n".join(lines)

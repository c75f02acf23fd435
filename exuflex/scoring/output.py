"""Writing an observer outcome: estimates and result summary (with provenance); the command line adds the
figures (:func:`exuflex.plots.observer_figures`)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from ..runs import SignalsCsvWriter, atomic_write_text, dump_json, package_versions, write_signals_csv
from ..sensors import Signals

__all__ = ["EstimatesTable", "EstimatesWriter", "estimates_table", "summary_table", "write_outcome"]


def estimates_table(mech, outcome, observer=None) -> Signals:
    """The physical estimates with their standard deviations and the absolute tip position.

    Columns: the physical quantities (q, dq/dt, tip elastic displacement and rate; :func:`exuflex.observer.session.physical_names`),
    the absolute tip position and velocity ``tip_x tip_y dtip_x dtip_y`` (rigid + elastic,
    :func:`exuflex.sensors.absolute_tip`), then ``std_<name>`` for every quantity whose standard deviation the
    filter's covariance gives to first order: q and dq/dt from the posterior variances; with the full covariance
    (``store_P="full"``, :func:`exuflex.scoring.physical.physical_covariance`) also the tip elastic columns and the
    absolute tip position, ``J_q P_qq J_q' + J_q P_qe + P_eq J_q' + P_ee`` with ``J_q`` the rigid tip point's
    sensitivity to q. The absolute tip velocity's standard deviation would need the second derivative of the
    kinematics and is not given. A filter with a payload-scale state adds ``payload_scale`` (its estimate) and,
    where the estimator reports it (the payload EKF's model average, the IMM's nominal mode), ``p_nominal``: the
    nominal payload's posterior probability. An outcome that kept no per-sample record (:func:`.run.observe_run` with
    ``keep="summary"``) has no table: write it as the filter runs (:class:`EstimatesWriter`)."""
    res = outcome.estimate.result
    if outcome.estimate.physical is None or res.x_hat is None:
        raise ValueError("estimates_table: the outcome kept no per-sample estimates (observe_run(keep='all') "
                         "keeps them; EstimatesWriter writes them as the filter runs)")
    return EstimatesTable(mech, observer).rows(outcome.estimate.physical, res.x_hat, res.P, res.nominal_p)


class EstimatesTable:
    """:func:`estimates_table` a block of rows at a time: :meth:`rows` on successive blocks of one record gives
    the rows of the table of the whole record (the solvers' warm starts and held evaluations are carried from
    one block to the next)."""

    def __init__(self, mech, observer=None):
        from ..erls.kinematics import Kinematics
        from ..sensors import tip_point

        self.mech, self.observer = mech, observer
        self.tp = tip_point(mech)
        self._tip: dict = {}  # absolute_tip's solver and warm start
        self._cov: dict = {}  # physical_covariance's held rows and warm start
        self._kin = Kinematics(mech) if self.tp is not None else None  # the tip position's sensitivity
        self._z = None

    def rows(self, phys: Signals, x_hat: np.ndarray, P: np.ndarray | None, nominal_p: np.ndarray | None = None
             ) -> Signals:
        """The table's rows for the physical estimates ``phys`` of a block, the filter's states ``x_hat`` and
        covariances ``P`` (diagonal (n, nx), full (n, nx, nx), or None) of the same rows, and the nominal payload's
        probability ``nominal_p`` (n,) where reported."""
        from ..sensors import ABSOLUTE_TIP_NAMES, absolute_tip

        mech, observer, tp = self.mech, self.observer, self.tp
        names, cols, units = list(phys.names), [phys.data], list(phys.units or ("",) * len(phys.names))
        if tp is not None:
            tip = absolute_tip(mech, phys, on_error="nan", carry=self._tip)
            names += list(ABSOLUTE_TIP_NAMES)
            cols.append(tip.data)
            units += list(tip.units or ("m", "m", "m/s", "m/s"))
        nq = len(mech.coordinates)
        n = len(phys.t)
        std_names, std_cols = [], []
        if P is not None and P.ndim == 3 and observer is not None:
            from .physical import physical_covariance

            C = physical_covariance(observer, x_hat, P, carry=self._cov)
            sd = np.sqrt(np.clip(np.diagonal(C, axis1=1, axis2=2), 0, None))
            std_names += [f"std_{n}" for n in phys.names[: sd.shape[1]]]
            std_cols.append(sd)
            if tp is not None:
                from ..erls.kinematics import KinematicsError

                kin = self._kin
                sdt = np.full((n, 2), np.nan)
                q = phys.data[:, :nq]
                z = self._z
                for k in range(n):
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
                self._z = z
                std_names += ["std_tip_x", "std_tip_y"]
                std_cols.append(sdt)
        elif P is not None and observer is not None:
            Pd = P if P.ndim == 2 else np.diagonal(P, axis1=1, axis2=2)
            r = observer.model.r
            std_names += [f"std_{n}" for n in phys.names[: 2 * nq]]
            std_cols.append(np.sqrt(np.clip(np.hstack([Pd[:, :nq], Pd[:, r : r + nq]]), 0, None)))
        if std_cols:
            names += std_names
            cols += std_cols
            units += [units[names.index(n[4:])] for n in std_names]
        it = None if observer is None else getattr(observer.ekf.model, "i_theta", None)
        for name, col in (("payload_scale", None if it is None else x_hat[:, it]), ("p_nominal", nominal_p)):
            if col is not None:
                names.append(name)
                cols.append(np.asarray(col, float).reshape(-1, 1))
                units.append("1")
        return Signals(phys.t, tuple(names), np.hstack(cols), tuple(units))


class EstimatesWriter:
    """``estimates.csv`` in ``out_dir`` written as the filter runs: a ``sink`` for :func:`.run.observe_run`
    that turns each :class:`~exuflex.observer.session.EstimateChunk` into rows of :func:`estimates_table` (:class:`EstimatesTable`)
    and appends them (:class:`exuflex.runs.SignalsCsvWriter`: the bytes :func:`write_outcome` writes for the
    whole table, atomically, readable by everyone). Use as a context manager: leaving it normally renames the
    file into place; by an exception it removes the partial file (and the folder, if it made it and it is still
    empty)."""

    def __init__(self, out_dir, mech, observer=None):
        self.dir = Path(out_dir)
        self._made = not self.dir.exists()
        self.dir.mkdir(parents=True, exist_ok=True)
        self.path = self.dir / "estimates.csv"
        self._table = EstimatesTable(mech, observer)
        self._csv = None
        self.rows_written = 0

    def __call__(self, chunk) -> None:
        res = chunk.result
        sig = self._table.rows(chunk.physical, res.x_hat, res.P, res.nominal_p)
        if self._csv is None:
            self._csv = SignalsCsvWriter(self.path, sig.names)
        self._csv.write(sig)
        self.rows_written += len(sig.t)

    def __enter__(self) -> EstimatesWriter:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        if kind is None and self._csv is not None:
            self._csv.close()
            return
        if self._csv is not None:
            self._csv.abort()
        if self._made and self.dir.is_dir() and not any(self.dir.iterdir()):
            self.dir.rmdir()


def write_outcome(out_dir, mech, run, outcome, observer=None, *, estimates: bool = True) -> Path:
    """Write ``estimates.csv`` (physical estimates, absolute tip, standard deviations: :func:`estimates_table`) and
    ``result.json`` (metrics, settings, versions) into ``out_dir``; every file is written atomically, readable by
    everyone (0644). ``estimates=False``: ``result.json`` only (``estimates.csv`` was written as the filter ran,
    :class:`EstimatesWriter`)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if estimates:
        write_signals_csv(out / "estimates.csv", estimates_table(mech, outcome, observer))
    summary = dict(outcome.summary)
    summary["versions"] = package_versions()
    summary["run_meta"] = {k: run.meta.get(k) for k in ("engine", "seed", "model", "settings") if k in run.meta}
    atomic_write_text(out / "result.json", dump_json(summary, default=float))
    return out


_UNITS = {"rad": "rad", "rad/s": "rad/s", "m": "m", "m/s": "m/s"}


#: what the bound column of :func:`summary_table` is, and how to read a ratio (printed under the table)
BOUND_NOTE = ("bound: the RMS over the scored samples of the posterior Cramer-Rao bound's standard deviation, the "
              "Kalman covariance recursion of the observer's model linearised along the {along}, with the stated "
              "noise and the log's sampling (docs/bound.md). A consistent filter's RMS error scatters about it: "
              "ratios below 1 are expected about as often as above (a linear-Gaussian model's Kalman filter reaches "
              "the bound; for this nonlinear model the linearised bound is an approximation).")


def summary_table(mech, outcome, bound: bool = True) -> str:
    """The result as text: a header (samples, model, channels, NIS), then one row per physical quantity with its
    unit, RMS and max error against the truth (if any), the bound for this log (the posterior Cramer-Rao bound's
    RMS over the scored samples, :func:`.bound.estimation_bound`; with smoothing the smoothed bound) and their
    ratio, and a note saying what the bound is."""
    s = outcome.summary
    from ..observer.session import physical_names, physical_units

    res = outcome.estimate.result
    lines = [f"{mech.name}: {len(res.t)} samples, reduced model {s['reduced_ndof']} dofs, channels "
             f"{' '.join(s.get('channels_used') or s['channels'])}",
             f"wall {s['wall_s']:.2f} s, real-time factor {s['real_time_factor']:.2f}, mean NIS {s['nis_mean']:.2f} "
             f"(expected {s['nis_expected']:.1f})"]
    if s.get("diverged"):
        lines.append(f"DIVERGED: the estimates became non-finite at t = {s['diverged_at']} s")
    elif s.get("nis_inconsistent"):
        when = (f"from t = {s['nis_flagged_at']} s" if s.get("nis_flagged_at") is not None else
                f"over the whole log (mean NIS {s['nis_mean']:.3g} against {s['nis_expected']:.3g})")
        lines.append(f"NIS inconsistent {when} (the innovations exceed what the filter's "
                     "covariance explains: model mismatch or noise settings; the estimates stay finite)")
    units = dict(zip(physical_names(mech), physical_units(mech), strict=True))
    met = outcome.metrics
    bnd = outcome.bound or {}
    smoothed = bool(s.get("smoothed"))
    est = "smoothed" if smoothed else "RMS error"
    if met:
        lines.append(f"{'quantity':10s} {'unit':>6s} {est:>11s} {'max error':>11s} {'bound':>11s} {'ratio':>6s}"
                     + (f" {'filtered':>11s} {'f. bound':>11s} {'ratio':>6s}" if smoothed else ""))
        fe, fb = s.get("filtered_rms_error") or {}, s.get("filtered_bound_rms") or {}
        for k, v in met["rms_error"].items():
            b = bnd.get(k)
            ratio = f"{v / b:6.2f}" if b else "     -"
            bs = f"{b:11.3g}" if b else "          -"
            row = f"{k:10s} {units.get(k, ''):>6s} {v:11.3g} {met['max_error'][k]:11.3g} {bs} {ratio}"
            if smoothed and k in fe and fb.get(k):
                row += f" {fe[k]:11.3g} {fb[k]:11.3g} {fe[k] / fb[k]:6.2f}"
            lines.append(row)
    elif bound and bnd:
        lines.append(f"{'quantity':10s} {'unit':>6s} {'bound':>11s}")
        for k, b in bnd.items():
            lines.append(f"{k:10s} {units.get(k, ''):>6s} {b:11.3g}")
    elif not bnd:
        lines.append("no truth to score against and no bound (exuflex observe --bound: the bound along the plan)")
    if bnd and (met or bound):
        along = (s.get("bound_for") or {}).get("along", "truth")
        words = {"truth": "true trajectory", "plan": "planned trajectory (the log has no truth)",
                 "q_ref": "reference pose at rest (no manoeuvre)"}.get(along, along)
        note = BOUND_NOTE.format(along=words)
        if smoothed:
            note += " Smoothed estimates are scored against the smoothed bound (RTS on the bound's covariances)."
        lines += textwrap.wrap(note, 110)
    return "\n".join(lines)

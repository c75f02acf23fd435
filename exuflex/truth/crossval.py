"""Cross-validation of the Exudyn ground truth against the ERLS full-order engine on a manoeuvre.

Both engines are driven by the same torque table on the integration grid (the rigid computed torques
of the planned manoeuvre) from the same start, and compared on the true states of
:func:`exuflex.sensors.true_states` (coordinates q and the tip's elastic displacement). This module
does not import :mod:`exudyn` itself (only :func:`truth_vs_erls` does, through
:func:`exuflex.groundtruth.simulate_truth`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..mechanism import Mechanism

if TYPE_CHECKING:  # the sensors module pulls in the ERLS model: imported where a function needs it
    from ..sensors import Signals

__all__ = ["TruthComparison", "compare_truths", "manoeuvre_table", "truth_vs_erls"]

log = logging.getLogger(__name__)


@dataclass
class TruthComparison:
    """Agreement of two truths: max ``|dq|`` per coordinate (rad) and normalised RMS of the tip's elastic
    displacement per component (RMS of the difference / RMS of the reference)."""

    q_max_abs: dict[str, float]
    tip_nrms: dict[str, float]
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def q_max(self) -> float:
        return max(self.q_max_abs.values())

    @property
    def tip_nrms_max(self) -> float:
        return max(self.tip_nrms.values()) if self.tip_nrms else 0.0

    def as_dict(self) -> dict:
        return {
            "q_max_abs_rad": self.q_max_abs,
            "tip_nrms": self.tip_nrms,
            "q_max_rad": self.q_max,
            "tip_nrms_max": self.tip_nrms_max,
            **self.extra,
        }


def compare_truths(mech: Mechanism, test: Signals, ref: Signals) -> TruthComparison:
    """Compare true-state tables (same time grid) of ``test`` against ``ref``."""
    from ..sensors import tip_dof_names, tip_point

    if len(test.t) != len(ref.t) or not np.allclose(test.t, ref.t, rtol=0, atol=1e-9):
        raise ValueError(f"compare_truths: different time grids ({len(test.t)} vs {len(ref.t)} samples)")
    qmax = {n: float(np.max(np.abs(test[n] - ref[n]))) for n in mech.coordinate_names}
    nrms = {}
    if tip_point(mech) is not None:
        for n in tip_dof_names(mech):
            d = test[n] - ref[n]
            nrms[n] = float(np.sqrt(np.mean(d**2) / np.mean(ref[n] ** 2)))
    return TruthComparison(qmax, nrms)


def manoeuvre_table(mech: Mechanism, duration: float, h: float = 1e-4, plan_dt: float = 1e-3):
    """The manoeuvre's rigid computed torques on the integration grid ``k h``.

    Planned at ``plan_dt`` (exact inverse kinematics and inverse dynamics) and interpolated linearly
    onto the grid (planning at ``h`` directly differs by order ``plan_dt^2`` times the torque's curvature).

    Returns
    -------
    t (n,), tau (n, n_motors), q0, qd0
    """
    from ..manoeuvre import open_loop_torque, plan

    p = plan(mech, dt=plan_dt, t_end=duration)
    tau_p = open_loop_torque(mech, p)
    n = round(duration / h) + 1
    t = np.arange(n) * h
    tau = np.column_stack([np.interp(t, p.t, tau_p[:, j]) for j in range(tau_p.shape[1])])
    return t, tau, p.q[0], p.qd[0]


def truth_vs_erls(
    mech: Mechanism,
    duration: float | None = None,
    h: float = 1e-4,
    plan_dt: float = 1e-3,
    erls_truth: Signals | None = None,
    table=None,
    form: str = "lagrange",
    **truth_kwargs,
) -> tuple[TruthComparison, Signals, Signals]:
    """Simulate the Exudyn truth and (unless ``erls_truth`` is given) the ERLS engine on the manoeuvre.

    Parameters
    ----------
    duration : default the manoeuvre's.
    erls_truth : true states of an ERLS run under the same table (e.g. ``read_run(dir).truth``).
    table : (t, tau, q0, qd0) as from :func:`manoeuvre_table` (computed if None).
    form : the ERLS full-order model's form (:class:`exuflex.erls.model.ErlsModel`), if it is simulated here.
    **truth_kwargs : passed to :func:`exuflex.groundtruth.simulate_truth`.

    Returns
    -------
    comparison (Exudyn vs ERLS), Exudyn true states, ERLS true states; ``comparison.extra`` holds the
    wall times.
    """
    from ..groundtruth import simulate_truth
    from ..sensors import monotonic_record, true_states
    from .engines import erls_truth as erls_engine

    if mech.manoeuvre is None:
        raise ValueError(f"{mech.name}: the model has no manoeuvre")
    duration = float(mech.manoeuvre.duration if duration is None else duration)
    output_dt = 1.0 / mech.sample_rate_hz
    t, tau, q0, qd0 = manoeuvre_table(mech, duration, h, plan_dt) if table is None else table
    t0 = time.perf_counter()
    rec = simulate_truth(mech, t, tau, duration, h=h, output_dt=output_dt, q0=q0, **truth_kwargs)
    extra = {"exudyn_wall_s": time.perf_counter() - t0}
    exu = true_states(mech, monotonic_record(rec))
    if erls_truth is None:
        t0 = time.perf_counter()
        rec_e = erls_engine(mech, t, tau, duration, h, output_dt, q0, qd0, integrator="rk4", form=form)
        extra["erls_wall_s"] = time.perf_counter() - t0
        erls_truth = true_states(mech, monotonic_record(rec_e))
    cmp = compare_truths(mech, exu, erls_truth)
    cmp.extra.update(extra)
    log.info("Exudyn vs ERLS on %s: q max %.3g rad, tip NRMS %s", mech.name, cmp.q_max, cmp.tip_nrms)
    return cmp, exu, erls_truth

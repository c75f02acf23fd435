"""The reduced model's modal report, as the ``modes --reduced`` CLI prints it."""

from __future__ import annotations

import numpy as np

from .accuracy import accuracy_along, accuracy_indices
from .basis import CraigBampton
from .path import manoeuvre_configurations

__all__ = ["reduced_modes_report"]


def reduced_modes_report(model, q=None, masters=None, n_interior=None, q_star=None, fmax: float = 180.0,
                         ranking: str = "imr", along: int = 41) -> dict:
    """Build the basis and compare the reduced and full modes at ``q`` (default: the model's q_ref).

    Returns a JSON-ready dict: ``ndof``, ``masters`` (all master names, q first), ``interior_modes``,
    ``frequencies_hz`` (reduced modes matched to the full modes below ``fmax``), ``nco`` and
    ``freq_error_pct`` aligned with the full model's modes below ``fmax``, plus the basis' details, and
    ``along``: the worst NCO and frequency error over ``along`` configurations of the model's manoeuvre
    (equally spaced in time; not those the interior modes were chosen on), where they occur and at which full
    mode (``None`` without a manoeuvre or with ``along=0``); ``static``: the static corrections' figures
    (:func:`_static`).
    """
    if isinstance(n_interior, str) and n_interior != "auto":
        n_interior = int(n_interior)
    cb = CraigBampton(model, masters=masters, q_star=q_star, n_interior=n_interior, ranking=ranking, band_hz=fmax)
    q = np.asarray(model.mech.q_ref if q is None else q, float)
    acc = accuracy_indices(cb, q, band_hz=fmax)
    return {
        "ndof": int(cb.r),
        "masters": list(model.mech.coordinate_names) + list(cb.masters),
        "interior_modes": int(cb.n_interior),
        "ranking": ranking,
        "kept_interior_hz": [float(f) for f in cb.interior_frequencies_hz[cb.kept]],
        "q_star": cb.q_star.tolist(),
        "frequencies_hz": acc.reduced_hz.tolist(),
        "full_frequencies_hz": acc.full_hz.tolist(),
        "nco": acc.nco.tolist(),
        "freq_error_pct": acc.freq_error_pct.tolist(),
        "thresholds": {"nco_min": cb.nco_min, "freq_error_max_pct": cb.freq_error_max_pct},
        "ok": acc.ok(cb.nco_min, cb.freq_error_max_pct),
        "basis_s": cb.build_seconds,
        "along": _along(cb, along) if along else None,
        "truncation": cb.truncation,
        "static": _static(cb),
    }


def _static(cb: CraigBampton) -> dict | None:
    """The static corrections' figures (:mod:`.static`): their count (included in ``interior_modes``), the largest
    residual reading without and with them (noise sd) and where, the limit, what each was taken from, their Ritz
    frequencies at q* and the load amplitudes; None where none were considered (a fixed count, no planned input)."""
    st = cb.static
    if st is None:
        return None
    a, v = st.amplitudes
    row, c = st.worst[st.n] if st.worst[st.n] is not None else (None, 0)
    return {
        "count": int(st.n),
        "figure_without": float(st.figure[0]),
        "figure": float(st.figure[st.n]),
        "limit": st.limit,
        "met": st.met,
        "worst_row": row,
        "worst_q": cb.path_q[c].tolist(),
        "picked": [{"q": cb.path_q[i].tolist(), "from": what} for i, what in st.picked],
        "ritz_hz": [float(f) for f in cb.interior_frequencies_hz[st.rest[: st.n]]],
        "max_acceleration": dict(zip(cb.model.mech.coordinate_names, map(float, a))),
        "max_rate": dict(zip(cb.model.mech.coordinate_names, map(float, v))),
    }


def _along(cb: CraigBampton, n: int) -> dict | None:
    """The worst indices over ``n`` configurations of the manoeuvre (see :func:`reduced_modes_report`)."""
    qs = manoeuvre_configurations(cb.model.mech, n)
    if qs is None:
        return None
    accs = [a for a in accuracy_along(cb, qs, warn=False) if a.nco.size]  # the basis' band: fmax
    if not accs:
        return None
    a = min(accs, key=lambda a: a.worst_nco)
    b = max(accs, key=lambda a: a.worst_error_pct)
    return {
        "configurations": len(qs),
        "worst_nco": a.worst_nco,
        "worst_nco_q": a.q.tolist(),
        "worst_nco_mode_hz": float(a.full_hz[np.argmin(a.nco)]),
        "worst_freq_error_pct": b.worst_error_pct,
        "worst_freq_error_q": b.q.tolist(),
        "worst_freq_error_mode_hz": float(b.full_hz[np.argmax(b.freq_error_pct)]),
        "ok": all(x.ok(cb.nco_min, cb.freq_error_max_pct) for x in accs),
    }

"""Observability of a sensor set: the paper's argument for its choice of encoders and strain gauges.

At each configuration of a grid the reduced model is linearised over one measurement interval
(``z+ = A z``, ``y = H z``) and the observability matrix ``O = [H; H A; ...; H A^(n-1)]`` is formed on a
*scaled* state (every state divided by its typical magnitude: 1 rad and 1 rad/s for the rigid
coordinates, 1 mm and 0.1 m/s for the elastic ones), with every channel divided by its noise. Its rank
and smallest singular value say whether, and how well, the channels determine every state: a singular
value of 1 means one noise standard deviation of the measurements per unit of scaled state.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..mechanism import Mechanism
from .reduced import ReducedObserverModel

__all__ = ["ObservabilityResult", "observability"]


@dataclass(frozen=True)
class ObservabilityResult:
    channels: tuple[str, ...]
    q: np.ndarray  # (n_cfg, nq)
    rank: np.ndarray  # (n_cfg,)
    sigma_min: np.ndarray  # (n_cfg,) smallest singular value of the scaled observability matrix
    nx: int

    @property
    def observable(self) -> bool:
        return bool(np.all(self.rank == self.nx))

    def as_dict(self) -> dict:
        return {
            "channels": list(self.channels),
            "nx": self.nx,
            "min_rank": int(self.rank.min()),
            "observable_everywhere": self.observable,
            "sigma_min_worst": float(self.sigma_min.min()),
            "sigma_min_median": float(np.median(self.sigma_min)),
        }


def _scales(som: ReducedObserverModel) -> np.ndarray:
    nq, r = som.nq, som.r
    d = np.empty(som.nx)
    d[:nq] = 1.0
    d[nq:r] = 1e-3
    d[r : r + nq] = 1.0
    d[r + nq :] = 0.1
    return d


def observability(som: ReducedObserverModel, mech: Mechanism, channels: Sequence[str], qs, dt: float | None = None,
                  rank_tol: float = 1e-9) -> ObservabilityResult:
    """Rank and smallest singular value of the scaled observability matrix at each configuration ``qs``."""
    dt = dt or 1.0 / mech.sample_rate_hz
    sensors = {s.name: s for s in mech.sensors}
    noise = np.array([sensors[c].noise_std if sensors[c].noise_std > 0 else 1.0 for c in channels])
    d = _scales(som)
    qs = np.atleast_2d(np.asarray(qs, float))
    ranks, smin = [], []
    u = np.zeros(len(mech.motors))
    for q in qs:
        z = som.initial_state(q)
        A = som.frozen_interval(z, u, dt)[0].F
        _, H = som.measure(z, channels)
        As = A * d[None, :] / d[:, None]
        Hs = H * d[None, :] / noise[:, None]
        blocks, M = [], Hs
        for _ in range(som.nx):
            blocks.append(M)
            M = M @ As
        O = np.vstack(blocks)
        sv = np.linalg.svd(O, compute_uv=False)
        ranks.append(int(np.sum(sv > rank_tol * sv[0])))
        smin.append(float(sv[-1]))
    return ObservabilityResult(tuple(channels), qs, np.array(ranks), np.array(smin), som.nx)

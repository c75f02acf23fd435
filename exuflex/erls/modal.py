"""Modal analysis of the ERLS model linearised about a configuration at rest.

At rest (q' = 0, u = 0) the velocity and geometric terms of eq. 2 vanish to first order, so the
linearised model is ``M(q) dx'' + K(q) dx = 0`` with ``K = diag(0, K_uu)``.

- *motors free* (torque-driven): all of x vibrates; the mechanism's ``nq`` zero-frequency modes are
  reported separately and dropped;
- *motors locked*: q is held, only u vibrates (``M_uu``, ``K_uu``).
Mode shapes are also given as physical nodal displacements ``W phi`` (x, y, theta of every node).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from .model import ErlsModel

__all__ = ["ModalResult", "modal_analysis"]


@dataclass(frozen=True)
class ModalResult:
    q: np.ndarray
    locked: bool
    frequencies_hz: np.ndarray  # elastic modes, ascending
    shapes: np.ndarray  # (n, n_modes) in the model coordinates x (mass-normalised)
    nodal_shapes: np.ndarray  # (3 n_nodes, n_modes) physical nodal displacements
    rigid_frequencies_hz: np.ndarray  # the dropped mechanism modes (free case), ~0
    names: tuple[str, ...]  # names of the coordinates in ``shapes``

    def below(self, fmax: float) -> np.ndarray:
        return self.frequencies_hz[self.frequencies_hz <= fmax]


def modal_analysis(model: ErlsModel, q=None, locked: bool = False) -> ModalResult:
    """Eigenfrequencies and modes of the linearised model at ``q`` (default: the model's q_ref)."""
    q = np.asarray(model.mech.q_ref if q is None else q, float)
    cfg = model.configuration(q)
    M = model.mass(cfg)
    K = model.stiffness(cfg)
    nq = model.nq
    if locked:
        Mi, Ki = M[nq:, nq:], K[nq:, nq:]
        w2, V = sla.eigh(Ki, Mi)
        full = np.zeros((model.n, V.shape[1]))
        full[nq:] = V
        n_rigid = 0
        names = model.names
    else:
        w2, full = sla.eigh(K, M)
        n_rigid = nq
        names = model.names
    f = np.sqrt(np.clip(w2, 0.0, None)) / (2 * np.pi)
    order = np.argsort(w2)
    f, full = f[order], full[:, order]
    rigid = f[:n_rigid]
    f, full = f[n_rigid:], full[:, n_rigid:]
    return ModalResult(q, locked, f, full, cfg.W @ full, rigid, names)

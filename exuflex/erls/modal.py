"""Modal analysis of the ERLS model linearised about a configuration at rest.

At rest (q' = 0, u = 0) the velocity and geometric terms of eq. 2 vanish to first order, so the
linearised model is ``M(q) dx'' + K(q) dx = 0`` with ``K = diag(0, K_uu)``.

- *motors free* (torque-driven): all of x vibrates; the mechanism's ``nq`` zero-frequency modes are
  reported separately and dropped;
- *motors locked*: the coordinates' encoder readings ``q + G u`` are held
  (:meth:`~exuflex.erls.model.ErlsModel.coordinate_reading_rows`), only u vibrates and q follows it,
  ``dq = -G du``: ``Z' M Z``, ``Z' K Z`` with ``Z = [-G; I]`` (``M_uu``, ``K_uu`` where ``G = 0``: no
  relative angle coordinate, whose reading adds the other link's elastic rotation at the joint);
- *q held* (``hold_readings=False``): the ERLS coordinates themselves held, ``M_uu``, ``K_uu``: the constraint of
  the Craig-Bampton interior (:mod:`exuflex.reduction`), the same as *motors locked* without a relative angle
  coordinate.

Mode shapes are also given as physical nodal displacements ``W phi`` (x, y, theta of every node).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from .model import ErlsModel

__all__ = ["ModalResult", "aligned_ratios", "damping_ratios", "modal_analysis"]

MATCH_TOL = 0.02  # a damped eigenvalue belongs to an undamped mode if |s| / w - 1 is below this


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


def modal_analysis(model: ErlsModel, q=None, locked: bool = False, hold_readings: bool = True) -> ModalResult:
    """Eigenfrequencies and modes of the linearised model at ``q`` (default: the model's q_ref); ``locked``: the
    motors locked, the encoders' readings held (``hold_readings``, module docstring) or q itself."""
    q = np.asarray(model.mech.q_ref if q is None else q, float)
    cfg = model.configuration(q)
    M = model.mass(cfg)
    K = model.stiffness(cfg)
    nq = model.nq
    if locked:
        Z = _locked_basis(model, hold_readings)
        w2, V = sla.eigh(Z.T @ K @ Z, Z.T @ M @ Z)
        full = Z @ V
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


def damping_ratios(model: ErlsModel, q=None, locked: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(f_hz, zeta)``: the modes' natural frequencies ``|s| / 2 pi`` and damping ratios ``-Re s / |s|`` from
    the eigenvalues ``s`` (``Im s > 0``) of the state matrix at rest at ``q``
    (:meth:`~exuflex.erls.model.ErlsModel.state_matrix`; ``locked``: its elastic motions with every encoder's
    reading ``q + G u`` held, the constraint :func:`modal_analysis` holds by default), ascending, the
    mechanism's zero modes dropped. With the model's damping (module docstring of :mod:`exuflex.erls.model`,
    "Damping") the free modes' ``zeta`` is ``alpha / (2 w) + beta w / 2`` mode by mode (the stated damping is
    that of the free modes; locked modes have other ratios)."""
    q = np.asarray(model.mech.q_ref if q is None else q, float)
    cfg = model.configuration(q)
    A, _ = model.state_matrix(cfg)
    if locked:  # u only, the readings held (x = Z u): [[0, I], [-M_L^-1 K_L, -M_L^-1 C_L]], M_L = Z' M Z, ...
        ne = model.ne
        Z = _locked_basis(model)
        MK = np.linalg.solve(Z.T @ model.mass(cfg) @ Z,
                             np.hstack([Z.T @ model.stiffness(cfg) @ Z, Z.T @ model.damping(cfg) @ Z]))
        A = np.block([[np.zeros((ne, ne)), np.eye(ne)], [-MK[:, :ne], -MK[:, ne:]]])
    return _oscillating(sla.eigvals(A))


def _locked_basis(model: ErlsModel, hold_readings: bool = True) -> np.ndarray:
    """(n, ne) ``Z = [-G; I]``: the motions with every coordinate's encoder reading ``q + G u`` held (else
    ``[0; I]``, q held)."""
    Z = np.zeros((model.n, model.ne))
    if hold_readings:
        Z[: model.nq] = -model.coordinate_reading_rows()
    Z[model.nq :] = np.eye(model.ne)
    return Z


def _oscillating(s: np.ndarray, rigid_hz: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    s = s[(s.imag > 0.0) & (np.abs(s) > 2 * np.pi * rigid_hz)]
    s = s[np.argsort(np.abs(s))]
    return np.abs(s) / (2 * np.pi), -s.real / np.abs(s)


def aligned_ratios(f_hz, f_damped, zeta) -> np.ndarray:
    """The damping ratio of each undamped mode ``f_hz`` (ascending): that of the nearest unused damped
    eigenvalue within :data:`MATCH_TOL` of it (``nan`` if none: an overdamped mode has no oscillating pair)."""
    f_damped, zeta = np.asarray(f_damped, float), np.asarray(zeta, float)
    used = np.zeros(len(f_damped), bool)
    out = np.full(len(f_hz), np.nan)
    for i, f in enumerate(np.asarray(f_hz, float)):
        d = np.where(used, np.inf, np.abs(f_damped / f - 1.0))
        if len(d) and d.min() <= MATCH_TOL:
            j = int(np.argmin(d))
            used[j] = True
            out[i] = zeta[j]
    return out

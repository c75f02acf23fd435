"""The interior-mode ranking's score (IMR, :mod:`.basis`): how much of the band modes' remainder beyond the Guyan
shapes each interior mode carries. Its own module because the basis (at q*) and the path sampling
(:mod:`.path`, along the manoeuvre) both rank with it."""

from __future__ import annotations

import numpy as np

__all__ = ["interior_mode_scores"]


def interior_mode_scores(Phi_all: np.ndarray, M_ss: np.ndarray, band_shapes_s: np.ndarray, band_shapes_m: np.ndarray,
                         B: np.ndarray) -> np.ndarray:
    """IMR score of every interior mode (the ranking in :mod:`.basis`).

    Parameters
    ----------
    Phi_all : (s, n_int) all interior modes, M_ss-orthonormal.
    M_ss : (s, s) slave mass block.
    band_shapes_s, band_shapes_m : slave and elastic-master rows of the full band modes (s, n_band), (m_e, n_band).
    B : (s, m_e) Guyan shapes of the elastic masters.
    """
    r = band_shapes_s - B @ band_shapes_m
    c = Phi_all.T @ M_ss @ r  # (n_int, n_band)
    norms = np.einsum("ij,ik,kj->j", r, M_ss, r)
    norms = np.where(norms > 0, norms, 1.0)
    return (c**2 / norms).sum(axis=1)

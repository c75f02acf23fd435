"""The filter's quantiles: chi-square (its NIS tests) and standard normal (its input-step test)."""

from __future__ import annotations

import numpy as np
from scipy.special import gammaincinv, ndtri

__all__ = ["chi2_ppf", "norm_ppf"]


def chi2_ppf(q, dof):
    """Quantile ``q`` of the chi-square distribution with ``dof`` degrees of freedom, ``2 P^-1(dof/2, q)``.

    ``P^-1`` is the inverse of the regularised lower incomplete gamma function (the arithmetic of
    ``scipy.stats.chi2.ppf`` for ``0 <= q <= 1``, through ``scipy.special`` so that the filter does not import
    ``scipy.stats``, a large import, to evaluate it).
    """
    return 2 * gammaincinv(np.asarray(dof, float) / 2, q)


def norm_ppf(q):
    """Quantile ``q`` of the standard normal distribution (``scipy.special.ndtri``)."""
    return ndtri(q)

"""Quantiles of the χ² and normal distributions: the gates, consistency bands, requirement
confidence bounds and conflict thresholds read them.

They are the formulas ``scipy.stats`` evaluates (``chi2.ppf(q, k) = 2·P⁻¹(k/2, q)`` with ``P`` the
regularised lower incomplete gamma function, ``norm.ppf = ndtri``), called through
``scipy.special`` directly: ``scipy.stats`` is slow to import, and every start of the command
line would pay for it.
``tests/test_distributions.py`` checks them against ``scipy.stats``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import gammaincinv, ndtri

__all__ = ["chi2_ppf", "norm_ppf"]


def chi2_ppf(q: ArrayLike, dof: ArrayLike):
    """x with P(χ²_dof ≤ x) = q (``scipy.stats.chi2.ppf``); NaN outside q ∈ [0, 1] or dof ≤ 0."""
    return 2.0 * gammaincinv(np.asarray(dof, dtype=np.float64) / 2.0, q)


def norm_ppf(q: ArrayLike):
    """x with P(N(0, 1) ≤ x) = q (``scipy.stats.norm.ppf``)."""
    return ndtri(q)

"""The χ² and normal quantiles of :mod:`tertiary.core.distributions` against scipy.stats (the oracle),
and the reason the module exists: the package imports without scipy.stats."""

import subprocess
import sys

import numpy as np
import pytest
from scipy.stats import chi2, norm

from tertiary.core.distributions import chi2_ppf, norm_ppf

Q = np.array([0.0, 1e-12, 1e-6, 0.0027, 0.025, 0.05, 0.5, 0.9, 0.95, 0.975, 0.9973, 0.999, 1 - 1e-9, 1.0])


@pytest.mark.parametrize("dof", [1, 2, 3, 6, 2.5, 1e-9, 40, 400])
def test_chi2_quantile_is_scipy_stats(dof):
    np.testing.assert_array_equal(chi2_ppf(Q, dof), chi2.ppf(Q, dof))


def test_chi2_quantile_known_values_and_arrays():
    # the gate values the docstrings quote: 9.0 for one dof at 2Φ(3) − 1, 7.81 for 3 dof at 95 %
    assert chi2_ppf(2 * norm.cdf(3.0) - 1, 1) == pytest.approx(9.0, rel=1e-12)
    assert chi2_ppf(0.95, 3) == pytest.approx(7.814727903251178, rel=1e-12)
    k = np.array([1.0, 4.0, 9.0])
    np.testing.assert_array_equal(chi2_ppf(np.array([0.1, 0.5, 0.9]), k), chi2.ppf([0.1, 0.5, 0.9], k))
    assert np.isnan(chi2_ppf(1.5, 3)) and np.isnan(chi2_ppf(0.5, 0)) and np.isnan(chi2_ppf(0.5, -1))


def test_normal_quantile_is_scipy_stats():
    np.testing.assert_array_equal(norm_ppf(Q), norm.ppf(Q))
    assert norm_ppf(0.975) == pytest.approx(1.959963984540054, rel=1e-14)


def test_the_package_and_cli_import_without_scipy_stats():
    """Importing scipy.stats cost 1.4 s of every command's start: the package, the safety
    package and the CLI must not import it (tests and benchmarks may, as an oracle)."""
    code = "import sys, tertiary, safety, tertiary.cli.commands; print(sorted(m for m in sys.modules if m.startswith('scipy.stats')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"

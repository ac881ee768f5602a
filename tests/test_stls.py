import numpy as np

import robust_sindy as rs

from .conftest import LORENZ_TRUE, lorenz_library, random_problem


def test_stls_recovers_noise_free_lorenz_exactly():
    theta, y = lorenz_library(0, degree=2, noisy=False)
    res = rs.fit(theta, y, method="stls", threshold=0.05)
    assert res.converged
    np.testing.assert_array_equal(res.coef != 0, LORENZ_TRUE != 0)
    np.testing.assert_allclose(res.coef, LORENZ_TRUE, rtol=1e-8, atol=1e-8)


def test_stls_zeroes_small_terms_and_ols_does_not(lorenz2):
    theta, y = lorenz2
    stls = rs.fit(theta, y, method="stls", threshold=0.05)
    ols = rs.fit(theta, y, method="ols")
    nonzero = stls.coef[stls.coef != 0]
    assert np.all(np.abs(nonzero) >= 0.05)
    assert np.count_nonzero(ols.coef) == ols.coef.size
    np.testing.assert_allclose(ols.coef, np.linalg.lstsq(theta, y, rcond=None)[0])


def test_stls_sweep_limit_is_reported():
    theta, y = random_problem(30)
    import pytest

    with pytest.warns(rs.ConvergenceWarning, match="max_sweeps"):
        res = rs.fit(theta, y, method="stls", threshold=0.5, max_sweeps=1)
    assert not res.converged

"""Temporal screen, robust derivatives, diagnostics and data-size checks."""

import warnings

import numpy as np
import pytest

from robust_sindy import HuberSINDy, PolynomialLibrary
from robust_sindy.differentiation import local_polynomial_derivative
from robust_sindy.model import IdentificationWarning
from robust_sindy.selection import correlation_time
from robust_sindy.selection.screening import temporal_screen
from robust_sindy.systems import Lorenz


def _smooth(m=1500, seed=0, noise=1e-3):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 15.0, m)
    x = np.column_stack([np.sin(t), np.cos(2.3 * t) + 0.3 * t, np.exp(np.sin(0.7 * t))])
    return t, x, x + noise * rng.normal(size=x.shape)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_temporal_screen_finds_single_entry_spikes_and_nothing_else(seed):
    t, _, x = _smooth(seed=seed)
    rng = np.random.default_rng(seed + 10)
    bad = np.zeros(x.shape, dtype=bool)
    idx = rng.choice(x.size, 60, replace=False)
    bad.flat[idx] = True
    x[bad] += rng.choice([-1, 1], 60) * rng.uniform(0.2, 1.0, 60)
    s = temporal_screen(x, t)
    assert s.flags[bad].mean() >= 0.95
    assert s.flags[~bad].mean() <= 0.005
    # flagged entries are repaired to their local prediction
    assert np.abs(s.repaired[bad & s.flags] - _smooth(seed=seed)[1][bad & s.flags]).max() < 0.02


def test_temporal_screen_is_quiet_on_clean_data_and_unit_free():
    t, _, x = _smooth()
    s = temporal_screen(x, t)
    assert s.flags.mean() <= 0.002
    scaled = temporal_screen(x * [1e3, 1e-3, 7.0], t * 1e-2)
    assert np.array_equal(scaled.flags, s.flags)


def test_local_polynomial_derivative_ignores_masked_outliers():
    t, clean, x = _smooth(noise=0.0)
    true = np.column_stack(
        [np.cos(t), -2.3 * np.sin(2.3 * t) + 0.3, 0.7 * np.cos(0.7 * t) * clean[:, 2]]
    )
    d = local_polynomial_derivative(x, t)
    assert np.abs(d - true).max() < 1e-4
    x[700, 1] += 5.0
    mask = np.ones(x.shape, dtype=bool)
    mask[700, 1] = False
    assert np.abs(local_polynomial_derivative(x, t, mask=mask) - true).max() < 1e-3
    assert np.abs(local_polynomial_derivative(x, t) - true).max() > 1.0  # without the mask


def test_correlation_time_of_white_and_smooth_residuals():
    rng = np.random.default_rng(0)
    white = rng.normal(size=(5000, 1))
    assert correlation_time(white)[0] < 1.2
    smooth = np.convolve(rng.normal(size=5020), np.ones(21) / 21, mode="valid")[:, None]
    assert correlation_time(smooth)[0] > 10


def test_too_few_samples_for_the_library_is_an_error():
    x = np.random.default_rng(0).normal(size=(8, 3))
    with pytest.raises(ValueError, match="x has 8 samples but the library has 10 terms"):
        HuberSINDy().fit(x, 0.1, x_dot=x)


@pytest.mark.filterwarnings("ignore::robust_sindy.ConvergenceWarning")
def test_few_samples_per_term_warn_and_say_so_in_the_diagnostics():
    data = Lorenz().generate(t_end=0.4)  # 41 samples for 20 cubic terms
    with pytest.warns(IdentificationWarning, match="samples per library term"):
        model = HuberSINDy(library=PolynomialLibrary(degree=3)).fit(
            data.x, data.t, x_dot=data.x_dot
        )
    assert model.diagnostics_.samples_per_term < 5
    assert model.diagnostics_.problems()


def test_clean_data_gives_diagnostics_without_problems():
    data = Lorenz().generate(t_end=5.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model = HuberSINDy().fit(data.x, data.t, x_dot=data.x_dot)
    d = model.diagnostics_
    assert d.problems() == []
    assert d.flagged_fraction <= 0.02
    assert d.certified.all()
    assert "no problem found" in repr(d)

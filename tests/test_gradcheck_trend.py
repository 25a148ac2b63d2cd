"""The gradient report's trend fit (benchmarks.gradcheck.trend_fit): the finite difference of a
rough objective at an optimiser's scale."""

import math

import numpy as np

from benchmarks.gradcheck import trend_fit


def test_trend_of_a_line_is_its_slope():
    x = np.linspace(4.75, 5.25, 9)
    fit = trend_fit(x, 0.2 + 0.03 * x, 5.0, 0.05)
    assert math.isclose(fit["slope"], 0.03, rel_tol=1e-10)
    assert math.isclose(fit["slope_inner"], 0.03, rel_tol=1e-10)
    assert fit["stderr"] < 1e-12 and fit["rms"] < 1e-14


def test_trend_sees_through_fine_wiggles_and_skips_failed_samples():
    """J = trend + wiggles four times finer than the span: the local slope (0.03 + 0.025 cos 50 x)
    ranges over 0.005-0.055, the fitted slope stays within a few standard errors (~15 %) of the
    trend's, and a failed sample (NaN) is left out."""
    x = np.linspace(4.75, 5.25, 9)
    J = 0.2 + 0.03 * x + 5e-4 * np.sin(50 * x)
    J[2] = np.nan
    fit = trend_fit(x, J, 5.0, 0.05)
    assert len(fit["x"]) == 8
    assert abs(fit["slope"] - 0.03) < 3 * fit["stderr"] < 0.2 * 0.03
    assert 2.5e-4 < fit["rms"] < 6e-4      # the wiggles' RMS, 5e-4 / sqrt(2)

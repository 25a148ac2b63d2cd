"""The gradient report's trend fit (benchmarks.gradcheck.trend_fit): the finite difference of a
rough objective at an optimiser's scale."""

import math

import numpy as np

from benchmarks.gradcheck import report_table, trend_fit


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


def _row(objective, x, truncate=0, central=(), trend=None, autograd=1.0):
    deltas = [1e-4, 1e-5, 1e-6][:len(central)]
    mid = central[len(central) // 2] if central else math.nan
    return {"fluid": "numerical", "objective": objective, "frames": 100, "param": "frequency", "x": x, "J": 0.1,
            "autograd": autograd, "deltas": deltas, "central": list(central), "truncate": truncate,
            "fd_spread": (max(central) - min(central)) / abs(mid) if central else math.nan,
            "autograd_error": (autograd - mid) / abs(mid) if central else math.nan, "trend": trend or {}}


def test_report_joins_runs_one_line_per_point_with_full_backpropagation():
    """Differences from one run, the trend from another, a truncated window left out; the points
    in order."""
    rows = [_row("speed", 7.0, central=(2.0, 2.0, 2.0)),
            _row("speed", 3.0, central=(1.0, 1.1, 1.2), autograd=1.21),
            _row("speed", 3.0, trend={"span": 0.05, "slope": 0.9, "stderr": 0.1}, autograd=5.0),
            _row("speed", 3.0, truncate=10, autograd=0.01)]
    lines = report_table(rows).splitlines()[2:]
    assert len(lines) == 2
    assert "| 3 |" in lines[0] and "| 7 |" in lines[1]
    cells = [c.strip() for c in lines[0].strip("|").split("|")]
    assert cells[6] == "1.21"                      # autograd of the run with the differences
    assert cells[8] == "18 %" and cells[9] == "+10.0 %"
    assert cells[10] == "0.9 +- 0.1 (5 %)"
    assert lines[1].rstrip().endswith("| - |")     # no trend measured at 7 Hz

"""Result plots exist as PNG and SVG and show every method / simulator."""

import imageio.v2 as imageio
import numpy as np

from fishsim.render.plots import plot_optimisation_history, plot_validation


def test_optimisation_history(tmp_path):
    histories = {"gradient descent": {"objective": np.linspace(1, 0.1, 10), "parameter": np.linspace(3, 5, 10)},
                 "CMA-ES": {"objective": np.linspace(1, 0.3, 6), "parameter": [3, 4.5, 3.8, 5.2, 4.9, 5.0]}}
    png, svg = plot_optimisation_history(histories, tmp_path / "history", optimum=5.0)
    assert png.suffix == ".png" and svg.suffix == ".svg"
    assert imageio.imread(png)[..., :3].std() > 5
    text = svg.read_text()
    assert "<svg" in text and "CMA-ES" in text and "gradient descent" in text


def test_validation_curves(tmp_path):
    freqs = [1.0, 2.0, 3.0, 4.0]
    values = {"HydroNet": [0.1, 0.2, 0.28, 0.35], "numerical": [0.11, 0.19, 0.3, 0.33]}
    png, svg = plot_validation(freqs, values, tmp_path / "sub" / "validation.png",
                               errors={"HydroNet": [0.01] * 4})
    assert png.exists() and svg.exists()
    assert "HydroNet" in svg.read_text() and "numerical" in svg.read_text()

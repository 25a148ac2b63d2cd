"""Result plots exist as PNG and SVG and show every method / simulator."""

import imageio.v2 as imageio
import numpy as np

from fishsim.render.plots import plot_optimisation_history, plot_validation


def test_optimisation_history(tmp_path):
    adam = {"objective": np.linspace(0.1, 1, 10), "frames": np.arange(1, 11) * 200.0,
            "parameters": {"frequency": np.linspace(3, 5, 10)}}
    cma = {"objective": [0.1, 0.5, 0.3, 0.9, 0.8, 0.95], "frames": np.arange(1, 7) * 400.0,
           "parameters": {"frequency": [3, 4.5, 3.8, 5.2, 4.9, 5.0], "amplitude": [10, 11, 12, 12, 13, 12]}}
    for h in (adam, cma):
        h["best"] = np.maximum.accumulate(np.asarray(h["objective"], float))
    png, svg = plot_optimisation_history({"adam": adam, "CMA-ES": cma}, tmp_path / "history",
                                         units={"frequency": "Hz"})
    assert png.suffix == ".png" and svg.suffix == ".svg"
    assert imageio.imread(png)[..., :3].std() > 5
    text = svg.read_text()
    assert "<svg" in text and "CMA-ES" in text and "adam" in text and "fish-frames" in text


def test_validation_curves(tmp_path):
    freqs = [1.0, 2.0, 3.0, 4.0]
    values = {"HydroNet": [0.1, 0.2, 0.28, 0.35], "numerical": [0.11, 0.19, 0.3, 0.33]}
    png, svg = plot_validation(freqs, values, tmp_path / "sub" / "validation.png",
                               errors={"HydroNet": [0.01] * 4})
    assert png.exists() and svg.exists()
    assert "HydroNet" in svg.read_text() and "numerical" in svg.read_text()

"""Muscle layouts (fishsim/solid/muscles.py): the layer's area fractions are exact and mesh-
independent, differentiable in the thickness, the paper's stations are the mesher's elements,
and the config rejects impossible muscle settings."""

import numpy as np
import pytest
import torch

from fishsim.errors import ConfigError
from fishsim.mesh import make_fish_mesh
from fishsim.mesh.fish_mesh import ACTUATOR_TOP
from fishsim.mesh.triangulate import element_areas
from fishsim.solid import SolidModel
from fishsim.solid.controller import WaveController
from fishsim.solid.muscles import (
    layer_fractions,
    layer_muscles,
    layer_weights,
    positive_part_area,
    station_muscles,
    surface_half_widths,
)


def test_positive_part_area_matches_sampling():
    """Closed-form area where a linear function is >= 0, against 200k barycentric samples."""
    rng = np.random.default_rng(0)
    d = torch.as_tensor(rng.uniform(-1, 1, (40, 3)))
    area = torch.ones(40)
    exact = positive_part_area(d, area).numpy()
    r = rng.random((200_000, 2))
    flip = r.sum(1) > 1
    r[flip] = 1 - r[flip]
    bary = np.stack([1 - r.sum(1), r[:, 0], r[:, 1]], 1)               # uniform in a triangle
    sampled = ((bary @ d.numpy().T) >= 0).mean(0)
    np.testing.assert_allclose(exact, sampled, atol=4e-3)


def _layer_area(mesh, thickness, x_range=(0.05, 0.95)):
    f_top, f_bot = layer_fractions(mesh, torch.tensor(thickness), x_range)
    A = element_areas(mesh.points, mesh.triangles)
    return float((A * f_top.numpy()).sum()), float((A * f_bot.numpy()).sum())


def test_layer_area_is_the_body_integral_and_mesh_independent():
    """Each layer's area is thickness x the integral of the half-width over [x0, x1] (to the
    outline's chord error), the same on a 4 mm and a 2 mm mesh; thickness 1 fills the slab."""
    L = 0.2
    X = np.linspace(0.05 * L, 0.95 * L, 20001)
    areas = []
    for edge in (4e-3, 2e-3):
        mesh = make_fish_mesh(edge_length=edge)
        w_top, w_bot = surface_half_widths(mesh, X)
        integral = np.trapezoid(0.5 * (w_top - w_bot), X)
        top, bottom = _layer_area(mesh, 0.3)
        assert top == pytest.approx(0.3 * integral, rel=2e-3) and bottom == pytest.approx(0.3 * integral, rel=2e-3)
        full_top, full_bottom = _layer_area(mesh, 1.0)
        assert full_top + full_bottom == pytest.approx(np.trapezoid(w_top - w_bot, X), rel=1e-6)
        areas.append(top + bottom)
    assert areas[0] == pytest.approx(areas[1], rel=3e-3)


def test_layer_muscles_lie_on_their_side_and_cover_the_range():
    mesh = make_fish_mesh(edge_length=3e-3)
    layout = layer_muscles(mesh, 0.3)
    centroid = mesh.points[mesh.triangles[layout.elements]].mean(1)
    assert np.all((layout.fraction > 0) & (layout.fraction <= 1))
    top, bottom = layout.top_share == 1, layout.top_share == 0
    assert np.all(centroid[top, 1] > 0) and np.all(centroid[bottom, 1] < 0)
    assert centroid[:, 0].min() < 0.06 * mesh.length and centroid[:, 0].max() > 0.94 * mesh.length
    assert np.all((centroid[:, 0] > 0.04 * mesh.length) & (centroid[:, 0] < 0.96 * mesh.length))


def test_layer_fractions_are_differentiable_in_the_thickness():
    mesh = make_fish_mesh(edge_length=5e-3)
    elements = layer_muscles(mesh, 0.45).elements
    weights = torch.as_tensor(np.random.default_rng(1).standard_normal((2, len(elements))))

    def f(t):
        f_top, f_bot = layer_fractions(mesh, t, elements=elements)
        return (weights[0] * f_top).sum() + (weights[1] * f_bot).sum()

    assert torch.autograd.gradcheck(f, (torch.tensor(0.3, dtype=torch.float64, requires_grad=True),))


def test_station_muscles_are_the_mesh_actuators():
    mesh = make_fish_mesh(edge_length=4e-3)
    layout = station_muscles(mesh)
    np.testing.assert_array_equal(layout.elements, mesh.actuated)
    np.testing.assert_array_equal(layout.top_share == 1, mesh.actuator[mesh.actuated] == ACTUATOR_TOP)
    model = SolidModel(mesh)
    np.testing.assert_allclose(model.muscle_weight, 6e5 * element_areas(mesh.points, mesh.triangles)[mesh.actuated])


def test_layer_weights_match_the_model_and_contract_both_sides():
    mesh = make_fish_mesh(edge_length=4e-3)
    model = SolidModel(mesh, muscles=layer_muscles(mesh, 0.3))
    w, share = layer_weights(model, torch.tensor(0.3, dtype=torch.float64))
    np.testing.assert_allclose(w.numpy(), model.muscle_weight, rtol=1e-12)
    np.testing.assert_allclose(share.numpy(), model.muscle_top_share, rtol=1e-12)
    u = WaveController.default(mesh.length).contraction(model, 0.43)
    assert bool((u[:, model.muscle_top_share == 1] > 0).any()) and bool((u[:, model.muscle_top_share == 0] > 0).any())
    assert bool((u >= 0).all()) and float(u.max()) < 0.3


@pytest.mark.parametrize("thickness, x_range", [(0.0, (0.05, 0.95)), (1.5, (0.05, 0.95)), (0.3, (0.5, 0.4))])
def test_impossible_layers_are_config_errors(thickness, x_range):
    with pytest.raises(ConfigError):
        layer_muscles(make_fish_mesh(edge_length=5e-3), thickness, x_range)


@pytest.mark.parametrize("override, message", [("fish.muscles=stations", "fish.muscles must be"),
                                               ("fish.muscle_thickness=0", "fish.muscle_thickness"),
                                               ("fish.muscle_thickness=2", "fish.muscle_thickness")])
def test_cli_rejects_bad_muscle_settings(override, message):
    from typer.testing import CliRunner

    from fishsim.cli import app

    result = CliRunner().invoke(app, ["simulate", "fluid=none", override])
    assert result.exit_code == 2 and message in result.output

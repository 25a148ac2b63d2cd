"""The sub-iterations' relaxation (fishsim.coupling.added_mass): Aitken's factor on a linear
fixed-point map, the body axis and the surge set without the stabilisation's mass."""

import math

import torch

from fishsim.coupling.added_mass import aitken_relaxed, body_axis, mass_centroid, surge_without_stabilisation


def test_aitken_reaches_a_linear_maps_fixed_point_in_two_passes():
    # x -> c x + b per sample: the secant of two residuals is exact, omega_1 = 1 / (1 - c), and
    # the second relaxed pass lands on b / (1 - c) whenever that omega lies within the bounds
    c = torch.tensor([-0.8, -0.55, 0.0, 0.3], dtype=torch.float64)[:, None, None]
    b = torch.randn(4, 5, 2, dtype=torch.float64)
    x = torch.zeros_like(b)
    x, memory = aitken_relaxed(x, c * x + b, None)
    assert not torch.allclose(x, b / (1 - c))
    x, memory = aitken_relaxed(x, c * x + b, memory)
    torch.testing.assert_close(x, b / (1 - c), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(memory[1].flatten(), (1 / (1 - c)).flatten())


def test_body_axis_follows_the_long_axis():
    s = torch.linspace(-1, 1, 41, dtype=torch.float64)
    body = torch.stack((0.1 * s, 0.01 * torch.sin(7 * s)), -1)          # long along x
    mass = 1 + s ** 2
    for angle in (0.0, 0.4, -1.2):
        rot = torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]], dtype=torch.float64)
        e = body_axis((body @ rot.T + 0.3)[None], mass)[0, 0]
        assert abs(abs(e @ rot[:, 0]) - 1) < 1e-3, (angle, e)


def test_surge_follows_the_force_without_the_stabilisations_mass():
    torch.manual_seed(0)
    mass = torch.rand(30, dtype=torch.float64) + 0.5
    qdot, qdot_t, force = (torch.randn(2, 30, 2, dtype=torch.float64) for _ in range(3))
    axis = torch.tensor([[[0.6, 0.8]], [[1.0, 0.0]]], dtype=torch.float64)
    h = 0.01
    out = surge_without_stabilisation(qdot, qdot_t, force, axis, mass, h)
    along = lambda v: (mass_centroid(v, mass) * axis).sum(-1)
    across = lambda v: (mass_centroid(v, mass) * axis.flip(-1) * torch.tensor([-1.0, 1.0])).sum(-1)
    expected = along(qdot_t) + h * (force.sum(1, keepdim=True) * axis).sum(-1) / mass.sum()
    torch.testing.assert_close(along(out), expected)
    torch.testing.assert_close(across(out), across(qdot))
    torch.testing.assert_close(out - qdot, (out - qdot)[:, :1].expand_as(out))     # a rigid shift

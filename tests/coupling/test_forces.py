"""Force modes, x-axis fixing, burn-in, and the two one-call directions of the layer."""

import pytest
import torch

from fishsim.coupling import (
    CouplingConfig,
    burn_in_scale,
    fext_from_surface,
    fluid_to_solid,
    solid_to_fluid,
)
from fishsim.errors import ConfigError
from fishsim.fields import Boundary, Grid
from tests.coupling.shapes import fish_outline

N = 7
SURFACE = torch.tensor([5, 0, 2, 6])


def surface_forces():
    return torch.arange(2 * 4 * 2, dtype=torch.float64).view(2, 4, 2) - 5.0


def test_per_node_places_forces_on_surface_nodes():
    f = fext_from_surface(surface_forces(), SURFACE, N)
    assert f.shape == (2, N, 2)
    assert torch.equal(f[:, SURFACE], surface_forces())
    assert torch.equal(f[:, [1, 3, 4]], torch.zeros(2, 3, 2, dtype=f.dtype))


def test_average_mode_keeps_total_force_on_every_node():
    f = fext_from_surface(surface_forces(), SURFACE, N, mode="average")
    assert torch.allclose(f.sum(1), surface_forces().sum(1))
    assert torch.allclose(f, f[:, :1].expand_as(f))


def test_average_mode_with_masses_is_a_uniform_acceleration_without_torque():
    """Shared in proportion to the node masses, the total force F gives every node the same
    acceleration F / M, so it exerts no torque about the centre of mass, whatever the mesh's
    grading (F / N on every node of unequal masses does)."""
    mass = torch.tensor([1.0, 4.0, 0.5, 2.0, 1.0, 3.0, 0.25], dtype=torch.float64)
    q = torch.randn(N, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    f = fext_from_surface(surface_forces(), SURFACE, N, mode="average", mass=mass)
    assert torch.allclose(f.sum(1), surface_forces().sum(1))
    a = f / mass[:, None]
    assert torch.allclose(a, a[:, :1].expand_as(a))
    r = q - (mass[:, None] * q).sum(0) / mass.sum()
    torque = r[:, 0] * f[..., 1] - r[:, 1] * f[..., 0]
    assert torch.allclose(torque.sum(1), torch.zeros(2, dtype=torch.float64), atol=1e-12)


@pytest.mark.parametrize("mode", ["per_node", "average"])
def test_fix_lateral_zeros_y(mode):
    f = fext_from_surface(surface_forces(), SURFACE, N, mode=mode, fix_lateral=True)
    assert (f[..., 1] == 0).all()
    assert torch.allclose(f.sum(1)[:, 0], surface_forces().sum(1)[:, 0])


def test_burn_in_scale():
    assert [burn_in_scale(t, 4) for t in (0, 1, 2, 4, 9)] == [0.0, 0.25, 0.5, 1.0, 1.0]
    assert burn_in_scale(0, 0) == 1.0
    f = fext_from_surface(surface_forces(), SURFACE, N, scale=burn_in_scale(1, 4))
    assert torch.allclose(f[:, SURFACE], 0.25 * surface_forces())


def test_config_rejects_bad_values():
    with pytest.raises(ConfigError):
        CouplingConfig(sigma=0.0)
    with pytest.raises(ConfigError):
        CouplingConfig(ibm_weight="inside")


def test_layer_round_trip_dtypes_and_burn_in():
    grid, cfg = Grid(), CouplingConfig(n_burn_in=10)
    qs = fish_outline(120)
    interior = qs.mean(1, keepdim=True)
    q = torch.cat([interior, qs], 1).repeat(2, 1, 1)  # node 0 interior, 1..S the surface
    surface = torch.arange(1, 121).numpy()
    qdot = torch.zeros_like(q)
    qdot[..., 0] = 0.2
    boundary = solid_to_fluid(q, qdot, surface, grid, cfg)
    assert isinstance(boundary, Boundary) and boundary.mask.dtype == torch.float32
    # v_d is the solid's own velocity (no factor b) wherever the band reaches, 0 elsewhere
    band = boundary.velocity[:, 0] != 0
    assert torch.allclose(boundary.velocity[:, 0][band], torch.tensor(0.2, dtype=boundary.velocity.dtype))
    assert (boundary.mask[:, 0][~band] == 0).all()
    p = (1000.0 * grid.cell_centres()[..., 1])[None, None].repeat(2, 1, 1, 1)
    f = fluid_to_solid(q, p, boundary, surface, grid, cfg, step=5)
    assert f.shape == q.shape and f.dtype == torch.float64
    assert (f[:, 0] == 0).all()
    area = 0.0023034
    assert torch.allclose(f.sum(1)[:, 1], torch.tensor(-0.5 * 1000.0 * area, dtype=f.dtype), rtol=1e-3)

"""IBM forces: pressure (divergence theorem, uniform pressure, the paper's variants) and the
viscous traction (exact for linear velocity fields, differentiable)."""


import pytest
import torch

from fishsim.coupling import CouplingConfig, area_vectors, ibm_force, polygon_area, soft_mask
from fishsim.errors import ConfigError
from fishsim.fields import Grid
from tests.coupling.shapes import ellipse, fish_outline

GRID = Grid()
G = 1000.0  # Pa/m


def linear_pressure(axis, dtype):
    return (G * GRID.cell_centres(dtype=dtype)[..., axis])[None, None]


@pytest.mark.parametrize("shape", [ellipse(200), fish_outline(200)], ids=["ellipse", "fish"])
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-5), (torch.float32, 2e-4)])
@pytest.mark.parametrize("axis", [0, 1])
@pytest.mark.parametrize("weight", ["outside", "fluid"])
def test_divergence_theorem_linear_pressure(shape, dtype, tol, axis, weight):
    """sum_k f_k = -integral p n dl = -grad p * area (p = G x_axis), whichever cells are sampled."""
    mask = soft_mask(shape, GRID, dtype=dtype)
    force = ibm_force(shape, linear_pressure(axis, dtype), mask, GRID, weight=weight).sum(1)[0]
    expected = torch.zeros(2, dtype=torch.float64)
    expected[axis] = -G * polygon_area(shape)[0]
    assert (force - expected).norm() < tol * G * polygon_area(shape)[0]


def test_uniform_pressure_no_net_force():
    shape = fish_outline(200)
    p = torch.full((1, 1, GRID.H, GRID.W), 250.0, dtype=torch.float64)
    f = ibm_force(shape, p, soft_mask(shape, GRID), GRID)
    assert f.sum(1).abs().max() < 1e-12
    assert torch.allclose(f.norm(dim=-1).sum(), torch.tensor(250.0 * 0.39, dtype=f.dtype), rtol=0.05)


def test_force_direction_is_inward_for_positive_pressure():
    shape = ellipse(64, axes=(0.03, 0.03))
    p = torch.full((1, 1, GRID.H, GRID.W), 1.0, dtype=torch.float64)
    f = ibm_force(shape, p, soft_mask(shape, GRID), GRID)
    outward = shape - shape.mean(1, keepdim=True)
    assert ((f * outward).sum(-1) < 0).all()


def test_paper_variants_are_biased_on_the_thin_fish():
    """The paper's weighted mean (b or 1 - b) is off by ~30 % for a y-gradient on the thin
    fish: its sampling point sits ~1 cell inside / outside the surface.  Documents the default."""
    shape = fish_outline(200)
    mask = soft_mask(shape, GRID)
    exact = G * polygon_area(shape)[0]
    for weight in ("fluid", "body"):
        f = ibm_force(shape, linear_pressure(1, torch.float64), mask, GRID, weight=weight, fit="mean")
        assert abs(f.sum(1)[0, 1] + exact) > 0.2 * exact
    f = ibm_force(shape, linear_pressure(0, torch.float64), mask, GRID, area="paper", fit="mean", weight="none")
    assert abs(f.sum(1)[0, 0] + exact) > 0.1 * exact  # l_k n_k at the sharp tail tip


def test_fluid_weight_ignores_pressure_inside_the_body():
    shape = ellipse(128, axes=(0.04, 0.02))
    mask = soft_mask(shape, GRID)
    p_in = 1e3 * (mask > 0.999).double()  # arbitrary pressure deep inside, 0 in the fluid
    scale = 1e3 * area_vectors(shape).norm(dim=-1)  # |force| if the node saw p_in
    leak = ibm_force(shape, p_in, mask, GRID).norm(dim=-1)  # 1 - b < 1e-3 on those cells
    paper = ibm_force(shape, p_in, mask, GRID, weight="body", fit="mean").norm(dim=-1)
    assert (leak < 1e-3 * scale).all() and (paper > 0.1 * scale).all()


def test_sampled_pressure_is_continuous_across_cell_boundaries():
    """The kernel window moves by a whole cell when a node crosses a cell boundary; the taper
    keeps p_k continuous there (it jumped by ~3e-5 of the pressure scale before) and smooth: its
    central difference quotient does not depend on the step across four decades."""
    import torch

    from fishsim.coupling.ibm import surface_pressure
    from fishsim.fields import Grid

    torch.manual_seed(0)
    g = Grid(40, 40, 2.5e-3)
    p = torch.randn(1, 1, 40, 40, dtype=torch.float64)
    mask = torch.zeros_like(p)
    for fit in ("mean", "linear"):
        def p_at(x, fit=fit):
            qs = torch.tensor([[[x, 20.3 * g.dx]]], dtype=torch.float64)
            return float(surface_pressure(qs, p, mask, g, g.dx ** 2, "fluid", fit)[0, 0])

        x0 = 20 * g.dx                       # a cell boundary
        assert abs(p_at(x0 + 1e-12) - p_at(x0 - 1e-12)) < 1e-9
        quotients = [(p_at(x0 + d) - p_at(x0 - d)) / (2 * d) for d in (1e-5, 1e-6, 1e-7, 1e-8)]
        assert max(quotients) - min(quotients) < 1e-3 * abs(quotients[-1])


def test_outside_weight_reads_each_side_of_a_thin_plate():
    """A plate 1 mm thick (under half a cell) between pressures +P above and -P below: the pressure
    pushes it down with 2 P L.  "outside" reads each node's own side (its cells beyond the band,
    b < 0.05, above the node's tangent): measured 0.02 % off.  "fluid" (1 - b) also reads the other
    side, one or two cells away, and recovers 12 % of the force (the body-side "body": 31 %)."""
    shape = ellipse(256, axes=(0.05, 0.0005))
    mask = soft_mask(shape, GRID)
    y = GRID.cell_centres(dtype=torch.float64)[..., 1]
    P = 100.0
    p = (P * torch.sign(y - 0.125))[None, None]
    exact = 2 * P * 0.1
    outside = ibm_force(shape, p, mask, GRID, weight="outside").sum(1)[0]
    fluid = ibm_force(shape, p, mask, GRID, weight="fluid").sum(1)[0]
    assert abs(outside[1] + exact) < 1e-3 * exact and abs(outside[0]) < 1e-6 * exact
    assert abs(fluid[1]) < 0.2 * exact


def traction(qs, qdots, v, mask, grid, mu, sigma_prime=6.25e-6):
    """The viscous traction alone: ``ibm_force`` with ``viscous`` on a zero pressure."""
    p = torch.zeros(v.shape[0], 1, grid.H, grid.W, dtype=v.dtype)
    return ibm_force(qs, p, mask, grid, sigma_prime, viscous=(qdots, v, mu))


def linear_velocity(grad, u0):
    """v = u0 + grad x at the cell centres, [1, 2, H, W] (float64)."""
    x = GRID.cell_centres(dtype=torch.float64)
    return (u0 + torch.einsum("ab,hwb->hwa", grad, x)).permute(2, 0, 1)[None]


@pytest.mark.parametrize("shape", [ellipse(200), fish_outline(200)], ids=["ellipse", "fish"])
def test_viscous_traction_is_exact_for_a_linear_flow(shape):
    """v = u0 + G x with the nodes moving with it (no slip): the fit through each node's velocity
    recovers G, so f_k = mu (G + G^T) a_k at every node, whatever cells are sampled, up to the fit's
    regularisation (1e-6 sigma' on moments ~0.1 sigma' across the one-sided samples: measured
    1.3e-5); on a closed surface these add up to 0 (sum_k a_k = 0)."""
    grad = torch.tensor([[0.3, 2.0], [-1.5, -0.3]], dtype=torch.float64)  # trace 0: divergence free
    u0 = torch.tensor([0.05, -0.02], dtype=torch.float64)
    qdots = u0 + shape @ grad.T
    mu = 1.25e-4
    f = traction(shape, qdots, linear_velocity(grad, u0), soft_mask(shape, GRID), GRID, torch.tensor([mu]))
    expected = mu * area_vectors(shape) @ (grad + grad.T).T
    assert (f - expected).abs().max() < 1e-4 * expected.abs().max()
    assert f.sum(1).abs().max() < 1e-4 * f.norm(dim=-1).sum()


def test_viscous_traction_is_differentiable():
    """Autograd of the traction matches central differences in the node positions, their
    velocities and the fluid velocity (float64, a coarse grid)."""
    grid = Grid(16, 24, 5e-3)
    shape = ellipse(24, axes=(0.03, 0.012), centre=(0.06, 0.04)).requires_grad_(True)
    qdots = (0.01 * torch.randn(shape.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
             ).requires_grad_(True)
    v = (0.1 * torch.randn(1, 2, grid.H, grid.W, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
         ).requires_grad_(True)
    mask = soft_mask(shape.detach(), grid, sigma=2e-6, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda q, u, w: traction(q, u, w, mask, grid, 1e-3, 2.5e-5),
                                    (shape, qdots, v), eps=1e-7, atol=1e-9, rtol=1e-4)


def test_viscous_traction_needs_the_outside_pressure_weight():
    with pytest.raises(ConfigError, match="viscous"):
        CouplingConfig(viscous=True, ibm_weight="fluid")
    with pytest.raises(ConfigError, match="viscous"):
        CouplingConfig(viscous=True, force="exchange")
    shape = ellipse(64)
    v = torch.zeros(1, 2, GRID.H, GRID.W, dtype=torch.float64)
    with pytest.raises(ValueError, match="outside"):
        ibm_force(shape, v[:, :1], soft_mask(shape, GRID), GRID, weight="fluid", viscous=(shape, v, 1e-3))


@pytest.mark.parametrize("shape", [ellipse(200), fish_outline(200)], ids=["ellipse", "fish"])
def test_the_wall_fit_is_exact_for_a_linear_pressure_of_the_imposed_slope(shape):
    """``fit="wall"`` imposes dp/dn = -rho a.n at each node: with accelerations whose imposed
    slope is the linear field's own (a_k = -(G.n_k) n_k / rho), the plane is exact and the forces
    obey the divergence theorem as the free fit does; with a = 0 (dp/dn = 0) they do not."""
    rho = 50.0
    mask = soft_mask(shape, GRID, dtype=torch.float64)
    a = area_vectors(shape)
    n = a / a.norm(dim=-1, keepdim=True)
    grad = torch.tensor([0.3, 1.0], dtype=torch.float64) * G
    p = (GRID.cell_centres(dtype=torch.float64) @ grad)[None, None]
    acceleration = -(n @ grad).unsqueeze(-1) * n / rho
    force = ibm_force(shape, p, mask, GRID, fit="wall", wall=(acceleration, rho)).sum(1)[0]
    expected = -grad * polygon_area(shape)[0]
    assert (force - expected).norm() < 1e-5 * expected.norm()
    still = ibm_force(shape, p, mask, GRID, fit="wall", wall=(torch.zeros_like(shape), rho)).sum(1)[0]
    assert (still - expected).norm() > 1e-2 * expected.norm()


def test_the_wall_fit_needs_the_outside_samples_and_accelerations():
    with pytest.raises(ConfigError, match="ibm_fit=wall needs coupling.ibm_weight=outside"):
        CouplingConfig(ibm_fit="wall", ibm_weight="fluid")
    shape = ellipse(64)
    p = torch.zeros(1, 1, GRID.H, GRID.W, dtype=torch.float64)
    with pytest.raises(ValueError, match="needs wall="):
        ibm_force(shape, p, soft_mask(shape, GRID), GRID, fit="wall")

"""The compiled coupling (fishsim/coupling/kernels.py) against the torch formulas it replaces on
the CPU (band.py, mask.py, ibm.py): the same band selection, the same mask, boundary velocity and
IBM force to round-off, the same vector-Jacobian products, and central differences (gradcheck)."""

import dataclasses
import math

import pytest
import torch
from torch.autograd import gradcheck

from fishsim.coupling import CouplingConfig, solid_to_fluid
from fishsim.coupling.band import band_margin, surface_band, torch_nearest_and_inside
from fishsim.coupling.ibm import ibm_force, torch_ibm_force
from fishsim.coupling.kernels import LINEAR_FIT, WALL_FIT, BandBoundary, OutsidePressureForce, _nearest
from fishsim.coupling.mask import SIGMA, band_boundary, boundary_velocity, element_distances, soft_mask
from fishsim.fields import Grid

GRID = Grid(H=40, W=60, dx=2.5e-3)


def bent_fish(B=2, n=60, seed=0):
    """B jittered, bent ccw fish-like outlines (a thin tail) of n nodes, [B, n, 2] float64, and
    random node velocities."""
    g = torch.Generator().manual_seed(seed)
    s = torch.linspace(0, 1, n // 2 + 1, dtype=torch.float64)[:-1]
    half = 0.006 * torch.sin(math.pi * s.clamp(0.02, 1)) ** 0.7 + 3e-4       # half-width, thin at the tail
    shapes = []
    for b in range(B):
        x = 0.04 + 0.08 * s
        y = 0.05 + 0.01 * torch.sin(4 * s + b)
        top = torch.stack([x, y + half], -1)
        bottom = torch.stack([x, y - half], -1)
        q = torch.cat([bottom, top.flip(0)], 0)
        shapes.append(q + 2e-4 * torch.rand(q.shape, generator=g, dtype=torch.float64))
    qs = torch.stack(shapes)
    return qs, torch.randn(qs.shape, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("distance", ["segment", "node"])
@pytest.mark.parametrize("k_nearest", [8, 24, 200])
def test_band_selection_matches_the_torch_one(distance, k_nearest):
    """The same inside flags and the same K' nearest elements (as sets; the compiled ranking is in
    float64, so only near-ties at the K'-th may differ, which these outlines do not have)."""
    qs, _ = bent_fish()
    band = surface_band(qs, GRID, band_margin(SIGMA, GRID.dx), k_nearest, distance)
    k = band.nearest.shape[-1]
    h = int(band.centres[0, :, 1].unique().numel())
    nearest, inside = torch_nearest_and_inside(qs - band.origin, band.centres, k, distance, (h, band.flat.shape[1] // h))
    assert torch.equal(band.inside, inside) and 0 < int(inside.sum()) < inside.numel()
    same = (band.nearest.sort(-1).values == nearest.sort(-1).values).all(-1)
    assert same.float().mean() > 0.9
    # where the sets differ, they are ties: the same K' squared distances (a cell nearest to a
    # vertex is equally near both segments that share it)
    e_compiled, _ = element_distances(qs, band, torch.float64)
    e_torch, _ = element_distances(qs, dataclasses.replace(band, nearest=nearest), torch.float64)
    assert torch.allclose(e_compiled.sort(-1).values, e_torch.sort(-1).values, rtol=1e-5, atol=1e-12)
    again, _, _ = _nearest((qs - band.origin).numpy(), band.centres.numpy(), k, distance == "segment",
                           band.flat.shape[1] // h, math.inf)
    assert torch.equal(torch.from_numpy(again), band.nearest)


@pytest.mark.parametrize("distance, mean, k_nearest, tau", [
    ("segment", "harmonic", 24, 5e-7), ("segment", "arithmetic", 24, 5e-7), ("node", "arithmetic", 24, 5e-7),
    ("segment", "harmonic", 200, 5e-7), ("segment", "harmonic", 24, 2e-6), ("node", "harmonic", 200, 1e-7)])
def test_mask_velocity_and_their_adjoint_equal_the_torch_formulas(distance, mean, k_nearest, tau):
    """b, v_d and the vector-Jacobian products w.r.t. q and qdot to round-off (float64), for the
    truncated (K' < S) and the full soft-min, with the velocity's temperature tau equal to the
    mask's xi (one set of weights) or not, and with the far cells left unranked by the selection
    (``surface_band(sigma=...)``) or not.  The compiled pass gives the cells outside the body with
    b < 4e-18 b = v_d = 0 (every consumer reads v_d as b v_d), so v_d and its cotangent are
    compared on the other cells."""
    qs, qdots = bent_fish()
    band = surface_band(qs, GRID, band_margin(SIGMA, GRID.dx), k_nearest, distance)
    unranked = surface_band(qs, GRID, band_margin(SIGMA, GRID.dx), k_nearest, distance, SIGMA)
    assert band.unranked is None and bool(unranked.unranked.any())      # some cells were left unranked
    g = torch.Generator().manual_seed(5)
    cot_b = torch.randn(2, 1, GRID.H, GRID.W, generator=g, dtype=torch.float64)
    cot_v = torch.randn(2, 2, GRID.H, GRID.W, generator=g, dtype=torch.float64)
    near = soft_mask(qs, GRID, distance=distance, mean=mean, band=band, dtype=torch.float64) > 4.3e-18
    cot_v = cot_v * near

    def run(compiled_band=None):
        q, qd = qs.clone().requires_grad_(True), qdots.clone().requires_grad_(True)
        if compiled_band is not None:
            b, v = band_boundary(q, qd, compiled_band, GRID, tau=tau, mean=mean, dtype=torch.float64)
        else:
            b = soft_mask(q, GRID, distance=distance, mean=mean, band=band, dtype=torch.float64)
            v = boundary_velocity(q, qd, b, GRID, tau, distance=distance, band=band, weighted=False)
        ((b * cot_b).sum() + (v * cot_v).sum()).backward()
        return b.detach(), (v * near).detach(), q.grad, qd.grad

    reference = run()
    for compiled in (run(band), run(unranked)):
        for got, want in zip(compiled, reference):
            scale = want.abs().max()
            assert scale > 0 and (got - want).abs().max() <= 1e-10 * scale, float((got - want).abs().max() / scale)


def test_band_boundary_gradient_against_central_differences():
    qs, qdots = bent_fish(B=1, n=30)
    band = surface_band(qs, GRID, band_margin(SIGMA, GRID.dx), 8)
    args = (band.centres, band.nearest, band.inside, band.unranked, 5e-7, 5e-7, 5e-7, True, True, band.truncated, torch.float64)
    fn = lambda q, qd: BandBoundary.apply(q - band.origin, qd, *args)
    assert gradcheck(fn, (qs.requires_grad_(True), qdots.requires_grad_(True)), eps=1e-8, atol=1e-6, rtol=1e-4,
                     fast_mode=True)


def test_solid_to_fluid_in_float32_matches_the_float64_torch_reference():
    """The coupling's CPU path (compiled, float64 inside, float32 out) against the torch formulas
    in float64: b within float32 round-off, v_d too where b >= 4e-18 (beyond, the compiled pass
    sets v_d = 0)."""
    qs, qdots = bent_fish(B=1)
    cfg = CouplingConfig()
    surface = torch.arange(qs.shape[1])
    out = solid_to_fluid(qs, qdots, surface, GRID, cfg, dtype=torch.float32)
    band = surface_band(qs, GRID, band_margin(cfg.sigma, GRID.dx), cfg.k_nearest, cfg.distance)
    b = soft_mask(qs, GRID, cfg.xi, cfg.sigma, cfg.distance, cfg.mean, band, torch.float64)
    v = boundary_velocity(qs, qdots, b, GRID, cfg.tau, cfg.distance, band, weighted=False)
    assert out.mask.dtype == torch.float32 and (out.mask.double() - b).abs().max() < 1e-6
    near = b > 4.3e-18
    assert ((out.velocity.double() - v) * near).abs().max() < 1e-6 * v.abs().max()


@pytest.mark.parametrize("fit", ["linear", "mean", "wall"])
def test_ibm_force_and_its_adjoint_equal_the_torch_formulas(fit):
    """The compiled IBM pressure force (outside weights, chord elements) and its vector-Jacobian
    products w.r.t. the surface, the pressure and the mask (and, for the wall fit, the nodes'
    accelerations), against ibm.py's torch formulas (float64), for two fish, one of them partly
    outside the grid's edge cells."""
    qs, _ = bent_fish()
    qs[1] += torch.tensor([-0.038, 0.0], dtype=torch.float64)        # its tail within the kernel of x = 0
    mask = soft_mask(qs, GRID, dtype=torch.float64)
    g = torch.Generator().manual_seed(7)
    y = torch.arange(GRID.H, dtype=torch.float64).view(1, 1, -1, 1)
    p = 50 * torch.randn(2, 1, GRID.H, GRID.W, generator=g, dtype=torch.float64) + 30 * y
    cot = torch.randn(2, qs.shape[1], 2, generator=g, dtype=torch.float64)
    acc = 20 * torch.randn(2, qs.shape[1], 2, generator=g, dtype=torch.float64)
    rho = torch.tensor([50.0, 1000.0], dtype=torch.float64)

    def run(fn):
        q, pr, b, a = (t.detach().clone().requires_grad_(True) for t in (qs, p, mask, acc))
        f = fn(q, pr, b, GRID, fit=fit, wall=(a, rho) if fit == "wall" else None)
        (f * cot).sum().backward()
        return (f.detach(), q.grad, pr.grad, b.grad) + ((a.grad,) if fit == "wall" else ())

    for got, want in zip(run(ibm_force), run(torch_ibm_force)):
        scale = want.abs().max()
        assert scale > 0 and (got - want).abs().max() <= 1e-10 * scale, float((got - want).abs().max() / scale)


def test_ibm_force_read_from_the_mesh_nodes_equals_it_on_the_polyline():
    """``ibm_force(nodes, surface=index)`` (the rollout's call: compiled, the polyline read from
    the nodes) gives the polyline's forces bit for bit and their gradient on its nodes, zero on the
    others."""
    qs, _ = bent_fish()
    nodes = torch.stack([qs, qs + 1e-3], 2).flatten(1, 2).requires_grad_(True)     # the polyline: even nodes
    qs.requires_grad_(True)
    mask = soft_mask(qs, GRID, dtype=torch.float64).detach()
    p = 50 * torch.randn(2, 1, GRID.H, GRID.W, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    got, want = ibm_force(nodes, p, mask, GRID, surface=torch.arange(0, nodes.shape[1], 2)), ibm_force(qs, p, mask, GRID)
    assert torch.equal(got, want)
    cot = torch.randn(got.shape, generator=torch.Generator().manual_seed(10), dtype=torch.float64)
    (g_nodes,), (g_qs,) = torch.autograd.grad((got * cot).sum(), nodes), torch.autograd.grad((want * cot).sum(), qs)
    assert torch.equal(g_nodes[:, 0::2], g_qs) and not g_nodes[:, 1::2].any() and g_qs.abs().max() > 0


def test_compiled_ibm_force_gradient_against_central_differences():
    qs, _ = bent_fish(B=1, n=30)
    mask = soft_mask(qs, GRID, dtype=torch.float64).detach()
    p = torch.randn(1, 1, GRID.H, GRID.W, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    fn = lambda q, pr, b: OutsidePressureForce.apply(q, pr, b, None, 0.05, GRID.dx, 6.25e-6, 4, LINEAR_FIT)
    assert gradcheck(fn, (qs.requires_grad_(True), p.requires_grad_(True), mask.requires_grad_(True)), eps=1e-8,
                     atol=1e-6, rtol=1e-4, fast_mode=True)
    acc = torch.randn(qs.shape, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    wall = lambda q, pr, b, a: OutsidePressureForce.apply(q, pr, b, None, 0.05, GRID.dx, 6.25e-6, 4, WALL_FIT, a, 50.0)
    assert gradcheck(wall, (qs, p, mask, acc.requires_grad_(True)), eps=1e-8, atol=1e-6, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("B", [1, 3])
def test_band_cells_equal_the_torch_window(B):
    """The compiled window (``band_selection``), cell indices, centres and origin are band.py's
    torch ones, bit for bit
    (float64), also for a fish whose window is clipped by the grid's edge."""
    from fishsim.coupling.band import _band_cells
    from fishsim.coupling.kernels import band_selection

    qs, _ = bent_fish(B=B)
    qs = qs.clone()
    qs[-1, :, 0] -= qs[-1, :, 0].min() - 0.2 * GRID.dx              # the last one at the left edge
    for margin in (0, 3):
        flat, centres, (h, w) = _band_cells(qs, GRID, margin)
        origin = 0.5 * (qs.amin(1, keepdim=True) + qs.amax(1, keepdim=True))
        got = band_selection(qs, GRID.dx, GRID.H, GRID.W, margin, 5, True)
        assert got[6] == (h, w) and torch.equal(got[0], flat)
        assert torch.equal(got[2], origin) and torch.equal(got[1], centres - origin)


def test_the_union_with_the_walls_on_the_band_equals_the_union_on_the_grid():
    """``with_walls`` forms the fish + walls union on the band's cells only (compiled on the CPU
    from the mesh nodes, kernels.FishOnGrid; torch operations elsewhere, ``torch_band_union``);
    both equal ``grid.union`` over the whole grid, values and gradients w.r.t. the nodes, their
    velocities and a swim tunnel's speed scaling the walls' velocity, for two fish, one of them
    in a wall band, whose surface is every other node of the mesh; in float32 the compiled union
    equals the torch one bit for bit."""
    from fishsim.coupling import fish_band, solid_to_fluid, united_with_nothing, with_walls
    from fishsim.coupling.layer import torch_band_union
    from fishsim.fields import Boundary
    from fishsim.fluid.grid import channel, union

    qs, qdots = bent_fish()
    qs[1] += torch.tensor([0.035, -0.01], dtype=torch.float64)          # into the walls' inflow band
    q = torch.stack([qs, qs + 1e-3], 2).flatten(1, 2).requires_grad_(True)    # surface: the even nodes
    qdot = torch.stack([qdots, -qdots], 2).flatten(1, 2).requires_grad_(True)
    walls = channel(GRID, 1.0, 3, 5, 1, None, torch.float64)
    speed = torch.tensor([0.3, -0.2], dtype=torch.float64, requires_grad=True)
    surface, cfg = torch.arange(0, q.shape[1], 2), CouplingConfig()
    alone, fields = solid_to_fluid(q, qdot, surface, GRID, cfg, torch.float64), lambda x: (x.mask, x.velocity)
    meets = lambda field: bool((alone.mask[1] * field.abs() > 0.1).any())
    assert meets(walls.mask[0, 0]) and meets(walls.velocity[0, 0]) and not (alone.mask[0] * walls.mask[0] > 0).any()
    want = fields(union(alone, Boundary(walls.mask, walls.velocity * speed.view(2, 1, 1, 1))))
    walls = united_with_nothing(walls)
    fish = fish_band(q, qdot, surface, GRID, cfg, torch.float64)
    for got in (fields(with_walls(q, qdot, surface, GRID, cfg, walls, speed)),
                fields(torch_band_union(*fish, GRID, walls, speed))):
        for a, b in zip(got, want):
            assert (a - b).abs().max() <= 1e-15 * b.abs().max()
        g = torch.Generator().manual_seed(3)
        cot = [torch.randn(x.shape, generator=g, dtype=torch.float64) for x in want]
        grads = [torch.autograd.grad(sum((c * x).sum() for c, x in zip(cot, out)), (q, qdot, speed),
                                     retain_graph=True) for out in (got, want)]
        for a, b in zip(*grads):
            assert (a - b).abs().max() <= 1e-12 * b.abs().max()
    walls = united_with_nothing(channel(GRID, 1.0, 3, 5, 1, None, torch.float32))     # the fluid's float32
    got = with_walls(q, qdot, surface, GRID, cfg, walls, speed)
    want = torch_band_union(*fish_band(q, qdot, surface, GRID, cfg), GRID, walls, speed.float())
    assert torch.equal(got.mask, want.mask) and torch.equal(got.velocity, want.velocity)


@pytest.mark.parametrize("pieces", [2, 3])
def test_one_fish_cut_over_threads_gives_the_one_thread_result_bit_for_bit(pieces):
    """A single fish's band selection, mask, boundary velocity and IBM force are cut into one
    piece per torch thread (kernels._each_fish's ``split``): the same nearest elements in the same
    order (each block of rows starts from the bound a pass over every row would have), inside and
    unranked flags, b, v_d and force, bit for bit, as one thread gives; a fish on a thin window
    (more pieces than its mask has rows of ranked cells) too."""
    from fishsim.coupling.kernels import NEGLIGIBLE, _band_boundary, _selection

    def run():
        out = []
        for qs in (bent_fish(B=1)[0], bent_fish(B=1, seed=3)[0] * torch.tensor([1.0, 0.3], dtype=torch.float64)):
            qdots = torch.randn(qs.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
            sel = _selection(qs.numpy(), GRID.dx, GRID.H, GRID.W, band_margin(SIGMA, GRID.dx), 25, True, NEGLIGIBLE * SIGMA)
            flat, centres, _, rel, nearest, inside, unranked, _ = sel
            b, u = _band_boundary((rel, qdots.numpy(), centres, nearest, inside, unranked, 5e-7, SIGMA, 5e-7, True,
                                   True, True))
            mask = torch.zeros(1, 1, GRID.H, GRID.W, dtype=torch.float64)
            mask.view(1, -1)[0, torch.from_numpy(flat[0])] = torch.from_numpy(b[0])
            p = torch.randn(1, 1, GRID.H, GRID.W, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
            f = OutsidePressureForce.apply(qs, p, mask, None, 0.5, GRID.dx, GRID.dx ** 2, 3, LINEAR_FIT)
            out += [nearest, inside, unranked, b, u, f.numpy()]
        return out

    serial = run()
    torch.set_num_threads(pieces)                   # restored by conftest's fixture
    split = run()
    assert all(a.shape == c.shape and (a == c).all() for a, c in zip(serial, split))
    assert serial[2].any() and not serial[2].all()  # some cells unranked, some ranked

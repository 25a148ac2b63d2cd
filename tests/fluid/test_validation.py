"""Physics validations of the numerical fluid against published data (VALIDATION.md).

Slow ones are marked; all are sized for CI on 2 cores (see each docstring for the measured
numbers and for the full-size runs recorded once)."""


import numpy as np
import pytest
import torch

from fishsim.fluid import grid as G
from fishsim.fluid.base import Boundary, FluidParams, FluidState, Grid
from fishsim.fluid.numerical import NumericalFluid

D = torch.float64

# Ghia, Ghia & Shin 1982, J. Comput. Phys. 48:387, Table I: u on the vertical centreline, Re = 100.
GHIA_RE100 = [
    (1.0000, 1.00000), (0.9766, 0.84123), (0.9688, 0.78871), (0.9609, 0.73722), (0.9531, 0.68717),
    (0.8516, 0.23151), (0.7344, 0.00332), (0.6172, -0.13641), (0.5000, -0.20581), (0.4531, -0.21090),
    (0.2813, -0.15662), (0.1719, -0.10150), (0.1016, -0.06434), (0.0703, -0.04775), (0.0625, -0.04192),
    (0.0547, -0.03717), (0.0000, 0.00000),
]  # fmt: skip


def _disc(g: Grid, x0, y0, radius, dtype=D):
    """Soft disc mask [1, 1, H, W], b = 1/2 on the circle, linear ramp over one cell."""
    c = g.cell_centres(dtype=torch.float64)
    r = ((c[..., 0] - x0) ** 2 + (c[..., 1] - y0) ** 2).sqrt()
    return (0.5 - (r - radius) / g.dx).clamp(0, 1)[None, None].to(dtype)


def _moving(mask, vx, vy):
    return torch.cat([vx * mask, vy * mask], 1)


@pytest.mark.slow
def test_lid_driven_cavity_re100_matches_ghia():
    """Unit square, 64 x 64, lid u = 1 as a moving no-slip wall (ghost values), nu = 0.01, run to
    t = 12 (steady to 1e-3).  Measured: max |u - u_Ghia| = 0.0040 over Table I (0.0043 at t = 20)."""
    N = 64
    g = Grid(N, N, 1.0 / N)
    m = NumericalFluid(g, walls=G.WallBC(u_top=1.0))
    s = m.initial_state(1, dtype=D)
    bd = Boundary(torch.zeros(1, 1, N, N, dtype=D), torch.zeros(1, 2, N, N, dtype=D))
    pr = FluidParams(torch.tensor([1.0], dtype=D), torch.tensor([0.01], dtype=D), 0.01)
    for _ in range(1200):
        s = m.step(s, bd, pr)
    u = G.curl(s.a, g.dx)[0][0, 0, :, N // 2].numpy()  # vertical faces on x = 0.5
    y = np.concatenate([[0.0], (np.arange(N) + 0.5) * g.dx, [1.0]])
    u = np.concatenate([[0.0], u, [1.0]])
    err = max(abs(np.interp(yk, y, u) - uk) for yk, uk in GHIA_RE100)
    assert err <= 0.02


def _control_volume_force(v0, v1, p, rho, mu, h, dx, rows, cols):
    """Force on whatever is inside the cell block rows x cols (N/m, [B, 2]) from the momentum
    balance of the fluid in it: F = -dM/dt - sum_sides (rho v (v.n) + p n - mu dv/dn) ds,
    with cell-centred velocities, side values as the mean of the two cells across the side."""
    c0, c1 = G.faces_to_centres(v0), G.faces_to_centres(v1)
    (i0, i1), (j0, j1) = rows, cols
    M = [rho * c[..., i0:i1, j0:j1].sum((-2, -1)) * dx**2 for c in (c0, c1)]
    vb = 0.5 * (c0 + c1)
    sides = [  # (inside cells, outside cells, outward normal)
        ((slice(i0, i1), j0), (slice(i0, i1), j0 - 1), (-1.0, 0.0)),
        ((slice(i0, i1), j1 - 1), (slice(i0, i1), j1), (1.0, 0.0)),
        ((i0, slice(j0, j1)), (i0 - 1, slice(j0, j1)), (0.0, -1.0)),
        ((i1 - 1, slice(j0, j1)), (i1, slice(j0, j1)), (0.0, 1.0)),
    ]
    flux = 0.0
    for inside, outside, n in sides:
        vi, vo = vb[(..., *inside)], vb[(..., *outside)]
        ps = 0.5 * (p[(..., 0, *inside)] + p[(..., 0, *outside)])
        vs = 0.5 * (vi + vo)
        nn = torch.tensor(n, dtype=vb.dtype)[None, :, None]
        un = (vs * nn).sum(1, keepdim=True)
        flux = flux + ((rho * vs * un + ps[:, None] * nn - mu * (vo - vi) / dx) * dx).sum(-1)
    return -(M[1] - M[0]) / h - flux


def test_towed_disc_penalization_force_balances_fluid_momentum():
    """A disc (radius 4 cells) towed at 0.1 m/s through a closed tank from rest (Re = 100).
    Every step, the force from the penalization term equals the control-volume momentum balance
    (rate of change of fluid momentum + momentum flux + pressure + viscous traction on a box
    around the disc).  Measured: 3.4e-5 relative per step, 5e-7 on the mean drag; mean C_D 1.4."""
    g = Grid(48, 120, 2.5e-3)
    rho, mu, U, R = 50.0, 1e-3, 0.1, 0.01
    tank = G.closed_tank(g, 2, 2, dtype=D)
    m = NumericalFluid(g)
    pr = FluidParams(torch.tensor([rho], dtype=D), torch.tensor([mu], dtype=D), 0.01)
    rows, cols = (8, 40), (16, 80)
    region = torch.zeros(1, 1, g.H, g.W, dtype=D)
    region[..., rows[0] : rows[1], cols[0] : cols[1]] = 1
    s = m.initial_state(1, dtype=D)
    drag = []
    for k in range(30):
        body = _disc(g, 0.07 + U * k * pr.h, 0.06, R)
        bd = G.union(tank, Boundary(body, _moving(body, U, 0.0)))
        s1, diag = m.step_with_diagnostics(s, bd, pr)
        f_pen = diag.force(rho, region)[0]
        f_cv = _control_volume_force(G.curl(s.a, g.dx), G.curl(s1.a, g.dx), s1.p, rho, mu, pr.h, g.dx, rows, cols)[0]
        torch.testing.assert_close(f_pen, f_cv, rtol=1e-3, atol=1e-3 * f_pen.abs().max().item())
        drag.append(-f_pen[0].item())
        s = s1
    cd = np.mean(drag[10:]) / (0.5 * rho * U**2 * 2 * R)
    assert 1.0 < cd < 2.5  # an impulsively started disc near walls: O(1) drag, opposing the motion


def cylinder_wake(
    cells_per_d=20, length=20.0, width=16.0, x_centre=5.0, t_end=180.0, window=60.0, h=0.05, dtype=torch.float32
):
    """Flow past a fixed circular cylinder at Re = U D / nu = 100 (U = D = 1, nu = 0.01).

    Domain [0, length] x [0, width] in D, cylinder centre (x_centre, width/2); inflow and outflow bands
    (4 columns, v_x = U) on the short sides, free-slip walls top and bottom; uniform flow at t = 0,
    symmetry broken by spinning the cylinder (omega = 0.5 U/D) for t < 3.  Force: the penalization
    force summed over the cells within 1.5 D of the centre.  Returns (St, mean C_D, C_L amplitude)
    over the last ``window`` time units; St from upward zero crossings of C_L.
    """
    U, Dc, nu = 1.0, 1.0, 0.01
    dx = Dc / cells_per_d
    g = Grid(round(width / dx), round(length / dx), dx)
    xc, yc = x_centre, width / 2
    c = g.cell_centres(dtype=torch.float64)
    r = ((c[..., 0] - xc) ** 2 + (c[..., 1] - yc) ** 2).sqrt()
    body = _disc(g, xc, yc, Dc / 2, dtype)
    region = (r < 1.5 * Dc).to(dtype)[None, None]
    spin = torch.stack([-(c[..., 1] - yc), c[..., 0] - xc])[None].to(dtype) * body * 0.5
    inflow = G.channel(g, U, thickness_y=0, thickness_x=4, dtype=dtype)
    spinning, fixed = G.union(inflow, Boundary(body, spin)), G.union(inflow, Boundary(body, 0 * spin))
    m = NumericalFluid(g, walls=G.FREE_SLIP)
    y = (torch.arange(g.H + 1, dtype=dtype) * dx)[None, None, :, None]
    a0 = (U * y).expand(1, 1, g.H + 1, g.W + 1)
    s = FluidState(a0 - a0.mean(), torch.zeros(1, 1, g.H, g.W, dtype=dtype))
    pr = FluidParams(torch.tensor([1.0], dtype=dtype), torch.tensor([nu], dtype=dtype), h)
    t, cl, cd = [], [], []
    for k in range(round(t_end / h)):
        s, diag = m.step_with_diagnostics(s, spinning if k * h < 3.0 else fixed, pr)
        f = diag.force(1.0, region)[0] / (0.5 * U**2 * Dc)
        t.append((k + 1) * h), cd.append(f[0].item()), cl.append(f[1].item())
    t, cd, cl = np.array(t), np.array(cd), np.array(cl)
    keep = t > t_end - window
    t, cd, cl = t[keep], cd[keep], cl[keep] - cl[keep].mean()
    up = np.where((cl[:-1] < 0) & (cl[1:] >= 0))[0]
    t_up = t[up] - cl[up] * h / (cl[up + 1] - cl[up])
    st = (len(t_up) - 1) / (t_up[-1] - t_up[0]) * Dc / U
    return st, cd.mean(), (cl.max() - cl.min()) / 2


@pytest.mark.slow
def test_cylinder_re100_sheds_vortices_reduced():
    """Reduced CI version of the Re = 100 cylinder (10 cells per D, domain 16 D x 8 D, t = 120):
    checks that the wake sheds at the right frequency and drag within 15 %.  The full-size runs
    (20 cells per D, recorded in the report) are too slow for CI on 2 cores."""
    st, cd, cl = cylinder_wake(cells_per_d=10, length=16.0, width=8.0, x_centre=5.0, t_end=120.0, window=50.0, h=0.1)
    assert 0.15 <= st <= 0.20
    assert 1.25 <= cd <= 1.75
    assert 0.2 <= cl <= 0.5

"""Validation cases of the numerical fluid (docs/physics.md section 6; reference data in docs/validation.md).

Drivers shared by the tests (tests/fluid) and the benchmark (benchmarks/bench_fluid.py), each
returning the measured numbers:

* ``taylor_green``: decay rate of the Taylor-Green mode vs the discrete-Laplacian rate.
* ``lid_driven_cavity``: centreline velocity of the Re = 100 cavity vs Ghia, Ghia & Shin 1982.
* ``cylinder_wake``: Strouhal number, mean drag and lift amplitude of the Re = 100 cylinder.
* ``oscillating_cylinder``: the in-phase (added-mass) force on a cylinder oscillating in still
  fluid vs Stokes and Wang.

and the helpers they and the rigid-body tests use: ``disc_mask``, ``moving`` (rigid translation
velocity), ``disc_polyline`` (the disc's ccw surface for the IBM), ``control_volume_force``
(momentum balance of a box of fluid).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from fishsim.fields import Boundary, FluidParams, FluidState, Grid
from fishsim.fluid import grid as G
from fishsim.fluid.numerical import NumericalFluid

# Ghia, Ghia & Shin 1982, J. Comput. Phys. 48:387, Table I: u on the vertical centreline, Re = 100.
GHIA_RE100 = [
    (1.0000, 1.00000), (0.9766, 0.84123), (0.9688, 0.78871), (0.9609, 0.73722), (0.9531, 0.68717),
    (0.8516, 0.23151), (0.7344, 0.00332), (0.6172, -0.13641), (0.5000, -0.20581), (0.4531, -0.21090),
    (0.2813, -0.15662), (0.1719, -0.10150), (0.1016, -0.06434), (0.0703, -0.04775), (0.0625, -0.04192),
    (0.0547, -0.03717), (0.0000, 0.00000),
]  # fmt: skip

# The published benchmarks step by the CFL bound alone with one penalisation pass blending by b
# (the classic splitting they were validated with); the sub-step floor of the defaults is set
# for the swimming frame (h = 0.01 s, 2.5 mm cells) and would multiply these cases' cost by up
# to 4.
BENCHMARK_STEPPING = {"substeps": 1, "penalization_iterations": 1, "penalization_rate": None}


# ----------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------


def disc_mask(g: Grid, x0: float, y0: float, radius: float, dtype=torch.float64) -> Tensor:
    """Soft disc mask [1, 1, H, W] centred at (x0, y0) [m]: b = 1/2 on the circle of ``radius``
    [m], a linear ramp over one cell (b = clamp(1/2 - (r - radius) / dx, 0, 1))."""
    c = g.cell_centres(dtype=torch.float64)
    r = ((c[..., 0] - x0) ** 2 + (c[..., 1] - y0) ** 2).sqrt()
    return (0.5 - (r - radius) / g.dx).clamp(0, 1)[None, None].to(dtype)


def moving(mask: Tensor, vx, vy) -> Tensor:
    """Boundary velocity [B, 2, H, W] of a body translating at (vx, vy) [m/s] inside ``mask``."""
    return torch.cat([vx * mask, vy * mask], 1)


def disc_polyline(x0: float, y0: float, radius: float, nodes: int, dtype=torch.float64) -> Tensor:
    """The disc's surface as the closed counter-clockwise polyline [1, nodes, 2] (x, y) in m."""
    t = torch.arange(nodes, dtype=torch.float64) * (2 * math.pi / nodes)
    return torch.stack([x0 + radius * t.cos(), y0 + radius * t.sin()], -1)[None].to(dtype)


def control_volume_force(v0, v1, p, rho, mu, h, dx, rows, cols) -> Tensor:
    """Force on whatever is inside the cell block rows x cols (N/m, [B, 2]) from the momentum
    balance of the fluid in it: F = -dM/dt - sum_sides (rho v (v.n) + p n - mu dv/dn) ds,
    with cell-centred velocities, side values as the mean of the two cells across the side.

    v0, v1: face velocities (``Faces``) at the start and end of the step [m/s]; p: pressure of
    the step [B, 1, H, W] (Pa); rho (kg/m^3), mu (Pa s), h (s), dx (m); rows = (i0, i1), cols =
    (j0, j1): the half-open cell ranges of the box, at least one cell away from the grid edge."""
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


# ----------------------------------------------------------------------------------------------
# Taylor-Green decay
# ----------------------------------------------------------------------------------------------


class TaylorGreen(NamedTuple):
    rate: float  # measured kinetic-energy decay rate, 1/s
    discrete_rate: float  # 2 nu (8 / dx^2) sin^2(dx / 2), 1/s
    rel_error: float  # rate / discrete_rate - 1


def taylor_green(N: int = 32, U: float = 1.0, nu: float = 0.01, h: float = 0.02, steps: int = 50,
                 dtype=torch.float64) -> TaylorGreen:
    """Decay of the Taylor-Green mode vx = U sin(x) cos(y), vy = -U cos(x) sin(y) (k = 1).

    Box [0, pi]^2 in N x N cells (dx = pi / N) with free-slip walls (the mode satisfies them),
    rho = 1, kinematic viscosity ``nu``, no body; ``steps`` steps of h.  The kinetic energy
    E = sum v^2 over the faces decays as exp(-rate t); the discrete 5-point Laplacian gives
    rate = 2 nu (8 / dx^2) sin^2(dx / 2) (-> 4 nu as dx -> 0).  Units: lengths and times of the
    box (m, s when read as SI); the mode's Reynolds number is U pi / nu.
    """
    dx = math.pi / N
    g = Grid(N, N, dx)
    i = torch.arange(N + 1, dtype=dtype) * dx
    y, x = torch.meshgrid(i, i, indexing="ij")
    a = (U * torch.sin(x) * torch.sin(y))[None, None]
    m = NumericalFluid(g, walls=G.FREE_SLIP, **BENCHMARK_STEPPING)
    s = FluidState(a, torch.zeros(1, 1, N, N, dtype=dtype))
    bd = Boundary(torch.zeros(1, 1, N, N, dtype=dtype), torch.zeros(1, 2, N, N, dtype=dtype))
    pr = FluidParams(torch.tensor([1.0], dtype=dtype), torch.tensor([nu], dtype=dtype), h)

    def energy(s):
        return sum((c**2).sum() for c in G.curl(s.a, dx)).item()

    e0 = energy(s)
    for _ in range(steps):
        s = m.step(s, bd, pr)
    rate = -math.log(energy(s) / e0) / (h * steps)
    expected = 2 * nu * (8 / dx**2) * math.sin(dx / 2) ** 2
    return TaylorGreen(rate, expected, rate / expected - 1)


# ----------------------------------------------------------------------------------------------
# Lid-driven cavity (Ghia et al. 1982)
# ----------------------------------------------------------------------------------------------


class Cavity(NamedTuple):
    max_error: float  # max |u - u_Ghia| over Table I, in lid-speed units
    y: np.ndarray  # heights of the centreline samples (walls included), lid heights
    u: np.ndarray  # u / U_lid there


def lid_driven_cavity(N: int = 64, steps: int = 1200, h: float = 0.01, dtype=torch.float64) -> Cavity:
    """Lid-driven cavity at Re = 100 vs Ghia, Ghia & Shin 1982, Table I.

    Unit square in N x N cells, lid u = 1 at y = 1 as a moving no-slip wall (ghost values), the
    other walls no-slip at rest, rho = 1, nu = 0.01, from rest for ``steps`` steps of h (default
    t = 12: steady to 1e-3).  u on the vertical faces of the centreline x = 0.5 (N even), extended
    by the wall values 0 and 1, interpolated linearly to Ghia's heights.  Units: lid speed, side.
    """
    g = Grid(N, N, 1.0 / N)
    m = NumericalFluid(g, walls=G.WallBC(u_top=1.0), **BENCHMARK_STEPPING)
    s = m.initial_state(1, dtype=dtype)
    bd = Boundary(torch.zeros(1, 1, N, N, dtype=dtype), torch.zeros(1, 2, N, N, dtype=dtype))
    pr = FluidParams(torch.tensor([1.0], dtype=dtype), torch.tensor([0.01], dtype=dtype), h)
    for _ in range(steps):
        s = m.step(s, bd, pr)
    u = G.curl(s.a, g.dx)[0][0, 0, :, N // 2].double().numpy()  # vertical faces on x = 0.5
    y = np.concatenate([[0.0], (np.arange(N) + 0.5) * g.dx, [1.0]])
    u = np.concatenate([[0.0], u, [1.0]])
    err = max(abs(np.interp(yk, y, u) - uk) for yk, uk in GHIA_RE100)
    return Cavity(float(err), y, u)


# ----------------------------------------------------------------------------------------------
# Cylinder wake
# ----------------------------------------------------------------------------------------------


class CylinderWake(NamedTuple):
    strouhal: float  # f D / U
    drag: float  # mean C_D = F_x / (rho U^2 D / 2)
    lift_amplitude: float  # (max C_L - min C_L) / 2
    probe: tuple[float, ...] = ()  # the window's mean of each of ``probe``'s values, / (rho U^2 D / 2)


# The CI-sized cylinder (tests/fluid/test_validation.py, bench_fluid.validation): 16 cells per D on
# 24 D x 32 D (blockage 1/32), cylinder 6 D from the inflow, h = 0.1 D/U, to t = 80 D/U, the last 30
# averaged (the wake is periodic by then: to t = 120, the last 40, gave the same St, C_D and C_L
# to three digits).
CYLINDER_CI = {"cells_per_d": 16, "length": 24.0, "width": 32.0, "x_centre": 6.0, "t_end": 80.0, "window": 30.0,
               "h": 0.1}


def cylinder_wake(
    cells_per_d=20, length=20.0, width=16.0, x_centre=5.0, t_end=180.0, window=60.0, h=0.05, dtype=torch.float32,
    stepping: dict | None = None, probe: Callable[[Grid, FluidState, Boundary], Tensor] | None = None,
) -> CylinderWake:
    """Flow past a fixed circular cylinder at Re = U D / nu = 100 (U = D = 1, nu = 0.01, rho = 1).

    Domain [0, length] x [0, width] in D (``cells_per_d`` cells per D), cylinder centre
    (x_centre, width/2), soft disc mask (``disc_mask``); inflow and outflow bands (4 columns,
    v_x = U) on the short sides, free-slip walls top and bottom; uniform flow at t = 0, symmetry
    broken by spinning the cylinder (omega = 0.5 U/D) for t < 3; steps of h up to t_end (in D/U).
    Force: the penalization force (``StepDiagnostics.force``) summed over the cells within 1.5 D
    of the centre, per unit depth, made dimensionless by rho U^2 D / 2.  Returns (St, mean C_D,
    C_L amplitude) over the last ``window`` time units; St from upward zero crossings of C_L.
    stepping: ``NumericalFluid`` keywords (default ``BENCHMARK_STEPPING``); probe: forces [k] of
    each step's state and fixed-cylinder boundary (e.g. the coupling's IBM force summed over the
    surface), averaged over the window into ``CylinderWake.probe``.
    """
    U, Dc, nu = 1.0, 1.0, 0.01
    dx = Dc / cells_per_d
    g = Grid(round(width / dx), round(length / dx), dx)
    xc, yc = x_centre, width / 2
    c = g.cell_centres(dtype=torch.float64)
    r = ((c[..., 0] - xc) ** 2 + (c[..., 1] - yc) ** 2).sqrt()
    body = disc_mask(g, xc, yc, Dc / 2, dtype)
    region = (r < 1.5 * Dc).to(dtype)[None, None]
    spin = torch.stack([-(c[..., 1] - yc), c[..., 0] - xc])[None].to(dtype) * body * 0.5
    inflow = G.channel(g, U, thickness_y=0, thickness_x=4, dtype=dtype)
    spinning, fixed = G.union(inflow, Boundary(body, spin)), G.union(inflow, Boundary(body, 0 * spin))
    m = NumericalFluid(g, walls=G.FREE_SLIP, **(BENCHMARK_STEPPING if stepping is None else stepping))
    y = (torch.arange(g.H + 1, dtype=dtype) * dx)[None, None, :, None]
    a0 = (U * y).expand(1, 1, g.H + 1, g.W + 1)
    s = FluidState(a0 - a0.mean(), torch.zeros(1, 1, g.H, g.W, dtype=dtype))
    pr = FluidParams(torch.tensor([1.0], dtype=dtype), torch.tensor([nu], dtype=dtype), h)
    t, cl, cd, probed = [], [], [], []
    for k in range(round(t_end / h)):
        s, diag = m.step_with_diagnostics(s, spinning if k * h < 3.0 else fixed, pr)
        f = diag.force(1.0, region)[0] / (0.5 * U**2 * Dc)
        t.append((k + 1) * h), cd.append(f[0].item()), cl.append(f[1].item())
        if probe is not None and (k + 1) * h > t_end - window:
            probed.append(probe(g, s, fixed).double().numpy() / (0.5 * U**2 * Dc))
    t, cd, cl = np.array(t), np.array(cd), np.array(cl)
    keep = t > t_end - window
    t, cd, cl = t[keep], cd[keep], cl[keep] - cl[keep].mean()
    up = np.where((cl[:-1] < 0) & (cl[1:] >= 0))[0]
    t_up = t[up] - cl[up] * h / (cl[up + 1] - cl[up])
    st = (len(t_up) - 1) / (t_up[-1] - t_up[0]) * Dc / U
    mean_probe = tuple(float(x) for x in np.mean(probed, 0)) if probed else ()
    return CylinderWake(float(st), float(cd.mean()), float((cl.max() - cl.min()) / 2), mean_probe)


# ----------------------------------------------------------------------------------------------
# Oscillating cylinder
# ----------------------------------------------------------------------------------------------


class OscillatingCylinder(NamedTuple):
    beta: float  # Stokes number f D^2 / nu
    stokes_wang: float  # in-phase C_m of the unbounded viscous fluid, 1 + 4 / sqrt(pi beta)
    confinement: float  # potential-flow added mass in the box's inscribed circle / unbounded
    exchange: float  # in-phase C_m of the force the penalisation exchanges with the fluid
    probe: tuple[float, ...] = ()  # in-phase C_m of each of ``probe``'s forces


def in_phase_added_mass(force: np.ndarray, acceleration: np.ndarray, velocity: np.ndarray, mass: float) -> float:
    """C_m of the least-squares fit F = -C_m M a - c v of a force [N/m] in time (M [kg/m] the
    displaced fluid's mass): the part of F in phase with the body's acceleration, over M a."""
    coef = np.linalg.lstsq(np.stack([acceleration, velocity], 1), -force, rcond=None)[0]
    return float(coef[0] / mass)


def oscillating_cylinder(
    radius_cells=8, box_cells=160, dx=2.5e-3, rho=50.0, mu=1.25e-4, freq=2.0, amplitude=5e-3, periods=4, h=0.01,
    dtype=torch.float64, stepping: dict | None = None,
    probe: Callable[[Grid, FluidState, Boundary, tuple[float, float], tuple[float, float], float], Tensor] | None = None,
) -> OscillatingCylinder:
    """A rigid cylinder oscillating across still fluid, y(t) = y0 - A cos(w t), from rest, in a
    closed square box of ``box_cells``^2 cells of ``dx`` [m] (walls two cells thick), stepped
    with ``stepping`` (``NumericalFluid`` keywords; default its own defaults; h [s] a frame; the
    fish's: ``fishsim.fluid.factory.numerical_stepping`` of the numerical fluid's config).

    The hydrodynamic force on the body is the penalisation force within 2 R of the centre plus
    rho V dv_d/dt, the momentum put into the fluid inside the disc.  Its part in phase with the
    acceleration, over rho pi R^2 A w^2 (``in_phase_added_mass``, the last two periods), is compared
    with the unbounded viscous value of Stokes and Wang (1968, small KC = 2 pi A / D),
    C_m = 1 + 4 / sqrt(pi beta) + O(1 / beta), beta = f D^2 / nu, times the confinement of potential
    flow in a concentric circular box of radius R_b (the box's inscribed circle),
    (R_b^2 + R^2) / (R_b^2 - R^2).  probe(grid, state, boundary, centre [m], velocity [m/s], y
    acceleration [m/s^2] at the step's middle) -> y forces [k] (N/m, e.g. the coupling's IBM force
    summed over the surface) of each step's state.
    """
    g = Grid(box_cells, box_cells, dx)
    R, w, L = radius_cells * dx, 2 * math.pi * freq, box_cells * dx
    tank = G.closed_tank(g, 2, 2, dtype=dtype)
    m = NumericalFluid(g, **({} if stepping is None else stepping))
    pr = FluidParams(torch.tensor([rho], dtype=dtype), torch.tensor([mu], dtype=dtype), h)
    c = g.cell_centres(dtype=torch.float64)
    region = (((c[..., 0] - L / 2) ** 2 + (c[..., 1] - L / 2) ** 2).sqrt() < 2 * R).to(dtype)[None, None]
    s = m.initial_state(1, dtype=dtype)
    rows, v_prev = [], 0.0
    for k in range(round(periods / (freq * h))):
        y, vy = L / 2 - amplitude * math.cos(w * k * h), amplitude * w * math.sin(w * k * h)
        body = disc_mask(g, L / 2, y, R, dtype)
        bd = G.union(tank, Boundary(body, moving(body, 0.0, vy)))
        s, diag = m.step_with_diagnostics(s, bd, pr)
        inertia = rho * body.sum().item() * dx**2 * (vy - v_prev) / h
        acceleration = amplitude * w * w * math.cos(w * (k + 0.5) * h)
        probed = probe(g, s, bd, (L / 2, y), (0.0, vy), acceleration).tolist() if probe is not None else []
        t = (k + 1) * h  # the step's end, where the state is
        rows.append([t, diag.force(rho, region)[0][1].item() + inertia, *probed,
                     amplitude * w * w * math.cos(w * t), amplitude * w * math.sin(w * t)])
        v_prev = vy
    a = np.array(rows)
    a = a[a[:, 0] > (periods - 2) / freq]
    M = rho * math.pi * R**2
    cm = [in_phase_added_mass(a[:, i], a[:, -2], a[:, -1], M) for i in range(1, a.shape[1] - 2)]
    beta = freq * (2 * R) ** 2 * rho / mu
    Rb = L / 2 - 2 * dx
    return OscillatingCylinder(beta, 1 + 4 / math.sqrt(math.pi * beta), (Rb**2 + R**2) / (Rb**2 - R**2), cm[0],
                               tuple(cm[1:]))

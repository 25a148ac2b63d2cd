"""Physics validations of the numerical fluid against published data (docs/validation.md).

Slow ones are marked; all are sized for CI on 2 cores (see each docstring for the measured
numbers and for the full-size runs recorded once)."""

import math

import numpy as np
import pytest
import torch

from fishsim.coupling.ibm import ibm_force
from fishsim.fields import Boundary, FluidParams, Grid
from fishsim.fluid import grid as G
from fishsim.fluid.cases import (
    BENCHMARK_STEPPING,
    CYLINDER_CI,
    control_volume_force,
    cylinder_wake,
    disc_mask,
    disc_polyline,
    lid_driven_cavity,
    mask_pressure_force,
    moving,
)
from fishsim.fluid.numerical import NumericalFluid

D = torch.float64


@pytest.mark.slow
def test_lid_driven_cavity_re100_matches_ghia():
    """Unit square, 64 x 64, lid u = 1 as a moving no-slip wall (ghost values), nu = 0.01, run to
    t = 12 (steady to 1e-3).  Measured: max |u - u_Ghia| = 0.0040 over Table I (0.0043 at t = 20)."""
    err = lid_driven_cavity(N=64, steps=1200).max_error
    assert err <= 0.02


def test_towed_disc_penalization_force_balances_fluid_momentum():
    """A disc (radius 4 cells) towed at 0.1 m/s through a closed tank from rest (Re = 100).
    Every step, the force from the penalization term equals the control-volume momentum balance
    (rate of change of fluid momentum + momentum flux + pressure + viscous traction on a box
    around the disc).  Measured: 3.4e-5 relative per step, 5e-7 on the mean drag; mean C_D 1.4."""
    g = Grid(48, 120, 2.5e-3)
    rho, mu, U, R = 50.0, 1e-3, 0.1, 0.01
    tank = G.closed_tank(g, 2, 2, dtype=D)
    m = NumericalFluid(g, **BENCHMARK_STEPPING)
    pr = FluidParams(torch.tensor([rho], dtype=D), torch.tensor([mu], dtype=D), 0.01)
    rows, cols = (8, 40), (16, 80)
    region = torch.zeros(1, 1, g.H, g.W, dtype=D)
    region[..., rows[0] : rows[1], cols[0] : cols[1]] = 1
    s = m.initial_state(1, dtype=D)
    drag = []
    for k in range(30):
        body = disc_mask(g, 0.07 + U * k * pr.h, 0.06, R)
        bd = G.union(tank, Boundary(body, moving(body, U, 0.0)))
        s1, diag = m.step_with_diagnostics(s, bd, pr)
        f_pen = diag.force(rho, region)[0]
        f_cv = control_volume_force(G.curl(s.a, g.dx), G.curl(s1.a, g.dx), s1.p, rho, mu, pr.h, g.dx, rows, cols)[0]
        torch.testing.assert_close(f_pen, f_cv, rtol=1e-3, atol=1e-3 * f_pen.abs().max().item())
        drag.append(-f_pen[0].item())
        s = s1
    cd = np.mean(drag[10:]) / (0.5 * rho * U**2 * 2 * R)
    assert 1.0 < cd < 2.5  # an impulsively started disc near walls: O(1) drag, opposing the motion


@pytest.mark.slow
def test_cylinder_re100_strouhal_and_drag_in_published_bands():
    """CI version of the Re = 100 cylinder (``CYLINDER_CI``: 16 cells per D on 24 D x 32 D,
    blockage 1/32, h = 0.1 D/U, t = 120, last 40): Strouhal number and mean drag in the published
    bands of docs/validation.md.  Measured: St 0.171, C_D 1.48, C_L amplitude 0.32 (~2.5 min
    single-threaded).  On this domain C_D falls with resolution (10 cells/D 1.52, 12: 1.51,
    14: 1.50, 16: 1.48, 20: 1.46; St 0.167, 0.169, 0.170, 0.171, 0.173); on 16 D x 8 D
    (blockage 1/8) 10 cells/D gave St 0.177, C_D 1.67.  The force is the penalization force
    summed within 1.5 D of the centre (``cylinder_wake``)."""
    st, cd, cl = cylinder_wake(**CYLINDER_CI)
    assert 0.155 <= st <= 0.175
    assert 1.25 <= cd <= 1.50
    assert 0.2 <= cl <= 0.5


def _rigid_disc_forces(U, amp_y, freq, steps):
    """A disc (radius 4 cells = 1 cm, 31 surface nodes) in the closed tank of the towed-disc test
    (48 x 120 cells, dx = 2.5 mm, rho = 50, mu = 1e-3), moving at (U, A w sin(w t)) from rest, so
    x(t) = 0.07 + U t, y(t) = 0.06 - A cos(w t) [m].  Per step k (arrays [steps, 2], N/m):
    penalization force on the disc, its hydrodynamic part (the penalization force plus the
    momentum rho V dv_d/dt put into the fluid inside the disc), the IBM pressure force
    (``ibm_force`` summed over the nodes, on the step's pressure) and the grid pressure force
    (``mask_pressure_force``: -sum b grad p dx^2 over the disc's own mask)."""
    g = Grid(48, 120, 2.5e-3)
    rho, mu, R, w = 50.0, 1e-3, 0.01, 2 * math.pi * freq
    tank = G.closed_tank(g, 2, 2, dtype=D)
    m = NumericalFluid(g, **BENCHMARK_STEPPING)
    pr = FluidParams(torch.tensor([rho], dtype=D), torch.tensor([mu], dtype=D), 0.01)
    region = torch.zeros(1, 1, g.H, g.W, dtype=D)
    region[..., 8:40, 16:80] = 1
    s = m.initial_state(1, dtype=D)
    out, v_prev = [], 0.0
    for k in range(steps):
        t = k * pr.h
        xc, yc, vy = 0.07 + U * t, 0.06 - amp_y * math.cos(w * t), amp_y * w * math.sin(w * t)
        body = disc_mask(g, xc, yc, R)
        bd = G.union(tank, Boundary(body, moving(body, U, vy)))
        s1, diag = m.step_with_diagnostics(s, bd, pr)
        f_pen = diag.force(rho, region)[0]
        inertia = rho * body.sum().item() * g.dx**2 * torch.tensor([0.0, vy - v_prev], dtype=D) / pr.h
        f_ibm = ibm_force(disc_polyline(xc, yc, R, 31), s1.p, bd.mask, g).sum(1)[0]
        out.append(torch.stack([f_pen, f_pen + inertia, f_ibm, mask_pressure_force(s1.p, body, g.dx)[0]]))
        s, v_prev = s1, vy
    return torch.stack(out).numpy().transpose(1, 0, 2)  # [4, steps, 2]


def test_towed_disc_ibm_pressure_drag_vs_penalization():
    """The coupling's IBM pressure sampling (``ibm_force``: fluid-side cells, linear fit, chord
    elements; 31 nodes ~2 mm apart, sigma' = dx^2) on the towed disc of the test above (Re = 100,
    radius 4 cells, from rest), against (a) the grid pressure force -sum b grad p dx^2 and (b) the
    total (pressure + viscous) penalization drag.

    Measured (float64): (a) IBM / grid pressure drag 0.96 on the impulsive first step, then
    0.74 - 0.80 (mean 0.76 over steps 10-29; 0.77 at dx / 2 and dx / 4): the IBM extrapolates the
    fluid-side pressure to r = R, while the grid sum averages p over the one-cell ramp
    R -/+ dx/2, and p varies steeply across it.  (b) IBM / penalization drag 1.24 (C_D,p 1.72 vs
    C_D 1.38; 1.44 at dx / 2, 1.49 at dx / 4): the pressure-only drag *exceeds* the total, where
    the missing skin friction should make it ~0.8.  The surplus sits in a one-to-two cell layer of
    p next to the moving mask (the contour integral of p at R + 1.5 dx gives 0.96 of the total;
    four penalization passes per stage raise IBM / total to 3.2): the pressure of the
    penalize -> project splitting next to a moving body is not the physical surface pressure.
    Tolerances: (a) within 30 % every step, (b) same sign, ratio in [0.5, 1.5]."""
    pen, _, ibm, grid = _rigid_disc_forces(U=0.1, amp_y=0.0, freq=0.0, steps=30)
    assert np.all(np.abs(ibm[:, 0] - grid[:, 0]) <= 0.3 * np.abs(grid[:, 0]))
    drag_pen, drag_ibm = -pen[10:, 0].mean(), -ibm[10:, 0].mean()
    assert drag_pen > 0 and drag_ibm > 0  # both oppose the motion
    assert 0.5 <= drag_ibm / drag_pen <= 1.5


def test_oscillating_disc_ibm_pressure_force_vs_penalization():
    """The same disc oscillating across the tank, y = 0.06 - A cos(w t) (A = 5 mm, 2 Hz, from
    rest; Stokes number f D^2 / nu = 40, KC = 2 pi A / D = 1.6): a force dominated by added mass,
    i.e. by pressure.  Over steps 25-99 (1.5 periods), y components:

    Measured (float64): IBM vs grid pressure force -sum b grad p dx^2: least-squares ratio 0.92,
    relative L2 difference 0.13 (0.98 and 0.07 at dx / 2).  IBM vs the hydrodynamic force from the
    penalization (its force plus rho V dv_d/dt, the momentum given to the fluid inside the disc):
    ratio 0.86 (0.90 at dx / 2; grid pressure force: 0.93); amplitudes 0.0122 (IBM), 0.0132 (grid), 0.0141 N/m
    (total), vs 0.0124 N/m for the potential-flow added mass rho pi R^2 A w^2 in unbounded fluid.
    Tolerances: (a) relative L2 difference < 0.2, ratio in [0.8, 1.05]; (b) pressure fraction of
    the total in [0.7, 1.0]."""
    _, hyd, ibm, grid = _rigid_disc_forces(U=0.0, amp_y=0.005, freq=2.0, steps=100)
    f_hyd, f_ibm, f_grid = hyd[25:, 1], ibm[25:, 1], grid[25:, 1]
    assert np.linalg.norm(f_ibm - f_grid) < 0.2 * np.linalg.norm(f_grid)
    assert 0.8 <= (f_ibm @ f_grid) / (f_grid @ f_grid) <= 1.05
    assert 0.7 <= (f_ibm @ f_hyd) / (f_hyd @ f_hyd) <= 1.0

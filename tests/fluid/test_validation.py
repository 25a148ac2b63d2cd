"""Physics validations of the numerical fluid against published data (docs/validation.md).

Slow ones are marked; all are sized for CI on 2 cores (see each docstring for the measured
numbers and for the full-size runs recorded once)."""

import math

import numpy as np
import pytest
import torch

from benchmarks.bench_fluid import FISH_STEPPING
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
    moving,
    oscillating_cylinder,
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
    blockage 1/32, h = 0.1 D/U, t = 80, last 30): Strouhal number and mean drag in the published
    bands of docs/validation.md.  Measured: St 0.1714, C_D 1.483, C_L amplitude 0.324 (to t = 120,
    the last 40: 0.171, 1.48, 0.32; ~1.5 min single-threaded).  On this domain C_D falls with
    resolution (10 cells/D 1.52, 12: 1.51, 14: 1.50, 16: 1.48, 20: 1.46; St 0.167, 0.169, 0.170,
    0.171, 0.173; to t = 120); on 16 D x 8 D (blockage 1/8) 10 cells/D gave St 0.177, C_D 1.67.
    The force is the penalization force summed within 1.5 D of the centre (``cylinder_wake``)."""
    st, cd, cl, _ = cylinder_wake(**CYLINDER_CI)
    assert 0.155 <= st <= 0.175
    assert 1.25 <= cd <= 1.50
    assert 0.2 <= cl <= 0.5


STEPPINGS = {"benchmark": BENCHMARK_STEPPING,                   # 1 sub-step, 1 penalisation pass
             "fish": {},                                         # the fish's defaults: 8 sub-steps x 3 passes
             "rate": {"brinkman": 1e4}}                          # the rate penalisation, 8 sub-steps


def _rigid_disc_forces(U, amp_y, freq, steps, stepping, weight="outside"):
    """A disc (radius 4 cells = 1 cm, 31 surface nodes) in the closed tank of the towed-disc test
    (48 x 120 cells, dx = 2.5 mm, rho = 50, mu = 1e-3), moving at (U, A w sin(w t)) from rest, so
    x(t) = 0.07 + U t, y(t) = 0.06 - A cos(w t) [m].  Per step k (arrays [steps, 2], N/m):
    penalization force on the disc, its hydrodynamic part (the penalization force plus the
    momentum rho V dv_d/dt put into the fluid inside the disc), the IBM pressure force
    (``ibm_force`` with ``weight``, summed over the nodes, on the step's pressure) and the viscous
    traction (``ibm_force`` with ``viscous`` and no pressure, summed, on the step's velocity)."""
    g = Grid(48, 120, 2.5e-3)
    rho, mu, R, w = 50.0, 1e-3, 0.01, 2 * math.pi * freq
    tank = G.closed_tank(g, 2, 2, dtype=D)
    m = NumericalFluid(g, **stepping)
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
        qs = disc_polyline(xc, yc, R, 31)
        f_ibm = ibm_force(qs, s1.p, bd.mask, g, weight=weight).sum(1)[0]
        v = G.faces_to_centres(G.curl(s1.a, g.dx))
        u = torch.tensor([U, vy], dtype=D).expand_as(qs)
        f_visc = ibm_force(qs, torch.zeros_like(s1.p), bd.mask, g, viscous=(u, v, mu)).sum(1)[0]
        out.append(torch.stack([f_pen, f_pen + inertia, f_ibm, f_visc]))
        s, v_prev = s1, vy
    return torch.stack(out).numpy().transpose(1, 0, 2)  # [4, steps, 2]


@pytest.mark.parametrize("stepping", STEPPINGS)
def test_towed_disc_ibm_pressure_drag_vs_penalization(stepping):
    """The coupling's IBM pressure drag (``ibm_force``: cells beyond the band on each node's side,
    linear fit, chord elements; 31 nodes ~2 mm apart, sigma' = dx^2) on the towed disc of the test
    above (Re = 100, radius 4 cells, from rest, steps 10-29) against the total (pressure + viscous)
    drag the penalization exchanges with the fluid (the momentum balance of the test above).

    Measured (float64), IBM / total: 0.79 (benchmark stepping), 0.85 (fish, 8 sub-steps x 3
    passes; 0.80 at 2 passes, 0.89 at 4), 0.67 (rate; total C_D 1.38 / 0.93 / 1.01): the pressure
    share of a cylinder's drag at Re = 100 is ~0.7-0.8.  With the viscous traction
    (``ibm_force(viscous=...)``, C_D 0.33 at every stepping, about the skin-friction drag of a
    cylinder at Re = 100): 1.025 / 1.200 / 0.986 (1.143 at 2 passes, 1.243 at 4: the band stiffens
    with every pass, the pressure beyond it rises and the exchanged total falls).  The former
    default weight, 1 - b, also sampled the band, whose pressure is the penalization's and grows
    with its stiffness: 1.25 / 18.6 / 36 (the fish's sampled force was its pressure).
    Tolerances: pressure [0.6, 0.9], pressure + traction [0.9, 1.25]; the former weight at the
    fish's stepping > 5."""
    pen, _, ibm, visc = _rigid_disc_forces(U=0.1, amp_y=0.0, freq=0.0, steps=30, stepping=STEPPINGS[stepping])
    drag_pen, drag_ibm, drag_visc = -pen[10:, 0].mean(), -ibm[10:, 0].mean(), -visc[10:, 0].mean()
    assert drag_pen > 0 and drag_ibm > 0 and drag_visc > 0  # all oppose the motion
    assert 0.6 <= drag_ibm / drag_pen <= 0.9
    assert 0.9 <= (drag_ibm + drag_visc) / drag_pen <= 1.25
    if stepping == "fish":
        pen, _, ibm, _ = _rigid_disc_forces(U=0.1, amp_y=0.0, freq=0.0, steps=30, stepping={}, weight="fluid")
        assert ibm[10:, 0].mean() / pen[10:, 0].mean() > 5


@pytest.mark.parametrize("stepping", STEPPINGS)
def test_oscillating_disc_ibm_pressure_force_is_its_added_mass(stepping):
    """The same disc oscillating across the tank, y = 0.06 - A cos(w t) (A = 5 mm, 2 Hz, from
    rest; Stokes number f D^2 / nu = 40, KC = 2 pi A / D = 1.6): a force dominated by added mass,
    i.e. by pressure.  Over steps 25-99 (1.5 periods), y components.

    Measured (float64), benchmark / fish / rate stepping: IBM amplitude 0.0116 / 0.0127 / 0.0127
    N/m against rho pi R^2 A w^2 = 0.0124 N/m, the potential-flow added-mass force in unbounded
    fluid (-6.5 / +2.6 / +2.4 %); IBM / hydrodynamic force from the penalization (its force plus
    rho V dv_d/dt, the momentum given to the fluid inside the disc; amplitude 0.0139 / 0.0155 /
    0.0157): least-squares ratio 0.81 / 0.81 / 0.81 (the rest is viscous; with the viscous
    traction 0.87 / 0.84 / 0.83: the oscillating Stokes layer, sqrt(2 nu / w) = 1.8 mm, is under a
    cell).  The former weight 1 - b: amplitude 0.0120 / 0.0591 / 0.118.  Tolerances: amplitude
    within 10 %, ratio in [0.7, 0.9], and larger with the traction (at most 0.95)."""
    _, hyd, ibm, visc = _rigid_disc_forces(U=0.0, amp_y=0.005, freq=2.0, steps=100, stepping=STEPPINGS[stepping])
    f_hyd, f_ibm, f_visc = hyd[25:, 1], ibm[25:, 1], visc[25:, 1]
    added_mass = 50.0 * math.pi * 0.01**2 * 0.005 * (2 * math.pi * 2.0) ** 2
    assert abs(np.abs(f_ibm).max() - added_mass) < 0.1 * added_mass
    assert 0.7 <= (f_ibm @ f_hyd) / (f_hyd @ f_hyd) <= 0.9
    assert (f_ibm @ f_hyd) / (f_hyd @ f_hyd) < ((f_ibm + f_visc) @ f_hyd) / (f_hyd @ f_hyd) <= 0.95


def test_oscillating_cylinder_on_the_fish_grid_has_its_published_added_mass():
    """A 4 cm cylinder (16 cells per D) oscillating at 2 Hz, A = 5 mm, in the paper's fluid
    (rho 50, mu 1.25e-4: beta = f D^2 / nu = 1280, KC = 0.8) on the fish's grid and stepping, in a
    40 cm box (``oscillating_cylinder``): the in-phase (added-mass) force, in rho pi R^2 A w^2,
    against Stokes-Wang 1 + 4 / sqrt(pi beta) = 1.063 times the box's confinement, 1.021 (1.086).

    Measured with the fish's stepping since 2026-11-29 (the joint stage at 4 sub-steps; 8 give
    the same to 0.1 %): the penalisation's exchanged force 1.133 (+4.4 %: the converged
    penalisation holds the band's fluid to the body, a slightly larger effective body); the
    coupling's IBM force (``ibm_force``, 63 nodes ~0.8 cells apart) 1.027 (-5.4 %, -9.4 % of the
    exchange; the Stokes layer, 0.6 mm, is under a cell and its share of the in-phase force,
    2 / sqrt(pi beta) = 3 %, is missed). At 8 cells per D (radius 1 cm, 60 cm box) the IBM force
    is -15.5 % of the reference, the exchange +4.4 %: the issue's 5-10 % holds from 16 cells per D.
    With the split passes (8 x 3, the stepping before): exchange 1.071 (-1.4 %), IBM 0.996 (-8.3 %;
    at 8 cells per D -20 %). Tolerances: exchange within 5 %, IBM within 10 % of both."""
    R = 8 * 2.5e-3

    def ibm(g, s, bd, centre, velocity, acceleration):
        qs = disc_polyline(*centre, R, 63)
        return ibm_force(qs, s.p, bd.mask, g, sigma_prime=g.dx**2).sum(1)[0, 1:]

    res = oscillating_cylinder(8, 160, probe=ibm, stepping=FISH_STEPPING)
    reference = res.stokes_wang * res.confinement
    assert abs(res.exchange / reference - 1) < 0.05
    assert abs(res.probe[0] / reference - 1) < 0.10
    assert abs(res.probe[0] / res.exchange - 1) < 0.10


def test_the_wall_fit_gives_an_accelerating_cylinder_its_added_mass_from_8_cells_per_d():
    """The cylinder of the test above at 8 cells per D (2 cm, the fish's thickness; beta = 320,
    reference 1.132 in the 40 cm box) read with ``ibm_fit`` "wall": the plane through the samples
    beyond the band with its normal slope imposed, -rho a.n (a at the step's middle), instead of
    fitted. The free plane, fitted 0.5-2 cells out where the pressure falls off as R / r, is
    shallower than the wall's: measured C_m 0.957 (-15.4 % of the reference, -19.0 % of the
    exchange 1.182), with the wall's slope 1.098 (-3.0 / -7.1 %; docs/validation.md, "The wall's
    pressure gradient imposed"). Tolerances: within 5 % of the reference and 10 % of the exchange;
    the free plane more than 10 % short of both."""
    R, rho = 4 * 2.5e-3, 50.0

    def fits(g, s, bd, centre, velocity, acceleration):
        qs = disc_polyline(*centre, R, 31)
        a = torch.zeros_like(qs)
        a[..., 1] = acceleration
        return torch.stack([ibm_force(qs, s.p, bd.mask, g, g.dx**2).sum(1)[0, 1],
                            ibm_force(qs, s.p, bd.mask, g, g.dx**2, fit="wall", wall=(a, rho)).sum(1)[0, 1]])

    res = oscillating_cylinder(4, 160, probe=fits, stepping=FISH_STEPPING)
    reference = res.stokes_wang * res.confinement
    linear, wall = res.probe
    assert abs(wall / reference - 1) < 0.05 and abs(wall / res.exchange - 1) < 0.10
    assert linear < 0.9 * reference and linear < 0.9 * res.exchange

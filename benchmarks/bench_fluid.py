"""Numerical fluid timings on the paper's tank (100 x 300, dx = 2.5 mm, h = 0.01 s): ms per step
forward and forward + backward, B = 1 and B = 16, refinement r = 1 and 2, with the CFL sub-step
counts.  `run() -> dict` for the `make bench` driver; `python -m benchmarks.bench_fluid` prints it.

Scenario: a fish-shaped soft mask (length 10 cm, NACA-like thickness) undulating at 5 Hz with a
travelling wave whose tail speed reaches 0.5 m/s (Courant number u h / dx = 2), in a closed tank
with wall bands; rho = 50, mu = 0.125 mPa s.  The flow is warmed up for ``warmup`` steps from rest
(no grad) before timing, so the sub-step counts are those of a developed flow.  float32, CPU
threads as torch is configured.  Backward: gradient of the final kinetic energy w.r.t. the wave
amplitude (through mask velocity) after one step.

``bench_case`` times `fishsim simulate`'s numerical fluid (the joint stage at 4 sub-steps).
``joint_parts()`` (part of ``run()``) times the default joint stage's compiled parts per call at
B = 1; ``kernel_parts()`` (part of ``run()``) the compiled split passes' parts
(``fluid.implicit=false``: a frame at 8 sub-steps x 3 passes makes 16 predictor calls and 48 of
each pass part). ``validation()`` (part of ``run()``, also callable alone) re-measures the validation figures of
tests/fluid (fishsim.fluid.cases) at stated resolutions, with their wall times: the Taylor-Green
decay-rate error, the lid-driven cavity vs Ghia et al. (64 x 64), and the Re = 100 cylinder
(Strouhal number, mean C_D, C_L amplitude) at the CI-reduced size and at a larger one, and on the
fish's grid and stepping with the coupling's IBM drag beside the momentum exchange.
"""


from __future__ import annotations

import json
import math
import time
from contextlib import contextmanager
from functools import partial

import torch

from fishsim.config import NumericalConfig
from fishsim.coupling.ibm import ibm_force
from fishsim.fields import Boundary, FluidParams, FluidState, Grid
from fishsim.fluid import cases
from fishsim.fluid import grid as G
from fishsim.fluid.factory import make_fluid, numerical_stepping
from fishsim.fluid.numerical import IMMERSE_TOL, NumericalFluid
from fishsim.fluid.tank import TankConfig

GRID = Grid(100, 300, 2.5e-3)
LENGTH, FREQ, TAIL_SPEED = 0.1, 5.0, 0.5


def fish_boundary(grid: Grid, t: float, amplitude: torch.Tensor, batch: int = 1) -> Boundary:
    """Tank walls plus an undulating fish: centreline y_c(s) = y0 + A(s) sin(k s - w t),
    A(s) = amplitude (s / L)^2, half-thickness of a NACA 0012 profile (6 % of L at most), soft edge of one
    cell; boundary velocity dy_c/dt inside the body.  amplitude: scalar tensor [m]."""
    c = grid.cell_centres(dtype=amplitude.dtype)
    x0, y0, w, k = 0.3, grid.H * grid.dx / 2, 2 * math.pi * FREQ, 2 * math.pi / LENGTH
    s = ((c[..., 0] - x0) / LENGTH).clamp(0, 1)
    env = amplitude * s**2
    yc = y0 + env * torch.sin(k * s * LENGTH - w * t)
    half = 5 * 0.12 * LENGTH * (0.2969 * s.sqrt() - 0.126 * s - 0.3516 * s**2 + 0.2843 * s**3 - 0.1036 * s**4)
    inside = ((c[..., 0] > x0) & (c[..., 0] < x0 + LENGTH)).to(c.dtype)
    b = ((0.5 - ((c[..., 1] - yc).abs() - half) / grid.dx).clamp(0, 1) * inside)[None, None]
    vy = -env * w * torch.cos(k * s * LENGTH - w * t)
    vel = torch.stack([torch.zeros_like(vy), vy])[None] * b
    fish = Boundary(b.expand(batch, -1, -1, -1), vel.expand(batch, -1, -1, -1))
    return G.union(G.closed_tank(grid, 3, 5, batch, dtype=c.dtype), fish)


def _params(batch: int) -> FluidParams:
    return FluidParams(torch.full((batch,), 50.0), torch.full((batch,), 0.125e-3), 0.01)


def _time(fn, repeats: int) -> float:
    fn()  # warm caches / allocator
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t0) / repeats * 1e3


def _developed(model: NumericalFluid, warmup: int) -> tuple[FluidState, torch.Tensor]:
    """(the flow after ``warmup`` steps from rest around the undulating fish, B = 1; the wave
    amplitude [m])."""
    amp0 = torch.tensor(TAIL_SPEED / (2 * math.pi * FREQ))
    state = model.initial_state(1)
    with torch.no_grad():
        for n in range(warmup):
            state = model.step(state, fish_boundary(GRID, n * 0.01, amp0), _params(1))
    return state, amp0


def bench_case(refinement: int, batch: int, warmup: int = 30, repeats: int = 3) -> dict:
    """ms per step of `fishsim simulate`'s numerical fluid (its config's defaults: the joint stage
    at 4 sub-steps) at refinement r and batch B on the warmed-up fish flow."""
    model = make_fluid(NumericalConfig(refinement=refinement), TankConfig(H=GRID.H, W=GRID.W, dx=GRID.dx))
    state, amp0 = _developed(model, warmup)
    state = type(state)(**{k: (v.expand(batch, *v.shape[1:]).contiguous() if torch.is_tensor(v) else v)
                          for k, v in vars(state).items()})
    t = warmup * 0.01
    boundary, params = fish_boundary(GRID, t, amp0, batch), _params(batch)
    counts = []

    def forward():
        with torch.no_grad():
            _, diag = model.step_with_diagnostics(state, boundary, params)
        counts.append(int(diag.substeps.max()))

    def forward_backward():
        amp = amp0.clone().requires_grad_(True)
        new = model.step(state, fish_boundary(GRID, t, amp, batch), params)
        vx, vy = G.curl(new.a, GRID.dx)
        (vx.square().sum() + vy.square().sum()).backward()

    return {
        "forward_ms": _time(forward, repeats),
        "forward_backward_ms": _time(forward_backward, max(1, repeats - 1)),
        "substeps": counts[-1],
        "max_speed_m_s": max(c.abs().max().item() for c in G.curl(state.a, GRID.dx)),
    }


@contextmanager
def _threads(n: int):
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


# The Re = 100 cylinder: the CI size of tests/fluid/test_validation.py (16 cells per D) and a larger one,
# 20 cells per D on 24 D x 32 D (blockage 1/32; 20 min single-threaded next to two busy processes).
# Measured on the way there (20 cells per D, h = 0.05): 20 D x 16 D St 0.176, C_D 1.50;
# 20 D x 24 D St 0.176, C_D 1.50; 24 D x 32 D (cylinder 6 D from the inflow) St 0.173, C_D 1.46.
CYLINDER_CI = cases.CYLINDER_CI
CYLINDER_LARGE = {"cells_per_d": 20, "length": 24.0, "width": 32.0, "x_centre": 6.0, "t_end": 180.0, "window": 60.0,
                  "h": 0.05}


# The same cylinder on the fish's grid and stepping: D = 2 cm in 2.5 mm cells (8 cells per D), h = 0.01 s at
# U = 0.1 m/s (0.05 D/U), the fish's stepping (FISH_STEPPING, its rate in units of D / U), float64.
FISH_STEPPING = numerical_stepping(NumericalConfig())
"""``NumericalFluid`` keywords of `fishsim simulate`'s numerical fluid: the fish's stepping."""
FISH_TIME_UNIT = 0.2
"""D / U [s] of the fish-grid cylinder (D = 2 cm, U = 0.1 m/s), whose case runs in units of D / U:
the fish's penalisation rate (1/s) times this is the same rate in the case's time unit."""
CYLINDER_FISH_GRID = {"cells_per_d": 8, "length": 24.0, "width": 32.0, "x_centre": 6.0, "t_end": 120.0, "window": 40.0,
                      "h": 0.05, "dtype": torch.float64,
                      "stepping": {**FISH_STEPPING, "penalization_rate": FISH_STEPPING["penalization_rate"] * FISH_TIME_UNIT}}
CYLINDER_FISH_GRID_16 = {**CYLINDER_FISH_GRID, "cells_per_d": 16}   # a 4 cm cylinder in the fish's 2.5 mm cells


def coupling_drag(g: Grid, s: FluidState, bd: Boundary) -> torch.Tensor:
    """x forces on CYLINDER_FISH_GRID's cylinder as the coupling reads them: [IBM pressure, IBM
    viscous traction, IBM pressure with ``ibm_fit`` "wall" (dp/dn = 0: the body moves steadily)],
    summed over 31 surface nodes (kernel std one cell, sigma' = dx^2; the fluid's units: rho = U =
    D = 1, mu = 0.01)."""
    kw = CYLINDER_FISH_GRID
    qs = cases.disc_polyline(kw["x_centre"], kw["width"] / 2, 0.5, 31)
    v = G.faces_to_centres(G.curl(s.a, g.dx))
    pressure = ibm_force(qs, s.p, bd.mask, g, sigma_prime=g.dx**2).sum(1)[0]
    traction = ibm_force(qs, torch.zeros_like(s.p), bd.mask, g, sigma_prime=g.dx**2,
                         viscous=(torch.zeros_like(qs), v, 0.01)).sum(1)[0]
    wall = ibm_force(qs, s.p, bd.mask, g, sigma_prime=g.dx**2, fit="wall", wall=(torch.zeros_like(qs), 1.0)).sum(1)[0]
    return torch.stack([pressure[0], traction[0], wall[0]])


def coupling_heave(g: Grid, s: FluidState, bd: Boundary, centre: tuple[float, float], velocity: tuple[float, float],
                   acceleration: float, radius: float, mu: float, rho: float) -> torch.Tensor:
    """y forces on an oscillating cylinder as the coupling reads them [N/m]: [IBM pressure, IBM
    pressure + viscous traction, IBM pressure with ``ibm_fit`` "wall" (the wall-normal slope
    -rho a.n of the body's acceleration)], summed over surface nodes ~0.8 cells apart (as the
    fish's; at least 31), kernel std one cell."""
    qs = cases.disc_polyline(*centre, radius, max(31, round(2 * math.pi * radius / (0.8 * g.dx))))
    v = G.faces_to_centres(G.curl(s.a, g.dx))
    u = torch.tensor(velocity, dtype=qs.dtype).expand_as(qs)
    pressure = ibm_force(qs, s.p, bd.mask, g, sigma_prime=g.dx**2).sum(1)[0, 1]
    total = ibm_force(qs, s.p, bd.mask, g, sigma_prime=g.dx**2, viscous=(u, v, mu)).sum(1)[0, 1]
    a = torch.tensor((0.0, acceleration), dtype=qs.dtype).expand_as(qs)
    wall = ibm_force(qs, s.p, bd.mask, g, sigma_prime=g.dx**2, fit="wall", wall=(a, rho)).sum(1)[0, 1]
    return torch.stack([pressure, total, wall])


# The oscillating cylinder on the fish's grid, stepping and fluid (2.5 mm cells, h = 0.01 s, rho = 50,
# mu = 1.25e-4: the paper's): A = 5 mm at 2 Hz, radius 4 or 8 cells (1 or 2 cm), in a 60 cm box.
OSCILLATING_FISH_GRID = {"box_cells": 240, "dx": 2.5e-3, "rho": 50.0, "mu": 1.25e-4, "freq": 2.0, "amplitude": 5e-3}


def _oscillating(radius_cells: int) -> dict:
    t0 = time.perf_counter()
    kw = OSCILLATING_FISH_GRID
    probe = partial(coupling_heave, radius=radius_cells * kw["dx"], mu=kw["mu"], rho=kw["rho"])
    res = cases.oscillating_cylinder(radius_cells, **kw, probe=probe, stepping=FISH_STEPPING)
    reference = res.stokes_wang * res.confinement
    return {"resolution": f"{2 * radius_cells} cells per D, {kw['box_cells']}^2 cells of {kw['dx']:g} m, fish stepping",
            "beta": res.beta, "stokes_wang_times_confinement": reference,
            "cm_exchange": res.exchange, "cm_ibm_pressure": res.probe[0], "cm_ibm_pressure_traction": res.probe[1],
            "exchange_vs_reference": res.exchange / reference - 1,
            "ibm_vs_reference": res.probe[1] / reference - 1, "ibm_vs_exchange": res.probe[1] / res.exchange - 1,
            "cm_ibm_wall_fit": res.probe[2], "wall_fit_vs_reference": res.probe[2] / reference - 1,
            "wall_fit_vs_exchange": res.probe[2] / res.exchange - 1, "wall_s": time.perf_counter() - t0}


def _cylinder(kw: dict, probe=None) -> dict:
    t0 = time.perf_counter()
    st, cd, cl, probed = cases.cylinder_wake(**kw, probe=probe)
    n = kw["cells_per_d"]
    extra = {"cd_ibm_pressure": probed[0], "cd_ibm_traction": probed[1],
             "cd_ibm_pressure_wall_fit": probed[2]} if probed else {}
    return {**extra,
        "resolution": f"{n} cells/D, {kw['length']:g} D x {kw['width']:g} D "
        f"({round(kw['width'] * n)}x{round(kw['length'] * n)}), h = {kw['h']:g} D/U, "
        f"t = {kw['t_end']:g} D/U, last {kw['window']:g}",
        "strouhal": st,
        "mean_cd": cd,
        "cl_amplitude": cl,
        "wall_s": time.perf_counter() - t0,
    }


def validation(large: bool = True) -> dict:
    """Validation figures of the numerical fluid (fishsim.fluid.cases; references in
    docs/validation.md), each with its resolution and wall time [s], single-threaded (as the tests
    run; torch's intra-op threads only contend with other work at these sizes), float64 except
    the cylinder (float32):

    * Taylor-Green (the test's size: 32 x 32 on [0, pi]^2, h = 0.02, 50 steps) at Re = U pi / nu
      = 0.6 and 314: energy decay rate and its relative error vs the discrete-Laplacian rate.
    * Lid-driven cavity Re = 100, 64 x 64, t = 12: max |u - u_Ghia| (lid-speed units).
    * Cylinder Re = 100: St, mean C_D, C_L amplitude (penalization force within 1.5 D) at the
      CI-reduced size, on the fish's grid and stepping (``CYLINDER_FISH_GRID``, with the coupling's
      IBM pressure and traction drag coefficients) and, with ``large``, at ``CYLINDER_LARGE`` and
      on the fish's grid with 16 cells per D (``CYLINDER_FISH_GRID_16``, 16 min on one thread).
    * Oscillating cylinder (``OSCILLATING_FISH_GRID``, 8 and 16 cells per D): in-phase added-mass
      coefficient of the exchanged force and of the coupling's IBM force (pressure, and with the
      viscous traction) against Stokes-Wang times the box's confinement (~20 s each).
    """
    out = {"threads": 1}
    with _threads(1):
        for U, nu in ((0.01, 0.05), (1.0, 0.01)):
            t0 = time.perf_counter()
            tg = cases.taylor_green(32, U, nu, 0.02, 50)
            out[f"taylor_green_Re{U * math.pi / nu:.3g}"] = {
                "resolution": "32x32 on [0, pi]^2, h = 0.02, 50 steps",
                "rate": tg.rate,
                "rel_error": tg.rel_error,
                "wall_s": time.perf_counter() - t0,
            }
        t0 = time.perf_counter()
        err = cases.lid_driven_cavity(N=64, steps=1200).max_error
        out["ghia_re100"] = {"resolution": "64x64, h = 0.01, t = 12", "max_abs_error": err,
                             "wall_s": time.perf_counter() - t0}
        out["cylinder_re100_ci"] = _cylinder(CYLINDER_CI)
        out["cylinder_re100_fish_grid"] = _cylinder(CYLINDER_FISH_GRID, coupling_drag)
        for radius in (4, 8):
            out[f"oscillating_cylinder_fish_grid_{2 * radius}"] = _oscillating(radius)
        if large:
            out["cylinder_re100_large"] = _cylinder(CYLINDER_LARGE)
            out["cylinder_re100_fish_grid_16"] = _cylinder(CYLINDER_FISH_GRID_16, coupling_drag)
    return out


def kernel_parts(warmup: int = 30, repeats: int = 200) -> dict:
    """ms per call of the compiled numerical step's parts (fishsim/fluid/kernels.py) on the
    warmed-up fish flow of ``bench_case``, B = 1, one thread, best of 5 means: the predictor and
    its adjoint (16 calls a frame each at 8 sub-steps), one penalise + divergence pass, one
    Poisson solve (DCT along x, Thomas sweeps along y, inverse DCT; through ``inverse_array`` and,
    as the step runs it, ``inverse_sample`` alone) and one gradient subtraction (48 each a frame at
    3 passes)."""
    import numpy as np

    from fishsim.fluid import kernels as K
    from fishsim.linalg.dct import inverse_array, inverse_sample, neumann_inverse

    state, amp = _developed(NumericalFluid(GRID), warmup)
    vx, vy = (c.numpy().reshape(1, *c.shape[-2:]).copy() for c in G.curl(state.a, GRID.dx))
    b = [c.expand(1, 1, *c.shape[-2:]).numpy().reshape(1, *c.shape[-2:]).copy()
         for c in G.face_masks(fish_boundary(GRID, warmup * 0.01, amp).mask)]
    nu, dt, inv_dx, walls = np.array([2.5e-6]), np.array([0.01 / 8]), 1 / GRID.dx, (False, 0.0, 0.0, 0.0, 0.0)
    wx, wy, gx, gy = np.empty_like(vx), np.empty_like(vy), np.zeros_like(vx), np.zeros_like(vy)
    ux, uy, px, py = np.empty_like(vx), np.empty_like(vy), np.zeros_like(vx), np.zeros_like(vy)
    div, phi_sum = np.empty((1, GRID.H, GRID.W), vx.dtype), np.zeros((1, GRID.H, GRID.W), vx.dtype)
    inverse = neumann_inverse(GRID.H, GRID.W, GRID.dx, None, torch.float32)
    g_nu, g_dt = np.zeros(1), np.zeros(1)
    parts = {
        "predictor": lambda: K._forward_serial(vx, vy, nu, dt, inv_dx, walls, wx, wy),
        "predictor_adjoint": lambda: K._backward_serial(vx, vy, nu, dt, inv_dx, walls, vx, vy, gx, gy, g_nu,
                                                        g_dt, False, False),
        "penalize_divergence": lambda: K._penalize_divergence_sample(vx[0], vy[0], *(c[0] for c in b), *(c[0] for c in b),
                                                                     inv_dx, ux[0], uy[0], div[0], px[0], py[0]),
        "poisson_solve": lambda: inverse_array(div, inverse),
        "poisson_solve_compiled": lambda: inverse_sample(div[0], inverse.pivots, inverse.dx),
        "subtract_gradient": lambda: K._subtract_gradient_sample(ux[0], uy[0], div[0], inv_dx, wx[0], wy[0], phi_sum[0]),
    }
    with _threads(1):
        return {f"{name}_ms": min(_time(fn, repeats) for _ in range(5)) for name, fn in parts.items()}


def joint_parts(warmup: int = 30, repeats: int = 50) -> dict:
    """ms per call of the default stage's compiled parts (the joint penalisation + projection,
    fishsim/fluid/kernels.py and pressure.py) on the warmed-up fish flow of ``bench_case``, B = 1,
    one thread, best of 5 means, with the arguments one step passes them: a frame at n sub-steps
    (``substeps``) makes one ``subdomain`` set-up (the Schwarz preconditioner's S and its banded
    factor), 2 n predictor calls and 2 n joint solves (``immerse``: a PCG of ``pcg_iterations``
    iterations, each a preconditioner call, symmetric multiplicative Schwarz: two banded solves on
    S, one DCT Poisson solve, two passes of A = -div(c grad .) over the field, and one more pass
    of A); the backward as many predictor adjoints and adjoint solves. ``frame_forward_ms`` adds
    the parts up to a forward step."""
    import numpy as np

    from fishsim.fluid import kernels as K
    from fishsim.fluid import pressure as P
    from fishsim.linalg.dct import inverse_sample

    model = make_fluid(NumericalConfig(), TankConfig(H=GRID.H, W=GRID.W, dx=GRID.dx))
    state, amp = _developed(model, warmup)
    calls, original = [], K._sample_immersed_steps             # one step's arguments, as it passes them
    K._sample_immersed_steps = lambda *args: calls.append(args) or original(*args)
    try:
        with torch.no_grad():
            model.step(state, fish_boundary(GRID, warmup * 0.01, amp), _params(1))
    finally:
        K._sample_immersed_steps = original
    (vx, vy, sx, sy, dx_, dy_, cx, cy, a, nu, dt, count, inv_dx, walls, pivots, pdx, *solver, tol,
     max_iter) = calls[0][:24]
    cells, band, width, perm, inverse, _ = solver
    adjoint_tol = IMMERSE_TOL[torch.from_numpy(vx).dtype][1]
    wx, wy, gx, gy = np.empty_like(vx), np.empty_like(vy), np.zeros_like(vx), np.zeros_like(vy)
    K._sample_forward(vx, vy, nu, dt, inv_dx, walls, wx, wy)
    phi, px, py = np.zeros(cx.shape[:1] + cy.shape[1:], vx.dtype), np.zeros_like(vx), np.zeros_like(vy)
    f = np.random.default_rng(0).standard_normal(phi.shape).astype(vx.dtype)
    f -= f.mean()
    inv_dx2 = vx.dtype.type(inv_dx * inv_dx)
    z, t = np.empty_like(f), np.empty_like(f)
    iterations = P._pcg_sample(cx, cy, f, np.zeros_like(f), inv_dx2, pivots, pdx, *solver, tol, max_iter)
    gs = [np.zeros_like(c) for c in (vx, vy, vx, vy)]
    parts = {
        "subdomain": lambda: P.subdomain(cx.astype(np.float64), cy.astype(np.float64), 1 / inv_dx),
        "predictor": lambda: K._sample_forward(vx, vy, nu, dt, inv_dx, walls, wx, wy),
        "predictor_adjoint": lambda: K._sample_backward(vx, vy, nu, dt, inv_dx, walls, vx, vy, gx, gy, False, False),
        "immerse": lambda: K._immerse_sample(wx, wy, sx, sy, dx_, dy_, cx, cy, a, inv_dx, pivots, pdx, *solver, tol,
                                             max_iter, phi.copy(), px, py),
        "immerse_adjoint": lambda: K._immerse_adjoint_sample(vx, vy, np.zeros_like(phi), px, py, wx, wy, phi, sx, sy,
                                                             dx_, dy_, cx, cy, a, inv_dx, pivots, pdx, *solver,
                                                             adjoint_tol, max_iter, *gs),
        "pcg_iteration": lambda: (P._precondition_sample(cx, cy, f, inv_dx2, pivots, pdx, *solver, z, t),
                                  P._apply_sample(cx, cy, z, inv_dx2, t)),
        "banded_solve_on_S": lambda: P._local_sample(f, cells, band, width, perm, inverse, z),
        "dct_poisson_solve": lambda: inverse_sample(f, pivots, pdx),
        "apply_A": lambda: P._apply_sample(cx, cy, f, inv_dx2, t),
    }
    with _threads(1):
        out = {f"{name}_ms": min(_time(fn, repeats) for _ in range(5)) for name, fn in parts.items()}
    out.update(substeps=int(count), subdomain_cells=len(cells), half_bandwidth=int(width),
               pcg_iterations=int(iterations),
               frame_forward_ms=out["subdomain_ms"] + 2 * int(count) * (out["predictor_ms"] + out["immerse_ms"]))
    return out


def run() -> dict:
    """All cases (the r = 2, B = 16 forward + backward: 14 s per step on the 2-core CPU)."""
    out = {"grid": f"{GRID.H}x{GRID.W}", "threads": torch.get_num_threads()}
    out["kernel_parts_B1"] = kernel_parts()
    out["joint_parts_B1"] = joint_parts()
    for r in (1, 2):
        for batch in (1, 16):
            out[f"r{r}_B{batch}"] = bench_case(r, batch)
    out["validation"] = validation()
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))

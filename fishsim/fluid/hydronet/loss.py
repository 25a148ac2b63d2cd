"""HydroNet's unsupervised physics loss (paper Eqs. 7-9; Wandel et al. 2021), in grid units.

Per sample, with R the IMEX momentum residual of ``fishsim.fluid.residual`` (Pa/m) and the
reference scales of ``scales.py`` (U* = dx/h, R* = rho U*/h):

    L_p = sum_f w_f (R_f / R*)^2 / N,            w = fluid face weight (1 - b_f, 0 on the box walls)
    L_b = sum_f b_f ((v_f - v_d,f) / U*)^2 / N,   b_f = boundary face weight
    L   = beta L_p + gamma L_b                        (Wandel: beta = 1, gamma = 20)
    objective = mean over the batch of log(L + eps)

with N the number of faces (x and y). Averaging the masked squares over all faces, as Wandel's
code does, fixes the balance per face (a boundary face counts gamma / beta = 20 times a fluid
face) whatever the share of solid in the scene or crop; normalising each term by its own mask
instead would weight boundary faces by 20 N_fluid / N_solid (~100 in our crops), changing with
the scene.

Scaling. R / R* = R h^2 / (rho dx) = (R dx) / (rho U*^2): the paper's "rescale by 1/0.0025 = 400"
multiplies R (Pa/m) by dx (m), which makes it a pressure; dividing further by P* = rho U*^2 makes it
dimensionless and equal to the residual Wandel's code computes in grid units (dx = h = rho = 1).
Likewise (v - v_d) / U* is the boundary error in cells per step. So both terms are O(1) for O(1)
velocity changes per step, independent of rho, and Wandel's tested balance beta : gamma = 1 : 20
keeps its meaning. (Dividing R by 400 but keeping v in m/s would weight L_p about 160x more than
this at rho = 50, 2.5 mm, 0.01 s.)

Teacher term (optional, ``teacher > 0`` in training). With (v*, p*) the numerical solver's step
from the same state and boundary (``fishsim.fluid.numerical``):

    L_t = sum_f ((v_f - v*_f) / U*)^2 / N + sum_f ((grad (p - p*))_f dx / P*)^2 / N

the velocity error in cells per step plus the pressure-gradient error, on every face (the
coupling reads the pressure across the body's band, inside it too), both in the units of L_p (a velocity error dv in one step is a residual dv / h, i.e.
dv / U* in units of R*). The physics loss alone admits wrong solutions: in the soft-mask band
the fluid and boundary terms conflict, and the network's rollouts reach a lower L than the
solver's own steps while swimming 4-8x less far. L_t anchors the network to the solver's
discrete dynamics on the network's own rollout states (solver-in-the-loop one-step targets).

Pressure value term (optional, ``teacher_pressure = kappa > 0``): L_t += kappa L_P with

    L_P = sum_c w_c dp~_c^2 / (sum_c w_c p~*_c^2 + P_0 sum_c w_c),   w = 1 - b_c,  P_0 = 1e-4,

in units of P*, with x~ = x - sum_c w_c x_c / sum_c w_c the mean-free part on the fluid cells:
the squared relative error of the pressure, ``validate``'s e_p^2 (P_0 a floor for still scenes).
The gradient term fixes p - p* up to a constant but weighs an error spread over L cells by
1 / L^2: on the held-out fish the shipped network's large-scale pressure (its lateral dipole's
far field) missed by 18-26 % while its gradient term was a tenth of the absolute error's. Relative,
L_P weighs each sample's pressure alike: absolute, it was 100-200 P*^2 on the training pool
(impulsive starts), 100x the rest of L_t.

Energy term (optional, ``energy > 0`` in training, with the teacher). The relative error of the
step's kinetic energy on the fluid faces,

    L_E = ((E - E*) / (E* + E_0))^2,     E = sum_f w_f (v_f / U*)^2 / N,  w = 1 - b_f,  E_0 = 1e-4

(E_0: a floor, a mean speed of 0.01 cells per step, for still scenes). L_t weighs every face's
error alike, so a gain of a fraction of a percent per step applied to the whole flow costs it
next to nothing, yet over 150 steps it compounds: the network's rollouts held ~2x the solver's
kinetic energy. L_E is that systematic part alone.

Advection scheme. The residual's (vbar . grad) vbar uses Koren's limited third-order upwind
interpolation (``grid.advection``, the numerical solver's scheme), not Wandel's central one.
Central differences cannot see a 2-cell (checkerboard) mode and at the paper's viscosity
(nu* = 0.004) the Laplacian barely does, so a net trained with "central" let grid-scale vorticity
noise grow in its rollouts at almost no cost (measured on such a rollout: fluid-face residual 3e-3
central vs 3e-2 Koren; the numerical solver's own steps give 2.7e-9 with Koren in the fluid, so
its discrete dynamics are almost an exact minimiser). Eager, the Koren residual costs ~0.15 s per
batch of 16 at 64 x 128 (10x central); ``torch.compile`` brings it back to ~15 ms
(fishsim/learn/train.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from fishsim.fields import Boundary, FluidParams, FluidState, Grid
from fishsim.fluid.grid import curl, gradient, vector_to_faces
from fishsim.fluid.hydronet.scales import scales_of
from fishsim.fluid.residual import boundary_face_masks, fluid_face_masks, momentum_residual

EPS = 1e-12


@dataclass(frozen=True)
class LossConfig:
    """beta: weight of L_p; gamma: weight of L_b (Wandel: 1 and 20); eps: floor inside the log;
    scheme: advective interpolation of the residual, "koren" (default) or "central" (Wandel)."""

    beta: float = 1.0
    gamma: float = 20.0
    eps: float = EPS
    scheme: str = "koren"


@dataclass(frozen=True)
class LossTerms:
    """Per-sample terms [B] (dimensionless) and the scalar training objective mean(log(L + eps));
    ``teacher``: L_t [B] when trained against the solver, ``energy``: L_E [B] with the energy
    term (each then included in ``total``)."""

    momentum: Tensor
    boundary: Tensor
    total: Tensor
    objective: Tensor
    teacher: Tensor | None = None
    energy: Tensor | None = None


def masked_mean(q: tuple[Tensor, Tensor], w: tuple[Tensor, Tensor]) -> Tensor:
    """sum_f w_f q_f / N over the N x- and y-faces of each sample, [B]."""
    num = sum((wi * qi).flatten(1).sum(1) for qi, wi in zip(q, w))
    return num / sum(qi[0].numel() for qi in q)


def momentum_loss(old: FluidState, new: FluidState, boundary: Boundary, params: FluidParams,
                  grid: Grid, scheme: str = "koren") -> Tensor:
    """L_p [B]: fluid-masked mean of the squared IMEX residual in units of R* = rho U* / h."""
    s = scales_of(grid, params)
    r = momentum_residual(curl(old.a, grid.dx), curl(new.a, grid.dx), new.p, params.rho, params.mu,
                          params.h, grid, scheme=scheme)
    return masked_mean(tuple((ri / s.residual) ** 2 for ri in r), fluid_face_masks(boundary.mask))


def boundary_loss(new: FluidState, boundary: Boundary, params: FluidParams, grid: Grid) -> Tensor:
    """L_b [B]: boundary-masked mean of ((v_t+1 - v_d) / U*)^2, v_d averaged onto the faces."""
    u = grid.dx / params.h
    v, v_d = curl(new.a, grid.dx), vector_to_faces(boundary.velocity)
    err = tuple(((vi - di) / u) ** 2 for vi, di in zip(v, v_d))
    return masked_mean(err, boundary_face_masks(boundary.mask))


def hydronet_loss(old: FluidState, new: FluidState, boundary: Boundary, params: FluidParams,
                  grid: Grid, cfg: LossConfig = LossConfig()) -> LossTerms:
    """L = beta L_p + gamma L_b per sample and the objective mean_B log(L + eps) (module docstring).

    old: (a_t, p_t), new: (a_t+1, p_t+1) in physical units; boundary: b, v_d of the step.
    """
    lp = momentum_loss(old, new, boundary, params, grid, cfg.scheme)
    lb = boundary_loss(new, boundary, params, grid)
    total = cfg.beta * lp + cfg.gamma * lb
    return LossTerms(lp, lb, total, torch.log(total + cfg.eps).mean())


def teacher_loss(new: FluidState, target: FluidState, params: FluidParams, grid: Grid,
                 boundary: Boundary | None = None, pressure: float = 0.0) -> Tensor:
    """L_t [B]: squared velocity and pressure-gradient errors on all faces of ``new`` against the
    solver's ``target`` step, in grid units, plus ``pressure`` times L_P, the pressure's squared
    relative error on the fluid cells of ``boundary`` (module docstring)."""
    s = scales_of(grid, params)
    dv = tuple(((x - y) / s.velocity) ** 2 for x, y in zip(curl(new.a, grid.dx), curl(target.a, grid.dx)))
    dg = tuple((g * grid.dx / s.pressure) ** 2 for g in gradient(new.p - target.p, grid.dx))
    ones = tuple(torch.ones_like(d[:1]) for d in dv)
    lt = masked_mean(dv, ones) + masked_mean(dg, ones)
    return lt if pressure == 0 else lt + pressure * pressure_value_loss(new, target, boundary, params, grid)


def mean_free(p: Tensor, w: Tensor) -> Tensor:
    """p [B, 1, H, W] less its w-weighted mean over each sample's cells (w = 1 - b: the fluid's)."""
    return p - (w * p).sum(dim=(-2, -1), keepdim=True) / w.sum(dim=(-2, -1), keepdim=True).clamp_min(1.0)


PRESSURE_FLOOR = 1e-4  # P_0: a pressure of 0.01 P* on every fluid cell


def pressure_value_loss(new: FluidState, target: FluidState, boundary: Boundary, params: FluidParams,
                        grid: Grid) -> Tensor:
    """L_P [B]: the squared relative error of the mean-free pressure on the fluid cells (w = 1 - b),
    sum_c w_c dp~_c^2 / (sum_c w_c p~*_c^2 + P_0 sum_c w_c), in units of P* (module docstring)."""
    w = 1.0 - boundary.mask
    s = scales_of(grid, params)
    dp, ref = mean_free(new.p - target.p, w) / s.pressure, mean_free(target.p, w) / s.pressure
    total = lambda x: (w * x).flatten(1).sum(1)
    return total(dp**2) / (total(ref**2) + PRESSURE_FLOOR * total(torch.ones_like(w)))


ENERGY_FLOOR = 1e-4   # E_0: a mean speed of 0.01 cells per step


def energy_loss(new: FluidState, target: FluidState, boundary: Boundary, params: FluidParams,
                grid: Grid) -> Tensor:
    """L_E [B]: the squared relative error of ``new``'s kinetic energy on the fluid faces against
    the solver's ``target`` step (module docstring), in grid units."""
    s = scales_of(grid, params)
    w = fluid_face_masks(boundary.mask)
    energy = [masked_mean(tuple((c / s.velocity) ** 2 for c in curl(x.a, grid.dx)), w) for x in (new, target)]
    return ((energy[0] - energy[1]) / (energy[1] + ENERGY_FLOOR)) ** 2

"""Numerical reference fluid: incompressible Navier-Stokes by projection on the MAC grid
(docs/physics.md section 6), implementing the ``FluidModel`` contract.

One step advances (a, p) by h with n sub-steps of dt = h / n, each a Heun (SSP-RK2) step whose
two stages are the same three phases (Chorin projection with Brinkman penalization):

    predict    w = v + dt [ -(v . grad) v + nu lap v ]          advection: Koren-limited 3rd-order
                                                               upwind flux form; viscosity explicit
    penalize   u = (1 - beta_f) w + beta_f v_d                 Brinkman blend, beta_f a rate from
                                                               the mask (or implicit, finite lambda)
    project    v = u - grad phi,  lap phi = div u              DCT-II direct solve, div v ~ 1e-15

    constrain  K times: w <- project(penalize(w))              alternating projections
    stage 1:  v1 = constrain(predict(v))
    stage 2:  v' = constrain((v + predict(v1)) / 2)

The blend is a rate (``penalization_rate`` = lambda_p, 1/s, ``fluid.penalization_rate``): each
pass blends by

    beta_f = 1 - (1 - b_f)^e,   e = lambda_p dt / K,

the exact relaxation of dv/dt = -lambda_p ln(1 - b_f) (v_d - v) over dt / K, so that a band cell
relaxes towards the body at a rate that does not depend on how the frame is cut into sub-steps and
passes, nor on the grid's sub-steps (the core, b = 1, is set to v_d by every pass). The default
lambda_p = 2400 1/s gives beta_f = b_f, bit for bit, at K = 3, n = 8 of a 0.01 s frame
(``penalization_iterations``, ``substeps``; the split passes' settings, `fishsim simulate`'s
default until the joint stage below replaced them on 2026-11-29). In the limit it is Brinkman-penalised Navier-Stokes
with permeability 1 / (lambda_p ln(1 / (1 - b))); one pass leaves a slip inside the body (the
projection's pressure gradient acts there too), which the next removes, and the answer converges
once the passes do. On the paper's fish (120 frames) 4 / 8 / 16 sub-steps give 123.0 / 125.3 /
125.7 mm at 5 Hz (observed order 2.8), 1 / 3 / 9 passes 121.6 / 125.3 / 125.6, one sub-step more
or less moves a fish by <= 0.15 %, and the grid r = 1 / 2 / 4 converges at an observed order ~3
at 5 and 7 Hz (docs/validation.md, "The blend as a rate"). Three passes do not converge the slip
of a body only a few cells thick: there the answer grows with K n towards the converged passes'
limit (a 6 x 0.8 cm ellipse's added mass 1.200 / 1.265 / 1.311 at n = 8 / 16 / 32, 1.362 / 1.366
/ 1.369 with K = 81). With ``penalization_rate`` None every pass blends by b_f whatever dt (the
default until 2026-11-29): the band then relaxes K n times a frame and creeps into the mask's
Gaussian tail as n or K grows, with no limit (the fish drifted by a few per cent from K n = 24 to
256, and a refined grid, whose sub-steps are r times more, saw a stiffer body). The coupling reads
the fish's pressure beyond the band (fishsim/coupling/ibm.py), and a converged penalisation gives
the fish its full added mass, which the coupling's added-mass stabilisation must match
(``coupling.added_mass_ratio``).

Rate penalisation (``brinkman`` = lambda, ``fluid.brinkman``): the body forcing is a rate,
dv/dt = ... + lambda chi(b) (v_d - v), taken implicitly together with the projection, so that the
pressure and the forcing balance in one solve instead of alternating (below b_f stands for the
face's chi(b), ``penalised_fraction``: a smoothstep of the mask with compact support, so that the
penalised body has a fixed extent):

    (1 + lambda dt b_f) v = w + lambda dt b_f v_d - grad phi,   div v = 0
    ->  u = (w + lambda dt b_f v_d) / (1 + lambda dt b_f),  c_f = 1 / (1 + lambda dt b_f),
        -div(c grad phi) = -div u  (PCG, fishsim.fluid.pressure),  v = u - c grad phi.

It is a discretisation of one PDE (Brinkman-penalised Navier-Stokes with permeability
1 / (lambda b)), so it converges as dt -> 0: a thin ellipse heaving broadside in the paper's tank
has an added mass of 1.3394 / 1.3408 / 1.3415 rho pi a^2 at n = 4 / 8 / 16 (lambda = 1e4 1/s,
momentum exchange; ~11 PCG iterations a solve), where the split scheme's grows without limit (0.83 / 0.91 / 0.99 /
1.13 at n = 4 / 8 / 16 / 32 by the sampled pressure, 1.24 / 1.36 / 1.44 at n = 4 / 8 / 16 by
momentum exchange): any blend towards v_d once per sub-step stiffens the soft band as n
grows.  It also converges in lambda, measured by the momentum the body exchanges with the fluid
(``StepDiagnostics.cell_forces``): 1.341 / 1.383 / 1.397 at lambda = 1e4 / 1e5 / 1e6 1/s, n = 8
(with b itself as the weight: 1.531 / 1.680 / 1.807, no limit). The pressure sampled around the
surface does not converge in lambda (1.14 / 3.10 / 22.6): the pressure inside a stiffly
penalised body is not a surface pressure, so forces from this scheme are momentum exchange.

The passes' limit (``implicit``, ``fluid.implicit``): the same joint solve with the split
scheme's own rate, lambda = lambda_p and b_f replaced by s_f = -ln(1 - b_f) (``rate_weight``), is
the limit K -> infinity of the passes (each of which relaxes exactly at that rate, then projects)
taken by implicit Euler instead of alternation, a discretisation of the same Brinkman-penalised
PDE. It converges in sub-steps at once, thin bodies included: the 6 x 0.8 cm ellipse's added mass
(sampled pressure) is 1.3679 / 1.3692 / 1.3699 / 1.3703 at n = 4 / 8 / 16 / 32, where the passes
reach 1.362 / 1.369 only at K = 81, n = 8 / 32 (8 x 3: 1.200), and 1.3645 at n = 2; the
paper's fish (120 frames, 3 / 5 / 7 Hz, added-mass ratio 5) swims 44.36 / 126.00 / 237.19 mm at
n = 2, within 0.2 % of n = 1, 3, 4 and 8 and 0.5 / 0.2 / 1.5 % of the passes at 16 x 9. Its
gradient to a few per cent: on a 60-frame fish (5 mm cells) d(head x)/d(f) is 1.2867 / 1.2405 /
1.2522 e-2 at n = 4 / 8 / 16 at the defaults (ratio 6.75, no force ramp); with the paper's
20-frame ramp at ratio 6.5 1.0729 / 1.0924 / 1.1399 / 1.1989 / 1.2321 e-2 at n = 2 / 3 / 4 / 8 /
16 (the head x within 0.15 % at every n), the ramp's frames outside the stabilisation's window
(fishsim/coupling/config.py) making it sensitive. `fishsim simulate` runs it at n = 4
(``fluid.implicit``, ``fluid.substeps``). Its cost is a PCG solve a stage (~8 iterations to a
relative residual of 1e-6 with the Schwarz preconditioner), compiled on the CPU with its adjoint
(``kernels.SplitStep``).

Sub-steps are per sample and fixed: n_b = max(r * substeps, the count that keeps sample b's
advective Courant number max|v| dt / dx <= ``cfl`` and its diffusion number nu dt / dx^2 <=
``diffusion``).  The Courant and diffusion bounds are a stability safety net (`fishsim simulate`
sets cfl = 0.8: its 4 sub-steps hold up to 0.8 m/s on the 2.5 mm grid, and the frequency study's
7 Hz fish, peaking at 1.14 m/s, runs 4-6). A count that changes with the parameters is a jump of
the frame map, small where the stage is converged in the sub-steps (the joint stage: one more
moves the fish by <= 0.2 %; the split passes' counts were kept fixed for this reason), and each
sample's result is independent of its batch mates (a batch runs max n_b
sub-steps; a sample that needs fewer keeps its state after its own n_b).
The returned pressure is the one whose gradient the step applied, p = rho (phi1/2 + phi2) / dt
averaged over the sub-steps (mean free), so (v, v', p) satisfy the IMEX momentum residual
(``fishsim.fluid.residual``) to truncation error.

Refinement r: the step runs on the r-times finer grid (dx / r, at least r sub-steps so dt <= h / r).
Prolongation: a bilinearly on the vertices (so v stays divergence free). The body (b, v_d) is read
on the fine grid (``boundary_grid``): the rollout samples the fish's soft mask there, so refining
resolves one body model, b(x) with its physical softness, instead of the r = 1 samples' bilinear
interpolant (a softer, wider band: on the frequency study's 30-frame episode it moved the 3 Hz
fish by +22 %, which had read as grid error); a boundary given on the r = 1 grid is prolonged
bilinearly (edge-clamped).  Restriction: a by injection at the coarse vertices (so the coarse
face velocity is the exact mean of the fine face velocities along it: flux conserving), p by the
mean of the r x r fine cells.  The returned state is a ``RefinedState`` that also carries the fine
potential, so successive steps keep the fine-scale flow; a plain ``FluidState`` input is prolonged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from fishsim.errors import SimulationBlowUp
from fishsim.fields import Boundary, FluidParams, FluidState, Grid, RefinedState, all_finite, rest_state
from fishsim.fluid.grid import (
    MASK_FLOOR,
    NO_SLIP,
    Faces,
    WallBC,
    advection,
    curl,
    divergence,
    face_masks,
    gradient,
    laplacian_faces,
    stream_function,
    vector_to_faces,
    zero_walls,
)
from fishsim.fluid.kernels import Immersion, Predict, SplitStep, face_speed
from fishsim.fluid.pressure import SchwarzPreconditioner, WeightedPoisson
from fishsim.fluid.residual import per_sample
from fishsim.linalg.dct import neumann_inverse, solve_neumann_poisson


@dataclass(frozen=True)
class StepDiagnostics:
    """What one step did, for validation.

    substeps: number of sub-steps n_b of each sample (dt = h / n_b), [B] int64.
    penalty: mean penalization acceleration over the step on the (fine) faces, m/s^2:
        the velocity the penalization added, divided by h.  rho * penalty is the force per unit
        area the body and wall bands exert on the fluid.
    dx: spacing of ``penalty`` (the fine grid), m.
    refinement: r.
    mask, start, end, h: the step's (fine) face masks b_f, velocities v before and v' after it
        and its length, kept (not copied) so that ``inertia`` is computed only when asked for.
    """

    substeps: int
    penalty: Faces
    dx: float
    refinement: int
    mask: Faces | None = None
    start: Faces | None = None
    end: Faces | None = None
    h: float | None = None

    @property
    def inertia(self) -> Faces | None:
        """b_f (v' - v) / h on the (fine) faces, m/s^2: the rate of change of the velocity of the
        fluid held in the bodies (volume fraction b_f), which moves with them."""
        if self.mask is None:
            return None
        return tuple(bc * (c - o) / self.h for bc, c, o in zip(self.mask, self.end, self.start))

    def force(self, rho: Tensor | float, region: Tensor | None = None) -> Tensor:
        """Hydrodynamic force on the penalized body, [B, 2] (x, y) in N/m (per unit depth):

            F = - sum_faces rho * penalty * w_f dx^2

        the reaction to the Brinkman force on the fluid (the momentum the penalization injects
        per unit time).  ``region`` [B, 1, H, W] on the r = 1 grid (a cell mask around the body)
        restricts the sum to faces whose cells are in it (weight w_f = face average of region;
        default: every face, i.e. body and wall bands together).
        """
        px, py = self.penalty
        rho_ = per_sample(rho, px)
        if region is None:
            wx, wy = torch.ones_like(px), torch.ones_like(py)
        else:
            wx, wy = face_masks(_prolong_centres(region.to(px), self.refinement))
        fx = -(rho_ * px * wx).sum(dim=(-3, -2, -1)) * self.dx**2
        fy = -(rho_ * py * wy).sum(dim=(-3, -2, -1)) * self.dx**2
        return torch.stack([fx, fy], -1)


    def cell_forces(self, rho: Tensor | float, share: Faces | None = None) -> Tensor:
        """Hydrodynamic force the fluid exerts on the bodies from each cell of the r = 1 grid,
        [B, 2, H, W] N/m (per unit depth), by momentum exchange:

            f_face = rho dx^2 s_f (b_f (v' - v) / h - penalty)     per (fine) face

        The reaction to the penalization (what the fluid feels, viscous stress included) minus
        the momentum the fluid inside the body gains by moving with it (the body carries that
        fluid; its inertia is not a hydrodynamic force: a body accelerating in a fluid at rest
        would otherwise feel the inside fluid's mass as extra drag). ``share`` s_f: the share of
        each fine face's penalization that belongs to the body of interest (``body_share``;
        default 1: every body and wall band). Each face's force goes half to each of its two
        cells, then the r x r fine cells are summed, so the total is exact (but half of each
        box-wall face, which carries only the walls' share).
        """
        px, py = self.penalty
        ix, iy = self.inertia if self.inertia is not None else (torch.zeros_like(px), torch.zeros_like(py))
        sx, sy = share if share is not None else (1.0, 1.0)
        scale = per_sample(rho, px) * self.dx**2
        fx, fy = scale * sx * (ix - px), scale * sy * (iy - py)
        cells = torch.cat([0.5 * (fx[..., :-1] + fx[..., 1:]), 0.5 * (fy[..., :-1, :] + fy[..., 1:, :])], 1)
        r = self.refinement
        return cells if r == 1 else F.avg_pool2d(cells, r) * r * r

    def body_share(self, body: Tensor, total: Tensor) -> Faces:
        """s_f on the fine faces: the share b_body,f / b_total,f of each face's penalization that
        belongs to ``body`` (its cell mask [B, 1, ., .] on the fine or the r = 1 grid) when the
        fluid was given the united mask ``total`` (b_total = 1 - (1 - b_body)(1 - b_other)); 0
        where nothing is penalised, 1 wherever only the body is."""
        r, px = self.refinement, self.penalty[0]
        fine = None if r == 1 else (px.shape[-2], px.shape[-1] - 1)
        pairs = zip(*(face_masks(_on_grid(m, fine, r)) for m in (body, total)))
        return tuple(b / t.clamp_min(MASK_FLOOR) for b, t in pairs)


def _on_grid(q: Tensor, shape: tuple[int, int] | None, r: int) -> Tensor:
    """A cell field [B, C, ., .] on the fine grid of ``shape`` (H, W): as given if it is there
    (or r = 1), else (on the r = 1 grid) prolonged bilinearly."""
    return q if r == 1 or q.shape[-2:] == shape else _prolong_centres(q, r)


def _prolong_centres(q: Tensor, r: int) -> Tensor:
    """Cell-centred field to the r-times finer grid, bilinear, edge-clamped."""
    return q if r == 1 else F.interpolate(q, scale_factor=r, mode="bilinear", align_corners=False)


def _prolong_vertices(a: Tensor, r: int) -> Tensor:
    """Vertex field to the r-times finer grid, bilinear (coarse vertices are fine vertices)."""
    if r == 1:
        return a
    H, W = a.shape[-2] - 1, a.shape[-1] - 1
    return F.interpolate(a, size=(r * H + 1, r * W + 1), mode="bilinear", align_corners=True)


COMPILED = True
"""Run the CPU's split-scheme sub-steps and the Koren predictor as the compiled loops of
``fishsim.fluid.kernels`` (False: the torch formulas everywhere; the tests' reference)."""


def _mean_free(q: Tensor) -> Tensor:
    return q - q.mean(dim=(-2, -1), keepdim=True)


# --------------------------------------------------------------------------------------------
# The three phases (each a pure function of its inputs)
# --------------------------------------------------------------------------------------------


def predict(v: Faces, nu: Tensor, dt: Tensor | float, dx: float, walls: WallBC, scheme: str) -> Faces:
    """Explicit momentum update without pressure: w = v + dt [ -(v.grad)v + nu lap v ].
    Wall faces keep their (prescribed) normal velocity. On the CPU with the Koren scheme the same
    formula runs compiled, with its hand-written adjoint (``kernels.Predict``)."""
    if COMPILED and scheme == "koren" and v[0].device.type == "cpu":
        return Predict.apply(v[0], v[1], nu, dt, dx, walls)
    adv = advection(v, dx, walls, scheme)
    lap = zero_walls(laplacian_faces(v, dx, walls))
    return tuple(c + dt * (nu * L - A) for c, A, L in zip(v, adv, lap))


def penalize(w: Faces, b: Faces, v_d: Faces, lam_dt: Tensor | float | None = None) -> tuple[Faces, Faces]:
    """Brinkman penalization of the body and wall bands, returns (u, u - w).

    lam_dt None:  u = (1 - b_f) w + b_f v_d                      (the limit lambda -> inf with a
                                                                  soft mask: a volume-fraction blend)
    lam_dt = lambda dt:  u = (w + lambda dt b_f v_d) / (1 + lambda dt b_f)   (implicit Euler of
                                                                  dv/dt = lambda b (v_d - v))
    The normal velocity on the box-wall faces becomes b_f v_d (impermeable where b_f = 0).
    """
    def one(wc: Tensor, bc: Tensor, vc: Tensor) -> Tensor:
        if lam_dt is None:
            return wc + bc * (vc - wc)
        return (wc + lam_dt * bc * vc) / (1 + lam_dt * bc)

    ux, uy = _box_faces_from(tuple(one(*t) for t in zip(w, b, v_d)), (b[0] * v_d[0], b[1] * v_d[1]))
    return (ux, uy), (ux - w[0], uy - w[1])


def _box_faces_from(inner: Faces, box: Faces) -> Faces:
    """``inner``'s interior faces with ``box``'s four box-wall faces (the x faces' first and last
    columns, the y faces' first and last rows)."""
    (ix, iy), (bx, by) = inner, box
    return (torch.cat([bx[..., :1], ix[..., 1:-1], bx[..., -1:]], -1),
            torch.cat([by[..., :1, :], iy[..., 1:-1, :], by[..., -1:, :]], -2))


def project(u: Faces, dx: float, inverse: Tensor | None = None) -> tuple[Faces, Tensor]:
    """Helmholtz projection onto divergence-free fields: v = u - grad phi with lap phi = div u
    (Neumann walls, DCT-II direct solve), wall faces unchanged; returns (v, phi), phi in m^2/s.
    On return div v = 0 to round-off wherever the net wall flux of u is zero."""
    phi = solve_neumann_poisson(divergence(u, dx), dx, inverse)
    gx, gy = gradient(phi, dx)
    return (u[0] - gx, u[1] - gy), phi


CHI_SUPPORT = (0.05, 0.95)
"""The mask values over which the rate penalisation's weight chi(b) rises from 0 to 1 (with the
default mask softness, half a cell either side of the surface)."""


def penalised_fraction(b: Tensor) -> Tensor:
    """chi(b) = S((b - b_0) / (b_1 - b_0)), S(t) = t^2 (3 - 2 t) on [0, 1] (C^1), (b_0, b_1) =
    CHI_SUPPORT: the rate penalisation's weight, 0 where b < b_0. Its compact support gives the
    body a fixed extent, so lambda -> infinity has a limit; penalising b itself, whose Gaussian
    tail never vanishes, the body grows with lambda without bound (cells with lambda dt b >> 1
    move with it: s^2 ~ sigma ln(lambda dt))."""
    lo, hi = CHI_SUPPORT
    t = ((b - lo) / (hi - lo)).clamp(0.0, 1.0)
    return t * t * (3 - 2 * t)


RATE_CAP = 1.0 - 1e-6
"""The mask value at which ``rate_weight`` stops growing (-ln(1e-6) = 13.8: the body's core)."""


def rate_weight(b: Faces) -> Faces:
    """s_f = -ln(1 - b_f) (b_f capped at ``RATE_CAP``), the split blend's relaxation rate per unit
    lambda_p (module docstring): the weight of ``NumericalFluid(implicit=True)``'s joint solve.
    The box-wall faces keep b_f (their normal velocity is b_f v_d in ``penalize``)."""
    return _box_faces_from(tuple(-torch.log1p(-c.clamp(max=RATE_CAP)) for c in b), b)


IMMERSE_TOL = {torch.float32: (1e-3, 1e-4), torch.float64: (1e-6, 1e-6)}
"""The joint solves' PCG relative residuals |f - A phi| / |f| (forward, adjoint) by the fluid's
dtype. float32 (the default): the swimming study (120 frames, 3 / 5 / 7 Hz) moves by <= 0.01 %
from 1e-6 (1e-2: 0.3 %), the thin ellipse's added mass by <= 0.05 %, the 60-frame gradient of
tests/test_gradients_scale.py by 0.035-0.04 % (the adjoint's tolerance is what moves it: 1e-3 there
gave 0.10 %); 1-4 iterations a forward solve (3.1 on average at the Schwarz overlap 12) instead of
8-9. float64 (finite-difference checks) stays at 1e-6, so the map is smooth on the 1e-6 steps
those checks take."""
IMMERSE_MAX_ITER = 200  # 1-9 iterations a solve on the fish (rate penalisation 2400 1/s, implicit at n = 4)


def immersion_weights(b: Faces, lam_dt: Tensor | float) -> Faces:
    """c_f = 1 / (1 + lambda dt b_f), the face weights of ``immerse``'s Poisson solve."""
    return tuple(1 / (1 + lam_dt * bc) for bc in b)


def immerse(w: Faces, b: Faces, v_d: Faces, lam_dt: Tensor | float, dx: float,
            start: Tensor | None = None,
            precondition: SchwarzPreconditioner | None = None) -> tuple[Faces, Tensor, Faces]:
    """The rate penalisation and the projection in one implicit solve (module docstring):
    v = u - c grad phi with u = (w + lambda dt b_f v_d) / (1 + lambda dt b_f), c_f = 1 / (1 +
    lambda dt b_f) and -div(c grad phi) = -div u.  Returns (v, phi [m^2/s], the forcing's
    increment v - w + grad phi = lambda dt b_f (v_d - v) [m/s]).  Differentiable (implicit
    differentiation of the PCG solve, fishsim.fluid.pressure.WeightedPoisson); ``start``: PCG's
    initial guess for phi (detached); ``precondition``: the SchwarzPreconditioner of c, built once
    per step (c is fixed over a step's sub-steps; None: built for this solve)."""
    u, _ = penalize(w, b, v_d, lam_dt)
    cx, cy = immersion_weights(b, lam_dt)
    tol, adjoint_tol = IMMERSE_TOL[w[0].dtype]
    phi = WeightedPoisson.apply(cx, cy, -divergence(u, dx), dx, tol, IMMERSE_MAX_ITER, start, precondition,
                                adjoint_tol)
    gx, gy = gradient(phi, dx)
    v = (u[0] - cx * gx, u[1] - cy * gy)
    return v, phi, (v[0] - w[0] + gx, v[1] - w[1] + gy)


# --------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------


class NumericalFluid:
    """Projection-method Navier-Stokes solver with Brinkman penalization (module docstring).

    grid: the r = 1 grid of the states and boundaries it exchanges.
    refinement: r in {1, 2, 4, ...}: internal grid dx / r, sub-steps <= h / r.
    walls: box-wall condition for the tangential velocity (default no-slip at rest; a lid is
        ``WallBC(u_top=U)``; ``FREE_SLIP`` for slip walls).
    scheme: advection interpolation, "koren" (default) or "central".
    substeps: sub-steps per step on the r = 1 grid (r * substeps on the refined one): the floor of
        each sample's count (module docstring).
    cfl: largest advective Courant number max|v| dt / dx per sub-step (default 0.5), a safety net
        above the floor.
    diffusion: largest nu dt / dx^2 per sub-step (default 0.2).
    brinkman: lambda [1/s] of the rate penalisation solved jointly with the projection
        (``immerse``; converges in sub-steps); None (default): the split blend scheme.
    max_substeps: raise ``SimulationBlowUp`` when a step would need more (runaway velocity).
    penalization_iterations: K, times penalize + project is applied per stage (alternating
        projections; 1 = classic Chorin-Brinkman splitting, more = less slip inside the body);
        the split scheme only (``brinkman`` None).
    penalization_rate: lambda_p [1/s] of the split scheme's blend, beta_f = 1 - (1 - b_f)^(lambda_p
        dt / K) (module docstring; the default 2400: beta_f = b_f at 8 sub-steps x 3 passes of
        0.01 s); None: beta_f = b_f at any dt (the band stiffens with K n).
    implicit: solve each stage's relaxation at ``penalization_rate`` and its projection jointly
        (``immerse`` with the weight ``rate_weight``): the passes' limit K -> infinity, converged
        in sub-steps from n = 2, thin bodies included (module docstring); a PCG solve a stage.
    """

    exerts_force = True
    threads_per_sample = False   # one thread a sample (kernels.SplitStep)

    def __init__(
        self,
        grid: Grid,
        refinement: int = 1,
        walls: WallBC = NO_SLIP,
        scheme: str = "koren",
        cfl: float = 0.5,
        diffusion: float = 0.2,
        brinkman: float | None = None,
        substeps: int = 8,
        max_substeps: int = 400,
        penalization_iterations: int = 3,
        penalization_rate: float | None = 2400.0,
        implicit: bool = False,
    ):
        if refinement < 1:
            raise ValueError(f"refinement must be a positive integer, got {refinement}")
        if brinkman is not None and not brinkman > 0:
            raise ValueError(f"brinkman (lambda) must be > 0 or None, got {brinkman}")
        if penalization_rate is not None and not penalization_rate > 0:
            raise ValueError(f"penalization_rate must be > 0 (1/s) or None, got {penalization_rate}")
        if implicit and (penalization_rate is None or brinkman is not None):
            raise ValueError("implicit needs penalization_rate (the rate it solves for) and brinkman None")
        if substeps < 1 or penalization_iterations < 1:
            raise ValueError(f"substeps and penalization_iterations must be >= 1, got {substeps}, "
                             f"{penalization_iterations}")
        self.grid = grid
        self.refinement = int(refinement)
        self.fine = Grid(grid.H * refinement, grid.W * refinement, grid.dx / refinement)
        self.walls, self.scheme = walls, scheme
        self.cfl, self.diffusion, self.brinkman = cfl, diffusion, brinkman
        self.substeps, self.max_substeps = int(substeps), max_substeps
        self.penalization_iterations = int(penalization_iterations)
        self.penalization_rate = penalization_rate
        self.implicit = bool(implicit)

    # -- contract ------------------------------------------------------------------------------

    def initial_state(self, batch: int, device=None, dtype=torch.float32) -> FluidState:
        """Fluid at rest: a = 0, p = 0 on the r = 1 grid; refined (r > 1), a RefinedState whose
        fine potential is 0 too, so that every state of an episode has the same tensors."""
        rest = rest_state(self.grid, batch, device, dtype)
        if self.refinement == 1:
            return rest
        fine_a = torch.zeros(batch, 1, self.fine.H + 1, self.fine.W + 1, device=device, dtype=dtype)
        return RefinedState(a=rest.a, p=rest.p, fine_a=fine_a)

    def step(self, state: FluidState, boundary: Boundary, params: FluidParams,
             start: FluidState | None = None) -> FluidState:
        """(a_t, p_t, b_t, v_d,t) -> (a_t+1, p_t+1); p_t is not needed by a projection method.
        The new state's ``solves`` are the joint stages' potentials [B, 2 n_max, rH, rW] (stage
        1 and 2 of each sub-step; None with the split passes, whose solves are direct);
        ``start``: this step's result from the same or nearby inputs (a recomputation; the
        coupling's pass before), whose ``solves`` start the joint stages' PCG (a recomputation's
        solves then take no iteration)."""
        return self.step_with_diagnostics(state, boundary, params, start)[0]

    # -- the step ------------------------------------------------------------------------------

    def step_with_diagnostics(
        self, state: FluidState, boundary: Boundary, params: FluidParams, start: FluidState | None = None
    ) -> tuple[FluidState, StepDiagnostics]:
        """``step`` plus what it did (sub-step count, penalization force density)."""
        r, dx, h = self.refinement, self.fine.dx, params.h
        v = v_start = curl(self._fine_potential(state), dx)
        fine = (self.fine.H, self.fine.W)
        b = face_masks(_on_grid(boundary.mask, fine, r))
        v_d = vector_to_faces(_on_grid(boundary.velocity, fine, r))
        rho, mu = per_sample(params.rho, v[0]), per_sample(params.mu, v[0])
        nu = mu / rho
        n = self._count_substeps(v, b, v_d, nu, h)                      # [B]
        dt = (h / n.to(v[0])).view(-1, 1, 1, 1)
        beta = self._blend_weight(b, h, n)
        guess = None if start is None or self.stiffness is None else start.solves
        if guess is not None and guess.shape[1] != 2 * int(n.max()):      # not this step's record
            guess = None
        if self._compiled(v[0]):                      # the same sub-steps in one compiled call
            stage = self.penalization_iterations if self.stiffness is None else \
                Immersion(self.stiffness, *IMMERSE_TOL[v[0].dtype], IMMERSE_MAX_ITER)
            vx, vy, p_sum, *pen_sum, solves = SplitStep.apply(*v, *beta, *v_d, nu, dt, n, self._inverse(v[0]), dx,
                                                              self.walls, stage, guess)
            v, solves = (vx, vy), (solves.flatten(1, 2) if solves.shape[2] else None)
        else:
            v, p_sum, pen_sum, solves = self._substeps(v, beta, v_d, nu, dt, n, guess)
        self._check_finite(v, h)
        a = stream_function(v, dx)
        p = _mean_free(rho * p_sum / h)
        if r > 1:
            new = RefinedState(a=_mean_free(a[..., ::r, ::r]), p=F.avg_pool2d(p, r), fine_a=a, solves=solves)
        else:
            new = FluidState(a=a, p=p, solves=solves)
        diag = StepDiagnostics(n, tuple(q / h for q in pen_sum), dx, r, b, v_start, v, h)
        return new, diag

    def _blend_weight(self, b: Faces, h: float, n: Tensor) -> Faces:
        """The split scheme's blend weight of a pass, beta_f = 1 - (1 - b_f)^e with e = lambda_p h /
        (n K) per sample (module docstring): b_f itself, bit for bit, in every sample whose e = 1
        (the defaults; whatever its batch mates' e) and with ``penalization_rate`` None; the joint
        solve's weight: chi(b) (``brinkman``) or ``rate_weight`` (``implicit``). Differentiable in b."""
        if self.brinkman is not None:
            return tuple(penalised_fraction(x) for x in b)
        if self.implicit:
            return rate_weight(b)
        if self.penalization_rate is None:
            return b
        e = self.penalization_rate * h / (n.numpy() * self.penalization_iterations)    # [B] float64
        exact = np.abs(e - 1) < 1e-12
        if exact.all():
            return b
        keep = torch.from_numpy(exact).to(b[0].device).view(-1, 1, 1, 1)
        e = torch.from_numpy(e).to(b[0]).view(-1, 1, 1, 1)
        return tuple(torch.where(keep | (c >= 1), c, -torch.expm1(e * torch.log1p(-torch.where(c < 1, c, 0))))
                     for c in b)

    def _substeps(self, v: Faces, b: Faces, v_d: Faces, nu: Tensor, dt: Tensor, n: Tensor,
                  guess: Tensor | None = None):
        """The step's sub-steps as torch formulas, sample b stopping after its own n_b; returns (v',
        sum of the sub-steps' pressure potentials, of their penalisation increments, the joint
        stages' potentials [B, 2 n_max, H, W] or None). ``guess``: the stages' starts (``step``;
        any field is a valid start: a step of fewer sub-steps gives its own)."""
        p_sum, pen_sum, solves = 0.0, (0.0, 0.0), []
        n_min, n_max = int(n.min()), int(n.max())
        last, precondition = None, None
        if self.stiffness is not None:       # one preconditioner for every solve of the step
            weights = tuple(c.detach() for c in immersion_weights(b, self.stiffness * dt))
            precondition = SchwarzPreconditioner(weights, self.fine.dx)
        for i in range(n_max):
            known = guess is not None and 2 * i + 1 < guess.shape[1]    # a guess from fewer sub-steps: the rest start as usual
            starts = (guess[:, 2 * i, None], guess[:, 2 * i + 1, None]) if known else (last, None)
            new, phi, pen, stages = self._substep(v, b, v_d, nu, dt, starts, precondition)
            last = stages[1]
            if i >= n_min:                            # samples past their own count keep their state
                active = (i < n).to(v[0]).view(-1, 1, 1, 1)
                new = tuple(active * c + (1 - active) * o for c, o in zip(new, v))
                phi, pen = active * phi, tuple(active * q for q in pen)
            v = new
            p_sum = p_sum + phi
            pen_sum = tuple(s + q for s, q in zip(pen_sum, pen))
            if self.stiffness is not None:
                solves += [x.detach() for x in stages]
        return v, p_sum, pen_sum, (torch.cat(solves, 1) if solves else None)

    def _substep(self, v: Faces, b: Faces, v_d: Faces, nu: Tensor, dt: Tensor,
                 starts: tuple[Tensor | None, Tensor | None] = (None, None),
                 precondition: SchwarzPreconditioner | None = None):
        """One Heun (SSP-RK2) sub-step; returns (v', pressure potential phi1/2 + phi2 [m^2/s],
        penalization increment pen1/2 + pen2 [m/s], the stages' potentials (phi1, phi2): phi2
        the next solve's start). ``starts``: the stages' guesses for phi (the second's None: the
        first's solution), ``precondition``: the step's preconditioner (rate penalisation only)."""
        dx, walls, scheme = self.fine.dx, self.walls, self.scheme
        v1, phi1, pen1 = self._constrain(predict(v, nu, dt, dx, walls, scheme), b, v_d, dt, starts[0], precondition)
        w2 = tuple(0.5 * (c + q) for c, q in zip(v, predict(v1, nu, dt, dx, walls, scheme)))
        v2, phi2, pen2 = self._constrain(w2, b, v_d, dt, phi1 if starts[1] is None else starts[1], precondition)
        return v2, 0.5 * phi1 + phi2, tuple(0.5 * q1 + q2 for q1, q2 in zip(pen1, pen2)), (phi1, phi2)

    def _constrain(self, w: Faces, b: Faces, v_d: Faces, dt: Tensor, start: Tensor | None = None,
                   precondition: SchwarzPreconditioner | None = None):
        """The body and the incompressibility for one stage; returns (v, phi, penalisation
        increment). With a joint solve (``stiffness``: ``brinkman``, or ``implicit``): ``immerse``
        (``start``: PCG's guess for phi, ``precondition``: the step's). Else project(penalize(w)),
        repeated ``penalization_iterations`` times (alternating projections onto {v = v_d in the
        body} and {div v = 0}), phi and the increment summed over them (on the CPU the whole
        sub-step loop runs compiled: ``kernels.SplitStep``)."""
        if self.stiffness is not None:
            return immerse(w, b, v_d, self.stiffness * dt, self.fine.dx, start, precondition)
        inverse = self._inverse(w[0])
        phi_sum, pen_sum = 0.0, (0.0, 0.0)
        for _ in range(self.penalization_iterations):
            u, pen = penalize(w, b, v_d)
            w, phi = project(u, self.fine.dx, inverse)
            phi_sum = phi_sum + phi
            pen_sum = tuple(s + q for s, q in zip(pen_sum, pen))
        return w, phi_sum, pen_sum

    # -- helpers -------------------------------------------------------------------------------

    def _fine_potential(self, state: FluidState) -> Tensor:
        r = self.refinement
        fine_a = getattr(state, "fine_a", None)
        if r > 1 and fine_a is not None and fine_a.shape[-2:] == (self.fine.H + 1, self.fine.W + 1):
            return fine_a
        return _prolong_vertices(state.a, r)

    @property
    def boundary_grid(self) -> Grid:
        """The grid whose cells the step reads the body on at full resolution: the fine one."""
        return self.fine

    def _compiled(self, like: Tensor) -> bool:
        """Whether the step's sub-steps run as ``kernels.SplitStep`` (Koren advection on the CPU,
        the passes or a joint solve) rather than the torch formulas (other devices and schemes; the
        reference the compiled loops are tested against)."""
        return COMPILED and like.device.type == "cpu" and self.scheme == "koren"

    @property
    def stiffness(self) -> float | None:
        """lambda [1/s] of the stage's joint penalisation + projection solve (``immerse``):
        ``brinkman``, or ``penalization_rate`` when ``implicit``; None for the split passes."""
        if self.brinkman is not None:
            return self.brinkman
        return self.penalization_rate if self.implicit else None

    def _inverse(self, like: Tensor) -> Tensor:
        return neumann_inverse(self.fine.H, self.fine.W, self.fine.dx, like.device, like.dtype)

    def _count_substeps(self, v: Faces, b: Faces, v_d: Faces, nu: Tensor, h: float) -> Tensor:
        """n_b [B] (int64, on the CPU): the largest of r * substeps and the counts that keep sample
        b's max|v| (h/n) / dx <= cfl and nu (h/n) / dx^2 <= diffusion, the speed the larger of the
        fluid's and the bodies' b_f |v_d| (b the face masks, not a joint solve's weight: counted
        with ``rate_weight``, up to 13.8, the implicit option took 4-10 sub-steps where 4 hold the
        CFL bound)."""
        dx = self.fine.dx
        with torch.no_grad():
            if self._compiled(v[0]):
                speed = face_speed(v, b, v_d)
            else:
                speed = torch.stack([torch.maximum(c.abs().amax(dim=(1, 2, 3)), (bc * vc).abs().amax(dim=(1, 2, 3)))
                                     for c, bc, vc in zip(v, b, v_d)]).amax(0).double().cpu()
            nu_b = np.broadcast_to(nu.detach().double().cpu().numpy().reshape(-1), speed.shape[:1])
        speed = speed.numpy()                             # [B] float64: a few numpy operations
        if not np.isfinite(speed).all():
            raise SimulationBlowUp(
                "fluid step: non-finite velocity in the input state or boundary "
                "velocity; the previous step diverged (CFL/viscous instability) or v_d is NaN"
            )
        n = np.maximum(float(self.refinement * self.substeps),
                       np.maximum(np.ceil(speed * h / (self.cfl * dx)),
                                  np.ceil(nu_b * h / (self.diffusion * dx**2)))).astype(np.int64)
        if int(n.max()) > self.max_substeps:
            b = int(n.argmax())
            raise SimulationBlowUp(
                f"fluid step: max |v| = {float(speed[b]):.3g} m/s, nu = {float(nu_b[b]):.3g} m^2/s "
                f"need {int(n[b])} sub-steps (> max_substeps = {self.max_substeps}) at h = {h:g} s, dx = {dx:g} m: "
                "runaway velocity (CFL); check the boundary velocity, h and mu/rho"
            )
        return torch.from_numpy(n)

    def _check_finite(self, v: Faces, h: float) -> None:
        if not all_finite(*v):
            raise SimulationBlowUp(
                f"fluid step: non-finite velocity after the step "
                f"(h = {h:g} s, {self.fine.H}x{self.fine.W} cells); likely an unstable sub-step count "
                "(fixed `substeps` too small for the CFL) or a non-finite mask/boundary velocity"
            )

"""The coupled swimmer and its batched, checkpointed episode: the one loop every command reuses.

One frame (docs/physics.md section 1, h = 0.01 s):

1. solid (q_t, qdot_t) -> soft mask b_t and boundary velocity v_d,t  (fish united with the walls)
2. fluid model (a_t, p_t, b_t, v_d,t) -> (a_t+1, p_t+1)             (HydroNet or numerical)
3. IBM: p_t+1 sampled around the surface nodes -> f_ext (burn-in scaled)
4. PD solid step with f_ext and the muscle contraction h(X, t_+1) -> (q_t+1, qdot_t+1)

In the vacuum (fishsim.fluid.vacuum.Vacuum, ``fluid=none``) steps 1-3 are skipped and f_ext = 0.
Every arrow is differentiable; ``rollout`` checkpoints segments of frames so long episodes fit in
memory: a segment's forward runs without an autograd graph (only its boundary states are kept)
and its backward recomputes it with one (``CheckpointedFrames``). The recomputation replays each
frame's iterative solves from the forward pass's solutions (the PD step's q_t+1 and the fluid's
state p_t+1 with its ``solves``, the numerical fluid's joint stages' potentials, kept detached
while the graph lives: 1.1 MB per fish and frame on the default grid, 140 kB with HydroNet), so
they converge without iterating and the backward pays only for the network, the coupling, the
numerical fluid's explicit parts and the adjoints (the numerical fluid's recomputation 14 instead
of 30 ms a frame); a second backward through the same graph replays them again. While a
segment is differentiated, the one before it is recomputed in a background thread (``Segments``),
so on two cores the recomputation runs beside the adjoints.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from concurrent.futures import Future
from contextlib import nullcontext
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from fishsim.compiled import serially, thread_pool
from fishsim.coupling import (
    CouplingConfig,
    exchange_to_solid,
    fish_band,
    fluid_to_solid,
    on_grid,
    united_with_nothing,
    with_walls,
)
from fishsim.coupling.added_mass import (
    aitken_relaxed,
    body_axis,
    mass_centroid,
    stabilise_translation,
    stabilised_velocity,
    stabilising_force,
    surge_without_stabilisation,
)
from fishsim.coupling.config import AVERAGE, WALL
from fishsim.coupling.forces import burn_in_scale
from fishsim.errors import ConfigError, SimulationBlowUp, stops_surface
from fishsim.fields import Boundary, FluidModel, FluidParams, FluidState, Grid, all_finite, gradient_free
from fishsim.fluid.grid import curl, faces_to_centres
from fishsim.mesh.triangulate import element_areas
from fishsim.solid import SolidModel, SolverCache, pd_step, predicted_start
from fishsim.solid.controller import WaveController


@dataclass(frozen=True)
class SwimState:
    """State of a batch of swimmers at one frame (never mutated).

    q, qdot: world-frame node positions (m) and velocities (m/s), [B, N, 2], float64.
    fluid: the fluid state (the vacuum's holds no field).
    qdot_prev: the previous frame's velocities (the added-mass stabilisation's a_t and the PD
        step's predicted start; None: a start from rest).
    tunnel: in a swim tunnel (``Swimmer(tunnel=True)``) the speed U of the water past the fish
        at this frame and the previous one, [B, 2] (m/s, float64); None elsewhere.
    """

    q: Tensor
    qdot: Tensor
    fluid: FluidState
    qdot_prev: Tensor | None = None
    tunnel: Tensor | None = None

    @property
    def previous_qdot(self) -> Tensor:
        """qdot_prev, or qdot where None (a start from rest: no acceleration, and predicted_start
        then makes the free flight)."""
        return self.qdot if self.qdot_prev is None else self.qdot_prev

    def tensors(self) -> tuple[Tensor, ...]:
        """The state as a tuple of tensors, the form checkpoint segments pass: q, qdot,
        ``previous_qdot``, the fluid state's tensors and the swim tunnel's speeds if any."""
        tunnel = () if self.tunnel is None else (self.tunnel,)
        return (self.q, self.qdot, self.previous_qdot, *self.fluid.tensors(), *tunnel)

    def with_tensors(self, tensors) -> SwimState:
        """The same kind of state (fluid state, tunnel or not) from ``tensors()``'s tuple."""
        n = len(self.fluid.tensors())
        expected = 3 + n + (self.tunnel is not None)
        if len(tensors) != expected:
            raise ValueError(f"a {type(self.fluid).__name__} swim state has {expected} tensors, got {len(tensors)}")
        q, qdot, qdot_prev, *rest = tensors
        return SwimState(q, qdot, self.fluid.with_tensors(rest[:n]), qdot_prev,
                         rest[n] if self.tunnel is not None else None)


@dataclass(frozen=True)
class SwimParams:
    """Per-sample parameters of an episode, each differentiable if it requires grad.

    controller: the travelling-wave controller ([B] tensors C, omega, gamma).
    E: Young's modulus [B] (Pa).
    fluid: rho, mu [B] and h; None: the vacuum's (rho = mu = 0).
    muscle_thickness: the muscle layer's thickness (a scalar tensor, fraction of the local
        half-width; shared by the batch, as the muscles are) to differentiate through, e.g. as a
        co-design parameter; None (default, no cost): the solid's fixed muscle weights. Its value
        must be the thickness the solid's muscle layer was built with (muscles.layer_muscles,
        within ``muscle_x_range``, the layer's (start, end) fractions of L); pd_step refuses
        weights that differ from the model's. A gradient step on it means rebuilding the solid
        at the new thickness (with the elements of a thicker layer, ``layer_muscles(...,
        elements=)``, the muscle list stays the same).
    """

    controller: WaveController
    E: Tensor
    fluid: FluidParams | None = None
    muscle_thickness: Tensor | None = None
    muscle_x_range: tuple[float, float] = (0.05, 0.95)

    def __post_init__(self):
        if self.fluid is None:                          # the vacuum's: rho = mu = 0
            zero = torch.zeros_like(self.E)
            object.__setattr__(self, "fluid", FluidParams(rho=zero, mu=zero))


@dataclass
class FrameOutput:
    """What one frame produced besides the new state (for outputs and objectives).

    f_ext: [B, N, 2] hydrodynamic nodal forces (N per unit depth; without the added-mass
        stabilisation's M^ a_t, which is a numerical device). contraction: [B, n_act].
    boundary: the combined fish + wall boundary seen by the fluid (None in vacuum).
    """

    f_ext: Tensor
    contraction: Tensor
    boundary: Boundary | None = None


@dataclass
class PhaseTimer:
    """Wall time spent in each phase of the frame (s), summed over frames."""

    seconds: dict = field(default_factory=lambda: {"coupling": 0.0, "fluid": 0.0, "solid": 0.0})

    def add(self, phase: str, t0: float, device: torch.device) -> float:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        now = time.perf_counter()
        self.seconds[phase] += now - t0
        return now


class Swimmer:
    """Fish (PD solid) + fluid model + coupling layer + tank walls: the coupled system.

    solid: SolidModel of the fish mesh; in a fluid, built with the coupling's
        ``added_mass_ratio`` (fishsim.coupling.added_mass), whose force M^ a_t each frame adds
        to the fluid's.  fluid: a FluidModel (fishsim.fluid.vacuum.Vacuum: none).
    coupling: CouplingConfig.  walls: the tank's Boundary [1, ., H, W] (mask 1 in the walls).
    fluid_dtype: dtype of the fluid fields (float32 for HydroNet and the numerical solver).
    hold_x: the constraint mode "held on the x axis" (the paper's thrust experiment, Fig. 5):
        after every solid step the fish's mass-weighted mean x displacement and x velocity are
        removed, so its centroid x never moves while it undulates and sways freely in y.
    hold_y: the same in y: the centroid stays on its start line (with hold_x, the paper's
        "centred along the x axis": no sideways drift, the body still undulates).
    tunnel: a swim tunnel whose water speed follows the fish (a flow-speed servo, as in a
        laboratory swim tunnel), so a fish swims steadily for as long as the episode lasts in a
        tank it would cross in seconds. The fish is held in x (hold_x) and the water flows at
        -U(t) through the end bands of the walls (``walls``: a channel of unit speed, scaled
        by -U each frame); U is the fish's swimming speed through the water, set by its x
        momentum (``tunnel_speed``). Everything else is as in free swimming.
    """

    def __init__(self, solid: SolidModel, fluid: FluidModel, coupling: CouplingConfig,
                 walls: Boundary | None = None, fluid_dtype: torch.dtype = torch.float32,
                 hold_x: bool = False, hold_y: bool = False, tunnel: bool = False):
        if tunnel and (not fluid.exerts_force or walls is None):
            raise ConfigError("a swim tunnel needs a fluid and its channel walls")
        self.solid, self.fluid, self.coupling = solid, fluid, coupling
        self.walls = None if walls is None else united_with_nothing(   # the fields the fluid gets: its dtype
            Boundary(walls.mask.to(fluid_dtype), walls.velocity.to(fluid_dtype)))
        self.fluid_dtype, self.hold = fluid_dtype, (hold_x or tunnel, hold_y)
        self.tunnel = tunnel
        self.surface = torch.as_tensor(solid.mesh.surface, dtype=torch.long)
        self.triangles = torch.as_tensor(solid.mesh.triangles, dtype=torch.long)
        if fluid.exerts_force and coupling.force == "exchange" and not hasattr(fluid, "step_with_diagnostics"):
            raise ConfigError("coupling.force=exchange needs the numerical fluid's momentum exchange "
                              "(fluid=numerical); use coupling.force=pressure with this fluid")
        self.added_mass = torch.as_tensor(solid.added_mass) if solid.added_mass.any() else None

    @property
    def h(self) -> float:
        return self.solid.h

    def initial_state(self, params: SwimParams, origin: tuple[float, float]) -> SwimState:
        """Fish at rest with its material frame translated to ``origin`` (x, y) in metres
        (material X = 0, the tail, sits at x = origin[0]); fluid at rest."""
        B = params.E.shape[0]
        q = torch.as_tensor(self.solid.mesh.points, dtype=torch.float64, device=params.E.device)
        q = (q + torch.tensor(origin, dtype=q.dtype, device=q.device)).expand(B, -1, -1).clone()
        fluid = self.fluid.initial_state(B, device=q.device, dtype=self.fluid_dtype)
        qdot = torch.zeros_like(q)
        tunnel = q.new_zeros(B, 2) if self.tunnel else None
        return SwimState(q=q, qdot=qdot, fluid=fluid, qdot_prev=qdot, tunnel=tunnel)

    def boundary(self, state: SwimState) -> Boundary:
        """Step 1: the fish's soft mask and velocity, united with the tank walls."""
        return self.fish_and_boundary(state, alone=False)[1]

    def fish_and_boundary(self, state: SwimState, grid: Grid | None = None,
                          alone: bool = True) -> tuple[Boundary | None, Boundary]:
        """(the fish's own Boundary, or None without ``alone``, the fish united with the tank
        walls) on ``grid``: the fluid's (default) or a finer one, r times (the walls' cell bands
        prolonged exactly)."""
        grid = self.fluid.grid if grid is None else grid
        band = None                                     # the fish on its band, selected once
        if alone or self.walls is None:
            band = fish_band(state.q, state.qdot, self.surface, grid, self.coupling, dtype=self.fluid_dtype)
        fish = None if band is None else on_grid(band, grid)
        if self.walls is None:
            return fish, fish
        r, walls = grid.W // self.fluid.grid.W, self.walls
        scale = -state.tunnel[:, 0] if self.tunnel else None    # the water comes at the fish (facing +x) at U
        if r > 1:
            walls = Boundary(*(F.interpolate(x, scale_factor=r, mode="nearest") for x in (walls.mask, walls.velocity)))
        return fish, with_walls(state.q, state.qdot, self.surface, grid, self.coupling, walls, scale, band)

    def tunnel_speed(self, state: SwimState, f_ext: Tensor, rho: Tensor, mass: Tensor, step: int) -> Tensor:
        """The swim tunnel's speed after this frame, [B, 2] (U_t+1, U_t), from the fish's x
        momentum: the fish of mass M and area A (per unit depth) swims through the water at U,

            (M + M^) (U_t+1 - U_t) / h = F_x,t + rho A (U_t - U_t-1) / h + s M^ (U_t - U_t-1) / h,

        F_x,t = sum_i f_ext,i,x the fluid's force on the held fish this frame. The rho A term
        undoes the tunnel's own doing: the whole channel's water accelerates with U, and the
        pressure gradient that drives it pushes on the body with rho A dU/dt (the buoyancy of an
        accelerating flow), a force a fish accelerating through still water does not feel. M^ =
        ``coupling.added_mass_ratio`` M is the coupling's added-mass stabilisation (s the force
        ramp's scale; fishsim.coupling.added_mass), on this rigid x mode as on a free fish's
        (its nodes' with per-node forces, its rigid translation with averaged ones): F_x,t
        answers the fish's acceleration of the frame before, and the fish's x added mass grows
        as it turns broadside (sin^2 of its heading times the heave's ~9 M), so without M^ the
        update is explicit in it: a 5 Hz fish held in y (``hold_y``), yawed past ~20 deg, made U
        alternate with a growth of ~1.5 a frame until the run blew up (frame 348)."""
        U, U_prev = state.tunnel.unbind(-1)
        area = float(self.solid.fem.area.sum())
        F = f_ext[..., 0].sum(1) + rho.to(U) * area * (U - U_prev) / self.h
        ratio = self.coupling.added_mass_ratio if self.fluid.exerts_force else 0.0
        U_next = stabilised_velocity(U, U_prev, self.h * F / mass.sum(), ratio, burn_in_scale(step, self.coupling.n_burn_in))
        return torch.stack([U_next, U], -1)

    def node_mass(self, like: Tensor) -> Tensor:
        """Lumped nodal masses [N] (kg per unit depth) as ``like``'s dtype and device."""
        return torch.as_tensor(self.solid.fem.mass, dtype=like.dtype, device=like.device)

    def added_mass_force(self, qdot: Tensor, qdot_prev: Tensor | None, step: int) -> Tensor | float:
        """s M^ (qdot - qdot_prev) / h, the added-mass stabilisation's share of the force in the
        frame ending at ``step`` (0 without an estimate), scaled with the fluid's force by the
        burn-in's s (``burn_in_scale``; fishsim.coupling.added_mass)."""
        if qdot_prev is None or self.added_mass is None:
            return 0.0
        scale = burn_in_scale(step, self.coupling.n_burn_in)
        return scale * stabilising_force(self.added_mass.to(qdot), qdot, qdot_prev, self.h)

    def muscle_weights(self, params: SwimParams) -> tuple[Tensor, Tensor] | None:
        """(PD weights [n_act], top shares [n_act]) of the solid's muscle layer as functions of
        ``params.muscle_thickness`` (muscles.layer_weights, ~15 ms on the default fish: the
        rollout computes them once per segment), or None without a thickness."""
        if params.muscle_thickness is None:
            return None
        from fishsim.solid.muscles import layer_weights

        thickness = params.muscle_thickness.to("cpu", torch.float64)
        return layer_weights(self.solid, thickness, params.muscle_x_range)

    def fluid_step(self, state: SwimState, fish: Boundary, boundary: Boundary, params: SwimParams,
                   t: int, start: SwimState | None, mass: Tensor, timer: PhaseTimer) -> tuple[FluidState, Tensor]:
        """Steps 2-3: the fluid's step and the force it exerts on the fish's nodes, by the sampled
        pressure or (``coupling.force=exchange``) by momentum exchange (fishsim.coupling); mass:
        the nodal masses [N] (how averaged forces are shared); timer: where the phases' time goes.
        The fluid reads the body on its ``boundary_grid`` if it has a finer one (a refined
        numerical fluid: the fish's mask is sampled on its fine cells); ``fish`` (the fish alone,
        None unless the momentum exchange needs it) and ``boundary`` are on the fluid's grid,
        where the sampled pressure is read."""
        t0, dev = time.perf_counter(), state.q.device
        fine = getattr(self.fluid, "boundary_grid", self.fluid.grid)
        body, body_boundary = (fish, boundary) if fine == self.fluid.grid else self.fish_and_boundary(
            state, fine, alone=self.coupling.force == "exchange")
        t0 = timer.add("coupling", t0, dev)
        if self.coupling.force == "exchange":
            fluid, diag = self.fluid.step_with_diagnostics(state.fluid, body_boundary, params.fluid,
                                                           start=None if start is None else start.fluid)
        else:
            fluid = self.fluid.step(state.fluid, body_boundary, params.fluid,
                                    start=None if start is None else start.fluid)
        require_finite(fluid_vector_potential_a=fluid.a, fluid_pressure_p=fluid.p)
        t0 = timer.add("fluid", t0, dev)
        if self.coupling.force == "exchange":
            share = diag.body_share(body.mask, body_boundary.mask)
            f_ext = exchange_to_solid(state.q, diag.cell_forces(params.fluid.rho, share), self.surface,
                                      self.fluid.grid, self.coupling, step=t + 1, mass=mass)
        else:
            viscous = None
            if self.coupling.viscous:
                v = faces_to_centres(curl(fluid.a, self.fluid.grid.dx))
                viscous = (state.qdot, v, params.fluid.mu)
            wall = None
            if self.coupling.ibm_fit == WALL:          # the nodes' acceleration of the frame before
                wall = ((state.qdot - state.previous_qdot) / self.h, params.fluid.rho)
            f_ext = fluid_to_solid(state.q, fluid.p, boundary, self.surface, self.fluid.grid,
                                   self.coupling, step=t + 1, mass=mass, viscous=viscous, wall=wall)
        timer.add("coupling", t0, dev)
        return fluid, f_ext

    def frame(self, state: SwimState, params: SwimParams, t: int,
              start: SwimState | None = None, muscles: tuple[Tensor, Tensor] | None = None,
              cache: SolverCache | None = None, timer: PhaseTimer | None = None) -> tuple[SwimState, FrameOutput]:
        """Advance one frame (module docstring); ``t`` is the index of the frame being left.
        ``start``: a guess of the new state (its q and fluid p) for the iterative solves
        (default: the PD step starts from ``predicted_start``, the fluid from p_t).
        ``muscles``: ``muscle_weights(params)`` if already computed (default: computed here).
        ``cache``: the PD solve's SolverCache of the frames' sequence (default: a fresh one).
        ``timer``: a PhaseTimer the frame adds its phases' wall time to (default: none kept)."""
        dev, clock = state.q.device, PhaseTimer() if timer is None else timer
        t0 = time.perf_counter()
        fluid, boundary = state.fluid, None
        f_ext, mass = torch.zeros_like(state.q), self.node_mass(state.q)
        if self.fluid.exerts_force:
            fish, boundary = self.fish_and_boundary(state, alone=self.coupling.force == "exchange")
            t0 = clock.add("coupling", t0, dev)
            fluid, f_ext = self.fluid_step(state, fish, boundary, params, t, start, mass, clock)
            t0 = time.perf_counter()
        if muscles is None:
            muscles = self.muscle_weights(params)
        weight, share = (None, None) if muscles is None else muscles
        contraction = params.controller.contraction(
            self.solid, (t + 1) * self.h, top_share=None if share is None else share.to(params.controller.C))
        solid_start = start.q if start is not None else (
            None if state.qdot_prev is None else predicted_start(state.q, state.qdot, state.qdot_prev, self.h))
        stabilising = self.added_mass_force(state.qdot, state.qdot_prev, t + 1)
        q, qdot = pd_step(self.solid, state.q, state.qdot, contraction, f_ext + stabilising,
                          params.E, start=solid_start, muscle_weight=weight, cache=cache)
        relax = None
        for _ in range(1, self.coupling.subiterations if self.fluid.exerts_force else 1):
            clock.add("solid", t0, dev)
            fluid, f_ext, boundary, q, qdot, relax = self.subiterate(state, q, qdot, fluid, params, t, contraction,
                                                                     weight, mass, cache, clock, relax)
            t0 = time.perf_counter()
        if self.fluid.exerts_force and self.coupling.force_mode == AVERAGE and state.qdot_prev is not None:
            free = (not self.hold[0], not self.hold[1])
            q, qdot = stabilise_translation(q, qdot, state.qdot, state.qdot_prev, mass,
                                            self.coupling.added_mass_ratio, self.h, free,
                                            burn_in_scale(t + 1, self.coupling.n_burn_in))
        if any(self.hold):
            q, qdot = hold_centroid(q, qdot, state.q, mass, self.hold)
        tunnel = self.tunnel_speed(state, f_ext, params.fluid.rho, mass, t + 1) if self.tunnel else None
        require_finite(solid_positions_q=q, solid_velocities_qdot=qdot)
        require_sound(q, qdot, self.triangles, self.fluid.grid if self.fluid.exerts_force else None)
        if self.fluid.exerts_force:
            require_bounded_force(f_ext, params.fluid.rho, self.solid.mesh.length)
        clock.add("solid", t0, dev)
        return SwimState(q, qdot, fluid, state.qdot, tunnel), FrameOutput(f_ext, contraction, boundary)

    def subiterate(self, state: SwimState, q: Tensor, qdot: Tensor, fluid: FluidState, params: SwimParams, t: int,
                   contraction: Tensor, weight: Tensor | None, mass: Tensor, cache: SolverCache | None,
                   clock: PhaseTimer, relax: tuple[Tensor, Tensor] | None
                   ) -> tuple[FluidState, Tensor, Boundary, Tensor, Tensor, tuple[Tensor, Tensor]]:
        """One more pass of the frame's exchange (``coupling.subiterations``): the fluid stepped
        again from frame t with the body at the estimate (q, qdot) of frame t+1, then the solid
        from frame t with that force F_k and the stabilisation's M^ (qdot - qdot_t) / h,

            (M + M^) a~ = F(body_k) + M^ a_k,    a_k = (qdot_k - qdot_t) / h,

        whose fixed point M a = F(body_t+1) does not contain M^ (the fluid's iterative solves start
        from ``fluid``, the pass before's state of frame t+1); the pass's velocities are then
        relaxed by Aitken's factor and their surge set without M^ (fishsim.coupling.added_mass:
        ``aitken_relaxed``, ``surge_without_stabilisation``), and q = q_t + h qdot.  ``relax``:
        the relaxation's memory from the frame's pass before (None at its first).  Returns (fluid
        state, F_k [B, N, 2], the boundary it saw, q, qdot, the relaxation's memory)."""
        estimate = SwimState(q, qdot, state.fluid, state.qdot, state.tunnel)
        fish, boundary = self.fish_and_boundary(estimate, alone=self.coupling.force == "exchange")
        fluid, f_ext = self.fluid_step(estimate, fish, boundary, params, t, dataclasses.replace(estimate, fluid=fluid),
                                       mass, clock)
        t0, dev = time.perf_counter(), q.device
        stabilising = self.added_mass_force(qdot, state.qdot, t + 1)
        _, qdot_pass = pd_step(self.solid, state.q, state.qdot, contraction, f_ext + stabilising, params.E, start=q,
                               muscle_weight=weight, cache=cache)
        qdot, relax = aitken_relaxed(qdot, qdot_pass, relax)
        qdot = surge_without_stabilisation(qdot, state.qdot, f_ext, body_axis(state.q, mass), mass, self.h)
        clock.add("solid", t0, dev)
        return fluid, f_ext, boundary, state.q + self.h * qdot, qdot, relax


def hold_centroid(q: Tensor, qdot: Tensor, q_prev: Tensor, mass: Tensor, axes: tuple[bool, bool]) -> Tensor:
    """The held constraint along each axis flagged in ``axes`` (x, y): shift q [B, N, 2] so that
    its mass-weighted centroid coordinate equals q_prev's, and remove the mass-weighted mean
    velocity from qdot (the momentum along that axis is zero). mass [N]. Returns (q, qdot),
    differentiable."""
    keep = torch.tensor(axes, dtype=q.dtype, device=q.device)
    return q - mass_centroid(q - q_prev, mass) * keep, qdot - mass_centroid(qdot, mass) * keep


# ------------------------------------------------------------------------------------------------
# Per-frame metrics (differentiable scalars per sample, [B])
# ------------------------------------------------------------------------------------------------


def head_node(mesh) -> int:
    """Index of the nose node (largest material X)."""
    return int(np.argmax(mesh.points[:, 0]))


def tail_node(mesh) -> int:
    """Index of the surface node closest to the tail tip (material (0, 0))."""
    pts = mesh.points[mesh.surface]
    return int(mesh.surface[np.argmin(np.hypot(pts[:, 0], pts[:, 1]))])


METRICS = ["head_x", "head_y", "tail_y", "centroid_x", "centroid_y", "thrust_x", "force_y", "power", "tunnel_u"]


def frame_metrics(swimmer: Swimmer, state: SwimState, out: FrameOutput) -> dict[str, Tensor]:
    """head_x, head_y, tail_y (m), centroid_x (m, mass weighted), thrust_x, force_y (N per unit
    depth, total hydrodynamic force on the fish), power (W per unit depth, the power the fish
    gives the fluid, P = -sum_i f_ext,i . (qdot_i + U e_x), in the water's rest frame),
    tunnel_u (m/s, the swim tunnel's water speed U during the frame; 0 outside a tunnel), each [B]."""
    mesh, mass = swimmer.solid.mesh, swimmer.node_mass(state.q)
    head, tail = head_node(mesh), tail_node(mesh)
    centroid = mass_centroid(state.q, mass)[:, 0]
    thrust = out.f_ext[..., 0].sum(1)
    U = state.tunnel[:, 1] if state.tunnel is not None else torch.zeros_like(thrust)
    power = -(out.f_ext * state.qdot).sum((1, 2)) - U * thrust
    values = [state.q[:, head, 0], state.q[:, head, 1], state.q[:, tail, 1], centroid[:, 0],
              centroid[:, 1], thrust, out.f_ext[..., 1].sum(1), power, U]
    return dict(zip(METRICS, values))


MAX_SPEED = 20.0  # m/s: a swimming fish of this size moves < 1 m/s; beyond this the coupling has run away
RUNAWAY_HINT = f"check coupling.added_mass_ratio, e.g. the default {CouplingConfig.added_mass_ratio:g}"


def require_sound(q: Tensor, qdot: Tensor, triangles: Tensor | None = None, grid: Grid | None = None) -> None:
    """Raise SimulationBlowUp when an element of the deformed fish q [B, N, 2] is inverted (its
    signed area <= 0; ``triangles`` [T, 3] ccw in the rest shape: the solid has folded over
    itself, which no elastic swimmer does), or, given the fluid's ``grid``, when a fish has left
    the tank or a node moves faster than MAX_SPEED (cheap per-frame checks, read in one pass: a
    run that went unphysical must not pass as complete)."""
    x_lo, x_hi, y_lo, y_hi, speed, area, where = _frame_checks(q, qdot, triangles)
    if area <= 0:
        b, k = divmod(where, len(triangles))
        raise SimulationBlowUp(f"element {k} of fish {b} is inverted (the body folded over itself): the "
                               "muscles or forces are too strong for the material (lower controller.amplitude, "
                               "raise solid.youngs_modulus) or the coupling ran away")
    if grid is None:
        return
    W, H = grid.W * grid.dx, grid.H * grid.dx
    if x_lo < 0 or x_hi > W or y_lo < 0 or y_hi > H:
        raise SimulationBlowUp(f"a fish left the {W:.3g} x {H:.3g} m tank (node at x in [{x_lo:.3g}, "
                               f"{x_hi:.3g}], y in [{y_lo:.3g}, {y_hi:.3g}] m): it "
                               "swam through a wall (the solid does not collide with the walls: start it farther "
                               f"away with origin=..., or run fewer frames) or the coupling ran away ({RUNAWAY_HINT})")
    if speed > MAX_SPEED:
        raise SimulationBlowUp(f"a node moves at {speed:.3g} m/s (> {MAX_SPEED:g} m/s): the coupling ran away "
                               f"({RUNAWAY_HINT})")


def _frame_checks(q: Tensor, qdot: Tensor, triangles: Tensor | None = None) -> tuple:
    """(x min, x max, y min, y max of the nodes q [B, N, 2], the largest |qdot|, the smallest
    signed element area of ``triangles`` [T, 3] (inf without) and its flat index b T + k), as
    floats: compiled on the CPU (solid.kernels.frame_checks, one pass), torch elsewhere."""
    q, qdot = q.detach(), qdot.detach()
    tri = torch.zeros(0, 3, dtype=torch.long) if triangles is None else triangles
    if q.device.type == "cpu":
        from fishsim.solid.kernels import frame_checks

        as_f64 = lambda t: np.ascontiguousarray(t.numpy(), dtype=np.float64)
        return frame_checks(as_f64(q), as_f64(qdot), np.ascontiguousarray(tri.numpy(), dtype=np.int64))
    return _torch_frame_checks(q, qdot, tri)


def _torch_frame_checks(q: Tensor, qdot: Tensor, tri: Tensor) -> tuple:
    """``_frame_checks`` in torch operations (any device)."""
    x, y = q[..., 0], q[..., 1]
    area = element_areas(q, tri.to(q.device)).reshape(-1)
    low = (float(area.min()), int(area.argmin())) if area.numel() else (np.inf, -1)
    return (float(x.min()), float(x.max()), float(y.min()), float(y.max()), float(qdot.norm(dim=-1).max()), *low)


def require_bounded_force(f_ext: Tensor, rho, length: float) -> None:
    """Raise SimulationBlowUp when the fluid's total force on a fish exceeds
    rho MAX_SPEED^2 L (N/m: the dynamic pressure of a MAX_SPEED flow over the whole body), which
    no flow the speed check allows can produce."""
    bound = torch.as_tensor(rho, dtype=f_ext.dtype, device=f_ext.device).reshape(-1) * MAX_SPEED**2 * length
    force = f_ext.detach().sum(1).norm(dim=-1)
    if bool((force > bound).any()):
        b = int(torch.argmax(force / bound))
        raise SimulationBlowUp(f"the fluid pushes fish {b} with {float(force[b]):.3g} N/m (> rho U^2 L = "
                               f"{float(bound[min(b, len(bound) - 1)]):.3g} N/m at U = {MAX_SPEED:g} m/s): the "
                               f"coupling ran away ({RUNAWAY_HINT})")


def require_finite(**fields: Tensor) -> None:
    """Raise SimulationBlowUp naming the first non-finite quantity (keyword names use _ for
    spaces: fluid_pressure_p -> "fluid pressure p"); the rollout adds the frame number."""
    for name, x in fields.items():
        if not all_finite(x):
            raise SimulationBlowUp(
                f"non-finite {name.replace('_', ' ')} (try a smaller controller amplitude, a longer "
                "coupling.n_burn_in, or fluid=numerical to check the surrogate)")


# ------------------------------------------------------------------------------------------------
# The episode
# ------------------------------------------------------------------------------------------------


def _param_tensors(params: SwimParams) -> tuple[Tensor, ...]:
    """The tensors of ``params`` (controller C, omega, gamma; E; fluid rho, mu; the muscle
    thickness if given)."""
    c = params.controller
    thickness = () if params.muscle_thickness is None else (params.muscle_thickness,)
    return (c.C, c.omega, c.gamma, params.E, params.fluid.rho, params.fluid.mu, *thickness)


def _with_param_tensors(params: SwimParams, tensors: tuple[Tensor, ...]) -> SwimParams:
    """``params`` with its tensors replaced (inverse of _param_tensors)."""
    C, omega, gamma, E, rho, mu, *rest = tensors
    controller = dataclasses.replace(params.controller, C=C, omega=omega, gamma=gamma)
    fluid_params = dataclasses.replace(params.fluid, rho=rho, mu=mu)
    thickness = None if params.muscle_thickness is None else rest[-1]
    return dataclasses.replace(params, controller=controller, E=E, fluid=fluid_params, muscle_thickness=thickness)


class Segments:
    """A rollout's checkpointed segments, for a backward that recomputes segment k - 1 in a
    background thread while segment k is differentiated. A segment's recomputation (a forward
    with a graph) is about half of its backward and depends only on the segment's inputs, so on
    two cores it runs beside the adjoints instead of before them. Same operations, same order:
    the gradients are those of a recomputation in turn, bit for bit (its compiled kernels run
    serially there, ``compiled.serially``). ``background``: recompute
    in the background at all. The rollout turns it on only when its batch leaves a torch thread
    idle (B < threads) and its fluid runs a sample on one thread: a batch that fills the threads,
    or HydroNet, whose convolutions use them all, gained nothing and lost cache (16 fish, 12
    frames: backward 6.3 -> 9.6 s; HydroNet, B = 1, 300 frames: 22.5-24.0 -> 20.2-25.5 s)."""

    def __init__(self, background: bool):
        self.background = background
        self.runs: list[tuple[Callable, list[Tensor], tuple[bool, ...]]] = []
        self.pending: dict[int, Future] = {}

    def add(self, run: Callable, inputs: tuple[Tensor, ...], wanted: tuple[bool, ...]) -> int:
        """Register a segment (its run, inputs and which inputs want a gradient); its index."""
        self.runs.append((run, [x.detach() for x in inputs], wanted))
        return len(self.runs) - 1

    def prefetch(self, k: int) -> None:
        """Start recomputing segment k in the background (nothing for k < 0 or if started)."""
        if self.background and k >= 0 and k not in self.pending:
            self.pending[k] = thread_pool(1, "fishsim-recompute").submit(serially, self.recompute, k)

    def take(self, k: int) -> tuple[list[Tensor], tuple[Tensor, ...]]:
        """(inputs, outputs) of segment k recomputed with a graph: the prefetched ones, else now."""
        future = self.pending.pop(k, None)
        return future.result() if future is not None else self.recompute(k)

    def recompute(self, k: int) -> tuple[list[Tensor], tuple[Tensor, ...]]:
        run, saved, wanted = self.runs[k]
        inputs = [x.detach().requires_grad_(w) for x, w in zip(saved, wanted)]
        with torch.enable_grad():
            return inputs, run(*inputs)


class CheckpointedFrames(torch.autograd.Function):
    """outputs = run(*inputs) computed without an autograd graph; the backward recomputes run
    with one and differentiates it w.r.t. the inputs (a segment's state and parameter tensors:
    gradients reach only what is passed in, never tensors run captures). ``segments``: the
    rollout's ``Segments``, where the segment registers, so that the previous segment's
    recomputation starts as this one's backward begins."""

    @staticmethod
    def forward(ctx, run: Callable, segments: Segments, *inputs: Tensor):
        ctx.segments, ctx.index = segments, segments.add(run, inputs, ctx.needs_input_grad[2:])
        ctx.set_materialize_grads(False)            # unused outputs: None, not zero tensors
        return run(*inputs)

    @staticmethod
    def backward(ctx, *grad_outputs: Tensor):
        inputs, outputs = ctx.segments.take(ctx.index)
        ctx.segments.prefetch(ctx.index - 1)
        pairs = [(o, g) for o, g in zip(outputs, grad_outputs) if g is not None and o.requires_grad]
        wrt = [x for x in inputs if x.requires_grad]
        grads = iter(torch.autograd.grad([o for o, _ in pairs], wrt, [g for _, g in pairs], allow_unused=True)
                     if pairs and wrt else [None] * len(wrt))
        return (None, None, *(next(grads) if x.requires_grad else None for x in inputs))


def _detached(state: SwimState) -> SwimState:
    """The solved parts of a state (q, the fluid's p and solves), detached, as a start for a
    recomputation."""
    solves = state.fluid.solves
    return SwimState(q=state.q.detach(), qdot=None, fluid=FluidState(
        a=None, p=state.fluid.p.detach(), solves=None if solves is None else solves.detach()))


def rollout(swimmer: Swimmer, state: SwimState, params: SwimParams, n_frames: int,
            segment: int = 0, on_frame: Callable[[int, SwimState, FrameOutput, dict], None] | None = None,
            start: int = 0, failures: dict[int, tuple[int, str]] | None = None,
            truncate: int = 0, cache: SolverCache | None = None,
            timer: PhaseTimer | None = None) -> tuple[SwimState, dict[str, Tensor]]:
    """Run ``n_frames`` frames from frame ``start``; return the final state and the per-frame
    metrics stacked to [n_frames, B] (differentiable w.r.t. the initial state and ``params``).

    segment: gradient-checkpoint segment length in frames (0: no checkpointing, keep every
        frame's graph). Only segment boundaries are stored; frames are recomputed in backward,
        and gradients then reach only the initial state and ``params`` (not tensors a custom
        fluid model holds, such as trainable weights: use segment=0 for those).
    on_frame(t, state, output, metrics): called once per frame after frame t (0-based, counted
        from ``start``) in the forward pass only (not again during checkpoint recomputation),
        e.g. to write outputs; raising stops the episode.
    failures: None (default): a sample that blows up stops the whole batch. A dict: isolate
        failing samples instead (a population of candidates): a sample whose frame blows up is
        found by re-running that frame one sample at a time, recorded as
        ``failures[b] = (frame, reason)`` and parked from then on (held at this call's initial
        state with zero muscle contraction, so it stays at rest and its gradients are zero); the
        others carry on. Raises only if every sample has failed.
    truncate: truncated backpropagation through time (0: none). Every ``truncate`` frames the
        state and the gait's phase omega t are detached, so the gradient of a frame's metrics
        reaches the parameters only through the frames since the last cut (a biased but bounded
        gradient for long episodes whose full gradient grows with their length; docs/physics.md
        section 9).
    cache: the PD solve's SolverCache (its preconditioner carried from frame to frame, its
        statistics); default: a fresh one, so that a call never depends on what ran before it
        (a resumed optimisation repeats an uninterrupted one exactly). Pass one to read the
        statistics or to carry the preconditioner over consecutive calls.
    timer: a PhaseTimer that the frames add their solid / fluid / coupling wall time to (a
        checkpointed backward's recomputation too).
    Raises SimulationBlowUp naming the frame if a state goes non-finite.
    A call with autograd off is gradient-free throughout (``fishsim.fields.gradient_free``: the
    fluid may take a faster path, HydroNet its compiled network).
    """
    marked = nullcontext() if torch.is_grad_enabled() else gradient_free(state.q.shape[0] * n_frames)
    with marked:
        recorded = [start - 1]
        isolate, rest = failures is not None, state
        alive = [torch.ones(state.q.shape[0], dtype=torch.bool, device=state.q.device)]
        masks: dict[int, Tensor] = {}             # frame -> the alive mask it ran with (replayed)
        seg = segment if segment > 0 and torch.is_grad_enabled() else n_frames
        solutions: dict[int, SwimState] = {}      # frame -> forward solution, replayed in recomputation
        cache = SolverCache() if cache is None else cache

        idle = state.q.shape[0] < torch.get_num_threads() and not swimmer.fluid.threads_per_sample
        tensors, chunks, segments = state.tensors(), [], Segments(background=idle)
        n_state = len(tensors)

        def run_frames(t0: int, count: int, anchor: float, *tensors: Tensor):
            s, rows = state.with_tensors(tensors[:n_state]), []
            p = _with_param_tensors(params, tensors[n_state:])
            if anchor:
                p = dataclasses.replace(p, controller=dataclasses.replace(p.controller, t_anchor=anchor))
            muscles = swimmer.muscle_weights(p)                     # once per segment, not per frame
            for t in range(t0, t0 + count):
                replay = t <= recorded[0]
                mask = masks[t] if replay and isolate else alive[0]
                s_in, p_in = park(s, p, mask, rest) if isolate else (s, p)
                try:
                    with stops_surface():
                        s_new, out = swimmer.frame(s_in, p_in, t, start=solutions.get(t) if replay else None,
                                                   muscles=muscles, cache=cache, timer=timer)
                except SimulationBlowUp as err:
                    if not isolate or replay:
                        raise SimulationBlowUp(f"simulation blew up at frame {t + 1}: {err}") from None
                    mask = mask & ~failing_samples(swimmer, s_in, p_in, t, mask, failures, err)
                    alive[0] = mask
                    s_in, p_in = park(s, p, mask, rest)
                    s_new, out = swimmer.frame(s_in, p_in, t, muscles=muscles, cache=cache, timer=timer)
                s = s_new
                m = frame_metrics(swimmer, s, out)
                if not replay:
                    masks[t] = mask
                    if on_frame is not None:
                        on_frame(t, s, out, m)
                    recorded[0] = t
                    if keep_solutions:
                        solutions[t] = _detached(s)
                rows.append(torch.stack(list(m.values())))
            return (*s.tensors(), torch.stack(rows))

        keep_solutions = seg < n_frames and any(x.requires_grad for x in (*tensors, *_param_tensors(params)))
        t, anchor = start, 0.0
        while t < start + n_frames:
            count = min(seg, start + n_frames - t)
            if truncate > 0 and torch.is_grad_enabled():
                done = t - start
                if done and done % truncate == 0:
                    tensors = tuple(x.detach() for x in tensors)
                    anchor = t * swimmer.h                  # the gait's phase is frozen with the state
                count = min(count, truncate - done % truncate)
            inputs = (*tensors, *_param_tensors(params))
            if seg < n_frames:
                result = CheckpointedFrames.apply(lambda *x, t0=t, n=count, a=anchor: run_frames(t0, n, a, *x), segments,
                                                  *inputs)
            else:
                result = run_frames(t, count, anchor, *inputs)
            tensors, rows = result[:-1], result[-1]
            chunks.append(rows)
            t += count
        stacked = torch.cat(chunks)  # [n_frames, n_metrics, B]
        return state.with_tensors(tensors), {name: stacked[:, i] for i, name in enumerate(METRICS)}


def _select(keep: Tensor, x: Tensor | None, other: Tensor | None) -> Tensor | None:
    """x where keep [B] is true, else other (per sample; None stays None)."""
    if x is None or other is None:
        return x
    return torch.where(keep.view(-1, *[1] * (x.ndim - 1)), x, other)


def park(state: SwimState, params: SwimParams, alive: Tensor, rest: SwimState) -> tuple[SwimState, SwimParams]:
    """Samples not ``alive`` [B] set to the ``rest`` state with zero muscle amplitude C (they
    stay at rest and pass no gradient); the others untouched."""
    if bool(alive.all()):
        return state, params
    def at_rest(name: str, x: Tensor) -> Tensor:                # a parked fish's fluid (fine flow too): at rest
        r = getattr(rest.fluid, name, None)
        return _select(alive, x, torch.zeros_like(x) if r is None else r)

    fluid = state.fluid.map(at_rest)
    qdot_prev = _select(alive, state.qdot_prev, rest.qdot_prev if rest.qdot_prev is not None else torch.zeros_like(rest.q))
    parked = SwimState(_select(alive, state.q, rest.q), _select(alive, state.qdot, rest.qdot), fluid, qdot_prev,
                       _select(alive, state.tunnel, rest.tunnel))
    C = params.controller.C
    controller = dataclasses.replace(params.controller, C=torch.where(alive, C, torch.zeros_like(C)))
    return parked, dataclasses.replace(params, controller=controller)


def _sample(state: SwimState, params: SwimParams, b: int) -> tuple[SwimState, SwimParams]:
    """Sample b of a batch as a batch of one."""
    one = lambda x: None if x is None else x[b:b + 1]
    fluid = state.fluid.map(lambda _, x: one(x))
    c = params.controller
    controller = dataclasses.replace(c, C=one(c.C), omega=one(c.omega), gamma=one(c.gamma))
    fp = dataclasses.replace(params.fluid, rho=one(params.fluid.rho), mu=one(params.fluid.mu))
    return (SwimState(one(state.q), one(state.qdot), fluid, one(state.qdot_prev), one(state.tunnel)),
            dataclasses.replace(params, controller=controller, E=one(params.E), fluid=fp))


def failing_samples(swimmer: Swimmer, state: SwimState, params: SwimParams, t: int, alive: Tensor,
                    failures: dict, err: Exception) -> Tensor:
    """Re-run frame t for each alive sample alone; return the mask [B] of those that blow up
    and record ``failures[b] = (frame, reason)``. Re-raises ``err`` if none fails alone (the
    batch's failure is then not any one sample's) or if every sample fails."""
    bad = torch.zeros_like(alive)
    with torch.no_grad():
        for b in torch.nonzero(alive).flatten().tolist():
            try:
                swimmer.frame(*_sample(state, params, b), t)
            except SimulationBlowUp as one:
                bad[b] = True
                failures[b] = (t + 1, str(one))
    if not bool(bad.any()) or bool((alive & ~bad).sum() == 0):
        raise SimulationBlowUp(f"simulation blew up at frame {t + 1}: {err}")
    return bad

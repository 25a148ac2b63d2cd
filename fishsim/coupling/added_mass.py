"""Added-mass stabilisation of the explicit (partitioned) fluid-solid coupling.

The coupled step (docs/physics.md section 1) is explicit: the pressure that pushes the solid in frame
t+1 is the fluid's answer to the body velocities of frame t.  A body accelerating by a in a fluid
feels a pressure force -M_a a (added mass M_a), so per mode the explicit scheme solves

    M a_{t+1} = f - M_a a_t          ->  a_{t+1} = -(M_a / M) a_t + ...,

which grows by M_a / M every frame when M_a > M: the classic added-mass instability of light
bodies.  Measured on the default fish (M = 0.23 kg/m, rho_s = 100 kg/m^3) in rho_f = 50 kg/m^3
(a rigid 2.5 Hz, 5 mm oscillation, least-squares fit F = -M_a a - c v of the IBM force;
tests/test_rollout.py::test_added_mass_of_the_fish_lies_in_the_stable_window): heave
M_a = 8.75 M with the numerical fluid at its defaults (2 penalisation passes x 8 sub-steps; a 2D
plate of the fish's length has rho_f pi (L/2)^2 = 6.8 M in unbounded fluid), 10.2 M with the
shipped HydroNet and its own pressure; surge 0.08 M and 0.03 M (2026-11-26, the pressure sampled
beyond the mask's band; with the former weight 1 - b: 7.8 M and 9.3 M; with 1 x 4 stepping, whose
leaky penalisation lets the pressure jump through the body, 5.4 M).  Unstabilised, the lateral force
alternates sign every frame and the run blows up.

The fix (an artificial added mass): the integrator gets an extra mass M^ and the part of the
fluid force it predicts moves to the implicit side,

    (M + M^) a_{t+1} = f_fluid,t+1 + M^ a_t,     a_t = (qdot_t - qdot_{t-1}) / h,

so per mode a_{t+1} = (M^ - M_a) / (M + M^) a_t + ...; exact (implicit) when M^ = M_a.  The
extra term M^ (a_t - a_{t+1}) is O(h): the scheme is consistent, keeps fixed points (a steady
force gives the same steady motion) and is linear in the velocities (differentiable, cheap).
Stability window: for a mass-spring mode of any stiffness under implicit Euler (scanned over
k h^2 / M in [1e-4, 1e5]), the spectral radius stays <= 1 for (M_a - M) / 2 <= M^ <= M + M_a;
an M^ far above M + M_a (e.g. lumped on the light surface nodes, where tangential motion has no
added mass) acts as negative damping.

M^ = ratio * M node by node (``SolidModel(..., added_mass_ratio=)``; isotropic, so the PD
matrices keep their per-axis structure and are still factorised once).  Default ratio = 6.75:
the fish's heave added mass is 9.2 M with the numerical fluid's joint stage (9.0 M with the
former 8 x 3 passes, 10.2 M with HydroNet), a window of 4.1 <= M^/M <= 10.2 by the bound above,
but the light tail sits nearer its edge: without a burn-in (the default) the 7 Hz fish's lateral
force carries 10.8 / 8.8 / 6.1 / 5.9 / 4.4 % of its energy above 35 Hz at ratios 6.5 / 6.75 / 7
/ 7.5 / 8 (frames 30-80, 4 sub-steps; with the paper's 20-frame force ramp 40 / 9.6 / 5.0 / 4.6
% at 5 / 6 / 6.5 / 7), HydroNet's 0.2 / 0.5 / 1.0 % at 5 / 7 / 9 (tests/test_rollout.py). The
upper edge is the tangential modes' (M_a ~ 0: M^ <= M), which every ratio above 1 exceeds; its
negative damping grows per second as h shrinks: at h = 0.0025 s (no burn-in) the frequency study
is sane at ratios 6.5 / 6.75 (45.3 / 113.9 / 227.3 and 46.9 / 115.2 / 229.0 mm at 3 / 5 / 7 Hz)
and wrong at 7 (65.5 / 133.6 / 247.4 mm; with a 20-frame force ramp 99.5 / 164.2 / 273.5, at h =
0.005 ratio 9 fails so). The window is narrow: 6.75 sits between the two edges. Measured with
the lateral (y) ratio kept and the axial (x) one set to 1 (a trial, not kept): at h = 0.0025
with a 0.2 s force ramp it failed as the isotropic ratio did, and at h = 0.01 it moved the 3 Hz
fish 11 % farther, so the tangential edge is not the body's axial motion alone; a ratio along
each node's surface normal would be the next trial.

A force ramp (``coupling.n_burn_in``, the paper's 20 frames) scales the fluid's force, hence its
added mass, by s = t / n_burn_in; were M^ kept, the window M^ <= M + s M_a would be left for s <
(ratio - 1) M / M_a (the first ~12 of 20 frames for the heave at ratio 6.5). Measured so
(numerical fluid, 3 / 5 / 7 Hz, 1.2 s): at h = 0.0025 s a 0.2 s ramp sent the 3 Hz fish 154 mm
instead of 45, and d(head x)/d(f) of the 60-frame gradient problem moved 8 % from 4 to 16
sub-steps (1.5 % without a ramp). So the ramp scales M^ a_t with the fluid's force (the solid
then starts as heavy as M + M^; an 80-frame ramp at h = 0.0025: 40.8 / 111.1 / 213.4 mm), and
the default has none. The ratio is above the surge window's
mass-spring bound (M^/M <= 1.08), but a free surge mode (no spring) only relaxes: a_t+1 = (M^ - M_a)/(M + M^)
a_t + f/(M + M^), a low-pass of the thrust's 2f oscillation that keeps its mean.  The ratio is not
a free knob: the lag it leaves, (M^ - M_a)(a_t - a_t+1), is O(h) but not small at 5-7 Hz (omega h
= 0.3-0.44); on the numerical fluid's 120-frame frequency study (3 / 5 / 7 Hz, joint stage at 2
sub-steps) ratios 5 / 6 / 7 / 8 / 10 move the 7 Hz fish 237.2 / 242.8 / 245.5 / 252.6 / 263.5 mm
and the 3 and 5 Hz ones by < 1 %. ``coupling.subiterations`` converges it away (fishsim.rollout).
"""

from __future__ import annotations

import torch
from torch import Tensor


def stabilising_force(mass: Tensor, qdot: Tensor, qdot_prev: Tensor, h: float) -> Tensor:
    """M^ a_t = m^_i (qdot_t - qdot_{t-1}) / h, [B, N, 2] N per unit depth (mass [N])."""
    return mass[None, :, None] * (qdot - qdot_prev) / h


def mass_centroid(x: Tensor, mass: Tensor) -> Tensor:
    """Mass-weighted mean over the nodes of a nodal field x [B, N, 2] (positions: the centroid;
    velocities: the momentum / M), [B, 1, 2]; mass [N]."""
    return (x * mass[None, :, None]).sum(1, keepdim=True) / mass.sum()


def stabilised_velocity(v: Tensor, v_prev: Tensor, dv: Tensor, ratio: float, scale: float = 1.0) -> Tensor:
    """A rigid mode's velocity after a step whose unstabilised change is dv = h F / M, with the
    added-mass stabilisation M^ = ratio M (module docstring): (M + M^) (v_t+1 - v_t) = h F +
    scale M^ (v_t - v_t-1), i.e. v_t+1 = v_t + (dv + scale ratio (v_t - v_t-1)) / (1 + ratio);
    v, v_prev: the velocities of frames t and t-1; scale: the force ramp's s. Differentiable."""
    return v + (dv + scale * ratio * (v - v_prev)) / (1 + ratio)


def stabilise_translation(q: Tensor, qdot: Tensor, qdot_t: Tensor, qdot_prev: Tensor, mass: Tensor,
                          ratio: float, h: float, axes: tuple[bool, bool], scale: float = 1.0) -> tuple[Tensor, Tensor]:
    """The added-mass stabilisation of the rigid translation along each axis flagged in ``axes``
    (x, y), applied after a solid step without M^ (module docstring).  The step gave the centroid
    velocity v' = v_c,t + h F / M; this returns (q, qdot) [B, N, 2] shifted rigidly so that

        v_c,t+1 = v_c,t + ((v' - v_c,t) + scale ratio h a_c,t) / (1 + ratio),

    q by h times the velocity shift (implicit Euler).  qdot_t, qdot_prev: the velocities of
    frames t and t-1; mass [N]; scale: the force ramp's s, which scales M^ a_c,t with the fluid's
    force (as per node).  Differentiable."""
    keep = torch.tensor(axes, dtype=q.dtype, device=q.device)
    v_new, v_t, v_prev = (mass_centroid(x, mass) for x in (qdot, qdot_t, qdot_prev))
    shift = (stabilised_velocity(v_t, v_prev, v_new - v_t, ratio, scale) - v_new) * keep
    return q + h * shift, qdot + shift


# Sub-iterations (``coupling.subiterations``, fishsim.rollout.Swimmer.frame): a pass maps the
# estimate of frame t+1 to a new one, per mode by the factor c = (M^ - M_a) / (M + M^).  Two modes
# are slow at the default ratio (measured on the 7 Hz fish, 60 frames): the surge (M_a ~ 0.08 M, c
# ~ +0.87), and the thin tail's lateral motion with the heave (local M_a above M^: c ~ -0.55, the
# change alternating in sign from pass to pass).  The surge is taken out of the passes' relaxation
# (``surge_without_stabilisation``: M dv/dt = F along the body axis, c = -M_a / M ~ -0.08), and
# the rest converges by Aitken's dynamic relaxation (``aitken_relaxed``), whose secant estimate of
# the factor suits a dominant mode of one sign.
AITKEN_FIRST = 0.65     # omega of a frame's first relaxed pass: 1 / (1 - c) for the tail's c ~ -0.55
AITKEN_BOUNDS = (0.05, 1.5)   # omega's range: a secant over a near-zero change of the residual is no estimate


def aitken_relaxed(x: Tensor, x_pass: Tensor, previous: tuple[Tensor, Tensor] | None) -> tuple[Tensor, tuple[Tensor, Tensor]]:
    """Aitken's dynamic relaxation of a fixed-point pass x -> x_pass, per sample ([B, ...]):
    with the residual r_k = x_pass - x,

        omega_k = -omega_k-1 r_k-1 . (r_k - r_k-1) / |r_k - r_k-1|^2     (omega_0 = AITKEN_FIRST),

    clamped to AITKEN_BOUNDS; returns (x + omega_k r_k, (r_k, omega_k)), the pair to pass as
    ``previous`` to the next pass (None at a frame's first).  Differentiable (omega included)."""
    r = x_pass - x
    dims = tuple(range(1, r.dim()))
    shape = (r.shape[0],) + (1,) * (r.dim() - 1)
    if previous is None:
        omega = torch.full(shape, AITKEN_FIRST, dtype=r.dtype, device=r.device)
    else:
        r_prev, omega_prev = previous
        dr = r - r_prev
        secant = (r_prev * dr).sum(dims, keepdim=True) / (dr * dr).sum(dims, keepdim=True).clamp_min(torch.finfo(r.dtype).tiny)
        omega = (-omega_prev * secant).clamp(*AITKEN_BOUNDS)
    return x + omega * r, (r, omega)


def body_axis(q: Tensor, mass: Tensor) -> Tensor:
    """Unit vector [B, 1, 2] along the principal axis of the largest mass spread of the nodes q
    [B, N, 2] (mass [N]): the fish's long axis, angle 0.5 atan2(2 C_xy, C_xx - C_yy) of the
    mass-weighted covariance C."""
    d = q - mass_centroid(q, mass)
    w = mass[None, :] / mass.sum()
    cxx, cyy, cxy = ((w * d[..., i] * d[..., j]).sum(1) for i, j in ((0, 0), (1, 1), (0, 1)))
    angle = 0.5 * torch.atan2(2 * cxy, cxx - cyy)
    return torch.stack((torch.cos(angle), torch.sin(angle)), -1)[:, None, :]


def surge_without_stabilisation(qdot: Tensor, qdot_t: Tensor, force: Tensor, axis: Tensor, mass: Tensor,
                                h: float) -> Tensor:
    """qdot [B, N, 2] shifted rigidly along the body axis ([B, 1, 2], ``body_axis``) so that the
    centroid's velocity along it follows the fluid's force without M^: M (v_e - v_e,t) = h F.e,
    F = sum of the nodal forces ``force`` (the internal forces sum to zero); qdot_t: frame t's
    velocities; mass [N] (the fish's own).  The surge's added mass is ~0.08 M, so a pass contracts
    its error by ~0.08 instead of M^ / (M + M^) ~ 0.87.  Differentiable."""
    along = lambda v: (mass_centroid(v, mass) * axis).sum(-1, keepdim=True)       # [B, 1, 1]
    target = along(qdot_t) + h * (force.sum(1, keepdim=True) * axis).sum(-1, keepdim=True) / mass.sum()
    return qdot + (target - along(qdot)) * axis

"""The coupling layer's settings (``CouplingConfig``) and the names of its options: plain values,
no torch, so the CLI's config (``fishsim.config``) imports them for a command's help without the
solvers. The options are explained where they act: band.py and mask.py (distance, mean), ibm.py
(ibm_weight, ibm_fit, ibm_area), forces.py (force_mode), exchange.py (force).
"""

from __future__ import annotations

from dataclasses import dataclass

from fishsim.errors import ConfigError

SEGMENT, NODE = "segment", "node"                     # distance (band.py, mask.py)
HARMONIC, ARITHMETIC = "harmonic", "arithmetic"       # mean (mask.py)
FLUID, OUTSIDE, BODY, NONE = "fluid", "outside", "body", "none"  # ibm_weight (ibm.py)
MEAN, LINEAR, WALL = "mean", "linear", "wall"         # ibm_fit (ibm.py)
CHORD, PAPER = "chord", "paper"                       # ibm_area (ibm.py)
PER_NODE, AVERAGE = "per_node", "average"             # force_mode (forces.py)

_CHOICES = {
    "distance": (SEGMENT, NODE),
    "mean": (HARMONIC, ARITHMETIC),
    "ibm_weight": (FLUID, OUTSIDE, BODY, NONE),
    "ibm_fit": (LINEAR, MEAN, WALL),
    "ibm_area": (CHORD, PAPER),
    "force_mode": (PER_NODE, AVERAGE),
    "force": ("pressure", "exchange"),
}


@dataclass(frozen=True)
class CouplingConfig:
    """Coupling parameters (SI units; the reasons for each default are in mask.py / ibm.py).

    xi: soft-min temperature of the mask distance, m^2 (paper 5e-7).
    sigma: mask softness, m^2 (paper values 5e-9, 5e-7, 5e-5): b goes 0.05 -> 0.95 over one
        2.5 mm cell at 5e-7.
    tau: soft-min temperature of the boundary velocity, m^2 (= xi: nearest surface point).
    sigma_prime: IBM Gaussian variance, m^2 (dx^2 = 6.25e-6: one-cell standard deviation).
    distance: "segment" (exact distance to the polyline, no scallops) | "node" (paper).
    mean: soft-min of the squared distances, "harmonic" (0 on the surface) | "arithmetic" (paper).
    ibm_weight: cells sampled for the pressure, "outside" (beyond the mask's band, on each node's
        own side) | "fluid" (1 - b, the former default) | "body" (b, paper) | "none".
    ibm_fit: "linear" (plane fit evaluated at the node) | "mean" (paper's weighted mean) |
        "wall" (the plane with the wall-normal slope -rho a.n imposed, a the node's acceleration
        of the frame before; needs ibm_weight "outside").
    ibm_area: "chord" (area vectors summing to 0) | "paper" (l_k n_k).
    viscous: add the viscous traction mu (grad v + grad v^T) n, fitted on the same cells as the
        pressure from the node's velocity (no slip) outwards (ibm.ibm_force); the paper
        neglects it.  Needs ibm_weight "outside" and force "pressure".
    force: "pressure" (the IBM-sampled pressure, the paper's; any fluid) | "exchange" (the
        momentum the numerical fluid's penalization exchanges with the body, viscous stress
        included; fishsim.coupling.exchange).
    sigma_spread: variance of the kernel spreading the exchanged force onto the surface nodes,
        m^2 (default (1.5 dx)^2 = 1.40625e-5; exchange.py).
    force_mode: "per_node" (free swimming) | "average" (paper's optimisation mode).
    fix_lateral: drop the y force ("x-axis fixed", paper Sec. 4.4).
    n_burn_in: the fluid's force and the stabilisation's M^ a_t are scaled by s = min(1, t /
        n_burn_in) (paper Sec. 3.4: the force alone, 20 frames); 0 (the default): not scaled,
        the controller's activation already ramps over t_a = 0.2 s from rest. Why M^ a_t is
        scaled too and why the default has no ramp: fishsim/coupling/added_mass.py.
    added_mass_ratio: the added-mass stabilisation's M^ / M (fishsim.coupling.added_mass);
        0 switches it off (plain explicit coupling, unstable for this light fish at the
        calibrated stroke).  Stable for (M_a - M) / 2 <= M^ <= M + M_a in every mode. Default
        6.75: the 7 Hz fish's lateral force is clean with the numerical fluid's joint stage from
        ~6.75 (without a burn-in), and at h = 0.0025 s ratio 7 already fails
        (fishsim/coupling/added_mass.py).
        Per node with per-node forces; on the translation with averaged ones.
    subiterations: passes of the fluid-solid exchange a frame (1: the explicit coupling). Each
        further pass re-steps the fluid from frame t with the body at the solid's estimate of
        frame t+1 and re-solves the solid with M^ (qdot_k - qdot_t) / h in place of M^ a_t
        (fishsim.rollout.Swimmer.subiterate): the fixed point M a = F(body_t+1) no longer
        contains M^, whose lag moves the explicit coupling's 7 Hz fish by ~1.2 % per unit of
        the ratio (docs/validation.md, "The frame step"). Each pass's velocities are relaxed by
        Aitken's factor, their surge set without M^ (fishsim.coupling.added_mass), and its fluid
        solves start from the pass before's: 6 passes settle the frequency study to < 1 % (7 Hz
        fish, 60 frames: 45.26 / 45.13 mm at 6 / 8) at 4.1-4.6x the explicit frame's cost; 3
        passes are 9 % off there and 2 unstable (refused; docs/validation.md, "Sub-iterations
        that settle"). Plain passes (before 2026-11-30) did not settle within 16;
        per-node forces and added_mass_ratio > 0 only.
    k_nearest: surface elements kept per cell (their soft-min is tapered to zero at the
        (K + 1)-th, fishsim.coupling.mask.softmin_weights). On the default graded fish (292
        surface segments, 0.35 mm at the tail tip) after 30 frames at 5 Hz, against all segments:
        K = 12: mask off by 1.2e-2 and b v_d by 7e-4 m/s; K = 16: 7e-5 and 4e-6; K = 24:
        4e-10 and 3e-11. Coupling forward + backward at B = 1: 11 ms (K = 12), 16.5 ms (K = 24).
    """

    xi: float = 5e-7
    sigma: float = 5e-7
    tau: float = 5e-7
    sigma_prime: float = 6.25e-6
    distance: str = SEGMENT
    mean: str = HARMONIC
    ibm_weight: str = OUTSIDE
    ibm_fit: str = LINEAR
    ibm_area: str = CHORD
    viscous: bool = False
    force: str = "pressure"
    sigma_spread: float = 1.40625e-5
    force_mode: str = PER_NODE
    fix_lateral: bool = False
    n_burn_in: int = 0
    added_mass_ratio: float = 6.75
    subiterations: int = 1
    k_nearest: int = 24

    def __post_init__(self):
        for name in ("xi", "sigma", "tau", "sigma_prime", "sigma_spread"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"coupling.{name} must be > 0 (m^2), got {getattr(self, name)}")
        for name, allowed in _CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ConfigError(f"coupling.{name} must be one of {allowed}, got {getattr(self, name)!r}")
        if self.viscous and (self.ibm_weight != OUTSIDE or self.force != "pressure"):
            raise ConfigError("coupling.viscous=true needs coupling.ibm_weight=outside and coupling.force=pressure "
                              f"(got {self.ibm_weight!r}, {self.force!r}): the exchanged force already holds the viscous stress")
        if self.ibm_fit == WALL and self.ibm_weight != OUTSIDE:
            raise ConfigError(f"coupling.ibm_fit=wall needs coupling.ibm_weight=outside (got {self.ibm_weight!r}): "
                              "the wall's slope is imposed on the samples beyond the band")
        if not self.added_mass_ratio >= 0:
            raise ConfigError(f"coupling.added_mass_ratio must be >= 0, got {self.added_mass_ratio}")
        if not 1 <= self.subiterations <= 32:
            raise ConfigError(f"coupling.subiterations must be in [1, 32], got {self.subiterations}")
        if self.subiterations == 2:     # measured: the 7 Hz fish drifted 37 mm sideways in 60 frames
            raise ConfigError("coupling.subiterations=2 is unstable (one unconverged pass is a scheme of its own): "
                              "use 1 (explicit) or 6 (converged within the frame)")
        if self.subiterations > 1 and (self.force_mode != PER_NODE or not self.added_mass_ratio > 0):
            raise ConfigError("coupling.subiterations > 1 needs coupling.force_mode=per_node and "
                              "coupling.added_mass_ratio > 0 (the passes converge through the stabilisation)")
        if self.n_burn_in < 0 or self.k_nearest < 1:
            raise ConfigError("coupling.n_burn_in must be >= 0 and coupling.k_nearest >= 1")

    @property
    def stabilisation_ratio(self) -> float:
        """M^ / M of the solid's per-node artificial mass in a fluid: ``added_mass_ratio`` with
        per-node forces, 0 with averaged ones, whose stabilisation acts on the rigid
        translation alone (fishsim.coupling.added_mass)."""
        return self.added_mass_ratio if self.force_mode == PER_NODE else 0.0

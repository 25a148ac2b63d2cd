"""The solid model: everything precomputed from the mesh for a material and solver options (config.py).

The projective-dynamics global matrix (docs/physics.md section 3) is, per axis ("per-axis split"),

    A(E) = M / h^2 + G^T diag(W(E)) G = M / h^2 + K_muscle + E K0          [N, N]

with W the per-row PD weights: every F row of element e gets E area_e / (1 + nu) (= 2 mu_s area,
co-rotated) plus E area_e nu / ((1 + nu)(1 - 2 nu)) (= lambda_s area, volume term, if enabled),
and the fiber row (j = 0, fiber m = (1, 0)) of a muscle element gets k_m area_e f_e (f_e its area
fraction inside the muscle layers, 1 for the paper's stations; muscles.py). A does not depend
on q or on the activations, so it is factorised once per distinct E and reused every step
(fishsim.solid.preconditioner builds and caches the factorisations).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from fishsim.errors import ConfigError
from fishsim.mesh.fish_mesh import FishMesh
from fishsim.solid.config import PDOptions, SolidMaterial
from fishsim.solid.fem import FemQuantities, NewtonBand, fem_quantities
from fishsim.solid.muscles import MuscleLayout, station_muscles
from fishsim.solid.packed import PackBand


@dataclass
class SolverStats:
    """Solver diagnostics: the last forward step's L-BFGS iterations and residual per sample,
    the last adjoint's CG iterations and number of samples solved directly, and running totals."""

    forward_iterations: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    forward_residual: np.ndarray = field(default_factory=lambda: np.zeros(0))
    backward_iterations: int = 0
    backward_direct: int = 0
    forward_steps: int = 0
    forward_iterations_total: int = 0
    backward_steps: int = 0
    backward_iterations_total: int = 0
    backward_direct_total: int = 0

    def record_forward(self, iterations: np.ndarray, residual: np.ndarray) -> None:
        self.forward_iterations, self.forward_residual = iterations, residual
        self.forward_steps += 1
        self.forward_iterations_total += int(iterations.max())

    def record_backward(self, iterations: int, direct: int) -> None:
        self.backward_iterations, self.backward_direct = iterations, direct
        self.backward_steps += 1
        self.backward_iterations_total += iterations
        self.backward_direct_total += direct


@dataclass
class SolverCache:
    """What the PD solve carries from one step to the next. The caller that runs a sequence of
    steps holds it and passes it to each pd_step (the rollout holds one per episode); the model
    never changes. A fresh cache gives the same steps within the solver's tolerance (it only
    refactorises at its first step), so a result depends on the cache's history only there.

    lagged: the batch's lagged Newton factors (preconditioner.LaggedFactors; None: none yet).
    factors: (kind, E) -> factorisation of a fixed preconditioner (preconditioner.factor).
    stats: the steps' diagnostics (SolverStats).
    """

    lagged: object = None
    factors: dict = field(default_factory=dict)
    stats: SolverStats = field(default_factory=SolverStats)


# Spring constant of an anchored node, in units of E (SolidModel's anchors).
ANCHOR_STIFFNESS = 1e2


class SolidModel:
    """Mesh, material, time step and precomputed operators of the PD solid (read-only after
    construction; what the solve carries between steps is a SolverCache the caller holds).

    fem: FemQuantities of the mesh (fem.mass: the fish's own lumped masses).
    added_mass: [N] added_mass_ratio * fem.mass, extra nodal mass (kg per unit depth) of the
        integrator: the coupling's added-mass stabilisation (fishsim.coupling.added_mass).
    mass: [N] fem.mass + added_mass (+ the anchors' mass), the mass of the implicit-Euler step.
    muscle_layout: the MuscleLayout (muscles.py): the paper's stations of mesh.actuator by
        default, or a muscle layer (muscles.layer_muscles).
    muscles: [n_act] actuated element indices; muscle_of: [T] the inverse map (-1: passive).
    muscle_top_share: [n_act] share of each muscle on the top side (controller.py).
    mesh_triangles: [T, 3] node indices (int64, contiguous, for the compiled kernels).
    muscle_weight: [n_act] k_m area fraction (Pa m^2).  mass_h2: [N] mass_i / h^2; mass_diag [2N]
    the same per DOF 2i + a (the diagonal of M/h^2 in the Newton matrix).
    K0: [N, N] sparse, dA/dE.  K_muscle: [N, N] sparse.
    anchors: [k] nodes held in place (a clamp, for validation cases such as a cantilever): each
        gets an extra mass ANCHOR_STIFFNESS E h^2 (kg per unit depth), so that its inertia
        m / h^2 acts as a spring of stiffness ANCHOR_STIFFNESS E (N/m per unit depth) towards
        its free flight; a force moves it ~1e-2 of what it moves a node held by elements alone
        (on the cantilever of fishsim/solid/beam.py the clamp's give changes the tip deflection
        by < 1e-3; stiffer anchors raise the force residual's round-off floor, ~1e-16
        ANCHOR_STIFFNESS E |q|, above the tolerances the validation needs).
    """

    def __init__(self, mesh: FishMesh, material: SolidMaterial = SolidMaterial(),
                 h: float = 0.01, options: PDOptions = PDOptions(),
                 added_mass_ratio: float = 0.0, muscles: MuscleLayout | None = None,
                 anchors: np.ndarray | None = None):
        if not h > 0:
            raise ConfigError(f"time step h must be positive, got {h}")
        self.mesh, self.material, self.h, self.options = mesh, material, float(h), options
        self.fem: FemQuantities = fem_quantities(mesh, material.density)
        self.muscle_layout = station_muscles(mesh) if muscles is None else muscles
        self.muscles = np.asarray(self.muscle_layout.elements, np.int64)
        self.muscle_top_share = np.asarray(self.muscle_layout.top_share, np.float64)
        self.muscle_weight = material.muscle_stiffness * self.fem.area[self.muscles] * self.muscle_layout.fraction
        self.muscle_of = np.full(self.fem.n_elements, -1, np.int64)      # element -> muscle index
        self.muscle_of[self.muscles] = np.arange(len(self.muscles))
        self.mesh_triangles = np.ascontiguousarray(mesh.triangles, np.int64)
        if not added_mass_ratio >= 0:
            raise ConfigError(f"added_mass_ratio must be >= 0, got {added_mass_ratio}")
        self.added_mass = added_mass_ratio * self.fem.mass
        self.anchors = np.zeros(0, np.int64) if anchors is None else np.unique(np.asarray(anchors, np.int64))
        anchor_mass = np.zeros_like(self.fem.mass)
        anchor_mass[self.anchors] = ANCHOR_STIFFNESS * material.youngs_modulus * self.h**2
        self.mass = self.fem.mass + self.added_mass + anchor_mass
        self.mass_h2 = self.mass / self.h**2
        self.mass_diag = np.repeat(self.mass_h2, 2)
        self.K0, self.K_muscle = self._stiffness_parts()

    @property
    def n_nodes(self) -> int:
        return self.fem.n_nodes

    @functools.cached_property
    def newton_band(self) -> NewtonBand:
        """Band layout of the [2N, 2N] Newton matrices (built on first use)."""
        return NewtonBand.of(self.fem.pattern)

    @functools.cached_property
    def pack_band(self) -> PackBand:
        """The Newton band of the compiled solver's packs (packed.py; built on first use)."""
        return PackBand(self.newton_band, self.mass_diag)

    @property
    def n_muscles(self) -> int:
        return len(self.muscles)

    def _stiffness_parts(self) -> tuple[sp.csc_matrix, sp.csc_matrix]:
        G, area, T = self.fem.G, self.fem.area, self.fem.n_elements
        per_E = np.tile(area * (self.material.corotated_per_E + self.material.volume_per_E), 2)
        muscle_rows = np.zeros(2 * T)
        muscle_rows[self.muscles] = self.muscle_weight            # fiber rows j = 0
        K0 = (G.T @ sp.diags(per_E) @ G).tocsc()
        K_muscle = (G.T @ sp.diags(muscle_rows) @ G).tocsc()
        return K0, K_muscle

"""A passive validation of the solid: a slender cantilever of the fish's material against
Euler-Bernoulli beam theory (static tip deflection and first bending frequency).

The beam: length l along X, thickness t along Y (|Y| <= t/2), clamped at X = 0 (the nodes there
are SolidModel anchors), triangulated by the fish's own mesher (Triangle, quality triangles of
a target edge). 2D quantities are per unit depth: I = t^3 / 12, A = t.

Which 2D Young's modulus. The solid's energies are per unit area of the plane: co-rotated
w/2 ||F - R||^2 with w = 2 mu_s area, which for small strain is mu_s eps : eps, i.e. in-plane
linear elasticity with Lame constants (lambda', mu') = (0, mu_s); with the optional volume term
lambda_s/2 ||F - D||^2 ~ lambda_s/4 (tr eps)^2, i.e. lambda' = lambda_s / 2. A beam bends under
uniaxial stress sigma_xx, with sigma_yy = 0 at its free faces, so its modulus is the in-plane
uniaxial one, E' = 4 mu' (lambda' + mu') / (lambda' + 2 mu'):
- default (no volume term): lambda' = 0, E' = 2 mu_s = E / (1 + nu) = 413.8 kPa for the fish's
  E = 6e5 Pa, nu = 0.45, and the in-plane Poisson ratio is 0. Plane stress (E) and plane strain
  (E / (1 - nu^2)) do not apply as such: they are what a 3D material with (E, nu) gives, while
  this 2D energy has no lambda term at all (docs/physics.md section 3: the volume term is optional);
  with lambda' = 0 the plane-stress and plane-strain reductions coincide at E' = 2 mu'.
- with the volume term: E' = 700.3 kPa (between plane stress 600 and plane strain 752.4 kPa).

Euler-Bernoulli: tip deflection under a tip load P (N per unit depth) delta = P l^3 / (3 E' I);
first bending frequency f_1 = (beta_1^2 / 2 pi) sqrt(E' I / (rho_s A l^4)), beta_1 = 1.8751.
Both neglect shear and rotary inertia; Timoshenko's shear term adds P l / (kappa mu' A) to delta,
0.6 (t / l)^2 of it for lambda' = 0 (0.15 % at l / t = 20).

The static case is one implicit-Euler PD step with a long time step (h = 100 s: the inertia
term M / h^2 is ~1e-14 of the stiffness, so the step is the static equilibrium); the dynamic
case releases the statically deflected beam (mostly the first mode) and times the tip's zero
crossings. Implicit Euler turns a mode of angular frequency w into z = 1 / (1 - i w h) per step:
its zero crossings are exactly pi / arg(z) steps apart and arg(z) = atan(w h), so
w = tan(theta) / h with theta the measured phase per step removes the integrator's (known)
period error exactly; its damping does not move the crossings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from fishsim.mesh.fish_mesh import ACTUATOR_NONE, FishMesh
from fishsim.mesh.triangulate import check_mesh, surface_polyline, triangulate_outline
from fishsim.solid.config import PDOptions, SolidMaterial
from fishsim.solid.model import SolidModel, SolverCache
from fishsim.solid.step import pd_step, rest_state

BETA_1 = 1.8751040687119611          # first root of cos(b) cosh(b) = -1
STATIC_H = 100.0                     # s: the "time step" of the static solve


def rectangle_mesh(length: float, thickness: float, edge_length: float, min_angle: float = 30.0) -> FishMesh:
    """Quality triangles of the rectangle [0, length] x [-thickness/2, thickness/2] (m), with
    boundary points every <= edge_length; no muscles. `length` is stored as the mesh length."""
    nx = max(math.ceil(length / edge_length), 1)
    ny = max(math.ceil(thickness / edge_length), 1)
    x, y = np.linspace(0.0, length, nx + 1), np.linspace(-thickness / 2, thickness / 2, ny + 1)
    ccw = np.concatenate([np.stack([x[:-1], np.full(nx, y[0])], 1),           # bottom, left -> right
                          np.stack([np.full(ny, x[-1]), y[:-1]], 1),          # right end, up
                          np.stack([x[::-1][:-1], np.full(nx, y[-1])], 1),    # top, right -> left
                          np.stack([np.full(ny, x[0]), y[::-1][:-1]], 1)])    # left end, down
    points, triangles = triangulate_outline(ccw, edge_length, min_angle)
    mesh = FishMesh(points, triangles, surface_polyline(points, triangles),
                    np.full(len(triangles), ACTUATOR_NONE, np.int8), float(length))
    check_mesh(mesh)
    return mesh


def plane_modulus(material: SolidMaterial) -> float:
    """E' (Pa): the solid's uniaxial in-plane modulus (module docstring), 2 mu' (lambda' + mu') /
    (lambda' + 2 mu') * 2 with mu' = mu_s and lambda' = lambda_s / 2 if the volume term is on, else 0."""
    E, nu = material.youngs_modulus, material.poisson_ratio
    mu = E / (2 * (1 + nu))
    lam = E * nu / ((1 + nu) * (1 - 2 * nu)) / 2 if material.volume_term else 0.0
    return 4 * mu * (lam + mu) / (lam + 2 * mu)


@dataclass(frozen=True)
class Cantilever:
    """A clamped beam: length l (m), thickness t (m), material; see the module docstring."""

    length: float = 0.1
    thickness: float = 0.005
    material: SolidMaterial = field(default_factory=SolidMaterial)

    @property
    def bending_stiffness(self) -> float:
        """E' I per unit depth (N m^2 / m)."""
        return plane_modulus(self.material) * self.thickness**3 / 12

    def tip_deflection(self, load: float) -> float:
        """Euler-Bernoulli tip deflection (m) under a tip load (N per unit depth)."""
        return load * self.length**3 / (3 * self.bending_stiffness)

    def first_frequency(self) -> float:
        """Euler-Bernoulli first bending frequency f_1 (Hz)."""
        rho_a = self.material.density * self.thickness
        return BETA_1**2 / (2 * math.pi) * math.sqrt(self.bending_stiffness / (rho_a * self.length**4))

    def mesh(self, edge_length: float) -> FishMesh:
        return rectangle_mesh(self.length, self.thickness, edge_length)

    def model(self, mesh: FishMesh, h: float, atol: float = 2e-6) -> SolidModel:
        """The solid with the X = 0 nodes anchored (clamped); atol in N per unit depth (2e-6:
        1.5e-4 of the load of a 1 mm tip deflection; a slender beam's Newton matrix is too badly
        conditioned for the banded solves to reach much less)."""
        clamp = np.flatnonzero(mesh.points[:, 0] <= 1e-9 * self.length)
        return SolidModel(mesh, self.material, h=h, options=PDOptions(atol=atol, max_iter=500), anchors=clamp)

    def tip_load(self, mesh: FishMesh, load: float) -> torch.Tensor:
        """Nodal forces [1, N, 2]: `load` (N per unit depth, +Y) on the X = l end, shared by its
        nodes in proportion to their tributary length on the end face."""
        tip = np.flatnonzero(mesh.points[:, 0] >= self.length * (1 - 1e-9))
        order = tip[np.argsort(mesh.points[tip, 1])]
        y = mesh.points[order, 1]
        share = np.zeros(len(y))
        share[:-1] += np.diff(y) / 2
        share[1:] += np.diff(y) / 2
        f = np.zeros((1, mesh.n_nodes, 2))
        f[0, order, 1] = load * share / share.sum()
        return torch.as_tensor(f)

    def _tip_nodes(self, mesh: FishMesh) -> np.ndarray:
        return np.flatnonzero(mesh.points[:, 0] >= self.length * (1 - 1e-9))

    def static_deflection(self, edge_length: float, load: float) -> tuple[float, torch.Tensor]:
        """(mean Y displacement of the end nodes (m), the deflected q [1, N, 2]) of the simulated
        beam under a tip load, from one long implicit-Euler step (module docstring)."""
        mesh = self.mesh(edge_length)
        model = self.model(mesh, STATIC_H)
        q0, qdot0 = rest_state(model)
        with torch.no_grad():
            q, _ = pd_step(model, q0, qdot0, torch.zeros(1, 0), self.tip_load(mesh, load))
        tip = self._tip_nodes(mesh)
        return float((q[0, tip, 1] - q0[0, tip, 1]).mean()), q

    def vibration_frequency(self, edge_length: float, load: float, h: float = 2e-3,
                            periods: float = 2.5) -> float:
        """First bending frequency (Hz) of the simulated beam: released at rest from its static
        deflection under a tip load, stepped by `h` for `periods` Euler-Bernoulli periods; the
        tip's zero crossings (after the first) give the phase per step, corrected for implicit
        Euler (module docstring)."""
        _, q = self.static_deflection(edge_length, load)
        mesh = self.mesh(edge_length)
        model = self.model(mesh, h)
        tip = self._tip_nodes(mesh)
        rest = torch.as_tensor(mesh.points)
        qdot, cache = torch.zeros_like(q), SolverCache()
        ys = [float((q[0, tip, 1] - rest[tip, 1]).mean())]
        steps = math.ceil(periods / (self.first_frequency() * h))
        with torch.no_grad():
            for _ in range(steps):
                q, qdot = pd_step(model, q, qdot, torch.zeros(1, 0), cache=cache)
                ys.append(float((q[0, tip, 1] - rest[tip, 1]).mean()))
        ys = np.array(ys)
        k = np.flatnonzero(np.sign(ys[1:]) != np.sign(ys[:-1]))
        crossings = k + ys[k] / (ys[k] - ys[k + 1])                 # fractional step of each crossing
        if len(crossings) < 3:
            raise RuntimeError("too few zero crossings to time the vibration; raise `periods`")
        steps_per_half = float(np.mean(np.diff(crossings[1:])))
        theta = math.pi / steps_per_half                              # phase per step, arg z
        return math.tan(theta) / h / (2 * math.pi)

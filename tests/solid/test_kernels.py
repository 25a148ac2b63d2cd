"""The compiled forward objective (packed.objective) and adjoint parameter gradients against the
numpy local step they fuse."""

import numpy as np
import pytest

from fishsim.solid import SolidMaterial, SolidModel, elastic
from fishsim.solid.solve import Objective
from fishsim.solid.step import parameter_gradients


def _deformed_batch(model, rng, angles):
    """[B, N, 2] positions: the rest shape rotated by each angle, plus per-node noise."""
    pts = model.mesh.points
    shapes = []
    for t in angles:
        R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        shapes.append(pts @ R.T * 1.02 + 2e-3 * rng.standard_normal(pts.shape))
    return np.stack(shapes)


def test_fused_objective_equals_numpy_local_step(coarse_mesh):
    """Phi and grad Phi agree to round-off for a batch with different rotations, contractions
    and Young's moduli (muscles stretched and compressed)."""
    model = SolidModel(coarse_mesh)
    rng = np.random.default_rng(0)
    X = _deformed_batch(model, rng, (0.1, 2.0, -1.0))
    Y = X + 1e-3 * rng.standard_normal(X.shape)
    contraction = rng.uniform(0.0, 0.4, (model.n_muscles, 3))
    objective = Objective(model, Y, contraction, np.array([6e5, 2e5, 1.5e6]))
    assert objective.fused
    phi, g = objective(X)
    objective.fused = False
    phi_ref, g_ref = objective(X)
    np.testing.assert_allclose(phi, phi_ref, rtol=1e-12)
    np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-12 * np.abs(g_ref).max())


def test_fused_objective_with_the_volume_term_equals_numpy_local_step(coarse_mesh):
    """The compiled volume term (element.volume_stress: the closest det-1 matrix by a lane-wise
    safeguarded Newton) gives the numpy energies.volume_projection's Phi and grad Phi."""
    model = SolidModel(coarse_mesh, SolidMaterial(volume_term=True))
    rng = np.random.default_rng(3)
    X = _deformed_batch(model, rng, (0.4, -1.3))
    X[1, :, 1] *= 0.8                                    # squash sample 1: det F well below 1
    Y = X + 1e-3 * rng.standard_normal(X.shape)
    objective = Objective(model, Y, rng.uniform(0.0, 0.4, (model.n_muscles, 2)), np.array([6e5, 1.5e6]))
    phi, g = objective(X)
    objective.fused = False
    phi_ref, g_ref = objective(X)
    np.testing.assert_allclose(phi, phi_ref, rtol=1e-12)
    np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-11 * np.abs(g_ref).max())


@pytest.mark.parametrize("B", [1, 2])
def test_fused_objective_of_the_rest_shape_is_pure_muscle(coarse_mesh, B):
    """At the rest shape with y = X, only contracting muscles store energy: Phi = sum_m w_m/2 u_m^2."""
    model = SolidModel(coarse_mesh)
    X = np.repeat(model.mesh.points[None], B, axis=0)
    u = np.full((model.n_muscles, B), 0.2)
    phi, _ = Objective(model, X, u, np.full(B, 6e5))(X)
    np.testing.assert_allclose(phi, (model.muscle_weight / 2 * 0.2**2).sum(), rtol=1e-12)


@pytest.mark.parametrize("volume_term", [False, True])
def test_compiled_parameter_gradients_equal_the_numpy_formulas(coarse_mesh, volume_term):
    """kernels.parameter_gradients (step.parameter_gradients), with and without the volume term, equals
    -lambda^T d(grad Phi)/d(u, E) from the projections: dS/du = w n on the fiber column,
    dS/dE = elastic.stress_per_E."""
    model = SolidModel(coarse_mesh, SolidMaterial(volume_term=volume_term))
    rng = np.random.default_rng(8)
    B = 3
    X = np.repeat(model.mesh.points[None], B, axis=0) * [0.97, 1.0] + 1e-4 * rng.standard_normal((B, model.n_nodes, 2))
    lam = rng.standard_normal(X.shape)
    contraction, E = rng.uniform(0, 0.3, (model.n_muscles, B)), np.array([3e5, 6e5, 9e5])
    grad_u, grad_E = parameter_gradients(model, X, contraction, E, lam)
    p = elastic.projections_at(model, X, contraction, E)
    dZ = elastic.deformation_gradients(model, elastic.to_columns(lam))
    dS0, dS1 = elastic.fiber_stress_per_contraction(p)
    np.testing.assert_allclose(grad_u, -(dZ[0, model.muscles, 0] * dS0 + dZ[0, model.muscles, 1] * dS1).T,
                               rtol=1e-10, atol=1e-12 * np.abs(grad_u).max())
    np.testing.assert_allclose(grad_E, -(dZ * elastic.stress_per_E(model, p)).sum(axis=(0, 1, 2)), rtol=1e-10)

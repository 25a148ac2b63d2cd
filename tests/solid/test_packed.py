"""The lane-packed solver (packed.py: eight samples in the lanes of one SIMD vector) computes what
the per-sample kernels compute: its vector operations, its Newton factors and solves (with a
lane whose exact Newton matrix is indefinite), its whole forward solve, a blown-up lane."""

import numba
import numpy as np
import pytest
import torch

from fishsim.solid import PDOptions, SolidModel, SolverCache, elastic, kernels, packed, pd_step, rest_state
from fishsim.solid.muscles import layer_muscles
from fishsim.solid.preconditioner import newton_factors
from fishsim.solid.simd import LANES, fma, isnan, lane, splat, vabs, vload, vmax, vsqrt, vstore, where
from fishsim.solid.solve import (
    Objective,
    _remove_net_residual,
    _solve_compiled,
    _solve_packed,
    from_packs,
    max_nodal_norm,
    pack_arrays,
    packs_of,
    pd_solve,
    to_packs,
)


@numba.njit
def _vector_expression(a, b, out) -> float:
    for o in range(0, a.size, LANES):
        x, y = vload(a, o), vload(b, o)
        z = where(x > y, fma(x, y, 1.0) - x / y, vsqrt(vabs(-y)) * 2.0)
        z += vmax(x, 0.25) - y / 3.0 + isnan(x / (x - x))
        vstore(out, o, z)
    return lane(splat(3.0) <= vload(a, 0), 2)


def test_vector_operations_match_numpy():
    rng = np.random.default_rng(0)
    a, b, out = rng.random((50, LANES)), rng.random((50, LANES)), np.empty((50, LANES))
    a[0, 3] = 0.0                                              # 0 / 0 in one lane
    third_lane = _vector_expression(a, b, out)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(a > b, a * b + 1.0 - a / b, np.sqrt(b) * 2.0)
        z += np.maximum(a, 0.25) - b / 3.0 + np.isnan(a / (a - a))
    np.testing.assert_allclose(out, z, rtol=1e-14)
    assert third_lane == float(3.0 <= a[0, 2])


def _batch(model: SolidModel, B: int, seed: int):
    """B perturbed fish, the third squashed to half its length (exact Newton matrix indefinite)."""
    rng = np.random.default_rng(seed)
    X0 = np.repeat(model.mesh.points[None], B, axis=0) + 1e-4 * rng.standard_normal((B, model.n_nodes, 2))
    X0[2] *= [0.5, 1.0]
    Y = X0 + 2e-4 * rng.standard_normal(X0.shape)
    contraction, E = rng.uniform(0, 0.3, (model.n_muscles, B)), rng.uniform(3e5, 9e5, B)
    return X0, Y, contraction, E


def test_packed_newton_solves_equal_the_per_sample_kernels(coarse_mesh):
    """newton_solve_packs (assembly from X, left-looking tiled factor, solve) against
    kernels.newton_factors + solve_samples for 11 samples in 2 packs (the second padded): the
    same solutions, and the same lanes flagged indefinite (the squashed sample and others)."""
    model = SolidModel(coarse_mesh)
    B = 11
    X0, _, contraction, E = _batch(model, B, seed=5)
    b = np.random.default_rng(6).standard_normal(X0.shape)
    p = elastic.project(model, elastic.deformation_gradients(model, elastic.to_columns(X0)), contraction, E)
    L = model.newton_band.empty(B)
    ok_ref = newton_factors(model, p, np.arange(B), L)
    x_ref = np.zeros_like(b)
    layout = model.newton_band.layout
    kernels.solve_samples(L, layout.perm, layout.inverse, b, np.flatnonzero(ok_ref), x_ref)

    lanes, band = packs_of(np.arange(B)), model.pack_band
    arrays = pack_arrays(Objective(model, X0, contraction, E).kernel_arrays, lanes)
    Z, ok = np.empty((2, *b.shape[1:], LANES)), np.zeros(lanes.shape, bool)
    packed.newton_solve_packs(to_packs(X0, lanes), to_packs(b, lanes), arrays, band.arrays, band.empty(2), Z, ok)
    x = np.zeros_like(b)
    from_packs(Z, lanes, x)
    ok_packed = np.zeros(B, bool)
    ok_packed[lanes[ok]] = True
    assert ok_packed.tolist() == ok_ref.tolist() and 0 < ok_ref.sum() < B and not ok_ref[2]
    np.testing.assert_allclose(x[ok_ref], x_ref[ok_ref], rtol=0, atol=1e-10 * np.abs(x_ref).max())


def test_packed_forward_equals_the_per_sample_compiled_path(coarse_mesh):
    """_solve_packed (8 lanes in lock step) takes each sample's steps of _solve_compiled with a
    fresh Newton factor at the start (both: exact, else projected for the squashed sample): the
    same iterations (+-1 for round-off at the stopping test) and q+, for 6 samples in one padded
    pack with different E and contractions."""
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    model = SolidModel(coarse_mesh)
    B = 6
    X0, Y, contraction, E = _batch(model, B, seed=3)
    objective = Objective(model, Y, contraction, E)
    _, g0 = objective(X0.copy())
    need = np.ones(B, bool)
    results = []
    for solve in (_solve_packed, lambda *args: _solve_compiled(objective, SolverCache(), X0, *args[1:])):
        X, g, iterations = X0.copy(), g0.copy(), np.zeros(B, np.int64)
        solve(objective, X, g, need, iterations)
        results.append((_remove_net_residual(model, X, g)[0], iterations, max_nodal_norm(g)))
    (X, iterations, residual), (X_ref, iterations_ref, residual_ref) = results
    assert (residual <= model.options.atol).all() and (residual_ref <= model.options.atol).all()
    assert (iterations > 2).all() and np.abs(iterations - iterations_ref).max() <= 1
    np.testing.assert_allclose(X, X_ref, rtol=0, atol=1e-7)


def test_packed_forward_stops_a_blown_up_lane(coarse_mesh):
    """A sample whose target y is not finite stops after its first iteration (NaN residual) and is
    reported unconverged, with a warning; its pack's other lanes converge as usual."""
    model = SolidModel(coarse_mesh)
    B = 5
    X0, Y, contraction, E = _batch(model, B, seed=4)
    X0[2], Y[2] = X0[0], Y[0]                                     # no squashed sample here
    Y[1, 3, 0] = np.inf
    with pytest.warns(RuntimeWarning, match="did not converge"):
        _, info = pd_solve(model, Y, X0, contraction, E, SolverCache())
    assert info.converged.tolist() == [True, False, True, True, True] and info.iterations[1] <= 1


@pytest.mark.parametrize("muscles", ["paper", "layer"])
def test_packed_batch_step_equals_per_sample_steps(coarse_mesh, muscles):
    """pd_step on 6 samples (one padded pack, forward and adjoint) against each sample alone (the
    per-sample path): the same q+, qdot+ and gradients of a loss w.r.t. q, qdot, activation,
    f_ext and E, to the tight solver tolerance; with the paper's station muscles and with the
    muscle layer (per-element weights from partial area fractions, elements of both sides)."""
    layout = layer_muscles(coarse_mesh, 0.3) if muscles == "layer" else None
    model = SolidModel(coarse_mesh, options=PDOptions(atol=1e-8, backward_rtol=1e-12), muscles=layout)
    g = torch.Generator().manual_seed(5)
    B = 6
    q, qdot = rest_state(model, B)
    qdot = qdot + 0.02 * torch.randn(qdot.shape, generator=g)
    u = 0.2 * torch.rand((B, model.n_muscles), generator=g)
    f = 1e-3 * torch.randn(q.shape, generator=g)
    E = torch.tensor([6e5, 3e5, 6e5, 9e5, 4e5, 7e5])
    weights = torch.randn((B, model.n_nodes, 2), generator=g)

    def outputs(sl):
        inputs = [x[sl].clone().requires_grad_() for x in (q, qdot, u, f, E)]
        q_next, qdot_next = pd_step(model, *inputs)
        loss = (weights[sl] * q_next).sum() + 0.1 * (weights[sl] * qdot_next).sum()
        return [q_next.detach(), qdot_next.detach(), *torch.autograd.grad(loss, inputs)]

    batch = outputs(slice(None))
    for b in range(B):
        for x, y in zip(batch, outputs(slice(b, b + 1))):
            torch.testing.assert_close(x[b:b + 1], y, atol=1e-9 * max(1.0, y.abs().max().item()), rtol=1e-6)

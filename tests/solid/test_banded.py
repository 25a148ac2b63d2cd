"""The banded Cholesky of the solid's SPD matrices solves to round-off, an indefinite matrix falls
back to SuperLU, and the compiled forward solve takes the numpy iteration's steps."""

import numba
import numpy as np
import pytest
import scipy.sparse as sp

from fishsim.linalg.banded import BandedCholesky, factor, solve, spd_factor
from fishsim.mesh import make_fish_mesh
from fishsim.solid import SolidModel, SolverCache, elastic
from fishsim.solid.preconditioner import LaggedNewton, pd_matrix, rest_newton_matrix
from fishsim.solid.solve import Objective, _lbfgs, _remove_net_residual, balanced_order, pd_solve


def test_banded_cholesky_solves_the_fish_matrices():
    model = SolidModel(make_fish_mesh(edge_length=4e-3))
    rng = np.random.default_rng(0)
    for K in (rest_newton_matrix(model, 6e5), pd_matrix(model, 6e5)):
        solver = spd_factor(K)
        assert isinstance(solver, BandedCholesky)
        b = rng.standard_normal((K.shape[0], 3))
        x = solver.solve(b)
        assert np.abs(K @ x - b).max() < 1e-10 * np.abs(b).max()
        np.testing.assert_allclose(solver.solve(b[:, 0]), x[:, 0], rtol=1e-12, atol=0)


def test_indefinite_matrix_falls_back_to_lu():
    K = sp.diags([2.0, -1.0, 3.0]).tocsc()
    solver = spd_factor(K)
    assert not isinstance(solver, BandedCholesky)
    np.testing.assert_allclose(solver.solve(np.array([2.0, 1.0, 3.0])), [1.0, -1.0, 1.0])


def test_band_kernels_match_dense_cholesky():
    """factor / solve (one matrix, width 1) on a random SPD band whose size is not a multiple of
    the factor's 4-row blocks equal numpy's dense Cholesky (the factor keeps 1 / L_jj on its
    diagonal); a matrix that is not positive definite is reported, not factorised."""
    rng = np.random.default_rng(1)
    n, w = 61, 5
    K = np.zeros((n, n))
    for i in range(1, w + 1):
        off = rng.standard_normal(n - i)
        K += np.diag(off, -i) + np.diag(off, i)
    K += np.diag(np.abs(K).sum(1) + 1.0)                       # diagonally dominant: SPD
    rows = -(-n // 4) * 4
    L = np.zeros((rows, w + 4))
    for j in range(n):
        for i in range(min(w, n - 1 - j) + 1):
            L[j, i] = K[j + i, j]
    L[n:, 0] = 1.0
    assert factor(L, w, 0.0) == 1.0
    C = np.linalg.cholesky(K)
    expected = [[(1 / C[j, j] if i == 0 else C[j + i, j]) if j + i < n else 0.0 for i in range(w + 1)] for j in range(n)]
    np.testing.assert_allclose(L[:n, :w + 1], expected, rtol=0, atol=1e-13 * np.abs(C).max())
    b = rng.standard_normal(n)
    x = np.empty(n)
    identity = np.arange(n)
    solve(L, w, identity, identity, b, x, np.empty(n), 0.0)
    np.testing.assert_allclose(K @ x, b, rtol=0, atol=1e-12 * np.abs(b).max())
    L_bad = np.zeros_like(L)
    L_bad[:, 0] = 1.0
    L_bad[n // 2, 0] = -1.0
    assert factor(L_bad, w, 0.0) == 0.0


def test_compiled_forward_equals_the_numpy_iteration(coarse_mesh):
    """solve.pd_solve's compiled path (factor and whole L-BFGS per sample, packed.lbfgs at width 1)
    takes the numpy iteration's steps (solve._lbfgs with the same lagged Newton H0): the same
    iteration counts (+-1 for round-off at the stopping test) and q+, for a batch with a compressed
    sample whose exact Newton matrix is indefinite (projected factor inside the kernel)."""
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    model = SolidModel(coarse_mesh)
    rng = np.random.default_rng(3)
    B = 3
    X0 = np.repeat(model.mesh.points[None], B, axis=0) + 1e-4 * rng.standard_normal((B, model.n_nodes, 2))
    X0[2] *= [0.5, 1.0]
    Y = X0 + 2e-4 * rng.standard_normal(X0.shape)
    contraction, E = rng.uniform(0, 0.3, (model.n_muscles, B)), np.array([6e5, 3e5, 6e5])
    p = elastic.project(model, elastic.deformation_gradients(model, elastic.to_columns(X0)), contraction, E)
    assert np.linalg.eigvalsh(elastic.newton_matrix(model, p, 2).toarray()).min() < 0     # indefinite
    cache = SolverCache()
    X, info = pd_solve(model, Y, X0, contraction, E, cache)
    assert info.converged.all() and (info.iterations > 2).all() and cache.lagged.banded.all()

    objective = Objective(model, Y, contraction, E)
    phi, g = objective(X0.copy())
    iterations = np.zeros(B, np.int64)
    X_ref, g_ref = _lbfgs(objective, LaggedNewton(model, SolverCache(), X0, contraction, E), X0.copy(), phi, g,
                          np.ones(B, bool), iterations)
    X_ref, _ = _remove_net_residual(model, X_ref, g_ref)
    # the dot products' summation order differs (compiled loop vs numpy): round-off may decide
    # one stopping test differently (seen: 48 vs 49 iterations, q+ 2.4e-9 m apart; the rest
    # agree to 1e-16 m). Both meet atol; atol / min(m/h^2) = 5e-5 m is the residual's scale.
    assert np.abs(info.iterations - iterations).max() <= 1
    np.testing.assert_allclose(X, X_ref, rtol=0, atol=1e-7)


def test_balanced_order_gives_each_thread_a_similar_cost():
    """numba's static schedule cuts the sample list into equal contiguous chunks; the order
    deals costly samples alternately so every chunk's total is close (here exactly equal)."""
    samples = np.arange(10, 26)
    cost = np.repeat([1, 3], 8)                         # the costly ones last, as in a sorted sweep
    order = balanced_order(samples, cost, 2)
    assert sorted(order) == list(samples)
    chunks = cost[order - 10].reshape(2, 8).sum(1)
    assert chunks[0] == chunks[1] == 16
    assert sorted(balanced_order(samples[:3], cost[:3], 4)) == list(samples[:3])   # more threads than samples


def test_compiled_forward_stops_a_blown_up_sample(coarse_mesh):
    """A sample whose target y is not finite stops after its first iteration (NaN residual) and is
    reported unconverged, with a warning; the batch's other sample converges as usual."""
    model = SolidModel(coarse_mesh)
    rng = np.random.default_rng(4)
    X0 = np.repeat(model.mesh.points[None], 2, axis=0) + 1e-4 * rng.standard_normal((2, model.n_nodes, 2))
    Y = X0 + 1e-4 * rng.standard_normal(X0.shape)
    Y[1, 3, 0] = np.inf
    with pytest.warns(RuntimeWarning, match="did not converge"):
        _, info = pd_solve(model, Y, X0, np.zeros((model.n_muscles, 2)), np.full(2, 6e5), SolverCache())
    assert info.converged.tolist() == [True, False] and info.iterations[1] <= 1

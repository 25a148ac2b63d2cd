"""The compiled solver's kernels (packed.py), written once for packs of eight samples in the lanes
of one SIMD vector and for one sample in plain floats, compute the same at both widths: the
lane-generic operations, the Newton factors and solves (with a lane whose exact Newton matrix is
indefinite), the whole forward solve, a blown-up lane."""

import numba
import numpy as np
import pytest
import torch

from fishsim.linalg.simd import (
    LANES,
    absolute,
    fill,
    lane_value,
    lanes_set,
    load,
    mask,
    maximum,
    multiply_add,
    nan_mask,
    select,
    splat,
    sqrt,
    store,
    width,
)
from fishsim.solid import (
    PDOptions,
    SolidMaterial,
    SolidModel,
    SolverCache,
    elastic,
    packed,
    pd_step,
    rest_state,
)
from fishsim.solid.muscles import layer_muscles
from fishsim.solid.packed import kernel_arrays
from fishsim.solid.solve import Objective, from_packs, pack_arrays, packs_of, pd_solve, to_packs


@numba.njit
def _expression(a, b, out, proto) -> tuple:
    W = width(proto)
    for o in range(0, a.size, W):
        x, y = load(a, o, proto), load(b, o, proto)
        z = select(mask(x > y), multiply_add(x, y, 1.0) - x / y, sqrt(absolute(-y)) * 2.0)
        z += maximum(x, 0.25) - y / 3.0 + nan_mask(x / select(mask(x <= 0.0), np.nan, x))
        store(out, o, z)
    first = mask(fill(proto, 3.0) <= load(a, 0, proto))
    return lane_value(first, W - 1), lanes_set(first)


@numba.njit
def _wide(a, b, out):
    return _expression(a, b, out, splat(0.0))


@numba.njit
def _narrow(a, b, out):
    return _expression(a, b, out, 0.0)


def test_lane_generic_operations_match_numpy_at_both_widths():
    rng = np.random.default_rng(0)
    a, b = rng.random((50, LANES)), rng.random((50, LANES))
    a[0, 3] = 0.0                                              # a NaN in one lane
    a[0, -1] = 3.5
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(a > b, a * b + 1.0 - a / b, np.sqrt(b) * 2.0)
        z += np.maximum(a, 0.25) - b / 3.0 + (a <= 0.0)
    out = np.empty_like(a)
    assert _wide(a, b, out) == (1.0, float((3.0 <= a[0]).sum()))
    np.testing.assert_allclose(out, z, rtol=1e-14)
    out = np.empty(a.size)
    assert _narrow(a.ravel(), b.ravel(), out) == (0.0, 0.0)
    np.testing.assert_allclose(out, z.ravel(), rtol=1e-14)


def _batch(model: SolidModel, B: int, seed: int):
    """B perturbed fish, the third squashed to half its length (exact Newton matrix indefinite)."""
    rng = np.random.default_rng(seed)
    X0 = np.repeat(model.mesh.points[None], B, axis=0) + 1e-4 * rng.standard_normal((B, model.n_nodes, 2))
    X0[2] *= [0.5, 1.0]
    Y = X0 + 2e-4 * rng.standard_normal(X0.shape)
    contraction, E = rng.uniform(0, 0.3, (model.n_muscles, B)), rng.uniform(3e5, 9e5, B)
    return X0, Y, contraction, E


def _dense(model: SolidModel, L: np.ndarray) -> np.ndarray:
    """The symmetric [2N, 2N] matrix of one sample's band L [rows, w + 4] (before factorising)."""
    layout = model.newton_band.layout
    w = layout.width
    n = len(layout.perm)
    K = np.zeros((n, n))
    for i in range(w + 1):
        j = np.arange(n - i)
        K[layout.perm[j + i], layout.perm[j]] = K[layout.perm[j], layout.perm[j + i]] = L[j, i]
    return K


@pytest.mark.parametrize("volume_term", [False, True])
@pytest.mark.parametrize("projected", [0.0, 1.0])
def test_compiled_newton_band_equals_the_numpy_newton_matrix(coarse_mesh, projected, volume_term):
    """The compiled assembly of a sample's Newton matrix into its band (packed._newton_band at
    width 1) equals elastic.newton_matrix (numpy element Hessians), exact and projected, for a
    compressed sample, with and without DiffPD's volume term."""
    model = SolidModel(coarse_mesh, SolidMaterial(volume_term=volume_term))
    X0, _, contraction, E = _batch(model, 3, seed=1)
    arrays, band = kernel_arrays(model, contraction, E), model.pack_band
    p = elastic.projections_at(model, X0, contraction, E)
    slot, diagonal, diagonal_values = band.arrays[:3]
    for b in (0, 2):
        L = np.empty(band.shape(1, 1)[1:3])
        packed._newton_band(X0[b], arrays[1], arrays[2], arrays[3][b], arrays[4][b], arrays[5], arrays[6], arrays[7][b],
                            projected, slot, diagonal, diagonal_values, L, np.empty(16), 0.0)
        K = elastic.newton_matrix(model, p, b, projected=bool(projected)).toarray()
        np.testing.assert_allclose(_dense(model, L), K, rtol=0, atol=1e-12 * np.abs(K).max())


def test_factors_take_the_exact_newton_matrix_where_it_is_positive_definite(coarse_mesh):
    """packed.factor + packed.solve (width 1, in parallel over the samples) solve each sample's
    exact Newton matrix where it is positive definite and the projected one where it is not (the
    squashed sample); packed.newton_solve (the adjoint's, exact only) flags that sample."""
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    model = SolidModel(coarse_mesh)
    B = 3
    X0, _, contraction, E = _batch(model, B, seed=2)
    R = np.random.default_rng(2).standard_normal(X0.shape)
    arrays, band = kernel_arrays(model, contraction, E), model.pack_band
    L, ok, Z = band.empty(B, 1), np.zeros((B, 1)), np.zeros_like(R)
    packed.factor(X0, arrays, band.arrays, L, np.arange(B), ok)
    packed.solve(L, band.arrays, R, np.arange(B), Z)
    p = elastic.projections_at(model, X0, contraction, E)
    definite = [np.linalg.eigvalsh(elastic.newton_matrix(model, p, b).toarray()).min() > 0 for b in range(B)]
    assert not definite[2] and any(definite) and ok.all()
    for b in range(B):
        K = elastic.newton_matrix(model, p, b, projected=not definite[b])
        np.testing.assert_allclose(K @ Z[b].ravel(), R[b].ravel(), rtol=0, atol=1e-9 * np.abs(R[b]).max())
    ok_exact, Z_exact = np.zeros((B, 1)), np.zeros_like(R)
    packed.newton_solve(X0, R, arrays, band.arrays, band.empty(B, 1), np.arange(B), Z_exact, ok_exact)
    assert (ok_exact[:, 0] > 0).tolist() == definite
    np.testing.assert_allclose(Z_exact[definite], Z[definite], rtol=0, atol=1e-12 * np.abs(Z).max())


def test_packs_of_eight_equal_single_samples(coarse_mesh):
    """At width 8 (11 samples in 2 packs, the second padded) the kernels give what they give one
    sample at a time: the adjoint's direct solves with the same lanes flagged indefinite, and
    the whole forward solve from a fresh factor (the same q+, and the same iterations up to
    round-off at the stopping test: +-1, or up to 20 % in a lane whose residual lingers near the
    tolerance, as the squashed sample 0 does: 53 iterations alone, 62 in its pack on an AVX-512
    machine, q+ the same to 2e-12 m)."""
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    model = SolidModel(coarse_mesh)
    B = 11
    X0, Y, contraction, E = _batch(model, B, seed=5)
    R = np.random.default_rng(6).standard_normal(X0.shape)
    arrays, band, lanes = kernel_arrays(model, contraction, E), model.pack_band, packs_of(np.arange(B))
    wide = pack_arrays(arrays, lanes)
    x_ref, ok_ref = np.zeros_like(R), np.zeros((B, 1))
    packed.newton_solve(X0, R, arrays, band.arrays, band.empty(B, 1), np.arange(B), x_ref, ok_ref)
    Z, ok = np.empty((2, *R.shape[1:], LANES)), np.zeros(lanes.shape)
    packed.newton_solve(to_packs(X0, lanes), to_packs(R, lanes), wide, band.arrays, band.empty(2), np.arange(2), Z, ok)
    x = np.zeros_like(R)
    from_packs(Z, lanes, x)
    ok_wide = np.zeros(B)
    ok_wide[lanes[ok > 0]] = 1.0
    assert ok_wide.tolist() == ok_ref[:, 0].tolist() and ok_ref[2, 0] == 0.0
    good = ok_ref[:, 0] > 0
    np.testing.assert_allclose(x[good], x_ref[good], rtol=0, atol=1e-10 * np.abs(x_ref[good]).max())

    opts = model.options
    _, g = Objective(model, Y, contraction, E)(X0.copy())
    X1, g1, its1, ok1 = X0.copy(), g.copy(), np.zeros((B, 1)), np.zeros((B, 1))
    packed.lbfgs(X1, Y, arrays, band.arrays, np.zeros(band.shape(B, 1)), np.ones(B, bool),
                 np.arange(B), opts.atol, opts.max_iter, opts.history, g1, its1, ok1)
    Xp, gp = to_packs(X0, lanes), to_packs(g, lanes)
    its8, ok8 = np.zeros(lanes.shape), np.zeros(lanes.shape)
    packed.lbfgs(Xp, to_packs(Y, lanes), wide, band.arrays, band.empty(2), np.ones(2, bool), np.arange(2),
                 opts.atol, opts.max_iter, opts.history, gp, its8, ok8)
    X8, iterations8 = np.zeros_like(X0), np.zeros(B)
    from_packs(Xp, lanes, X8)
    iterations8[lanes] = its8
    assert ok1.all() and ok8.all() and (its1 > 2).all()
    assert (np.abs(iterations8 - its1[:, 0]) <= np.maximum(1, 0.2 * its1[:, 0])).all(), (iterations8, its1[:, 0])
    np.testing.assert_allclose(X8, X1, rtol=0, atol=1e-7)


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

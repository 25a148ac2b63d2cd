"""The compiled loops of the numerical fluid (fishsim.fluid.kernels: Predict, SplitStep) against the
torch formulas they replace on the CPU: values, vector-Jacobian products, central differences,
batch independence."""

import pytest
import torch

from fishsim import compiled
from fishsim.fields import Boundary, FluidParams, FluidState, Grid
from fishsim.fluid import kernels, numerical
from fishsim.fluid.grid import FREE_SLIP, NO_SLIP, WallBC, advection, laplacian_faces, zero_walls
from fishsim.fluid.kernels import Predict
from fishsim.fluid.numerical import NumericalFluid

WALLS = {"no-slip": NO_SLIP, "slip": FREE_SLIP, "moving": WallBC(u_bottom=-0.2, u_top=0.3, v_left=-0.1, v_right=0.4)}


def _field(B, H, W, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, 1, H, W + 1, generator=g, dtype=dtype),
            torch.randn(B, 1, H + 1, W, generator=g, dtype=dtype))


def _torch_predict(vx, vy, nu, dt, dx, walls):
    """numerical.predict's formula, written with grid's torch stencils."""
    adv = advection((vx, vy), dx, walls, "koren")
    lap = zero_walls(laplacian_faces((vx, vy), dx, walls))
    return tuple(c + dt * (nu * L - A) for c, A, L in zip((vx, vy), adv, lap))


def _vjp(fn, v, nu, dt, walls, weights):
    x = [c.clone().requires_grad_() for c in v]
    nu, dt = nu.clone().requires_grad_(), dt.clone().requires_grad_()
    w = fn(x[0], x[1], nu, dt, 0.1, walls)
    sum((g * c).sum() for g, c in zip(weights, w)).backward()
    return list(w) + [x[0].grad, x[1].grad, nu.grad, dt.grad]


@pytest.mark.parametrize("walls", WALLS.values(), ids=WALLS.keys())
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-13), (torch.float32, 3e-6)])
def test_kernel_matches_the_torch_formula_and_its_adjoint(walls, dtype, tol):
    """Random fields (every limiter branch, both upwind directions), 7 x 9 cells, two samples with
    their own nu and dt: outputs and d<weights, w>/d(v, nu, dt)."""
    v, weights = _field(2, 7, 9, dtype), _field(2, 7, 9, dtype, seed=1)
    nu = torch.tensor([0.3, 0.05], dtype=dtype).view(2, 1, 1, 1)
    dt = torch.tensor([0.01, 0.02], dtype=dtype).view(2, 1, 1, 1)
    got = _vjp(Predict.apply, v, nu, dt, walls, weights)
    want = _vjp(_torch_predict, v, nu, dt, walls, weights)
    for name, x, y in zip(["wx", "wy", "dvx", "dvy", "dnu", "ddt"], got, want):
        assert (x - y).abs().max() <= tol * y.abs().max(), name


def test_kernel_gradient_against_central_differences():
    """float64 gradcheck in v (limiter kinks are not met within the difference step)."""
    v = tuple(c.requires_grad_() for c in _field(1, 5, 6, torch.float64, seed=3))
    assert torch.autograd.gradcheck(lambda vx, vy: Predict.apply(vx, vy, 0.05, 0.01, 0.2, NO_SLIP), v,
                                    eps=1e-7, atol=1e-6, rtol=1e-5)


def test_a_sample_does_not_depend_on_its_batch():
    """The samples run in parallel: sample 2 of a batch of 5 equals the same field alone, bit for bit."""
    vx, vy = _field(5, 12, 20, torch.float32, seed=4)
    batch = Predict.apply(vx, vy, 1e-3, 0.01, 0.05, NO_SLIP)
    alone = Predict.apply(vx[2:3], vy[2:3], 1e-3, 0.01, 0.05, NO_SLIP)
    assert torch.equal(batch[0][2:3], alone[0]) and torch.equal(batch[1][2:3], alone[1])


def _step_outputs(stage, dtype, compiled, monkeypatch):
    """One step of a 6 x 8-cell fluid with the constraint stage ``stage`` (NumericalFluid's
    options), two samples (the second fast enough that the CFL bound gives
    it more sub-steps than the first), random state, mask and body velocity; returns (a', p', the
    penalisation density, d<weights, outputs>/d(a, mask, velocity, mu))."""
    monkeypatch.setattr(numerical, "COMPILED", compiled)
    g = torch.Generator().manual_seed(5)
    grid = Grid(6, 8, 0.1)
    a = torch.randn(2, 1, 7, 9, generator=g, dtype=dtype) * torch.tensor([0.01, 0.5], dtype=dtype).view(2, 1, 1, 1)
    mask = torch.rand(2, 1, 6, 8, generator=g, dtype=dtype)
    velocity = torch.randn(1, 2, 6, 8, generator=g, dtype=dtype).expand(2, -1, -1, -1)
    mu = torch.tensor([1e-2, 2e-2], dtype=dtype)
    x = [t.clone().requires_grad_() for t in (a, mask, velocity, mu)]
    model = NumericalFluid(grid, substeps=2, cfl=0.5, **stage)
    new, diag = model.step_with_diagnostics(FluidState(a=x[0], p=torch.zeros(2, 1, 6, 8, dtype=dtype)),
                                            Boundary(x[1], x[2]), FluidParams(torch.full((2,), 50.0, dtype=dtype), x[3]))
    assert diag.substeps.tolist()[0] < diag.substeps.tolist()[1]
    y = [new.a, new.p, *diag.penalty]
    weights = [torch.randn(c.shape, generator=torch.Generator().manual_seed(k), dtype=dtype) for k, c in enumerate(y)]
    sum((q * c).sum() for q, c in zip(weights, y)).backward()
    return [c.detach() for c in y] + [c.grad for c in x]


STAGES = {"1 pass": {"penalization_iterations": 1}, "3 passes": {"penalization_iterations": 3},
          "implicit": {"implicit": True}, "brinkman": {"brinkman": 3e3}}


@pytest.mark.parametrize("stage, dtype, tol", [
    *((s, dtype, tol) for s in STAGES for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 2e-5))
      if dtype == torch.float64 or "pass" in s)])
def test_split_step_matches_the_torch_loop_and_its_adjoint(stage, dtype, tol, monkeypatch):
    """kernels.SplitStep (the CPU's sub-steps in one compiled call) against the torch loop it
    replaces, with the split passes and with the joint solve (its PCG to 1e-6 in both, from the
    same starts): the step's outputs and their vector-Jacobian product w.r.t. the state, the mask,
    the body velocity and mu, with samples of different sub-step counts. The joint solve in float64
    only: on this random scene (a random mask, body velocity and wall flux) float32 runs of either
    path end up to 130 % from float64 runs of the same inputs (the fish's float32 joint solves:
    tests/fluid/test_numerical.py)."""
    stage = STAGES[stage]
    got, want = (_step_outputs(stage, dtype, c, monkeypatch) for c in (True, False))
    names = ["a", "p", "pen_x", "pen_y", "da", "dmask", "dvelocity", "dmu"]
    for name, x, y in zip(names, got, want):
        assert x.shape == y.shape and (x - y).abs().max() <= tol * y.abs().max(), name


def test_split_step_in_sample_chunks_equals_one_thread(monkeypatch):
    """With two torch threads SplitStep runs its two samples (of different sub-step counts) as two
    chunks in two Python threads (compiled.in_sample_chunks), forward and adjoint: the outputs
    and the vector-Jacobian product equal one thread's, bit for bit."""
    one = _step_outputs(STAGES["3 passes"], torch.float32, True, monkeypatch)
    chunks = []
    monkeypatch.setattr(kernels, "sample_chunks", lambda N: chunks.append(compiled.sample_chunks(N)) or chunks[-1])
    torch.set_num_threads(2)
    two = _step_outputs(STAGES["3 passes"], torch.float32, True, monkeypatch)
    assert chunks == [[slice(0, 1), slice(1, 2)]]
    for name, x, y in zip(["a", "p", "pen_x", "pen_y", "da", "dmask", "dvelocity", "dmu"], one, two):
        assert torch.equal(x, y), name


def test_the_compiled_step_checks_equal_the_torch_ones():
    """``face_speed`` (the sub-step count's speed) and ``fields.all_finite`` (the blow-up check) against
    the torch formulas they replace on the CPU, a mask broadcast over the batch, and a NaN and an
    infinity each caught."""
    from fishsim.fields import all_finite
    from fishsim.fluid.kernels import face_speed

    g = torch.Generator().manual_seed(5)
    v = (torch.randn(3, 1, 6, 9, generator=g), torch.randn(3, 1, 7, 8, generator=g))
    b = (torch.rand(1, 1, 6, 9, generator=g), torch.rand(1, 1, 7, 8, generator=g))
    v_d = (9 * torch.randn(3, 1, 6, 9, generator=g), torch.randn(3, 1, 7, 8, generator=g))
    want = torch.stack([torch.maximum(c.abs().amax(dim=(1, 2, 3)), (bc * vc).abs().amax(dim=(1, 2, 3)))
                        for c, bc, vc in zip(v, b, v_d)]).amax(0).double()
    assert torch.equal(face_speed(v, b, v_d), want) and all_finite(*v)
    v[1][1, 0, 2, 3] = float("nan")
    v_d[0][2, 0, 4, 1] = float("inf")
    speed = face_speed(v, b, v_d)
    assert speed[0] == want[0] and speed[1:].isnan().all()
    assert not all_finite(*v) and all_finite(v[0]) and not all_finite(v_d[0])

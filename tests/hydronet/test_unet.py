"""HydroNet network: architecture, FluidModel contract, bounds, mean removal, conditioning."""

import dataclasses
import shutil

import pytest
import torch

from fishsim.fields import Boundary, FluidModel, FluidParams, FluidState
from fishsim.fluid.grid import closed_tank
from fishsim.fluid.hydronet.config import NetConfig
from fishsim.fluid.hydronet.unet import (
    HydroNet,
    HydroNetFluid,
    UNet,
    inference_copy,
    mirrored,
    network_inputs,
    to_canvas,
)

from .conftest import paper_params


def _random_inputs(grid, batch=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    state = FluidState(1e-4 * torch.randn(batch, 1, grid.H + 1, grid.W + 1, generator=g),
                       torch.randn(batch, 1, grid.H, grid.W, generator=g))
    tank = closed_tank(grid, 2, 3, batch)
    boundary = Boundary(tank.mask, 0.1 * torch.randn(batch, 2, grid.H, grid.W, generator=g) * tank.mask)
    return state, boundary


def test_wandel_unet2_parameter_count():
    """Wandel's UNet2 with hidden size 20 has 1,691,322 parameters (13 inputs, 2 outputs)."""
    assert sum(p.numel() for p in UNet(13, 2, 20, 4).parameters()) == 1_691_322


@pytest.mark.parametrize("shape", [(16, 32), (17, 45), (100 // 4, 300 // 4)])
def test_unet_any_size(shape):
    """Fully convolutional: odd sizes come back at their own size."""
    x = torch.randn(1, 13, *shape)
    assert UNet(13, 2, 4, 4)(x).shape == (1, 2, *shape)


@pytest.mark.parametrize("frozen", [False, True])
@pytest.mark.parametrize("channels_last", [False, True])
def test_pointwise_conv_is_conv_in_order_and_keeps_the_gradient_layout(channels_last, frozen):
    """The 1x1 output convolution as ordered multiply-adds, trainable (torch ops) or frozen (the
    compiled kernel on the CPU): conv2d's map to round-off, the same bits at one and two threads
    and sample by sample, its gradient w.r.t. x in x's memory format (so the ReLU before it
    differentiates two tensors of one layout) with the values of the per-channel sum over the
    outputs, and the two implementations within round-off of each other."""
    from fishsim.fluid.hydronet.unet import pointwise_conv

    torch.manual_seed(0)
    conv = torch.nn.Conv2d(6, 2, 1).requires_grad_(not frozen)
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    x = torch.randn(3, 6, 9, 14).contiguous(memory_format=fmt).requires_grad_()
    weight = torch.randn(3, 2, 9, 14)
    out = pointwise_conv(conv, x)
    torch.testing.assert_close(out, conv(x), rtol=1e-6, atol=1e-6)
    (out * weight).sum().backward()
    assert x.grad.is_contiguous(memory_format=fmt)
    w = conv.weight.detach()[:, :, 0, 0]
    want = torch.cat([(weight * w[None, :, c, None, None]).sum(1, keepdim=True) for c in range(6)], dim=1)
    assert torch.equal(x.grad, want)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert torch.equal(pointwise_conv(conv, x), out)
        assert torch.equal(torch.cat([pointwise_conv(conv, x[k:k + 1]) for k in range(3)]), out)
    finally:
        torch.set_num_threads(threads)
    other = pointwise_conv(conv.requires_grad_(frozen), x)
    torch.testing.assert_close(other, out, rtol=1e-6, atol=1e-6)


def test_canvas_layout(grid):
    """Centre fields go to the top-left H x W block of the vertex canvas; the mask is replicated."""
    b = torch.rand(1, 1, grid.H, grid.W)
    assert torch.equal(to_canvas(b, grid.H + 1, grid.W + 1)[..., : grid.H, : grid.W], b)
    canvas = to_canvas(b, grid.H + 1, grid.W + 1, mode="replicate")
    assert torch.equal(canvas[..., -1, :-1], b[..., -1, :])
    a = torch.zeros(1, 1, grid.H + 1, grid.W + 1)
    v = (torch.zeros(1, 1, grid.H, grid.W + 1), torch.zeros(1, 1, grid.H + 1, grid.W))
    x = network_inputs(a, b[:, :, :, :], b, torch.zeros(1, 2, grid.H, grid.W), v, torch.zeros(1, 2))
    assert x.shape == (1, 15, grid.H + 1, grid.W + 1)


def test_fluid_model_contract(grid, tiny_net):
    """HydroNetFluid is a FluidModel: rest state, shapes, dtype, inputs not mutated."""
    fluid = HydroNetFluid(HydroNet(tiny_net), grid)
    assert isinstance(fluid, FluidModel)
    rest = fluid.initial_state(3)
    assert rest.a.shape == (3, 1, grid.H + 1, grid.W + 1) and rest.p.shape == (3, 1, grid.H, grid.W)
    assert not rest.a.any() and not rest.p.any()
    state, boundary = _random_inputs(grid, 3)
    copies = [t.clone() for t in (state.a, state.p, boundary.mask, boundary.velocity)]
    new = fluid.step(state, boundary, paper_params(3))
    assert new.a.shape == state.a.shape and new.p.shape == state.p.shape and new.a.dtype == torch.float32
    for t, c in zip((state.a, state.p, boundary.mask, boundary.velocity), copies):
        assert torch.equal(t, c)
    assert not fluid.model.training


def test_step_is_differentiable(grid, tiny_net):
    """Gradients reach the state and the boundary velocity; the inference copy's weights are
    frozen (no weight gradients computed in a rollout's backward). Seeded: some initial draws of the
    tiny net have all-dead ReLUs, through which v_d reaches nothing (order-dependent under xdist)."""
    torch.manual_seed(0)
    fluid = HydroNetFluid(HydroNet(tiny_net), grid)
    state, boundary = _random_inputs(grid)
    a = state.a.clone().requires_grad_()
    vd = boundary.velocity.clone().requires_grad_()
    new = fluid.step(FluidState(a, state.p), Boundary(boundary.mask, vd), paper_params(2))
    (new.a.square().sum() + new.p.square().sum()).backward()
    assert a.grad.abs().sum() > 0 and vd.grad.abs().sum() > 0
    assert not any(w.requires_grad for w in fluid.model.parameters())


def test_a_batch_steps_in_chunks_each_sample_as_alone(grid, tiny_net):
    """A batch of more samples than ``CHUNK`` is evaluated chunk by chunk: every sample's step,
    and its gradient, is the one it has in a batch of its own (the symmetric step: 2 B samples)."""
    from fishsim.fluid.hydronet import unet

    torch.manual_seed(0)
    fluid = HydroNetFluid(HydroNet(tiny_net), grid)
    B = unet.CHUNK + 1
    state, boundary = _random_inputs(grid, batch=B)
    vd = boundary.velocity.clone().requires_grad_()
    new = fluid.step(state, Boundary(boundary.mask, vd), paper_params(B))
    new.a.square().sum().backward()
    last = slice(B - 1, B)
    vd_alone = boundary.velocity[last].clone().requires_grad_()
    alone = fluid.step(FluidState(state.a[last], state.p[last]), Boundary(boundary.mask[last], vd_alone),
                       paper_params(1))
    alone.a.square().sum().backward()
    torch.testing.assert_close(new.a[last], alone.a, rtol=1e-6, atol=0)
    torch.testing.assert_close(new.p[last], alone.p, rtol=1e-6, atol=1e-6 * float(alone.p.detach().abs().max()))
    torch.testing.assert_close(vd.grad[last], vd_alone.grad, rtol=1e-5, atol=1e-6 * float(vd_alone.grad.abs().max()))


def test_symmetric_step_is_equivariant_under_the_y_reflection(grid, tiny_net):
    """symmetric=True: the step of the mirrored tank is the mirrored step (to round-off), which the
    network alone is not; mirroring twice is the identity, and the mirror keeps v_x and flips v_y."""
    from fishsim.fluid.grid import curl

    torch.manual_seed(0)
    model = HydroNet(tiny_net)
    state, boundary = _random_inputs(grid)
    fields = (state.a, state.p, boundary.mask, boundary.velocity)
    for x, y in zip(mirrored(*mirrored(*fields)), fields):
        assert torch.equal(x, y)
    m = mirrored(*fields)
    (vx, vy), (mx, my) = curl(state.a, grid.dx), curl(m[0], grid.dx)
    torch.testing.assert_close(mx, torch.flip(vx, dims=(-2,)))
    torch.testing.assert_close(my, -torch.flip(vy, dims=(-2,)))
    mirror_state, mirror_boundary = FluidState(m[0], m[1]), Boundary(m[2], m[3])
    errors = {}
    for symmetric in (False, True):
        fluid = HydroNetFluid(model, grid, symmetric=symmetric)
        new, new_m = fluid.step(state, boundary, paper_params(2)), fluid.step(mirror_state, mirror_boundary, paper_params(2))
        back = mirrored(new_m.a, new_m.p, None, None)
        errors[symmetric] = max(float((back[0] - new.a).abs().max() / new.a.abs().max()),
                                float((back[1] - new.p).abs().max() / new.p.abs().max()))
    assert errors[True] < 1e-5 and errors[False] > 1e-3, errors


def test_inference_copy_folds_batchnorm_without_changing_the_map(grid, tiny_net):
    """Folding eval-mode BatchNorm (non-trivial running statistics) into the convolutions gives
    the original network's outputs to float32 round-off, and leaves the original untouched."""
    model = HydroNet(tiny_net)
    g = torch.Generator().manual_seed(1)
    for bn in (m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)):
        bn.running_mean.copy_(0.3 * torch.randn(bn.num_features, generator=g))
        bn.running_var.copy_(0.5 + torch.rand(bn.num_features, generator=g))
        bn.weight.data.copy_(1 + 0.2 * torch.randn(bn.num_features, generator=g))
        bn.bias.data.copy_(0.1 * torch.randn(bn.num_features, generator=g))
    model.eval()
    fused = inference_copy(model)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.modules())
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules()) > 0
    x = torch.randn(2, tiny_net.in_channels, grid.H + 1, grid.W + 1, generator=g)
    with torch.no_grad():
        expected = model.unet(x)
        torch.testing.assert_close(fused.unet(x), expected, rtol=1e-5, atol=1e-5 * expected.abs().max().item())


def test_bounded_outputs_and_mean_removal(grid, tiny_net):
    """a, p never leave A tanh(.) - mean (|x| <= 2 A in physical units) and are mean free."""
    model = HydroNet(tiny_net)
    with torch.no_grad():
        model.unet.outc.bias.fill_(1e6)
    state, boundary = _random_inputs(grid)
    params = paper_params(2)
    new = HydroNetFluid(model, grid).step(state, boundary, params)
    a_star, p_star = grid.dx**2 / params.h, 50.0 * (grid.dx / params.h) ** 2
    assert new.a.abs().max() <= 2 * tiny_net.bound_a * a_star * (1 + 1e-5)
    assert new.p.abs().max() <= 2 * tiny_net.bound_p * p_star * (1 + 1e-5)
    for x, scale in ((new.a, a_star), (new.p, p_star)):
        assert x.mean(dim=(-2, -1)).abs().max() < 1e-5 * scale


def test_residual_update_is_identity_for_zero_output(grid, tiny_net):
    """With a zero output layer, the step returns A tanh(a / A) - mean: a small state is kept."""
    model = HydroNet(tiny_net)
    with torch.no_grad():
        model.unet.outc.weight.zero_()
        model.unet.outc.bias.zero_()
    state, boundary = _random_inputs(grid)
    new = HydroNetFluid(model, grid).step(state, boundary, paper_params(2))
    a0 = state.a - state.a.mean(dim=(-2, -1), keepdim=True)
    torch.testing.assert_close(new.a, a0, rtol=1e-4, atol=1e-9)


def test_without_pressure_input_the_step_does_not_see_p_t(grid):
    """pressure_input=False: the step is the same for any p_t (p_t is neither a channel nor the
    update's base); with it (Wandel's), p_t changes both a_t+1 and p_t+1. Seeded (dead-ReLU draws,
    below)."""
    state, boundary = _random_inputs(grid)
    other = FluidState(state.a, 3.0 * torch.randn_like(state.p))
    for pressure_input in (False, True):
        torch.manual_seed(0)
        model = HydroNet(NetConfig(hidden=4, depth=2, pressure_input=pressure_input)).eval()
        fluid = HydroNetFluid(model, grid)
        one, two = fluid.step(state, boundary, paper_params(2)), fluid.step(other, boundary, paper_params(2))
        same = torch.equal(one.a, two.a) and torch.equal(one.p, two.p)
        assert same is not pressure_input


def test_conditioning_changes_the_step(grid):
    """condition=True: 15 input channels, and (rho, mu) change the output. The initial weights
    are seeded: with hidden = 4 some draws (2 of 40 seeds) give a net whose ReLUs are all dead on
    this input, whose output is then the same for any (rho, mu)."""
    torch.manual_seed(0)
    model = HydroNet(NetConfig(hidden=4, depth=2, condition=True)).eval()
    assert model.unet.inc[0].in_channels == 15
    state, boundary = _random_inputs(grid, 1)
    fluid = HydroNetFluid(model, grid)
    a1 = fluid.step(state, boundary, paper_params(1, 50.0, 1.25e-4)).a
    a2 = fluid.step(state, boundary, paper_params(1, 10.0, 1e-3)).a
    assert not torch.allclose(a1, a2)


def test_bf16_close_to_fp32(grid, tiny_net):
    """bfloat16 autocast of the trunk changes the step by a small fraction of its update."""
    fluid = HydroNetFluid(HydroNet(tiny_net), grid)
    state, boundary = _random_inputs(grid)
    params = paper_params(2)
    ref = fluid.step(state, boundary, params)
    fluid.bf16 = True
    low = fluid.step(state, boundary, params)
    change = (ref.a - state.a).abs().max()
    assert (low.a - ref.a).abs().max() < 0.05 * change


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(grid, tiny_net):
    model = HydroNet(tiny_net).eval()
    state, boundary = _random_inputs(grid)
    params = paper_params(2)
    ref = HydroNetFluid(model, grid).step(state, boundary, params)
    out = HydroNetFluid(model.cuda(), grid).step(
        FluidState(state.a.cuda(), state.p.cuda()), Boundary(boundary.mask.cuda(), boundary.velocity.cuda()),
        FluidParams(params.rho.cuda(), params.mu.cuda(), params.h))
    torch.testing.assert_close(out.a.cpu(), ref.a, rtol=1e-3, atol=1e-8)


def test_bf16_on_a_cpu_without_bf16_instructions_warns(tmp_path, monkeypatch, capsys):
    """``cpu_has_bf16`` reads AMX's or AVX512-BF16's flag; ``fluid.bf16=true`` on a CPU with
    neither (bf16 ~10x slower than float32 there) prints one warning line, and none with either
    or on a GPU."""
    from fishsim.fluid import factory
    from fishsim.fluid.hydronet import config

    files = {name: tmp_path / name for name in ("amx", "avx512", "avx2")}
    files["amx"].write_text("processor\t: 0\nflags\t\t: fpu sse avx2 avx512f amx_bf16 amx_tile\n")
    files["avx512"].write_text("processor\t: 0\nflags\t\t: fpu sse avx2 avx512f avx512_bf16\n")
    files["avx2"].write_text("processor\t: 0\nflags\t\t: fpu sse avx2 fma\n")
    has_bf16 = config.cpu_has_bf16
    assert has_bf16(str(files["amx"])) and has_bf16(str(files["avx512"]))
    assert not has_bf16(str(files["avx2"])) and not has_bf16(str(tmp_path / "missing"))
    for name, warns in (("avx2", True), ("avx512", False)):
        monkeypatch.setattr(config, "cpu_has_bf16", lambda path=str(files[name]): has_bf16(path))
        assert factory.warn_slow_bf16("cpu") is warns
        err = capsys.readouterr().err
        assert ("fluid.bf16=true" in err) is warns and err.count("\n") == int(warns)
    assert factory.warn_slow_bf16("cuda") is False


@pytest.mark.skipif(shutil.which("g++") is None and shutil.which("clang++") is None,
                    reason="torch.compile needs a C++ compiler on the CPU")
def test_compiled_network_in_gradient_free_rollouts_only(grid, tiny_net):
    """``compile``: the network's chunks of ``CHUNK`` samples run compiled (torch.compile) only
    where nothing is differentiated (``fishsim.fields.gradient_free``) and, at "auto", only in
    rollouts of ``COMPILE_MIN_WORK`` fish-frames or more; the compiled step is the eager step to
    round-off, and everywhere else the eager step's bits."""
    from fishsim.fields import gradient_free
    from fishsim.fluid.hydronet import unet

    torch.manual_seed(0)
    net = HydroNet(tiny_net)
    B = unet.CHUNK // 2                                  # the symmetric step: one whole chunk
    state, boundary = _random_inputs(grid, batch=B)
    eager = HydroNetFluid(net, grid, compile=False)
    fluid = HydroNetFluid(net, grid, compile=True)
    auto = HydroNetFluid(net, grid)
    step = lambda f: f.step(state, boundary, paper_params(B))
    with torch.no_grad():
        reference = step(eager)
        for outside in (step(fluid), step(auto)):        # no gradient-free rollout: eager, same bits
            assert torch.equal(outside.a, reference.a) and torch.equal(outside.p, reference.p)
        with gradient_free(unet.COMPILE_MIN_WORK - 1):
            below = step(auto)
            compiled = step(fluid)
        assert torch.equal(below.a, reference.a) and not auto._compiled_ran
    assert fluid._compiled_ran
    torch.testing.assert_close(compiled.a, reference.a, rtol=1e-5, atol=1e-6 * float(reference.a.abs().max()))
    torch.testing.assert_close(compiled.p, reference.p, rtol=1e-5, atol=1e-5 * float(reference.p.abs().max()))
    with gradient_free(unet.COMPILE_MIN_WORK), torch.enable_grad():   # autograd on: eager
        graph = step(fluid)
    assert torch.equal(graph.a.detach(), reference.a)
    with pytest.raises(ValueError, match="compile must be"):
        HydroNetFluid(net, grid, compile="sometimes")


def test_a_gradient_free_rollout_tells_the_fluid_its_work(monkeypatch):
    """``rollout`` with autograd off marks its frames gradient-free with B x frames; a
    differentiable rollout (its checkpointed forward included) does not."""
    from fishsim.config import load_config
    from fishsim.episode import build_episode
    from fishsim.fields import GRADIENT_FREE_WORK
    from fishsim.rollout import Swimmer, rollout

    seen = []
    frame = Swimmer.frame

    def recording(self, *args, **kwargs):
        seen.append(GRADIENT_FREE_WORK.get())
        return frame(self, *args, **kwargs)

    monkeypatch.setattr(Swimmer, "frame", recording)
    ep = build_episode(load_config("simulate", ["fluid=none", "batch.frequency=[3,5]"]))
    state = ep.swimmer.initial_state(ep.params, ep.origin)
    with torch.no_grad():
        rollout(ep.swimmer, state, ep.params, 3)
    assert seen == [6, 6, 6]
    seen.clear()
    E = ep.params.E.clone().requires_grad_()
    _, m = rollout(ep.swimmer, state, dataclasses.replace(ep.params, E=E), 2, segment=1)
    m["head_x"].sum().backward()
    assert seen and set(seen) == {0}


def test_a_network_that_cannot_compile_warns_once_and_runs_uncompiled(grid, tiny_net, monkeypatch, capsys):
    """Where torch.compile fails (no C++ compiler), one warning, then the eager network."""
    from fishsim.fields import gradient_free
    from fishsim.fluid.hydronet import unet

    def no_compiler(*args, **kwargs):
        def failing(*a, **k):
            raise RuntimeError("no C++ compiler")
        return failing

    monkeypatch.setattr(torch, "compile", no_compiler)
    B = unet.CHUNK // 2
    state, boundary = _random_inputs(grid, batch=B)
    net = HydroNet(tiny_net)
    fluid = HydroNetFluid(net, grid, compile=True)
    with torch.no_grad(), gradient_free(unet.COMPILE_MIN_WORK):
        steps = [fluid.step(state, boundary, paper_params(B)) for _ in range(2)]
        reference = HydroNetFluid(net, grid, compile=False).step(state, boundary, paper_params(B))
    assert all(torch.equal(s.a, reference.a) for s in steps) and fluid.compile is False
    assert capsys.readouterr().err.count("could not be compiled") == 1

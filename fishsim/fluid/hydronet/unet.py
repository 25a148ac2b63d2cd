"""HydroNet: the physics-constrained U-Net fluid step (paper Sec. 3.1; Wandel et al. 2021, "UNet2").

One step maps (a_t, p_t, b_t, v_d,t) -> (a_t+1, p_t+1). Inside the network everything is in grid
units (``scales.py``): velocities in U* = dx/h, the potential in A* = dx^2/h, pressure in
P* = rho U*^2, so the network sees O(1) numbers for every fluid and every grid spacing.

Canvas. All inputs are stacked on the (H+1) x (W+1) vertex grid of ``a``. A field whose entry [i, j]
sits at a face or cell centre is put at canvas index [i, j] (a half-cell shift the convolutions
absorb, as in Wandel's code) and padded on the bottom row / right column: with zeros for p, v and
v_d, by replication for the mask (the outermost cells are walls, so replicating keeps them solid).
Input channels (13, Wandel's order; +2 with ``condition=True``):

    p, a / A_IN, v_x, v_y, f, b v_dx, b v_dy, b, f p, f v_x, f v_y, b v_x, b v_y [, rho~, nu~]

with b the soft mask (1 solid), f = 1 - b, v = curl a, and the potential further divided by
A_IN = 32 (a's scale is set by the domain size, not by a cell, so in grid units it is O(10-100)).
Conditioning channels are constant: rho~ = (rho - 30) / 20 and nu~ = (ln nu* - ln 0.025) / 1.85,
both in [-1, 1] over rho in [10, 50] kg/m^3, mu in [0.125, 1] mPa s at 2.5 mm / 0.01 s. Once p is
divided by rho U*^2 the dimensionless equations depend on nu* = mu h / (rho dx^2) only.

Bounded residual update (grid units), then per-sample mean removal:

    a_t+1 = A tanh((a_t + da) / A),   p_t+1 = P tanh((p_t + dp) / P),   x <- x - mean(x)

A = 400 A* (0.25 m^2/s at 2.5 mm / 0.01 s): the mean-free potential of a 0.5 m/s stream across the
0.25 m tank is +-0.06 m^2/s, so realistic states use < 1/4 of the range and tanh stays within 2 % of
the identity there. P = 64 P* (200 Pa at rho = 50): the dynamic pressure of 0.5 m/s is 2 P* and
the inertial pressure of the tail (0.5 m/s * 2 pi 8 Hz over ~2 cm) ~ 8 P*; larger values only arise
from impulsive starts, which the bound clips (Wandel: "avoid filling the pool with diverged data").

With ``NetConfig.pressure_input=False`` the network reads p_t as zero, in its channels and as the
update's base: p_t+1 = P tanh(dp / P) - mean, a function of (a_t, b, v_d) alone, like the solver's
pressure (the multiplier that makes v_t+1 divergence-free; p_t enters it nowhere).
"""

from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from fishsim.fields import GRADIENT_FREE_WORK, Boundary, FluidParams, FluidState, Grid, rest_state
from fishsim.fluid.grid import curl
from fishsim.fluid.hydronet.config import NETWORK, PRESSURES, RECOVERED, NetConfig
from fishsim.fluid.hydronet.kernels import PointwiseConv, memory_format_of
from fishsim.fluid.hydronet.scales import scales_of
from fishsim.fluid.pressure import RecoveryConfig, recover_pressure
from fishsim.fluid.residual import per_sample

A_IN = 32.0
RHO_MID, RHO_HALF = 30.0, 20.0
LOG_NU_MID, LOG_NU_HALF = math.log(0.025), 1.85


class DoubleConv(nn.Sequential):
    """[conv 3x3 -> BatchNorm -> ReLU] x 2 (Wandel/milesial ``DoubleConv``)."""

    def __init__(self, c_in: int, c_out: int, c_mid: int | None = None):
        c_mid = c_mid or c_out
        super().__init__(
            nn.Conv2d(c_in, c_mid, 3, padding=1), nn.BatchNorm2d(c_mid), nn.ReLU(inplace=True),
            nn.Conv2d(c_mid, c_out, 3, padding=1), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True),
        )


class Up(nn.Module):
    """Bilinear x2 upsampling, pad to the skip's size, concat [skip, up], DoubleConv(c_in, c_out, c_in/2)."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.conv = DoubleConv(c_in, c_out, c_in // 2)

    def forward(self, x: Tensor, skip: Tensor) -> Tensor:
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        dy, dx = skip.shape[-2] - x.shape[-2], skip.shape[-1] - x.shape[-1]
        x = F.pad(x, (dx // 2, dx - dx // 2, dy // 2, dy - dy // 2))
        return self.conv(torch.cat([skip, x], dim=1))


class UNet(nn.Module):
    """Wandel's UNet2 trunk: ``depth`` max-pool levels down, bilinear up, 1x1 conv out.

    Channels c_k = hidden 2^k (k < depth); the bottleneck has c_{depth-1} channels. With
    hidden = 20, depth = 4, 13 inputs and 2 outputs it has Wandel's 1,691,322 parameters.
    Input [B, c_in, h, w], output [B, c_out, h, w].
    """

    def __init__(self, c_in: int, c_out: int, hidden: int = 20, depth: int = 4):
        super().__init__()
        ch = [hidden * 2**k for k in range(depth)]
        self.inc = DoubleConv(c_in, ch[0])
        self.downs = nn.ModuleList(
            nn.Sequential(nn.MaxPool2d(2), DoubleConv(ch[k - 1], c))
            for k, c in enumerate(ch[1:] + [ch[-1]], start=1)
        )
        self.ups = nn.ModuleList(Up(2 * ch[k], ch[k - 1] if k > 0 else ch[0]) for k in reversed(range(depth)))
        self.outc = nn.Conv2d(ch[0], c_out, 1)

    def forward(self, x: Tensor) -> Tensor:
        skips = [self.inc(x)]
        for down in self.downs:
            skips.append(down(skips[-1]))
        x = skips.pop()
        for up in self.ups:
            x = up(x, skips.pop())
        with torch.autocast(x.device.type, enabled=False):  # full-precision output under autocast
            return pointwise_conv(self.outc, x.to(self.outc.weight.dtype))


def pointwise_conv(conv: nn.Conv2d, x: Tensor) -> Tensor:
    """The 1x1 convolution ``conv`` of x [B, C, h, w] -> [B, O, h, w] as C multiply-adds
    over the channels in order: out = b + sum_c W[:, c] x[:, c].

    The same as ``conv(x)`` up to rounding, but the same bits whatever the thread count: the BLAS
    product of ``conv(x)`` with O = 2 outputs splits its sums by thread (on the CPU its last bit
    changed from one thread to two, which the solid's tolerance-stopped solve carried on to a
    1e-9 difference of the 60-frame gradient). The channels are taken by ``unbind``, whose
    backward stacks their gradients once: sliced one by one, each slice's backward wrote a zeroed
    gradient of x's full size and the C of them were summed (the U-Net's forward + backward at
    B = 4 on the paper's grid 61.5-63.5 -> 55.2-57.8 ms, the same bits).

    The frozen network (``inference_copy``: weights without grad) on the CPU runs the same sums
    as one compiled loop with its gradient (``kernels.PointwiseConv``, the same bits on this
    project's CPU; 0.59 against 1.63 ms forward at 4 samples on the paper's grid, and the B = 16
    episode's backward 33.8-35.5 against 35.5-37.1 ms a fish and frame); this formula is the
    reference, and runs on other devices and in training."""
    if x.device.type == "cpu" and not conv.weight.requires_grad:
        return PointwiseConv.apply(x, conv.weight[:, :, 0, 0], conv.bias)
    w, planes = conv.weight[:, :, 0, 0], GradientInLayout.apply(x).unbind(1)   # [O, C], C x [B, h, w]
    out = conv.bias[None, :, None, None] + w[None, :, 0, None, None] * planes[0][:, None]
    for c in range(1, len(planes)):
        out = torch.addcmul(out, w[None, :, c, None, None], planes[c][:, None])
    return out


class GradientInLayout(torch.autograd.Function):
    """The identity, whose backward hands x's gradient on in x's memory format (channels_last or
    contiguous). ``unbind``'s backward stacks the planes' gradients into a contiguous NCHW tensor;
    the ReLU before the 1x1 convolution holds a channels_last output, and torch's
    ``threshold_backward`` on the two layouts took 4.6-5.4 ms against 0.11 ms when both were
    channels_last ([4, 16, 101, 301], two threads). Same bits: a copy."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        ctx.fmt = memory_format_of(x)
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        return grad.contiguous(memory_format=ctx.fmt)


def to_canvas(x: Tensor, rows: int, cols: int, mode: str = "constant") -> Tensor:
    """Pad [B, C, r, c] on the bottom/right to the canvas [B, C, rows, cols] (zeros or replicate)."""
    pad = (0, cols - x.shape[-1], 0, rows - x.shape[-2])
    return F.pad(x, pad, mode=mode) if any(pad) else x


def network_inputs(a: Tensor, p: Tensor, b: Tensor, v_d: Tensor, v: tuple[Tensor, Tensor],
                   cond: Tensor | None) -> Tensor:
    """Stack the input channels on the vertex canvas (module docstring); all fields in grid units.

    a [B,1,H+1,W+1], p [B,1,H,W], b [B,1,H,W], v_d [B,2,H,W], v = (v_x [B,1,H,W+1], v_y [B,1,H+1,W]),
    cond [B,2] or None -> [B, 13 (+2), H+1, W+1].
    """
    rows, cols = a.shape[-2:]
    b = to_canvas(b, rows, cols, mode="replicate")
    f = 1.0 - b
    p = to_canvas(p, rows, cols)
    vel = torch.cat([to_canvas(v[0], rows, cols), to_canvas(v[1], rows, cols)], dim=1)
    chans = [p, a / A_IN, vel, f, b * to_canvas(v_d, rows, cols), b, f * p, f * vel, b * vel]
    if cond is not None:
        chans.append(cond[:, :, None, None].expand(-1, -1, rows, cols))
    return torch.cat(chans, dim=1)


class HydroNet(nn.Module):
    """The U-Net plus its physical-unit wrapper: (a, p, b, v_d, rho, mu) -> (a_t+1, p_t+1).

    ``forward`` takes and returns physical units (a in m^2/s, p in Pa, v_d in m/s, rho [B] kg/m^3,
    mu [B] Pa s, dx in m, h in s); the grid-unit conversion, bounds and mean removal are inside.
    """

    def __init__(self, cfg: NetConfig = NetConfig()):
        super().__init__()
        self.cfg = cfg
        self.unet = UNet(cfg.in_channels, 2, cfg.hidden, cfg.depth)
        self.freeze_norm = False

    def train(self, mode: bool = True) -> HydroNet:
        """nn.Module.train, except that with ``freeze_norm`` the BatchNorm layers stay in eval
        mode: normalised by their running statistics, which then never change, the map trained
        is the map inference runs (``TrainConfig.freeze_norm``)."""
        super().train(mode)
        if self.freeze_norm:
            for m in self.modules():
                if isinstance(m, nn.BatchNorm2d):
                    m.eval()
        return self

    def forward(self, a: Tensor, p: Tensor, b: Tensor, v_d: Tensor, rho: Tensor, mu: Tensor,
                dx: float, h: float) -> tuple[Tensor, Tensor]:
        grid = Grid(p.shape[-2], p.shape[-1], dx)
        s = scales_of(grid, FluidParams(rho=rho, mu=mu, h=h))
        a_g, vd_g = a / s.potential, v_d / s.velocity
        p_g = p / s.pressure if self.cfg.pressure_input else torch.zeros_like(p)
        v_g = curl(a_g, 1.0)
        cond = self._condition(rho, s.nu) if self.cfg.condition else None
        x = network_inputs(a_g, p_g, b, vd_g, v_g, cond)
        if x.dtype != self.unet.outc.weight.dtype and not torch.is_autocast_enabled(x.device.type):
            x = x.to(self.unet.outc.weight.dtype)
        if self.unet.inc[0].weight.is_contiguous(memory_format=torch.channels_last):
            x = x.contiguous(memory_format=torch.channels_last)
        out = self.unet(x).to(a.dtype)
        a_new = self._bounded(a_g + out[:, :1], self.cfg.bound_a)
        p_new = self._bounded(p_g + out[:, 1:, : p.shape[-2], : p.shape[-1]], self.cfg.bound_p)
        return a_new * s.potential, p_new * s.pressure

    @staticmethod
    def _condition(rho: Tensor, nu: Tensor) -> Tensor:
        """[B, 2] normalised (rho, ln nu*) in [-1, 1] over the paper's fluid range."""
        rho_n = (rho.reshape(-1) - RHO_MID) / RHO_HALF
        nu_n = (torch.log(nu.reshape(-1)) - LOG_NU_MID) / LOG_NU_HALF
        return torch.stack([rho_n, nu_n], dim=1).to(rho.dtype)

    @staticmethod
    def _bounded(x: Tensor, bound: float) -> Tensor:
        """x -> bound tanh(x / bound) with the per-sample spatial mean removed, [B, 1, r, c]."""
        y = bound * torch.tanh(x / bound)
        return y - y.mean(dim=(-2, -1), keepdim=True)


def mirrored(a: Tensor, p: Tensor, b: Tensor | None, v_d: Tensor | None) -> tuple:
    """The fields of the tank mirrored in y (rows reversed): the stream function changes sign
    (v = curl a: v_x -> v_x, v_y -> -v_y), the pressure and mask are flipped, the boundary
    velocity's y component changes sign. a [B,1,H+1,W+1], p and b [B,1,H,W], v_d [B,2,H,W] (b,
    v_d may be None). Its own inverse."""
    flip = lambda x: None if x is None else torch.flip(x, dims=(-2,))
    v = None if v_d is None else torch.cat([flip(v_d[:, :1]), -flip(v_d[:, 1:])], dim=1)
    return -flip(a), flip(p), flip(b), v


def inference_copy(model: HydroNet) -> HydroNet:
    """A frozen eval-mode copy of ``model`` with each BatchNorm folded into the convolution before
    it: with s = sqrt(running_var + eps), W' = W gamma / s and b' = (b - running_mean) gamma / s
    + beta, the same map to round-off with a third fewer ops. Its weights do not require grad, so
    a backward pass through the fluid skips the weight gradients (train the original)."""
    fused = copy.deepcopy(model).eval()
    for block in fused.modules():
        if isinstance(block, DoubleConv):
            for i in (0, 3):
                block[i], block[i + 1] = fuse_conv_bn_eval(block[i], block[i + 1]), nn.Identity()
    return fused.requires_grad_(False)


CHUNK = 4
"""The most samples ``HydroNetFluid.step`` passes the network at once on the CPU (a batch of B
fish is 2B samples with the symmetric step); a chunk's result is the same bits as the whole
batch's. Its activations (~50 MB a sample in a graph) then stay near the cache: on the paper's
grid, two threads, the shipped U-Net, 32 samples (2026-12-01), forward + backward took 17.0-18.7
ms a sample in chunks of 2-8 against 36.7 ms in one call, and a B = 16 episode (30 frames,
``benchmarks.bench_rollout.episode_timing``) 23.1 / 39.3 ms a fish and frame forward / backward
in chunks of 4, 22.4 / 43.2 in chunks of 8, 23.7 / 48.5 in chunks of 16, 33.0 / 94.9 whole."""


COMPILE_MIN_WORK = 4000
"""``HydroNetFluid(compile="auto")`` runs its compiled network in gradient-free rollouts of at
least this many fish-frames (``fishsim.fields.GRADIENT_FREE_WORK``): the compilation takes ~8-10 s
once per process and saves ~1-1.5 ms a fish-frame (``HydroNetFluid``), so from ~6,000-9,000
fish-frames on it pays for itself within the rollout; a CMA-ES generation of 16 fish over 500
frames is 8,000, and an optimisation's later generations reuse it (115.5 against 123.0 s)."""


class HydroNetFluid:
    """``FluidModel`` backed by a trained ``HydroNet``, run as its ``inference_copy`` (eval mode:
    BatchNorm uses running stats, folded into the convolutions).

    Differentiable w.r.t. the state and the boundary (not the network weights: train the
    network with ``fishsim train-hydronet``); batched over B; runs on the device of the inputs
    (the model must be there too). ``bf16=True`` runs the U-Net trunk under
    bfloat16 autocast (the bounded update and the unit conversions stay in float32).

    On the CPU the network's weights are kept channels_last (NHWC), and its input with them
    (``HydroNet.forward``): on the paper's grid, two threads, a U-Net evaluation took 30-39 ms
    NCHW and 26-27 ms NHWC at B = 1, 70-74 against 50-64 ms with its backward, 28-30 against
    23-26 ms a fish at B = 16 (2026-11-28).

    ``pressure``: "network" (default) returns the network's own pressure output (the paper's
    method); "recovered" returns the pressure that best satisfies the momentum equation for the
    network's velocities (``fishsim.fluid.pressure``, one PCG solve per step, settings
    ``recovery``), a repair for a network whose own pressure lags its velocities (the model
    shipped before 2026-11-26 gave 3x too little thrust with its own pressure).

    ``symmetric``: the step is the mean of the network's step and its mirror image in y,
    N_s(x) = (N(x) + M N(M x)) / 2 (``mirrored``: M flips the rows, a -> -a, v_y -> -v_y), one
    network evaluation at 2B: exactly equivariant under the tank's y reflection, which the
    network alone is not (its canvas stacks vertex and cell fields with bottom/right padding):
    the shipped model's fish drifted sideways the same way whichever way it first beat, 40 mm
    at 7 Hz over 120 frames against the solver's 2 mm.

    ``compile``: in a gradient-free rollout (``fishsim.fields.gradient_free``) on the CPU, run the
    float32 network's chunks of ``CHUNK`` samples through ``torch.compile`` (inductor, weights
    frozen as constants, so a convolution's ReLU and the input stacking fuse): "auto" (default)
    in rollouts of ``COMPILE_MIN_WORK`` fish-frames and more, True in every gradient-free rollout,
    False never. Its results differ from the eager network's by round-off (head x over 30 frames
    at B = 16: 2e-7 relative); a differentiable rollout, its checkpointed forward included, always
    runs the eager network, so a gradient is that of the trajectory it recomputes. Measured on the
    paper's grid, two threads (2026-12-01): 6.1-6.2 against 7.0-7.1 ms a sample, and a B = 16
    episode's forward 13.7-14.5 against 15.1-16.2 ms a fish and frame; ~8-10 s to compile, once
    per process. Where it cannot compile (no C++ compiler), one warning, then the eager network.
    """

    exerts_force = True
    threads_per_sample = True

    def __init__(self, model: HydroNet, grid: Grid, bf16: bool = False, pressure: str = NETWORK,
                 recovery: RecoveryConfig | None = None, symmetric: bool = True, compile: bool | str = "auto"):
        if pressure not in PRESSURES:
            raise ValueError(f"pressure must be one of {PRESSURES}, got {pressure!r}")
        if compile not in (True, False, "auto"):
            raise ValueError(f"compile must be true, false or auto, got {compile!r}")
        self.model = inference_copy(model)
        if next(self.model.parameters()).device.type == "cpu":   # NHWC convolutions: 15-25 % faster here
            self.model = self.model.to(memory_format=torch.channels_last)
        self.grid = grid
        self.bf16 = bf16
        self.pressure, self.recovery = pressure, recovery or RecoveryConfig()
        self.symmetric = symmetric
        self.compile, self._compiled, self._compiled_ran = compile, None, False

    def initial_state(self, batch: int, device=None, dtype=torch.float32) -> FluidState:
        """Fluid at rest: a = 0 [B,1,H+1,W+1], p = 0 [B,1,H,W]."""
        return rest_state(self.grid, batch, device, dtype)

    def step(self, state: FluidState, boundary: Boundary, params: FluidParams,
             start: FluidState | None = None) -> FluidState:
        """(a_t, p_t, b, v_d) -> (a_t+1, p_t+1): one network evaluation (and the pressure
        recovery, whose PCG starts from ``start``'s p, else from p_t)."""
        dev = state.a.device.type
        inputs = (state.a, state.p, boundary.mask, boundary.velocity)
        rho, mu = params.rho, params.mu
        if self.symmetric:
            B = state.a.shape[0]
            inputs = tuple(torch.cat([x.expand(B, *x.shape[1:]), y.expand(B, *y.shape[1:])])
                           for x, y in zip(inputs, mirrored(*inputs)))
            rho, mu = (per_sample(q, state.a).reshape(-1).expand(B).repeat(2) for q in (rho, mu))
        with torch.autocast(dev, dtype=torch.bfloat16, enabled=self.bf16):
            a, p = self._evaluate(inputs, rho, mu, params.h)
        if self.symmetric:
            (a, a_m), (p, p_m) = a.chunk(2), p.chunk(2)
            a_back, p_back = mirrored(a_m, p_m, None, None)[:2]
            a, p = 0.5 * (a + a_back), 0.5 * (p + p_back)
        if self.pressure == RECOVERED:
            dx = self.grid.dx
            p = recover_pressure(curl(state.a, dx), curl(a, dx), boundary.mask.to(a.dtype), params.rho,
                                 params.mu, params.h, self.grid, self.recovery,
                                 start=state.p if start is None else start.p)
        return FluidState(a=a, p=p)

    def _evaluate(self, inputs: tuple[Tensor, ...], rho: Tensor, mu: Tensor, h: float) -> tuple[Tensor, Tensor]:
        """The network on (a, p, b, v_d) [N, ...] (rho, mu: scalars or [N]), on the CPU in chunks
        of at most ``CHUNK`` samples, each chunk's graph its own (a GPU takes the batch whole);
        returns (a, p) [N, ...]."""
        n = max(x.shape[0] for x in inputs)
        if inputs[0].device.type != "cpu":
            return self.model(*inputs, rho, mu, self.grid.dx, h)
        compiled = self._compiles(inputs[0])
        part = lambda q, i: q[i:i + CHUNK] if torch.is_tensor(q) and q.ndim and q.shape[0] == n else q
        chunks = []
        for i in range(0, n, CHUNK):
            args = (*(part(x, i) for x in (*inputs, rho, mu)), self.grid.dx, h)
            whole = min(CHUNK, n - i) == CHUNK
            chunks.append(self._run_compiled(*args) if compiled and whole else self.model(*args))
        return tuple(torch.cat(q) for q in zip(*chunks)) if len(chunks) > 1 else chunks[0]

    def _compiles(self, like: Tensor) -> bool:
        """Whether this step runs the compiled network (``compile``): a gradient-free rollout of
        enough fish-frames, float32, no autocast."""
        work = GRADIENT_FREE_WORK.get()
        if self.compile is False or work == 0 or torch.is_grad_enabled() or self.bf16:
            return False
        return like.dtype == torch.float32 and (self.compile is True or work >= COMPILE_MIN_WORK)

    def _run_compiled(self, *args):
        """The compiled network on one chunk (compiled at the first call, for chunks of
        ``CHUNK`` samples only, so one compilation serves a process). If its first call fails,
        a one-line warning and the eager network from then on."""
        if self._compiled is None:
            self._compiled = torch.compile(self.model, dynamic=False, options={"freezing": True})
        if self._compiled_ran:
            return self._compiled(*args)
        try:
            out = self._compiled(*args)
        except Exception as err:                           # noqa: BLE001 (any backend failure)
            self.compile = False
            from rich.console import Console

            Console(stderr=True, soft_wrap=True).print(
                f"[yellow]warning: HydroNet's network could not be compiled ({type(err).__name__}); it runs "
                "uncompiled (results within round-off, ~10 % slower); fluid.compile=false skips the attempt[/]")
            return self.model(*args)
        self._compiled_ran = True
        return out

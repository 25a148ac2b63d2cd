"""The paper's Table 1 on this machine: a 300-frame episode on the 100 x 300 grid with the default
mesh in the swim tunnel (``tunnel=true``: the fish held in x, the water past it at its own speed;
free, the 5 Hz fish leaves the paper's 0.75 m tank after ~230 frames), B = 1 (warm-up, forward
with its solid / fluid / coupling split, backward, peak memory) and B = 16 (time per fish and
frame, over ``FISHSIM_BENCH_FRAMES_B16`` = 30 frames), for each fluid model; plus the distance
travelled in 1.2 s at 3-7 Hz (the paper's Fig. 4 in preview, free swimming), and the peak memory of
a ``FISHSIM_BENCH_FRAMES_LONG`` = 500-frame HydroNet episode (checkpointed every 10 frames), the
HydroNet episodes (B = 1 and 16) and optimiser units with its bfloat16 trunk (``fluid.bf16=true``;
fast only on a CPU with bf16 instructions, AMX or AVX512-BF16), and with the recovered
pressure instead of the network's own (``fluid.pressure=recovered``: timing and distances); and
for each fluid the optimisers' unit of work as ``fishsim optimize`` runs it (issue 21): an Adam
iteration of the paper's 500 frames (B = 1, forward + backward) and a CMA-ES generation of 16 fish
over 500 frames; and HydroNet's gradient-free B = 16 forward (as ``simulate`` and a CMA-ES
generation run it) with the network uncompiled and compiled (``fluid.compile=true``; its
compilation in the warm-up). ``FISHSIM_BENCH_FRAMES`` shortens the episode for a quick look.

Each measurement runs in a fresh process: memory freed by an earlier one stays resident in the
allocator, so a shared process would report the largest earlier peak instead of its own."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import torch

from fishsim.config import load_config
from fishsim.episode import build_episode
from fishsim.errors import SimulationBlowUp
from fishsim.fluid.kernels import Predict, SplitStep
from fishsim.fluid.pressure import WeightedPoisson
from fishsim.linalg.dct import NeumannPoisson
from fishsim.rollout import PhaseTimer, SwimParams, rollout
from fishsim.solid.step import PDStepFunction

FRAMES = int(os.environ.get("FISHSIM_BENCH_FRAMES", "300"))
FRAMES_B16 = int(os.environ.get("FISHSIM_BENCH_FRAMES_B16", "30"))  # B = 16: per-fish cost per frame
# Checkpoint segment lengths [frames]. At B = 16 the numerical fluid's backward tapes 8 sub-steps x 2
# passes a frame: a 5-frame segment peaked at 12.4 GB (2026-11-26) and a 10-frame one ran out of
# this machine's 24 GB, so B = 16 recomputed 3-frame segments; since 2026-12-01 1-frame ones: the
# 30-frame episode's peak 1.6 against 3.2 GB with HydroNet (1.3 against 1.55 GB numerical), and
# the first segment's first touch of that memory, which this VM backed at ~10-16 us a page in
# some hours (HydroNet's backward then 46-50 against 34-39 ms a fish and frame; numerical 15.7
# against 16.2-16.6 ms in any hour), a third. A long episode stores one more boundary state a
# frame (~0.25 MB a fish).
SEGMENT, SEGMENT_B16 = 10, 1
FRAMES_LONG = int(os.environ.get("FISHSIM_BENCH_FRAMES_LONG", "500"))  # peak memory of a long episode
FLUIDS = ["hydronet", "numerical"]


def _reset_peak() -> None:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def _peak_mib() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmHWM"):
                return int(line.split()[1]) / 1024
    return float("nan")


VARIANTS = {"hydronet-bf16": ["fluid=hydronet", "fluid.bf16=true"],
            "hydronet-recovered-pressure": ["fluid=hydronet", "fluid.pressure=recovered"],
            "hydronet-network-alone": ["fluid=hydronet", "fluid.symmetric=false"],
            "hydronet-compiled": ["fluid=hydronet", "fluid.compile=true"]}


def _fluid_overrides(fluid: str) -> list[str]:
    """The overrides of a fluid model or a ``VARIANTS`` key."""
    return list(VARIANTS.get(fluid, [f"fluid={fluid}"]))


def _episode(fluid: str, batch: int, frequencies=None, tunnel: bool = False):
    overrides = _fluid_overrides(fluid) + ["tunnel=true"] * tunnel
    if frequencies is not None:
        overrides.append("batch.frequency=[" + ",".join(str(f) for f in frequencies) + "]")
    elif batch > 1:
        overrides.append("batch.frequency=[" + ",".join(["5.0"] * batch) + "]")
    return build_episode(load_config("simulate", overrides))


def _differentiable(params: SwimParams) -> tuple[SwimParams, torch.Tensor]:
    omega = params.controller.omega.clone().requires_grad_(True)
    ctrl = type(params.controller)(params.controller.C, omega, params.controller.gamma, params.controller.t_a)
    return dataclasses.replace(params, controller=ctrl), omega   # the other parameters (muscles) kept


@contextmanager
def adjoint_clock(fluid_model):
    """Wall time [s] a backward spends in the solid's adjoint (``PDStepFunction.backward``) and in
    the fluid's own adjoints (the numerical fluid's compiled stage and Poisson solves, HydroNet's
    network between its module backward hooks, the pressure recovery's solve), summed into the
    yielded dict {"solid", "fluid"}; the rest of a backward is torch's taped ops (the coupling,
    the fluid's glue around its kernels) and the recomputation of checkpointed segments. Enter it
    before the forward: module backward hooks act only on calls made after they are registered."""
    seconds, restore = {"solid": 0.0, "fluid": 0.0}, []

    def timed(cls, phase):
        original = cls.backward

        def backward(ctx, *grads):
            t0 = time.perf_counter()
            try:
                return original(ctx, *grads)
            finally:
                seconds[phase] += time.perf_counter() - t0
        cls.backward = staticmethod(backward)
        restore.append(lambda: setattr(cls, "backward", staticmethod(original)))

    timed(PDStepFunction, "solid")
    for cls in (Predict, SplitStep, NeumannPoisson, WeightedPoisson):
        timed(cls, "fluid")
    net = getattr(fluid_model, "model", None)
    if net is not None:
        started = []
        pre = net.register_full_backward_pre_hook(lambda *_: started.append(time.perf_counter()))
        post = net.register_full_backward_hook(
            lambda *_: seconds.__setitem__("fluid", seconds["fluid"] + time.perf_counter() - started.pop()))
        restore += [pre.remove, post.remove]
    try:
        yield seconds
    finally:
        for undo in restore:
            undo()


def _warmed(fluid: str, batch: int):
    """(episode in the swim tunnel, its initial state, the warm-up's seconds): mesh, solid
    factorisation and fluid model built, and a first frame run without a graph (HydroNet's
    compilation with ``fluid.compile=true``)."""
    t0 = time.perf_counter()
    ep = _episode(fluid, batch, tunnel=True)
    state = ep.swimmer.initial_state(ep.params, ep.origin)
    with torch.no_grad():
        rollout(ep.swimmer, state, ep.params, 1)
    return ep, state, time.perf_counter() - t0


def episode_timing(fluid: str, batch: int, frames: int) -> dict:
    """Warm-up (build mesh, solid factorisation, fluid model; first frame), forward (split
    solid / fluid / coupling), backward of the distance swum through the water (head x + h sum U)
    w.r.t. omega (split: the checkpointed segments' recomputation, by phase; the solid's and the
    fluid's own adjoints, ``adjoint_clock``), peak RSS; checkpointed every SEGMENT frames
    (SEGMENT_B16 at B > 1); in the swim tunnel. The recomputation of every segment but the last
    runs in a background thread beside the adjoints (rollout.Segments), so the parts overlap and
    add up to more than the backward's wall time."""
    ep, state, warmup = _warmed(fluid, batch)
    sw = ep.swimmer
    params, omega = _differentiable(ep.params)
    timer = PhaseTimer()
    _reset_peak()
    with adjoint_clock(sw.fluid) as adjoint:    # its module hooks must be in place for the forward
        t0 = time.perf_counter()
        _, metrics = rollout(sw, state, params, frames, segment=SEGMENT if batch == 1 else SEGMENT_B16, timer=timer)
        forward = time.perf_counter() - t0
        split = dict(timer.seconds)
        timer.seconds = dict.fromkeys(timer.seconds, 0.0)     # from here: the backward's recomputation
        t0 = time.perf_counter()
        (metrics["head_x"][-1] + sw.h * metrics["tunnel_u"].sum(0)).sum().backward()
        backward = time.perf_counter() - t0
    recompute = dict(timer.seconds)
    tail = metrics["tail_y"][-20:, 0].detach()  # the last 0.2 s of fish 0
    return {"frames": frames, "batch": batch, "segment": SEGMENT if batch == 1 else SEGMENT_B16,
            "warmup_s": warmup, "forward_s": forward,
            "tail_peak_to_peak_m": float(tail.max() - tail.min()),
            "forward_solid_s": split["solid"], "forward_fluid_s": split["fluid"],
            "forward_coupling_s": split["coupling"], "backward_s": backward,
            "backward_recompute_s": sum(recompute.values()), "backward_recompute_split_s": recompute,
            "backward_solid_adjoint_s": adjoint["solid"], "backward_fluid_adjoint_s": adjoint["fluid"],
            "forward_per_fish_s": forward / batch, "backward_per_fish_s": backward / batch,
            "forward_ms_per_frame_per_fish": 1e3 * forward / (frames * batch),
            "forward_coupling_ms_per_frame_per_fish": 1e3 * split["coupling"] / (frames * batch),
            "backward_ms_per_frame_per_fish": 1e3 * backward / (frames * batch),
            "peak_rss_mib": _peak_mib(), "ddistance_domega": float(omega.grad[0])}


def forward_timing(fluid: str, batch: int, frames: int) -> dict:
    """A gradient-free episode (``fishsim simulate``, a CMA-ES generation) of ``batch`` fish at 5
    Hz in the swim tunnel: its set-up (HydroNet's compilation with ``fluid.compile=true``, in the
    first frame) and its forward per fish and frame."""
    ep, state, warmup = _warmed(fluid, batch)
    with torch.no_grad():
        t0 = time.perf_counter()
        rollout(ep.swimmer, state, ep.params, frames)
        forward = time.perf_counter() - t0
    return {"frames": frames, "batch": batch, "warmup_s": warmup, "forward_s": forward,
            "forward_ms_per_frame_per_fish": 1e3 * forward / (frames * batch)}


def distance_sweep(fluid: str, frequencies=(3.0, 4.0, 5.0, 6.0, 7.0), frames: int = 120) -> dict:
    """Head x-displacement after ``frames`` frames, one batched run over the frequencies."""
    ep = _episode(fluid, len(frequencies), frequencies)
    state = ep.swimmer.initial_state(ep.params, ep.origin)
    with torch.no_grad():
        _, m = rollout(ep.swimmer, state, ep.params, frames)
    d = (m["head_x"][-1] - state.q[:, ep.swimmer.solid.mesh.points[:, 0].argmax(), 0]).tolist()
    return {f"{f:g} Hz": dist for f, dist in zip(frequencies, d)}


def optimizer_timing(fluid: str, method: str, frames: int = FRAMES_LONG, popsize: int = 16) -> dict:
    """One iteration of ``fishsim optimize`` (``method`` adam: the paper's forward + backward of
    ``frames`` frames, B = 1; cma: a generation of ``popsize`` fish, one batched forward), in the
    swim tunnel with the centroid's y held (as the paper holds its fish: over 500 frames a free
    fish may turn into the tank's side wall, HydroNet's at frame 415), as a user runs it (a fresh
    process): its wall time as the optimiser reports it, and J; or, if the run failed, its
    error's last line. ``fluid``: a fluid model or a ``VARIANTS`` key."""
    with tempfile.TemporaryDirectory() as out:
        run = subprocess.run([sys.executable, "-m", "fishsim", "optimize", *_fluid_overrides(fluid),
                              f"optimizer.methods=[{method}]", "optimizer.iterations=1", f"optimizer.popsize={popsize}",
                              f"frames={frames}", "tunnel=true", "hold_y=true", f"out_dir={out}"],
                             check=False, capture_output=True, text=True)
        if run.returncode != 0:
            return {"failed": (run.stderr.strip().splitlines() or [f"exit status {run.returncode}"])[-1]}
        summary = json.loads((Path(out) / "summary.json").read_text())[method]
    return {"wall_s": summary["wall_s"], "fish_frames": summary["fish_frames"], "J": summary["best_J"]}


def _attempt(fn, *args):
    warnings.simplefilter("ignore", RuntimeWarning)
    try:
        return fn(*args)
    except SimulationBlowUp as err:
        return {"blew_up": str(err)}


def _recorded(fn, *args):
    """fn(*args) in a fresh process, or what went wrong if the simulation blew up (a result worth
    reporting)."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_attempt, fn, *args).result()


def run() -> dict:
    out = {}
    for fluid in FLUIDS:
        out[fluid] = {"B=1": _recorded(episode_timing, fluid, 1, FRAMES),
                      "B=16": _recorded(episode_timing, fluid, 16, FRAMES_B16),
                      "distance_1.2s_m": _recorded(distance_sweep, fluid),
                      f"Adam iteration, {FRAMES_LONG} frames": optimizer_timing(fluid, "adam"),
                      f"CMA-ES generation, 16 x {FRAMES_LONG} frames": optimizer_timing(fluid, "cma")}
    out["hydronet"][f"B=1, {FRAMES_LONG} frames"] = _recorded(episode_timing, "hydronet", 1, FRAMES_LONG)
    out["hydronet"]["B=16 gradient-free"] = _recorded(forward_timing, "hydronet", 16, FRAMES_B16)
    out["hydronet-compiled"] = {"B=16 gradient-free": _recorded(forward_timing, "hydronet-compiled", 16, FRAMES_B16)}
    out["hydronet-network-alone"] = {"B=1": _recorded(episode_timing, "hydronet-network-alone", 1, FRAMES)}
    out["hydronet-bf16"] = {"B=1": _recorded(episode_timing, "hydronet-bf16", 1, FRAMES),
                            "B=16": _recorded(episode_timing, "hydronet-bf16", 16, FRAMES_B16),
                            f"Adam iteration, {FRAMES_LONG} frames": optimizer_timing("hydronet-bf16", "adam"),
                            f"CMA-ES generation, 16 x {FRAMES_LONG} frames": optimizer_timing("hydronet-bf16", "cma")}
    out["hydronet-recovered-pressure"] = {"B=1": _recorded(episode_timing, "hydronet-recovered-pressure", 1, FRAMES),
                                          "distance_1.2s_m": _recorded(distance_sweep, "hydronet-recovered-pressure")}
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=1))

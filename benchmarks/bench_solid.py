"""Solid (projective dynamics) timings on the default fish (default muscle layer): forward / backward ms per step at
B = 1 and B = 16, PD iterations per step, mesh size and minimum angle, and the tail excursion the
default controller amplitude was calibrated to (5 Hz, vacuum). `run() -> dict` for the `make bench` driver;
`python benchmarks/bench_solid.py` prints the dict as JSON.

Scenario: the default controller in vacuum (5 Hz; B = 16 spreads 3-7 Hz over the batch), timed
over `steps` steps after `warmup` steps (past most of the activation ramp), float64 on the CPU;
each step starts L-BFGS from `predicted_start`, as the rollout does. torch runs one thread (it
only moves a few kB per step); the compiled solver spreads a batch's samples over numba's
threads (all cores by default; `NUMBA_NUM_THREADS` sets them).
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import torch

from fishsim.mesh import make_fish_mesh, mesh_quality
from fishsim.solid import SolidModel, pd_step, predicted_start, rest_state
from fishsim.solid.controller import WaveController
from fishsim.solid.model import SolverCache, SolverStats
from fishsim.solid.muscles import layer_muscles


def _controller(batch: int, length: float) -> WaveController:
    freqs = torch.linspace(3.0, 7.0, batch) if batch > 1 else torch.tensor([5.0])
    ctrl = WaveController.default(length, batch)
    return WaveController(ctrl.C, (2 * math.pi * freqs).to(torch.float64), ctrl.gamma, ctrl.t_a)


def _warm_state(model: SolidModel, ctrl: WaveController, warmup: int):
    """(q, qdot, qdot_prev) after ``warmup`` steps from rest."""
    q, qdot = rest_state(model, len(ctrl.C))
    qdot_prev, cache = qdot, SolverCache()
    with torch.no_grad():
        for k in range(warmup):
            qdot_prev, (q, qdot) = qdot, pd_step(model, q, qdot, ctrl.contraction(model, k * model.h),
                                                 start=predicted_start(q, qdot, qdot_prev, model.h), cache=cache)
    return q, qdot, qdot_prev


def _time_forward(model, ctrl, q, qdot, qdot_prev, start: int, steps: int) -> tuple[float, float, float]:
    """(ms per step, L-BFGS iterations per step of the batch's slowest sample, mean iterations
    per step and sample) without autograd."""
    its, cache = [], SolverCache()
    with torch.no_grad():
        t0 = time.perf_counter()
        for k in range(start, start + steps):
            guess = predicted_start(q, qdot, qdot_prev, model.h)
            qdot_prev = qdot
            q, qdot, info = pd_step(model, q, qdot, ctrl.contraction(model, k * model.h), return_info=True,
                                    start=guess, cache=cache)
            its.append(info.iterations)
        elapsed = time.perf_counter() - t0
    its = np.array(its)
    return 1e3 * elapsed / steps, float(its.max(1).mean()), float(its.mean())


def _time_backward(model, ctrl, q, qdot, start: int, steps: int) -> tuple[float, float]:
    """(ms per step of the adjoint pass, mean adjoint CG iterations per step); the loss is the
    tail's final lateral position plus the mean x-velocity, w.r.t. omega and the initial state."""
    omega = ctrl.omega.clone().requires_grad_()
    ctrl = WaveController(ctrl.C, omega, ctrl.gamma, ctrl.t_a)
    q, qdot = q.clone().requires_grad_(), qdot.clone().requires_grad_()
    q0, qdot0, cache = q, qdot, SolverCache()
    for k in range(start, start + steps):
        q, qdot = pd_step(model, q, qdot, ctrl.contraction(model, k * model.h), cache=cache)
    loss = q[:, :, 1].sum() + qdot[:, :, 0].mean()
    cache.stats = SolverStats()                         # the backward's statistics alone
    t0 = time.perf_counter()
    torch.autograd.grad(loss, [omega, q0, qdot0])
    elapsed = time.perf_counter() - t0
    return 1e3 * elapsed / steps, cache.stats.backward_iterations_total / steps


def tail_excursion(model: SolidModel, frequency: float = 5.0, t_end: float = 1.2, window: float = 0.2) -> float:
    """The calibration check of controller.DEFAULT_C: peak-to-peak lateral excursion (m) of the
    tail tip (X = 0) over the last ``window`` s of a ``t_end`` s stroke in vacuum."""
    ctrl = WaveController.default(model.mesh.length, 1, frequency)
    q, qdot = rest_state(model, 1)
    tail, ys, cache = int(np.argmin(model.mesh.points[:, 0])), [], SolverCache()
    n = round(t_end / model.h)
    with torch.no_grad():
        for k in range(n):
            q, qdot = pd_step(model, q, qdot, ctrl.contraction(model, k * model.h), cache=cache)
            if (k + 1) * model.h > t_end - window:
                ys.append(float(q[0, tail, 1]))
    return max(ys) - min(ys)


def run(steps: int = 20, warmup: int = 40, repeats: int = 7) -> dict:
    """Benchmark dict: mesh size, ms/step forward and backward at B = 1 and 16 (best of
    `repeats`, the machine is shared), iterations per step; and B = 1 ms/step at each edge length
    of the mesh-convergence study (3, 2, 1.4, 1 mm)."""
    torch.set_num_threads(1)
    mesh = make_fish_mesh()
    model = SolidModel(mesh, muscles=layer_muscles(mesh, 0.3))          # the default muscles
    out = {"nodes": model.n_nodes, "elements": mesh.n_elements, "actuated": model.n_muscles,
           "min_angle_deg": round(mesh_quality(mesh)["min_angle"], 2),
           "atol_N": model.options.atol, "backward_rtol": model.options.backward_rtol,
           "tail_peak_to_peak_5Hz_vacuum_m": round(tail_excursion(model), 5)}
    for B in (1, 16):
        ctrl = _controller(B, mesh.length)
        q, qdot, qdot_prev = _warm_state(model, ctrl, warmup)
        fwd, its, its_mean = min(_time_forward(model, ctrl, q, qdot, qdot_prev, warmup, steps) for _ in range(repeats))
        bwd, bits = min(_time_backward(model, ctrl, q, qdot, warmup, steps) for _ in range(repeats))
        out.update({f"forward_ms_B{B}": round(fwd, 3), f"backward_ms_B{B}": round(bwd, 3),
                    f"pd_iterations_B{B}": round(its, 2), f"pd_iterations_per_sample_B{B}": round(its_mean, 2),
                    f"adjoint_iterations_B{B}": round(bits, 2)})
    out["batch16_over_batch1_forward"] = round(out["forward_ms_B16"] / out["forward_ms_B1"], 2)
    out["batch16_over_batch1_backward"] = round(out["backward_ms_B16"] / out["backward_ms_B1"], 2)
    from benchmarks.study_solid_convergence import timing_study

    for r in timing_study(steps=steps, warmup=warmup, repeats=3):     # the cost of refining the fish
        out[f"edge_{r['edge_mm']:g}mm"] = {"nodes": r["nodes"], "forward_ms": round(r["forward_ms"], 2),
                                           "backward_ms": round(r["backward_ms"], 2)}
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))

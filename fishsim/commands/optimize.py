"""``fishsim optimize``: tune a swimmer's gait or design with a gradient method and/or CMA-ES.

Each method of ``optimizer.methods`` runs into <out_dir>/<method>/:

    history.h5    every iteration: the evaluated parameters x [n, P], objective J, gradient dJ/dx
                  (gradient methods), the method's mean, the best so far, cumulative fish-frames
                  and wall time, the failed members and why (``failures``: one line per
                  iteration, "member b at frame t: reason; ..."); CMA-ES also its whole
                  population (pop_x [n, lambda, P], pop_J)
    history.csv   the same, one row per iteration (without the population)
    state.pt      the optimiser's state after the last completed iteration (resume=true)
    best.yaml     the best parameters so far as a config: ``fishsim simulate --config best.yaml``

and <out_dir>/optimize.png/.svg (all methods on one figure, against iterations and fish-frames),
<out_dir>/summary.json. Every file is rewritten atomically after each iteration, so a run killed
at any point keeps everything up to its last completed iteration and continues from there; the
figure (1-2 s of drawing) after the first iteration, then at most every PLOT_EVERY_S seconds,
and after each method's last iteration.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import time
from pathlib import Path

import h5py
import numpy as np
import torch
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from fishsim.config import OptimizeConfig, SimulateConfig, to_yaml
from fishsim.errors import ConfigError, FishsimError, SimulationBlowUp
from fishsim.io.atomic import atomic_path, atomic_save, atomic_text
from fishsim.io.outdir import make_out_dir
from fishsim.optimize.config import OBJECTIVES, PARAMETERS
from fishsim.optimize.methods import make_method
from fishsim.optimize.problem import Problem, Space
from fishsim.render.plots import plot_optimisation_history
from fishsim.resources import announce_time, check_time

PLOT_EVERY_S = 30.0     # the history figure is redrawn at most this often during a method's run [s]


def run(cfg: OptimizeConfig) -> dict:
    """Run every method, write the outputs, print the summary; return it."""
    out_dir = make_out_dir("optimize", cfg.out_dir)
    _check_existing(cfg, out_dir)
    space = Space(list(cfg.params), list(cfg.params.values()))
    problem = Problem(cfg, space, cfg.objective, segment=cfg.optimizer.segment, truncate=cfg.optimizer.truncate)
    console = Console(stderr=True)
    histories: dict[str, list[dict]] = {}
    x0 = problem.initial_x()
    plotted, drawn = -math.inf, {}                     # time.monotonic() of the last figure, its iterations

    def report(method: str, rows: list[dict], last: bool = False) -> dict:
        """After every iteration: the method's best.yaml and summary.json of all so far; the
        figure too, unless it already shows them, when it is the method's last iteration or
        PLOT_EVERY_S have passed."""
        nonlocal plotted, drawn
        histories[method] = rows
        _write_best(cfg, space, rows, out_dir / method / "best.yaml")
        summary = {m: _summary(r, space, x0) for m, r in histories.items()}
        shown = {m: len(r) for m, r in histories.items()}
        if shown != drawn and (last or time.monotonic() - plotted >= PLOT_EVERY_S):
            _plot(histories, space, cfg, out_dir / "optimize")
            plotted, drawn = time.monotonic(), shown
        atomic_text(out_dir / "summary.json", json.dumps(summary, indent=2))
        return summary

    summary = {}
    for method in cfg.optimizer.methods:
        summary = report(method, optimise(problem, cfg, method, out_dir / method, console,
                                          on_iteration=lambda rows, m=method: report(m, rows)), last=True)
    _print(summary, space, cfg)
    Console().print(f"outputs: {out_dir}/ (per method: history.h5, history.csv, best.yaml; plot: optimize.png)")
    return summary


def _plot(histories: dict[str, list[dict]], space: Space, cfg: OptimizeConfig, stem: Path) -> None:
    """objective and parameters against iterations and fish-frames, every method on one figure."""
    unit = OBJECTIVES[cfg.objective.name]
    plot_optimisation_history(
        {m: {"objective": [r["J"] for r in rows], "best": [r["best_J"] for r in rows],
             "frames": [r["frames"] for r in rows],
             "parameters": {n: [r["x"][i] for r in rows] for i, n in enumerate(space.names)}}
         for m, rows in histories.items() if rows},
        stem, objective_label=f"{cfg.objective.name} J [{unit}]", units=PARAMETERS)


def _check_existing(cfg: OptimizeConfig, out_dir) -> None:
    """A run folder holding an earlier run is continued (resume=true) or replaced
    (overwrite=true), never silently restarted; resume=true needs something to resume."""
    started = [m for m in cfg.optimizer.methods if (out_dir / m / "state.pt").exists()]
    if started and not (cfg.resume or cfg.overwrite):
        raise ConfigError(f"{out_dir} already holds a run of {', '.join(started)}; pass resume=true to continue it, "
                          "overwrite=true to start again, or another out_dir")
    if cfg.resume and not started:
        raise ConfigError(f"resume=true but {out_dir} holds no run to continue (no <method>/state.pt); "
                          "drop resume=true to start one")


def optimise(problem: Problem, cfg: OptimizeConfig, name: str, folder: Path, console: Console,
             on_iteration=None) -> list[dict]:
    """One method's iterations, resumed from ``folder/state.pt`` when cfg.resume; returns the
    history rows; ``on_iteration(rows)`` after each completed iteration. A gradient run whose
    episode blows up or whose objective is not finite stops with a one-line error, the history
    up to the last completed iteration kept."""
    folder.mkdir(parents=True, exist_ok=True)
    o, space = cfg.optimizer, problem.space
    z0 = space.to_z(torch.tensor(problem.initial_x(), dtype=torch.float64)).tolist()
    method = make_method(name, z0, o.lr, o.sigma, o.popsize, o.seed, o.options)
    rows: list[dict] = []
    state_path = folder / "state.pt"
    if cfg.resume and state_path.exists():
        saved = torch.load(state_path, weights_only=False)
        method.load(saved["method"])
        rows = saved["rows"]
    cost = cfg.iteration_cost(name)
    left = o.iterations - len(rows)
    if o.budget is not None:
        left = min(left, max(0, (o.budget - (rows[-1]["frames"] if rows else 0)) // cost))
    fish = getattr(method, "popsize", 0) or 1
    executor = submitit_executor(o.submitit, folder / "jobs") if o.launcher == "submitit" and not method.uses_gradient else None
    seconds = check_time(cfg, fish, cfg.frames * left, gradient=method.uses_gradient)
    announce_time(seconds, f"{name}, {left} iterations", cfg.device)
    columns = (TextColumn(f"optimize {name}"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[status]}"),
               TimeElapsedColumn())
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task(name, total=o.iterations, completed=len(rows), status=_status(rows))
        for it in range(len(rows), o.iterations):
            if o.budget is not None and (rows[-1]["frames"] if rows else 0) + cost > o.budget:
                break
            z = method.ask()
            try:
                ev = (problem.evaluate(z, gradient=True, isolate=False) if method.uses_gradient else
                      problem.evaluate_population(z, o.max_batch, executor))
            except SimulationBlowUp as err:
                raise FishsimError(f"{name} stopped at iteration {it + 1}: {err}; the history of the "
                                   f"{len(rows)} completed iterations is kept in {folder}") from None
            if not bool(torch.isfinite(ev.J).any()):
                raise FishsimError(f"{name} stopped at iteration {it + 1}: every candidate failed "
                                   f"({_reasons(ev.failures)}); the history is kept in {folder}")
            method.tell(z, ev.J, ev.grad_z)
            rows.append(_row(it, name, space, z, ev, method, rows))
            _save(folder, rows, space, cfg, name)
            atomic_save({"method": method.state(), "rows": rows}, state_path)
            if on_iteration is not None:
                on_iteration(rows)
            bar.update(task, completed=it + 1, status=_status(rows))
            if not console.is_terminal:                 # piped or logged: a plain line per iteration
                print(f"[{time.strftime('%H:%M:%S')}] optimize {name}: iteration {it + 1}/{o.iterations}, "
                      f"{rows[-1]['frames']} fish-frames, {_status(rows)}", flush=True)
    return rows


def submitit_executor(options: dict, folder: Path):
    """A submitit executor for a population's chunks, logs in ``folder``: options' ``cluster``
    (slurm, local, debug; default: slurm where sbatch exists, else local) and the rest passed
    to update_parameters."""
    try:
        import submitit
    except ImportError:
        raise ConfigError("optimizer.launcher=submitit needs submitit: .venv/bin/pip install -e '.[sweep]'") from None
    opts = dict(options)
    executor = submitit.AutoExecutor(folder=folder, cluster=opts.pop("cluster", None))
    try:
        executor.update_parameters(**opts)
    except (ValueError, TypeError) as err:
        raise ConfigError(f"optimizer.submitit: {err}") from None
    return executor


def _row(it: int, name: str, space: Space, z: torch.Tensor, ev, method, rows: list[dict]) -> dict:
    """One iteration's record: the best candidate of this iteration, the gradient, the mean,
    the best so far and the cumulative cost."""
    J = ev.J.double()
    finite = torch.where(torch.isfinite(J), J, torch.full_like(J, -math.inf))
    k = int(torch.argmax(finite))
    x = space.to_x(z)
    grad = [math.nan] * len(space.names)
    if ev.grad_z is not None:
        zk = z[k].clone().requires_grad_(True)
        jac = torch.autograd.functional.jacobian(space.to_x, zk).diagonal()   # dx/dz, each x depends on its z
        grad = (ev.grad_z[k] / jac).tolist()
    prev = rows[-1] if rows else None
    best = prev is None or float(J[k]) > prev["best_J"]
    return {"iteration": it + 1, "method": name, "x": x[k].tolist(), "J": float(J[k]), "grad": grad,
            "mean_x": space.to_x(method.mean()).tolist(),
            "best_J": float(J[k]) if best else prev["best_J"], "best_x": x[k].tolist() if best else prev["best_x"],
            "frames": (prev["frames"] if prev else 0) + ev.frames,
            "seconds": (prev["seconds"] if prev else 0.0) + ev.seconds,
            "failed": len(ev.failures), "failures": {str(b): list(v) for b, v in ev.failures.items()},
            "pop_x": x.tolist(), "pop_J": J.tolist()}


def _status(rows: list[dict]) -> str:
    if not rows:
        return ""
    r = rows[-1]
    return f"J {r['J']:.4g}  best {r['best_J']:.4g}  x {', '.join(f'{v:.4g}' for v in r['x'])}"


def _reasons(failures: dict) -> str:
    """'member b at frame t: reason; ...' (keys may be ints or, in a saved history, strings)."""
    return "; ".join(f"member {b} at frame {f}: {why}" for b, (f, why) in sorted(failures.items(), key=lambda i: int(i[0])))


# ------------------------------------------------------------------------------------------------
# Outputs (each rewritten atomically after every iteration)
# ------------------------------------------------------------------------------------------------


def _save(folder: Path, rows: list[dict], space: Space, cfg: OptimizeConfig, name: str) -> None:
    with atomic_path(folder / "history.h5") as tmp, h5py.File(tmp, "w") as f:
        for key in ("iteration", "J", "best_J", "frames", "seconds", "failed"):
            f[key] = np.array([r[key] for r in rows])
        for key in ("x", "grad", "mean_x", "best_x"):
            f[key] = np.array([r[key] for r in rows], dtype=np.float64)
        f["failures"] = np.array([_reasons(r["failures"]) for r in rows], dtype=h5py.string_dtype())
        if len({len(r["pop_J"]) for r in rows}) == 1:
            f["pop_x"] = np.array([r["pop_x"] for r in rows], dtype=np.float64)
            f["pop_J"] = np.array([r["pop_J"] for r in rows], dtype=np.float64)
        f.attrs.update({"method": name, "parameters": space.names,
                        "units": [PARAMETERS[n] for n in space.names], "objective": cfg.objective.name,
                        "objective_unit": OBJECTIVES[cfg.objective.name], "frames_per_episode": cfg.frames,
                        "config": to_yaml(cfg)})
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["iteration", "frames", "seconds", "J", "best_J", "failed",
                *(f"{k}_{n}" for k in ("x", "grad", "mean") for n in space.names), "failures"])
    for r in rows:
        w.writerow([r["iteration"], r["frames"], f"{r['seconds']:.3f}", repr(r["J"]), repr(r["best_J"]), r["failed"],
                    *map(repr, r["x"] + r["grad"] + r["mean_x"]), _reasons(r["failures"])])
    atomic_text(folder / "history.csv", buf.getvalue())


def _write_best(cfg: OptimizeConfig, space: Space, rows: list[dict], path: Path) -> None:
    """The episode's config with the best parameters: a complete ``fishsim simulate`` config."""
    if not rows:
        return
    sim = SimulateConfig(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(SimulateConfig)})
    best = dict(zip(space.names, rows[-1]["best_x"]))
    c = sim.controller
    sim.controller = dataclasses.replace(c, frequency=best.get("frequency", c.frequency),
                                         amplitude=best.get("amplitude", c.amplitude),
                                         wave_number=best.get("wave_number", c.wave_number))
    if "youngs_modulus" in best:
        sim.solid = dataclasses.replace(sim.solid, material=dataclasses.replace(
            sim.solid.material, youngs_modulus=best["youngs_modulus"]))
    sim.out_dir = None
    header = (f"# best of fishsim optimize ({rows[-1]['method']}): {cfg.objective.name} J = {rows[-1]['best_J']:.6g} "
              f"{OBJECTIVES[cfg.objective.name]}\n# run it: fishsim simulate --config {path}\n")
    atomic_text(path, header + to_yaml(sim))


def _summary(rows: list[dict], space: Space, x0: list[float]) -> dict:
    if not rows:
        return {"iterations": 0}
    last = rows[-1]
    return {"start": dict(zip(space.names, x0)), "best": dict(zip(space.names, last["best_x"])),
            "best_J": last["best_J"], "iterations": len(rows), "fish_frames": last["frames"],
            "wall_s": round(last["seconds"], 2), "failed_members": sum(r["failed"] for r in rows),
            "first_best_iteration": next(r["iteration"] for r in rows if r["best_J"] == last["best_J"])}


def _print(summary: dict, space: Space, cfg: OptimizeConfig) -> None:
    unit = OBJECTIVES[cfg.objective.name]
    table = Table(title=f"fishsim optimize: {cfg.objective.name} [{unit}], {cfg.frames} frames, fluid={cfg.fluid.model}")
    for col in ("method", "start", "best", f"best J [{unit}]", "iterations", "fish-frames", "wall [s]", "failed"):
        table.add_column(col, justify="right")
    fmt = lambda d: ", ".join(f"{n} {d[n]:.4g}" for n in space.names)
    for m, s in summary.items():
        if s["iterations"]:
            table.add_row(m, fmt(s["start"]), fmt(s["best"]), f"{s['best_J']:.5g}", str(s["iterations"]),
                          str(s["fish_frames"]), f"{s['wall_s']:.1f}", str(s["failed_members"]))
    Console(width=max(Console().width, 140)).print(table)

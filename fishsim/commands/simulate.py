"""``fishsim simulate``: one episode of B fish swimming, written as a crash-safe HDF5 trajectory."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import torch
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from fishsim.config import SimulateConfig, to_yaml
from fishsim.episode import Episode, build_episode
from fishsim.errors import ConfigError, FishsimError
from fishsim.fluid.grid import curl, faces_to_centres
from fishsim.io.outdir import make_out_dir, output_file
from fishsim.io.trajectory import TrajectoryWriter, trajectory_series
from fishsim.io.xdmf import write_xdmf
from fishsim.resources import announce_time, check_time
from fishsim.rollout import METRICS, PhaseTimer, rollout


def open_writer(cfg: SimulateConfig, episode: Episode, path) -> TrajectoryWriter:
    """Declare every series of the run and write the static data (mesh, controller, config)."""
    sw, p = episode.swimmer, episode.params
    mesh, B = sw.solid.mesh, p.E.shape[0]
    fluid_shape = (cfg.tank.H, cfg.tank.W) if sw.fluid.exerts_force else None
    series = trajectory_series(mesh.n_nodes, B, sw.solid.n_muscles, METRICS, fluid_shape)
    static = {
        "mesh/points": mesh.points, "mesh/triangles": mesh.triangles, "mesh/surface": mesh.surface,
        "mesh/actuator": mesh.actuator, "mesh/muscles": sw.solid.muscles,
        "controller/frequency": (p.controller.omega / (2 * math.pi)).cpu().numpy(),
        "controller/amplitude": p.controller.C.cpu().numpy(),
        "controller/wave_number": p.controller.gamma.cpu().numpy(),
        "controller/youngs_modulus": p.E.cpu().numpy(),
    }
    return TrajectoryWriter(path, series, static, to_yaml(cfg), cfg.h, cfg.flush_every, dx=cfg.tank.dx)


def frame_record(t: int, state, out, metrics: dict, h: float) -> dict:
    """The per-frame series of frame t (after the step) as numpy arrays."""
    rec = {"solid/q": state.q, "solid/qdot": state.qdot, "solid/f_ext": out.f_ext,
           "controller/activation": out.contraction}
    rec = {k: v.detach().cpu().numpy() for k, v in rec.items()}
    rec.update({f"metrics/{k}": v.detach().cpu().numpy() for k, v in metrics.items()})
    rec["metrics/time"] = (t + 1) * h
    return rec


def fluid_record(t: int, state, out, dx: float) -> dict:
    """Fluid fields of frame t at cell centres (and a on vertices) as numpy arrays."""
    v = faces_to_centres(curl(state.fluid.a, dx))
    fields = {"fluid/p": state.fluid.p[:, 0], "fluid/vx": v[:, 0], "fluid/vy": v[:, 1],
              "fluid/mask": out.boundary.mask[:, 0], "fluid/a": state.fluid.a[:, 0]}
    rec = {k: x.detach().float().cpu().numpy() for k, x in fields.items()}
    rec["fluid/frame"] = t
    return rec


def run(cfg: SimulateConfig) -> dict:
    """Simulate, writing the trajectory as it goes; print and return the summary."""
    out_dir = make_out_dir("simulate", cfg.out_dir)
    path = output_file(out_dir, cfg.output, "trajectory.h5")
    if path.exists() and not cfg.overwrite:
        raise ConfigError(f"{path} already exists (an earlier run's result); pass overwrite=true to replace it "
                          "or choose another out_dir / output")
    seconds = check_time(cfg, cfg.batch.size, cfg.frames)
    episode = build_episode(cfg)
    announce_time(seconds, f"{cfg.frames} frames of {cfg.batch.size} fish", cfg.device)
    sw = episode.swimmer
    writer = open_writer(cfg, episode, path)
    state = sw.initial_state(episode.params, episode.origin)
    history = {k: [] for k in METRICS}
    t_start, timer = time.perf_counter(), PhaseTimer()

    near_wall: dict[int, int] = {}                 # fish -> first frame within a body width of a wall
    bounds = wall_bounds(cfg, sw.solid.mesh)
    with _progress() as progress:
        task = progress.add_task("simulate", total=cfg.frames)

        def on_frame(t, s, out, metrics):
            if sw.fluid.exerts_force:
                for b in wall_proximity(bounds, s.q):
                    if b not in near_wall:
                        near_wall[b] = t + 1
                        progress.console.print(f"[yellow]warning: fish {b} came within a body width of the tank wall at "
                                               f"frame {t + 1}; from here on its motion is wall-dominated[/]")
            writer.append(frame_record(t, s, out, metrics, cfg.h))
            if sw.fluid.exerts_force and (t + 1) % cfg.fluid_stride == 0:
                writer.append(fluid_record(t, s, out, cfg.tank.dx))
            writer.end_frame()
            for k, v in metrics.items():
                history[k].append(v.detach().cpu().numpy())
            progress.update(task, advance=1, description=f"simulate  head x {float(metrics['head_x'][0]):.4f} m")
            if not progress.console.is_terminal and (t + 1) % max(1, cfg.frames // 10) == 0:
                print(f"[{time.strftime('%H:%M:%S')}] simulate: frame {t + 1}/{cfg.frames}, head x "
                      f"{float(metrics['head_x'][0]):.4f} m, {time.perf_counter() - t_start:.0f} s", flush=True)

        # a batch carries on past a fish that blows up (marked failed, held at rest); one fish stops
        failures = {} if episode.params.E.shape[0] > 1 else None
        try:
            with torch.no_grad():
                rollout(sw, state, episode.params, cfg.frames, on_frame=on_frame, failures=failures, timer=timer)
        except (FishsimError, KeyboardInterrupt) as err:
            writer.close(complete=False, message=f"stopped: {err}", attrs=_grid_attrs(cfg))
            write_xdmf(path)
            raise type(err)(f"{err} (partial trajectory kept in {path}, marked incomplete)") from None
    wall = time.perf_counter() - t_start
    rows = fish_summaries(cfg, episode, history)
    summary = summarise(rows, len(history["head_x"]), wall, timer)
    write_summary_csv(rows, out_dir / "summary.csv")
    failed = {str(b): {"frame": f, "reason": why} for b, (f, why) in sorted((failures or {}).items())}
    writer.close(complete=True, attrs={**_grid_attrs(cfg), "failed_fish": json.dumps(failed),
                                       "near_wall_frame": json.dumps({str(b): f for b, f in near_wall.items()}),
                                       **{f"summary_{k}": v for k, v in summary.items() if isinstance(v, (int, float))}})
    summary["trajectory"] = str(path)
    for b, fail in failed.items():
        Console(stderr=True).print(f"[yellow]fish {b} blew up at frame {fail['frame']} and was held at rest from "
                                   f"then on (the others carried on): {escape(fail['reason'])}[/]")
    if failed:
        summary["failed fish"] = ", ".join(failed)
    if len(rows) > 1:
        _print_fish(rows, failed)
    summary["paraview"] = str(write_xdmf(path))
    _print(summary)
    return summary


def wall_bounds(cfg: SimulateConfig, mesh) -> tuple[list[float], list[float]]:
    """(lo, hi) corners (x, y in m) of the region farther than one body width (the mesh's largest
    thickness) from the fluid region's edge (the inner side of the wall bands)."""
    width = float(np.ptp(mesh.points[:, 1]))
    t, dx = cfg.tank, cfg.tank.dx
    return ([t.wall_x * dx + width, t.wall_y * dx + width],
            [(t.W - t.wall_x) * dx - width, (t.H - t.wall_y) * dx - width])


def wall_proximity(bounds: tuple[list[float], list[float]], q: torch.Tensor) -> list[int]:
    """The fish [B] with a node outside ``wall_bounds``, i.e. within a body width of a wall."""
    lo, hi = (q.new_tensor(b) for b in bounds)
    close = ((q < lo) | (q > hi)).flatten(1).any(1)
    return torch.nonzero(close).flatten().tolist()


def _grid_attrs(cfg: SimulateConfig) -> dict:
    return {"grid_h": cfg.tank.H, "grid_w": cfg.tank.W, "grid_dx": cfg.tank.dx, "fluid_model": cfg.fluid.model}


def summarise(rows: list[dict], n_frames: int, wall: float, timer: PhaseTimer) -> dict:
    """The run's summary: fish 0's numbers (``rows`` from ``fish_summaries``), the batch size and
    the wall time split solid/fluid/coupling (``timer``, the rollout's)."""
    split = timer.seconds
    return {"frames": n_frames, "batch": len(rows), **{k: v for k, v in rows[0].items() if k != "fish"},
            "wall time [s]": wall, "solid [s]": split["solid"], "fluid [s]": split["fluid"],
            "coupling [s]": split["coupling"]}


def fish_summaries(cfg: SimulateConfig, episode: Episode, history: dict) -> list[dict]:
    """One row per fish: its controller, the head's distance, the mean speed through the water
    (``fishsim.optimize.problem.mean_speed``) and the tail's peak-to-peak excursion over the
    whole tail beats of the second half, the mean thrust, and the Strouhal number f A / U (NaN
    with less than one beat or no forward speed). In a swim tunnel the distances count the water
    swum through."""
    from fishsim.optimize.problem import mean_speed, travel

    m = {k: torch.from_numpy(np.stack(v)).double() for k, v in history.items()}    # [frames, B]
    n, h = m["head_x"].shape[0], cfg.h
    s, water = travel(m, h), h * m["tunnel_u"].sum(0)
    c = episode.params.controller
    freqs = (c.omega / (2 * math.pi)).cpu().double()
    beats = torch.floor((n - n // 2) * h * freqs + 1e-9)                 # whole beats in the second half
    # the history starts after frame 1: s[0] stands for t = 0 and the window ends at s[-1]
    speeds = mean_speed(s[1:], s[0], h, beats.clamp(min=1) / freqs) if n > 1 else torch.full_like(freqs, math.nan)
    rows = []
    for b in range(m["head_x"].shape[1]):
        f, k = float(freqs[b]), round(float(beats[b]) / float(freqs[b]) / h)
        speed = float(speeds[b]) if k else float("nan")
        tail = m["tail_y"][n - k:, b] if k else m["tail_y"][n // 2:, b]
        amplitude = float(tail.max() - tail.min()) if len(tail) else 0.0
        st = f * amplitude / speed if k and speed > 1e-6 else float("nan")
        rows.append({"fish": b, "frequency [Hz]": f, "amplitude C [1/m]": float(c.C[b]),
                     "head distance [m]": float(m["head_x"][-1, b] - m["head_x"][0, b] + water[b]),
                     "mean speed [m/s]": speed, "mean thrust x [N]": float(m["thrust_x"][:, b].mean()),
                     "tail peak-to-peak [m]": amplitude, "Strouhal f A / U": st})
    return rows


def write_summary_csv(rows: list[dict], path) -> None:
    """The per-fish rows as CSV (one line per fish)."""
    import csv

    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def _progress() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), TimeRemainingColumn(), transient=False)


def _print_fish(rows: list[dict], failed: dict) -> None:
    """One row per fish of a batch (summary.csv holds the same)."""
    table = Table(title="per fish (summary.csv)")
    for key in rows[0]:
        table.add_column(escape(key), justify="right")
    for r in rows:
        table.add_row(*(f"{v:.4g}" if isinstance(v, float) else str(v) for v in r.values()),
                      style="yellow" if str(r["fish"]) in failed else None)
    Console(width=max(Console().width, 140)).print(table)


def _print(summary: dict) -> None:
    table = Table(title="fishsim simulate (fish 0)", show_header=False)
    for k, v in summary.items():
        table.add_row(escape(k), f"{v:.4g}" if isinstance(v, float) else escape(str(v)))
    Console().print(table)

"""A synthetic but real-looking trajectory for tests, benchmarks and trying the renderer
without a simulation: a fish-shaped mesh gliding along x with a travelling body wave, a
pressure dipole (high in front of the head, low behind) and a vortex in its wake.

Written with ``TrajectoryWriter`` in the layout ``fishsim simulate`` writes.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from fishsim.io.trajectory import TrajectoryWriter, trajectory_series


def fish_mesh(length: float, nx: int = 16, ny: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A structured fish mesh: points [N,2] (nose at x = 0), triangles [T,3], surface nodes [S].
    Half-width 0.1 L (0.15 + sin(pi x / L)) / 1.15; 2 ny + 1 nodes across."""
    x = np.linspace(0.0, length, nx + 1)
    half = 0.1 * length * (0.15 + np.sin(np.pi * x / length)) / 1.15
    s = np.linspace(-1.0, 1.0, 2 * ny + 1)
    points = np.array([(xi, si * hi) for xi, hi in zip(x, half) for si in s])
    rows = len(s)
    tris = []
    for i in range(nx):
        for j in range(rows - 1):
            a, b = i * rows + j, (i + 1) * rows + j
            tris += [(a, b, b + 1), (a, b + 1, a + 1)]
    idx = np.arange(len(points)).reshape(nx + 1, rows)
    surface = np.unique(np.concatenate([idx[:, 0], idx[:, -1], idx[0], idx[-1]]))
    return points, np.array(tris), surface


def fish_pose(points: np.ndarray, t: float, start: tuple[float, float], speed: float,
              freq: float = 2.0) -> np.ndarray:
    """World positions at time t: the nose (material x = 0) leads in +x, the body translates by
    speed * t and carries a lateral travelling wave growing towards the tail."""
    L = np.ptp(points[:, 0])
    xm = L - points[:, 0]                     # head at the largest x
    wave = 0.08 * L * (points[:, 0] / L) ** 2 * np.sin(2 * np.pi * (freq * t - points[:, 0] / L))
    return np.column_stack([start[0] + speed * t + xm, start[1] + points[:, 1] + wave])


def fluid_fields(q: np.ndarray, H: int, W: int, dx: float) -> dict[str, np.ndarray]:
    """Pressure dipole around the head, a vortex behind the tail, and a soft mask of the fish."""
    yc, xc = (np.mgrid[0:H, 0:W] + 0.5) * dx
    head, tail = q[np.argmax(q[:, 0])], q[np.argmin(q[:, 0])]
    L = head[0] - tail[0]
    r2 = lambda c: ((xc - c[0]) ** 2 + (yc - c[1]) ** 2) / (0.25 * L) ** 2
    p = 40.0 * np.exp(-r2(head + [0.1 * L, 0])) - 25.0 * np.exp(-r2(tail - [0.1 * L, 0]))
    vortex = tail - [0.3 * L, 0]
    g = 0.2 * np.exp(-r2(vortex))
    vx, vy = -g * (yc - vortex[1]) / L, g * (xc - vortex[0]) / L
    mask = ((np.abs(yc - q[:, 1].mean()) < 0.08 * L) & (xc > tail[0]) & (xc < head[0])).astype(float)
    return {"p": p, "vx": vx, "vy": vy, "mask": mask}


def surface_forces(points: np.ndarray, surface: np.ndarray, magnitude: float) -> np.ndarray:
    """Forces on surface nodes along the inward material normal (a uniform pressure push of
    ``magnitude`` N/m per node), zero on interior nodes."""
    f = np.zeros_like(points)
    side = np.sign(points[surface, 1])
    ends = np.where(points[surface, 0] < points[:, 0].mean(), 1.0, -1.0)   # world x is mirrored
    normal = np.where(side[:, None] != 0, np.column_stack([0 * side, side]),
                      np.column_stack([ends, 0 * ends]))
    f[surface] = -magnitude * normal
    return f


def write_synthetic_trajectory(path: str | Path, n_frames: int = 12, H: int = 20, W: int = 60,
                               dx: float = 2.5e-3, fluid_every: int = 2, batch: int = 1,
                               fluid: bool = True, complete: bool = True, grid_attrs: bool = True,
                               length: float | None = None, h: float = 0.01) -> Path:
    """Write a trajectory of a fish crossing a H x W grid; ``complete=False`` leaves it as a
    killed run would (flushed frames, ``complete`` False, at ``<path>.part``).  Returns the
    path of the file written."""
    length = length or 0.3 * W * dx
    points, tris, surface = fish_mesh(length)
    start = (0.1 * W * dx, 0.5 * H * dx)
    speed = 0.4 * W * dx / max(n_frames * h, 1e-12)
    series = trajectory_series(len(points), batch, 2, ["head_x"], (H, W) if fluid else None)
    static = {"mesh/points": points, "mesh/triangles": tris, "mesh/surface": surface,
              "mesh/actuator": np.where(np.arange(len(tris)) % 2, 1, 2)}
    w = TrajectoryWriter(path, series, static, "synthetic: true\n", h=h, flush_every=1)
    for t in range(n_frames):
        _write_frame(w, t, t * h, points, surface, start, speed, batch, (H, W, dx) if fluid else None,
                     fluid and t % fluid_every == 0)
    if not complete:
        w.flush()               # as a killed run: attributes never finalised, the file left as <name>.part
        return w.partial
    w.close(complete=True)
    if grid_attrs and fluid:
        with h5py.File(path, "r+") as f:
            f.attrs.update(grid_h=H, grid_w=W, grid_dx=dx)
    return Path(path)


def _write_frame(w, t, time, points, surface, start, speed, batch, grid, with_fluid) -> None:
    """One frame of every sample (sample b is shifted up by b * 2 dx)."""
    qs = np.stack([fish_pose(points, time, (start[0], start[1]), speed * (1 + 0.1 * b)) for b in range(batch)])
    fs = np.stack([surface_forces(points, surface, 0.5 + 0.2 * np.sin(7 * time)) for _ in qs])
    w.append({"solid/q": qs, "solid/qdot": np.zeros_like(qs) + [speed, 0.0], "solid/f_ext": fs,
              "controller/activation": np.zeros((batch, 2)),
              "metrics/head_x": qs[:, :, 0].max(axis=1), "metrics/time": time})
    if with_fluid:
        fields = [fluid_fields(q, *grid) for q in qs]
        w.append({f"fluid/{k}": np.stack([f[k] for f in fields]) for k in ("p", "vx", "vy", "mask")})
        w.append({"fluid/frame": t})
    w.end_frame()

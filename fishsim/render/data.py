"""What the renderer draws, read from a trajectory file for one batch sample.

``RenderData`` holds plain arrays: the fish (mesh and per-frame node positions, velocities,
fluid-to-solid forces), the stored fluid frames of that sample, and the grid geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fishsim.errors import InputFileError
from fishsim.io.trajectory import open_trajectory, read_trajectory

DEFAULT_DX = 2.5e-3
FLUID_KEYS = ("p", "vx", "vy", "mask")


@dataclass
class RenderData:
    """One sample of a trajectory, clipped to the frames that were written.

    points [N,2] material coordinates; triangles [T,3]; surface [S] node indices;
    time [n] s; q, qdot, f_ext [n,N,2] (m, m/s, N/m); fluid: {p, vx, vy, mask: [n_f,H,W]} at
    cell centres (row = y, column = x); fluid_frame [n_f] the frame index of each fluid frame;
    grid (H, W, dx) or None (vacuum run without grid attributes); actuator [T] the muscle side
    of each triangle (0 none, 1 top, 2 bottom) if the file has it.
    """

    path: Path
    points: np.ndarray
    triangles: np.ndarray
    surface: np.ndarray
    time: np.ndarray
    q: np.ndarray
    qdot: np.ndarray
    f_ext: np.ndarray
    fluid: dict[str, np.ndarray] = field(default_factory=dict)
    fluid_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    grid: tuple[int, int, float] | None = None
    complete: bool = True
    message: str = ""
    actuator: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return len(self.time)

    @property
    def name(self) -> str:
        return self.path.stem

    @property
    def has_fluid(self) -> bool:
        return "p" in self.fluid and len(self.fluid_frame) > 0

    @property
    def fish_length(self) -> float:
        return float(np.ptp(self.points[:, 0])) or 1.0

    def fluid_index(self, t: int) -> int | None:
        """Index of the latest stored fluid frame <= t (None before the first one or in vacuum)."""
        if not self.has_fluid:
            return None
        k = int(np.searchsorted(self.fluid_frame, t, side="right")) - 1
        return k if k >= 0 else None

    def extent(self) -> tuple[float, float, float, float]:
        """(x0, x1, y0, y1) of the view in metres: the fluid box, else the fish's reach."""
        if self.grid is not None:
            H, W, dx = self.grid
            return 0.0, W * dx, 0.0, H * dx
        lo, hi = self.q.reshape(-1, 2).min(0), self.q.reshape(-1, 2).max(0)
        m = 0.5 * self.fish_length
        return lo[0] - m, hi[0] + m, lo[1] - m, hi[1] + m


def load_render_data(path: str | Path, sample: int = 0) -> RenderData:
    """Read sample ``sample`` of a trajectory; InputFileError (one line) if it is not one."""
    tr = read_trajectory(path, load_fluid=False)
    path = Path(path)
    for key in ("mesh/points", "mesh/triangles", "solid/q"):
        if key not in tr.data:
            raise InputFileError(f"{path} is not a fishsim trajectory with a fish (no /{key})")
    q = tr["solid/q"]
    if sample >= q.shape[1]:
        raise InputFileError(f"{path} has {q.shape[1]} batch samples; sample={sample} does not exist")
    n = min(tr.n_frames, len(q), len(tr["metrics/time"]))
    zeros = np.zeros_like(q[:n, sample])
    data = RenderData(
        path=path,
        points=np.asarray(tr["mesh/points"], float),
        triangles=np.asarray(tr["mesh/triangles"], int),
        surface=_surface(tr.data),
        time=np.asarray(tr["metrics/time"][:n], float),
        q=q[:n, sample],
        qdot=tr["solid/qdot"][:n, sample] if "solid/qdot" in tr.data else zeros,
        f_ext=tr["solid/f_ext"][:n, sample] if "solid/f_ext" in tr.data else zeros,
        complete=tr.complete,
        message=str(tr.attrs.get("message", "")),
        actuator=np.asarray(tr["mesh/actuator"], int) if "mesh/actuator" in tr.data else None,
    )
    data.fluid, data.fluid_frame = _read_fluid(path, sample, n)
    data.grid = _grid(tr.attrs, data.fluid)
    return data


def _surface(data: dict) -> np.ndarray:
    """Surface node indices; all nodes if the file has none."""
    if "mesh/surface" in data:
        return np.asarray(data["mesh/surface"], int)
    return np.arange(len(data["mesh/points"]))


def _read_fluid(path: Path, sample: int, n: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The stored fluid frames of one sample whose frame index is < n (all fields same length)."""
    with open_trajectory(path) as f:
        if "fluid/frame" not in f or "fluid/p" not in f:
            return {}, np.zeros(0, int)
        keys = [k for k in FLUID_KEYS if f"fluid/{k}" in f]
        rows = min([len(f["fluid/frame"])] + [len(f[f"fluid/{k}"]) for k in keys])
        frame = np.asarray(f["fluid/frame"][:rows], int)
        rows = int(np.searchsorted(frame, n, side="left"))
        fluid = {k: np.asarray(f[f"fluid/{k}"][:rows, sample], np.float32) for k in keys}
    return fluid, frame[:rows]


def _grid(attrs: dict, fluid: dict) -> tuple[int, int, float] | None:
    """(H, W, dx) from the file's grid attributes, else from the fluid array shape."""
    dx = float(attrs.get("grid_dx", DEFAULT_DX))
    for h, w in (("grid_h", "grid_w"), ("grid_H", "grid_W")):    # grid_H/W: files before 2026-11-25
        if h in attrs and w in attrs:
            return int(attrs[h]), int(attrs[w]), dx
    if "p" in fluid:
        H, W = fluid["p"].shape[-2:]
        return int(H), int(W), dx
    return None

"""HDF5 trajectories: one file per run, readable after a crash, ``complete`` marked at the end.

Layout (every time series has the frame axis first and a batch axis B second)::

    /mesh/{points [N,2], triangles [T,3], surface [S], actuator [T]}
    /solid/{q, qdot, f_ext}            [T, B, N, 2]   m, m/s, N (per unit depth)
    /controller/activation             [T, B, n_act]  muscle contraction (top/bottom elements)
    /controller/{frequency, amplitude, wave_number, youngs_modulus}   [B]
    /fluid/{p, vx, vy, mask}           [T', B, H, W]  Pa, m/s (cell centres), 1 = solid
    /fluid/a                           [T', B, H+1, W+1]  m^2/s (vertices; exact restart)
    /fluid/frame                       [T']           frame index of each stored fluid frame
    /metrics/time                      [T]            s
    /metrics/<name>                    [T, B]         e.g. head_x, thrust_x
    /config                            the resolved config as a YAML string
    /fluid/grid, /xdmf                 added by fishsim.io.xdmf for its sidecars: the fluid grid as
                                       quadrilaterals, and per-frame views (virtual datasets, no
                                       data) that ``read_trajectory`` skips
    attributes: fishsim_version, h, units, complete, n_frames (final), message

The file is written as ``<name>.part`` and renamed to its name when the run ends (complete or
stopped and marked incomplete). Frames are kept in memory and appended every ``flush_every``
frames with the file opened, written and closed again, so between flushes the file on disk is a
closed, consistent HDF5 file: a killed run (even SIGKILL) leaves a ``<name>.part`` that plain
h5py and HDF5 tools open without ``h5clear``, holding every flushed frame, with
``complete = False``; and a running simulation's file can be read (between its flushes).
"""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Self

import h5py
import numpy as np

from fishsim import __version__
from fishsim.errors import FishsimError, InputFileError
from fishsim.io import conventions

CLOSE_WAIT = 120.0  # s a run's end waits for a program reading its trajectory

UNITS = "SI: m, s, kg, Pa; 2D forces per unit depth (N/m); densities per unit area"


class TrajectoryWriter:
    """Append frames to a trajectory file.

    series: {dataset path: (per-frame shape, dtype)} for every time series the run will write,
        declared when the file is created.
    static: {dataset path: array} written once (mesh, controller parameters).
    """

    def __init__(self, path: str | Path, series: dict[str, tuple[tuple, str]],
                 static: dict[str, np.ndarray], config_yaml: str, h: float, flush_every: int = 10,
                 dx: float | None = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.partial = partial_path(self.path)
        self.pending: dict[str, list[np.ndarray]] = {name: [] for name in series}
        self.flush_every = flush_every
        self._frames = 0
        with h5py.File(self.partial, "w") as f:
            f.attrs.update(fishsim_version=__version__, h=h, units=UNITS, complete=False, n_frames=0,
                           message="running (or killed before the end)")
            f.create_dataset("config", data=config_yaml)
            for name, arr in static.items():
                f.create_dataset(name, data=np.asarray(arr))
            for name, (shape, dtype) in series.items():
                big = np.prod(shape) > 4096          # fields: a chunk per frame; small series: blocks of frames
                f.create_dataset(name, shape=(0, *shape), maxshape=(None, *shape), dtype=dtype,
                                 chunks=(1 if big else max(1, min(256, 4096 // max(int(np.prod(shape)), 1))), *shape),
                                 compression="gzip" if big else None, compression_opts=1 if big else None)
            for name in [*static, *series]:
                conventions.describe(f, name, dx)

    def append(self, values: dict[str, np.ndarray]) -> None:
        """Append one frame of the named series (any subset, e.g. fluid only every k frames)."""
        for name, value in values.items():
            self.pending[name].append(np.array(value))

    def end_frame(self) -> None:
        """Mark the end of a frame; writes to disk every ``flush_every`` frames."""
        self._frames += 1
        if self._frames % self.flush_every == 0:
            self.flush()

    def flush(self, attrs: dict | None = None, wait: float = 2.0) -> bool:
        """Append the frames held in memory to the file (opened and closed again) and record
        n_frames and any ``attrs``. While another program reads the file (HDF5's lock), retry for
        ``wait`` seconds, then keep the frames in memory for the next flush (returns False)."""
        f = self._open(wait)
        if f is None:
            return False
        with f:
            for name, rows in self.pending.items():
                if rows:
                    ds = f[name]
                    n = ds.shape[0]
                    ds.resize(n + len(rows), axis=0)
                    ds[n:] = np.stack(rows).astype(ds.dtype, copy=False)
                    rows.clear()
            f.attrs["n_frames"] = self._frames
            f.attrs.update({conventions.snake(k): v for k, v in (attrs or {}).items()})
            conventions.grow(f)
        return True

    def close(self, complete: bool, message: str = "", attrs: dict | None = None) -> None:
        """Write what is left and record whether the run finished (``complete``), why not, and
        any extra file attributes (grid size, summary numbers); then rename to the final name.
        A program reading the file is waited for, up to ``CLOSE_WAIT`` seconds."""
        attrs = {**(attrs or {}), "complete": bool(complete),
                 "message": message or ("complete" if complete else "incomplete")}
        if not self.flush(attrs, wait=0.0):
            warnings.warn(f"{self.partial} is open in another program; waiting up to {CLOSE_WAIT:.0f} s for it "
                          "to close it", stacklevel=2)
            if not self.flush(attrs, wait=CLOSE_WAIT):
                raise FishsimError(f"{self.partial} stayed open in another program for {CLOSE_WAIT:.0f} s: it holds "
                                   "the frames flushed before, the last ones were not written; close that program "
                                   "before a run ends")
        os.replace(self.partial, self.path)

    def _open(self, wait: float) -> h5py.File | None:
        """The file opened for appending, or None while another program still holds HDF5's
        lock on it after ``wait`` seconds."""
        deadline = time.monotonic() + wait
        while True:
            try:
                return h5py.File(self.partial, "r+")
            except (OSError, BlockingIOError) as err:
                if "lock" not in str(err) and not isinstance(err, BlockingIOError):
                    raise
                if time.monotonic() >= deadline:
                    return None
                time.sleep(0.05)


def partial_path(path: Path) -> Path:
    """Where a trajectory is written until its run ends (then renamed to ``path``): an earlier
    file at ``path`` is never touched by a run that dies, and a killed run leaves
    ``<name>.part``, readable up to its last flushed frame."""
    return path.with_name(path.name + ".part")


@dataclass
class Trajectory:
    """A trajectory read back: every dataset keyed by its path, as a numpy array, or (read with
    ``lazy=True``) as the open file's h5py dataset, read only where sliced (``tr["fluid/p"][10, 0]``);
    a lazy trajectory holds the file open until ``close()`` or the end of a ``with`` block."""

    data: dict[str, np.ndarray]
    attrs: dict
    config_yaml: str
    complete: bool
    n_frames: int
    path: Path = field(default_factory=Path)
    file: h5py.File | None = None

    def __getitem__(self, key: str) -> np.ndarray:
        return self.data[key]

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_trajectory(path: Path, wait: float = 5.0) -> h5py.File:
    """Open for reading: normally (a truncated or foreign file fails in milliseconds). A file a
    running simulation is appending to at this moment is locked for the few milliseconds of its
    flush: retried for up to ``wait`` seconds. A file left by a killed run of an older fishsim, which
    kept it open in SWMR mode, is marked open for writing: read in SWMR mode."""
    deadline = time.monotonic() + wait
    while True:
        try:
            return h5py.File(path, "r")
        except OSError as err:
            text = str(err)
            if "truncated" in text:
                raise InputFileError(f"{path} is not a readable HDF5 file (truncated: the file is cut short); "
                                     "it may be corrupt, cut short, or not a fishsim trajectory") from None
            if any(w in text for w in ("already open for write", "consistency flags")):
                break
            if not ("unable to lock" in text or isinstance(err, BlockingIOError)) or time.monotonic() > deadline:
                raise InputFileError(f"{path} is not a readable HDF5 file ({err.__class__.__name__}); it may be "
                                     "corrupt, cut short, or not a fishsim trajectory") from None
            time.sleep(0.05)
    try:
        return h5py.File(path, "r", libver="latest", swmr=True)
    except OSError as err:
        raise InputFileError(f"{path} is not a readable HDF5 file ({err.__class__.__name__}); "
                             "it may be corrupt or not a fishsim trajectory") from None


def read_trajectory(path: str | Path, load_fluid: bool = True, lazy: bool = False) -> Trajectory:
    """Read a trajectory file; a crashed run's file is read up to its last flushed frame.
    ``lazy``: keep the file open and read nothing until sliced (large runs; see ``Trajectory``)."""
    path = Path(path)
    if not path.exists():
        part = partial_path(path)
        hint = (f"a run killed while writing it left {part}: read that" if part.exists()
                else "run `fishsim simulate` to make one")
        raise InputFileError(f"no such trajectory file: {path} ({hint})")
    f = open_trajectory(path)
    try:
        if "config" not in f or "metrics/time" not in f:
            raise InputFileError(f"{path} is an HDF5 file but not a fishsim trajectory "
                                 "(no /config or /metrics/time)")
        data: dict = {}

        def visit(name: str, obj) -> None:
            wanted = load_fluid or not name.startswith("fluid/")
            if isinstance(obj, h5py.Dataset) and name != "config" and wanted:
                data[name] = obj if lazy else obj[()]

        for top, obj in f.items():                     # /xdmf: the XDMF sidecars' views of the series
            if isinstance(obj, h5py.Group) and top != "xdmf":
                obj.visititems(lambda name, o, top=top: visit(f"{top}/{name}", o))
            else:
                visit(top, obj)
        attrs = dict(f.attrs)
        config_yaml = f["config"][()].decode() if isinstance(f["config"][()], bytes) else str(f["config"][()])
    except BaseException:
        f.close()
        raise
    if not lazy:
        f.close()
    complete = bool(attrs.get("complete", False))
    n_frames = int(attrs["n_frames"]) if complete else _flushed_frames(data)
    return Trajectory(data, attrs, config_yaml, complete, n_frames, path, f if lazy else None)


def _flushed_frames(data: dict[str, np.ndarray]) -> int:
    """Frames flushed to a possibly incomplete file (metrics/time is written last in a frame)."""
    return len(data["metrics/time"]) if "metrics/time" in data else 0


def trajectory_series(n_nodes: int, batch: int, n_act: int, metrics: list[str],
                      fluid_shape: tuple[int, int] | None = None) -> dict[str, tuple[tuple, str]]:
    """The per-frame series a simulation writes (see the module docstring)."""
    series: dict[str, tuple[tuple, str]] = {
        "solid/q": ((batch, n_nodes, 2), "f8"),
        "solid/qdot": ((batch, n_nodes, 2), "f8"),
        "solid/f_ext": ((batch, n_nodes, 2), "f8"),
        "controller/activation": ((batch, n_act), "f4"),
        "metrics/time": ((), "f8"),
    }
    series.update({f"metrics/{m}": ((batch,), "f8") for m in metrics})
    if fluid_shape is not None:
        H, W = fluid_shape
        series.update({f"fluid/{k}": ((batch, H, W), "f4") for k in ("p", "vx", "vy", "mask")})
        series["fluid/a"] = ((batch, H + 1, W + 1), "f4")
        series["fluid/frame"] = ((), "i8")
    return series

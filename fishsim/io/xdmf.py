"""XDMF sidecars for a trajectory: XML files beside ``trajectory.h5`` that describe the fish meshes
and fluid fields stored in it as time series, for ParaView / VTK and for meshio, with nothing
copied.

meshio reads XDMF 3 with whole HDF5 datasets only (no hyperslab of one), so ``write_xdmf`` adds
to the trajectory one view per fish b and frame t (per stored fluid frame k for the fluid): an
HDF5 virtual dataset, a name and a selection of the series it points at in the same file (source
file ``.``, so renaming the file keeps it valid), holding no data. Each costs ~0.5 kB of metadata
against the frame's 16 N bytes it names: +1.6 % on a fish-only run of the default fish (N = 1775,
measured on the mesh before its outline was snapped).

    /xdmf/solid/<name>/<b>/<t>    [N, 2]    = /solid/<name>[t, b]      q (m), qdot (m/s), f_ext (N/m)
    /xdmf/fluid/<name>/<b>/<k>    [H W]     = /fluid/<name>[k, b]      p (Pa), vx, vy (m/s), mask (1);
                                            cell (i, j) at i W + j (C order)

with <t>, <k> written with six digits (000012). Only the frames in the file get views (a stopped
run's flushed frames); writing the sidecars again after more frames adds the missing ones. The
fluid grid is stored once as quadrilaterals: /fluid/grid/points [(H+1)(W+1), 2] (m, vertex
(i, j) at i (W+1) + j, at (j dx, i dx)) and /fluid/grid/quads [H W, 4] (``add_fluid_grid``).
Times are /metrics/time (s); a fluid frame k has the time of its frame /fluid/frame[k].

Per fish b, two temporal collections, each step a grid:

    fish_<b>    every frame t: triangles /mesh/triangles, points /xdmf/solid/q/<b>/<t>; point
                data position (the points again), velocity (qdot), force (f_ext); cell data
                actuator (/mesh/actuator)
    fluid_<b>   every stored fluid frame k: the H x W cells of size dx from (0, 0) as
                quadrilaterals (/fluid/grid); cell data p, vx, vy, mask

Files (for ``trajectory.h5``; the trajectory's name with the suffixes below otherwise):

    trajectory.xdmf           every collection, fish_0, fluid_0, fish_1, ...: VTK's
                              ``vtkXdmfReader`` (ParaView's "Xdmf Reader") gives one block per
                              collection at a time, the fish moving; meshio cannot read it (one
                              time series a file)
    trajectory_fish<b>.xdmf   fish_<b> alone: ``meshio.xdmf.TimeSeriesReader`` reads points (frame
                              0's positions, [N, 2] m; meshio keeps its first step's mesh) and
                              triangles, and per step t the time and point data position (the fish
                              at t), velocity, force, cell data actuator; VTK reads it as above
    trajectory_fluid<b>.xdmf  fluid_<b> alone (runs with a fluid): meshio reads the grid's points
                              and quads, and per stored fluid frame the time and cell data p, vx,
                              vy, mask [H W]

Keep the files together: each names the trajectory by its file name, relative to its own folder.
The views need HDF5 1.10 or newer to be read; the trajectory's own datasets do not.
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import escape

import h5py
import numpy as np

FISH_SERIES = {"position": "solid/q", "velocity": "solid/qdot", "force": "solid/f_ext"}
FLUID_FIELDS = ("p", "vx", "vy", "mask")


def _number_type(dtype) -> str:
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        return "Float"
    return {"i": "Char", "u": "UChar"}[dtype.kind] if dtype.itemsize == 1 else {"i": "Int", "u": "UInt"}[dtype.kind]


def xdmf_path(trajectory: Path) -> Path:
    """Where the main sidecar of ``trajectory`` goes (every fish and fluid): the same name with .xdmf."""
    return Path(trajectory).with_suffix(".xdmf")


def fish_xdmf_path(trajectory: Path, b: int) -> Path:
    """Fish b's sidecar alone (the one meshio's TimeSeriesReader reads): <name>_fish<b>.xdmf."""
    trajectory = Path(trajectory)
    return trajectory.with_name(f"{trajectory.stem}_fish{b}.xdmf")


def fluid_xdmf_path(trajectory: Path, b: int) -> Path:
    """Fish b's fluid alone (meshio): <name>_fluid<b>.xdmf."""
    trajectory = Path(trajectory)
    return trajectory.with_name(f"{trajectory.stem}_fluid{b}.xdmf")


def view_path(series: str, b: int, t: int) -> str:
    """The view of ``/<series>[t, b]`` (see the module docstring)."""
    return f"xdmf/{series}/{b}/{t:06d}"


def write_xdmf(trajectory: str | Path) -> Path:
    """Add the missing per-frame views to a (complete or partial) trajectory file and write its
    XDMF sidecars (module docstring); returns the main one's path."""
    trajectory = Path(trajectory)
    with h5py.File(trajectory, "r+") as f:
        times = f["metrics/time"][()]
        n_frames = min(len(times), *(f[s].shape[0] for s in FISH_SERIES.values()))
        batch = f["solid/q"].shape[1]
        fields = [k for k in FLUID_FIELDS if f"fluid/{k}" in f]
        dx = float(f.attrs.get("grid_dx", 0.0))
        fluid_frames = f["fluid/frame"][()] if "fluid/frame" in f and fields and dx > 0 else np.zeros(0, np.int64)
        n_fluid = min(len(fluid_frames), *(f[f"fluid/{k}"].shape[0] for k in fields)) if len(fluid_frames) else 0
        n_fluid = int(np.sum(fluid_frames[:n_fluid] < len(times)))      # frames whose time is stored
        if n_fluid:
            add_fluid_grid(f, *f["fluid/p" if "fluid/p" in f else f"fluid/{fields[0]}"].shape[2:], dx)
        for series in FISH_SERIES.values():
            _add_views(f, series, n_frames)
        for k in fields if n_fluid else ():
            _add_views(f, f"fluid/{k}", n_fluid)
        if "xdmf" in f and "long_name" not in f["xdmf"].attrs:
            f["xdmf"].attrs["long_name"] = ("per-frame views (HDF5 virtual datasets: no data) of the series, "
                                            "for the XDMF sidecars (fishsim/io/xdmf.py)")
        shapes = {name: (f[name].shape, f[name].dtype) for name in
                  ("mesh/triangles", "mesh/actuator", "fluid/grid/points", "fluid/grid/quads",
                   *FISH_SERIES.values(), *(f"fluid/{k}" for k in fields)) if name in f}
    name = trajectory.name
    main = []
    for b in range(batch):
        fish = _temporal(f"fish_{b}", [_fish_grid(name, shapes, t, b, times[t]) for t in range(n_frames)])
        _write(fish_xdmf_path(trajectory, b), [fish])
        main.append(fish)
        if n_fluid:
            steps = [_fluid_grid(name, shapes, fields, k, b, times[int(fluid_frames[k])]) for k in range(n_fluid)]
            fluid = _temporal(f"fluid_{b}", steps)
            _write(fluid_xdmf_path(trajectory, b), [fluid])
            main.append(fluid)
    out = xdmf_path(trajectory)
    _write(out, main)
    return out


def _write(path: Path, collections: list[str]) -> None:
    path.write_text('<?xml version="1.0" ?>\n<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>\n<Xdmf Version="3.0">\n<Domain>\n'
                    + "\n".join(collections) + "\n</Domain>\n</Xdmf>\n")


def _add_views(f: h5py.File, series: str, n: int) -> None:
    """Views /xdmf/<series>/<b>/<t> of /<series>[t, b] for t < n, every b (those missing)."""
    source = f[series]
    shape = _view_shape(series, source.shape)
    whole = h5py.VirtualSource(source)
    for b in range(source.shape[1]):
        group = f.require_group(f"xdmf/{series}/{b}")
        have = set(group)
        for t in range(n):
            if f"{t:06d}" in have:
                continue
            layout = h5py.VirtualLayout(shape=shape, dtype=source.dtype)
            layout[...] = whole[t, b]
            group.create_virtual_dataset(f"{t:06d}", layout)


def _item(file: str, path: str, shape, dtype) -> str:
    """A whole HDF5 dataset as a DataItem."""
    dims = " ".join(str(s) for s in shape)
    return (f'<DataItem Dimensions="{dims}" NumberType="{_number_type(dtype)}" '
            f'Precision="{np.dtype(dtype).itemsize}" Format="HDF">{escape(file)}:/{path}</DataItem>')


def _view(file: str, shapes: dict, series: str, b: int, t: int) -> str:
    """The view of /<series>[t, b] as a DataItem (its shape from ``_view_shape``)."""
    shape, dtype = shapes[series]
    return _item(file, view_path(series, b, t), _view_shape(series, shape), dtype)


def _view_shape(series: str, shape: tuple) -> tuple:
    """A view's shape: a [frames, B, ...] series' [...], a fluid field's [H W] flattened."""
    return (int(np.prod(shape[2:])),) if series.startswith("fluid/") else tuple(shape[2:])


def _attribute(name: str, center: str, kind: str, data: str) -> str:
    return f'<Attribute Name="{name}" AttributeType="{kind}" Center="{center}">{data}</Attribute>'


def _fish_grid(file: str, shapes: dict, t: int, b: int, time: float) -> str:
    tri_shape, tri_dtype = shapes["mesh/triangles"]
    parts = [f'<Grid Name="fish_{b}_{t}" GridType="Uniform"><Time Value="{float(time)!r}"/>',
             (f'<Topology TopologyType="Triangle" NumberOfElements="{tri_shape[0]}">'
              f'{_item(file, "mesh/triangles", tri_shape, tri_dtype)}</Topology>'),
             f'<Geometry GeometryType="XY">{_view(file, shapes, "solid/q", b, t)}</Geometry>']
    parts += [_attribute(name, "Node", "Vector", _view(file, shapes, series, b, t))
              for name, series in FISH_SERIES.items()]
    if "mesh/actuator" in shapes:
        parts.append(_attribute("actuator", "Cell", "Scalar", _item(file, "mesh/actuator", *shapes["mesh/actuator"])))
    return "".join(parts) + "</Grid>"


def add_fluid_grid(f: h5py.File, H: int, W: int, dx: float) -> None:
    """Store the fluid grid as a quadrilateral mesh once (/fluid/grid/points [(H+1)(W+1), 2] m,
    /fluid/grid/quads [H W, 4], cell (i, j) at row i W + j, the fields' C order): VTK's XDMF
    reader puts 2D structured grids in the y-z plane, and meshio reads no structured grids."""
    if "fluid/grid/quads" in f:
        return
    y, x = np.meshgrid(np.arange(H + 1) * dx, np.arange(W + 1) * dx, indexing="ij")
    v = np.arange((H + 1) * (W + 1)).reshape(H + 1, W + 1)
    quads = np.stack([v[:-1, :-1], v[:-1, 1:], v[1:, 1:], v[1:, :-1]], -1).reshape(-1, 4)
    f.create_dataset("fluid/grid/points", data=np.stack([x.ravel(), y.ravel()], -1))
    f.create_dataset("fluid/grid/quads", data=quads.astype(np.int32))


def _fluid_grid(file: str, shapes: dict, fields: list[str], k: int, b: int, time: float) -> str:
    quads, points = shapes["fluid/grid/quads"], shapes["fluid/grid/points"]
    parts = [f'<Grid Name="fluid_{b}_{k}" GridType="Uniform"><Time Value="{float(time)!r}"/>',
             (f'<Topology TopologyType="Quadrilateral" NumberOfElements="{quads[0][0]}">'
              f'{_item(file, "fluid/grid/quads", *quads)}</Topology>'),
             f'<Geometry GeometryType="XY">{_item(file, "fluid/grid/points", *points)}</Geometry>']
    parts += [_attribute(field, "Cell", "Scalar", _view(file, shapes, f"fluid/{field}", b, k)) for field in fields]
    return "".join(parts) + "</Grid>"


def _temporal(name: str, steps: list[str]) -> str:
    return (f'<Grid Name="{name}" GridType="Collection" CollectionType="Temporal">\n'
            + "\n".join(steps) + "\n</Grid>")

"""An XDMF sidecar for a trajectory: ``trajectory.xdmf`` describes the fish meshes and fluid fields
stored in ``trajectory.h5`` so that ParaView (its XDMF reader) and VTK open the run as time
series, with nothing copied: every array is a hyperslab of a dataset of the HDF5 file (only the
fluid grid's points and quadrilaterals are added to it, once).

Per fish b of the batch, two temporal collections:

    fish_<b>    every frame: triangles (/mesh/triangles), node positions (/solid/q[t, b]) with point
                data velocity (/solid/qdot[t, b], m/s) and force (/solid/f_ext[t, b], N/m), cell
                data actuator (/mesh/actuator)
    fluid_<b>   every stored fluid frame k: the H x W cells of size dx from (0, 0) as quadrilaterals
                (/fluid/grid, written into the file once by ``write_xdmf``), cell data
                p (Pa), vx, vy (m/s), mask (/fluid/<name>[k, b])

Times are /metrics/time. XDMF 2 ("Xdmf Reader" in ParaView; ``vtkXdmfReader``).
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import escape

import h5py
import numpy as np


def _number_type(dtype) -> str:
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        return "Float"
    return {"i": "Char", "u": "UChar"}[dtype.kind] if dtype.itemsize == 1 else {"i": "Int", "u": "UInt"}[dtype.kind]


def xdmf_path(trajectory: Path) -> Path:
    """Where the sidecar of ``trajectory`` goes: the same name with .xdmf."""
    return Path(trajectory).with_suffix(".xdmf")


def write_xdmf(trajectory: str | Path) -> Path:
    """Write the XDMF sidecar of a (complete or partial) trajectory file; returns its path."""
    trajectory = Path(trajectory)
    with h5py.File(trajectory, "r+") as f:
        n_frames = f["metrics/time"].shape[0]
        times = f["metrics/time"][()]
        batch = f["solid/q"].shape[1]
        fluid_frames = f["fluid/frame"][()] if "fluid/frame" in f else np.zeros(0, np.int64)
        n_fluid = min(len(fluid_frames), *(f[f"fluid/{k}"].shape[0] for k in ("p", "vx", "vy", "mask")
                                           if f"fluid/{k}" in f)) if len(fluid_frames) else 0
        dx = float(f.attrs.get("grid_dx", 0.0))
        if n_fluid and dx > 0:
            add_fluid_grid(f, *f["fluid/p"].shape[2:], dx)
        shapes = {name: (ds.shape, ds.dtype) for name, ds in _datasets(f)}
    name = trajectory.name
    grids = []
    for b in range(batch):
        steps = [_fish_grid(name, shapes, t, b, times[t]) for t in range(n_frames)]
        grids.append(_temporal(f"fish_{b}", steps))
        if n_fluid and dx > 0:
            steps = [_fluid_grid(name, shapes, k, b, times[int(fluid_frames[k])]) for k in range(n_fluid)]
            grids.append(_temporal(f"fluid_{b}", steps))
    xml = ('<?xml version="1.0" ?>\n<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>\n<Xdmf Version="2.0">\n<Domain>\n'
           + "\n".join(grids) + "\n</Domain>\n</Xdmf>\n")
    out = xdmf_path(trajectory)
    out.write_text(xml)
    return out


def _datasets(f: h5py.File):
    found = []
    f.visititems(lambda n, o: found.append((n, o)) if isinstance(o, h5py.Dataset) else None)
    return found


def _item(file: str, path: str, shape, dtype) -> str:
    """A whole HDF5 dataset as a DataItem."""
    dims = " ".join(str(s) for s in shape)
    return (f'<DataItem Dimensions="{dims}" NumberType="{_number_type(dtype)}" '
            f'Precision="{np.dtype(dtype).itemsize}" Format="HDF">{escape(file)}:/{path}</DataItem>')


def _slab(file: str, shapes: dict, path: str, t: int, b: int) -> str:
    """The [t, b] slice of a [frames, B, ...] dataset: a HyperSlab DataItem of shape [...]."""
    shape, dtype = shapes[path]
    rest = shape[2:]
    start = " ".join(str(v) for v in (t, b, *([0] * len(rest))))
    stride = " ".join("1" for _ in shape)
    count = " ".join(str(v) for v in (1, 1, *rest))
    dims = " ".join(str(v) for v in rest)
    return (f'<DataItem ItemType="HyperSlab" Dimensions="{dims}" Type="HyperSlab">'
            f'<DataItem Dimensions="3 {len(shape)}" Format="XML">{start} {stride} {count}</DataItem>'
            f'{_item(file, path, shape, dtype)}</DataItem>')


def _attribute(name: str, center: str, kind: str, data: str) -> str:
    return f'<Attribute Name="{name}" AttributeType="{kind}" Center="{center}">{data}</Attribute>'


def _fish_grid(file: str, shapes: dict, t: int, b: int, time: float) -> str:
    tri_shape, tri_dtype = shapes["mesh/triangles"]
    parts = [f'<Grid Name="fish_{b}_{t}" GridType="Uniform"><Time Value="{float(time)!r}"/>',
             (f'<Topology TopologyType="Triangle" NumberOfElements="{tri_shape[0]}">'
             f'{_item(file, "mesh/triangles", tri_shape, tri_dtype)}</Topology>'),
             f'<Geometry GeometryType="XY">{_slab(file, shapes, "solid/q", t, b)}</Geometry>',
             _attribute("velocity", "Node", "Vector", _slab(file, shapes, "solid/qdot", t, b)),
             _attribute("force", "Node", "Vector", _slab(file, shapes, "solid/f_ext", t, b))]
    if "mesh/actuator" in shapes:
        parts.append(_attribute("actuator", "Cell", "Scalar", _item(file, "mesh/actuator", *shapes["mesh/actuator"])))
    return "".join(parts) + "</Grid>"


def add_fluid_grid(f: h5py.File, H: int, W: int, dx: float) -> None:
    """Store the fluid grid as a quadrilateral mesh once (/fluid/grid/points [(H+1)(W+1), 2] m,
    /fluid/grid/quads [H W, 4], cell (i, j) at row i W + j, the fields' C order): VTK's XDMF
    reader cannot read hyperslabs on its structured grids, and puts 2D ones in the y-z plane."""
    if "fluid/grid/quads" in f:
        return
    y, x = np.meshgrid(np.arange(H + 1) * dx, np.arange(W + 1) * dx, indexing="ij")
    v = np.arange((H + 1) * (W + 1)).reshape(H + 1, W + 1)
    quads = np.stack([v[:-1, :-1], v[:-1, 1:], v[1:, 1:], v[1:, :-1]], -1).reshape(-1, 4)
    f.create_dataset("fluid/grid/points", data=np.stack([x.ravel(), y.ravel()], -1))
    f.create_dataset("fluid/grid/quads", data=quads.astype(np.int32))


def _fluid_grid(file: str, shapes: dict, k: int, b: int, time: float) -> str:
    quads, points = shapes["fluid/grid/quads"], shapes["fluid/grid/points"]
    parts = [f'<Grid Name="fluid_{b}_{k}" GridType="Uniform"><Time Value="{float(time)!r}"/>',
             (f'<Topology TopologyType="Quadrilateral" NumberOfElements="{quads[0][0]}">'
             f'{_item(file, "fluid/grid/quads", *quads)}</Topology>'),
             f'<Geometry GeometryType="XY">{_item(file, "fluid/grid/points", *points)}</Geometry>']
    for field in ("p", "vx", "vy", "mask"):
        if f"fluid/{field}" in shapes:
            H, W = shapes[f"fluid/{field}"][0][2:]
            parts.append(_attribute(field, "Cell", "Scalar", _slab(file, shapes, f"fluid/{field}", k, b)
                                    .replace(f'Dimensions="{H} {W}" Type', f'Dimensions="{H * W}" Type', 1)))
    return "".join(parts) + "</Grid>"


def _temporal(name: str, steps: list[str]) -> str:
    return (f'<Grid Name="{name}" GridType="Collection" CollectionType="Temporal">\n'
            + "\n".join(steps) + "\n</Grid>")

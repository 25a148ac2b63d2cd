"""ParaView output: per-frame fish ``.vtu`` (meshio), fluid ``.vti`` image data, and ``.pvd``
collections that ParaView opens as time series.

``write_vtk_series(data, out_dir)`` writes, for one batch sample of a trajectory::

    out_dir/fish.pvd   out_dir/fish/fish_000000.vtu ...    points (x, y, 0), triangles,
                                                          point data velocity, force; cell data actuator
    out_dir/fluid.pvd  out_dir/fluid/fluid_000000.vti ...  cell data p, velocity, mask, vorticity;
                                                          origin 0, spacing dx (fluid frames only)
"""

from __future__ import annotations

import base64
import zlib
from collections.abc import Sequence
from pathlib import Path

import meshio
import numpy as np

VTK_TYPES = {np.dtype("float32"): "Float32", np.dtype("float64"): "Float64",
             np.dtype("int32"): "Int32", np.dtype("int64"): "Int64", np.dtype("uint8"): "UInt8"}


def _xyz(a: np.ndarray) -> np.ndarray:
    """[..., 2] -> [..., 3] with z = 0."""
    return np.concatenate([a, np.zeros_like(a[..., :1])], axis=-1)


def write_fish_vtu(path: Path, q: np.ndarray, triangles: np.ndarray, velocity: np.ndarray,
                   force: np.ndarray, actuator: np.ndarray | None = None) -> Path:
    """One fish frame: nodes q [N,2] (m), triangles [T,3], velocity and force [N,2] per node."""
    cell_data = {"actuator": [np.asarray(actuator, np.int32)]} if actuator is not None else {}
    mesh = meshio.Mesh(_xyz(q), [("triangle", np.asarray(triangles, np.int64))],
                       point_data={"velocity": _xyz(velocity), "force": _xyz(force)}, cell_data=cell_data)
    meshio.write(path, mesh, file_format="vtu")
    return path


def _encode(array: np.ndarray) -> str:
    """VTK XML inline binary, zlib-compressed in one block: base64(header) + base64(data)."""
    raw = np.ascontiguousarray(array).tobytes()
    packed = zlib.compress(raw, 1)
    header = np.array([1, len(raw), len(raw), len(packed)], dtype=np.uint64).tobytes()
    return base64.b64encode(header).decode() + base64.b64encode(packed).decode()


def _data_array(name: str, values: np.ndarray, components: int) -> str:
    values = np.asarray(values)
    values = values.astype(np.float32) if values.dtype.kind == "f" else values
    return (f'<DataArray type="{VTK_TYPES[values.dtype]}" Name="{name}" NumberOfComponents="{components}" '
            f'format="binary">{_encode(values)}</DataArray>')


def write_fluid_vti(path: Path, cell_fields: dict[str, np.ndarray], dx: float) -> Path:
    """Image data over the fluid box: H x W cells of size dx, origin (0, 0, 0).

    cell_fields: name -> [H, W] scalars or [H, W, 2] vectors (stored with z = 0); row = y,
    column = x, so C order is VTK's x-fastest cell order.
    """
    H, W = next(iter(cell_fields.values())).shape[:2]
    arrays = []
    for name, v in cell_fields.items():
        v = _xyz(v) if v.ndim == 3 else v
        arrays.append(_data_array(name, v.reshape(H * W, -1), 1 if v.ndim == 2 else 3))
    extent = f"0 {W} 0 {H} 0 0"
    scalars = next((k for k, v in cell_fields.items() if v.ndim == 2), "")
    xml = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" header_type="UInt64" '
        'compressor="vtkZLibDataCompressor">\n'
        f'<ImageData WholeExtent="{extent}" Origin="0 0 0" Spacing="{dx!r} {dx!r} {dx!r}">\n'
        f'<Piece Extent="{extent}">\n<PointData/>\n<CellData Scalars="{scalars}">\n'
        + "\n".join(arrays) + "\n</CellData>\n</Piece>\n</ImageData>\n</VTKFile>\n"
    )
    Path(path).write_text(xml)
    return path


def write_pvd(path: Path, files: Sequence[Path], times: Sequence[float]) -> Path:
    """A ParaView collection: each file (relative to the .pvd's folder) at its time."""
    path = Path(path)
    rows = "\n".join(f'  <DataSet timestep="{float(t)!r}" group="" part="0" file="{Path(f).relative_to(path.parent).as_posix()}"/>'
                     for f, t in zip(files, times))
    path.write_text('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
                    f"<Collection>\n{rows}\n</Collection>\n</VTKFile>\n")
    return path


def write_vtk_series(data, out_dir: Path, frames: Sequence[int] | None = None,
                     actuator: np.ndarray | None = None) -> dict[str, Path]:
    """Write a ParaView series for a ``fishsim.render.data.RenderData`` (one batch sample):
    the fish at ``frames`` (default all) and every stored fluid frame among them.
    Returns {"fish": fish.pvd, "fluid": fluid.pvd (if the run stored fluid)}."""
    from fishsim.render.fields import vorticity

    out_dir = Path(out_dir)
    frames = list(range(data.n_frames)) if frames is None else list(frames)
    (out_dir / "fish").mkdir(parents=True, exist_ok=True)
    fish = [write_fish_vtu(out_dir / "fish" / f"fish_{t:06d}.vtu", data.q[t], data.triangles, data.qdot[t],
                           data.f_ext[t], actuator) for t in frames]
    written = {"fish": write_pvd(out_dir / "fish.pvd", fish, data.time[frames])}
    if not data.has_fluid:
        return written
    (out_dir / "fluid").mkdir(exist_ok=True)
    wanted = set(frames)
    files, times = [], []
    for k, t in enumerate(data.fluid_frame):
        if int(t) not in wanted:
            continue
        fl = {key: v[k] for key, v in data.fluid.items()}
        cells = {"p": fl["p"]}
        if "vx" in fl and "vy" in fl:
            cells["velocity"] = np.stack([fl["vx"], fl["vy"]], axis=-1)
            cells["vorticity"] = vorticity(fl["vx"], fl["vy"], data.grid[2])
        if "mask" in fl:
            cells["mask"] = fl["mask"]
        files.append(write_fluid_vti(out_dir / "fluid" / f"fluid_{int(t):06d}.vti", cells, data.grid[2]))
        times.append(data.time[int(t)])
    written["fluid"] = write_pvd(out_dir / "fluid.pvd", files, times)
    return written

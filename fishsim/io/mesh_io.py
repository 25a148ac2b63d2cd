"""Fish mesh files: any meshio format chosen by the file extension (default .vtu).

Layout written by `write_mesh` (and required by `read_mesh`):
  points        [N, 3] float64, (X, Y, 0) in metres (3D: several formats need it)
  cells         one "triangle" block [T, 3], counter-clockwise
  cell data     actuator [T]: 0 none, 1 top, 2 bottom
  point data    surface_order [N]: k for the k-th node of the ccw surface polyline, -1 interior
                fishsim_length [N]: the body length L in metres (constant; point data survives
                every format, field data does not)
  optional      muscle_top, muscle_bottom [T] (cell data, float): each element's area fraction
                inside the muscle layer (fishsim/solid/muscles.py) it was written with, for
                viewers; not read back (a run recomputes the layer from the outline and its
                config; `actuator` keeps the paper's stations for fish.muscles=paper)
Formats without integer data (gmsh) store floats; `read_mesh` rounds them back.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import meshio
import numpy as np

from fishsim.errors import ConfigError, InputFileError, MeshError
from fishsim.mesh.fish_mesh import FishMesh
from fishsim.mesh.triangulate import check_mesh

DEFAULT_SUFFIX = ".vtu"
ACTUATOR_KEY, SURFACE_KEY, LENGTH_KEY = "actuator", "surface_order", "fishsim_length"
MAKE_ONE = "make one with `fishsim mesh`"
#: Where an extension names several meshio formats, the one fishsim uses (.msh: gmsh, not ansys).
PREFERRED_FORMATS = ("gmsh",)


def mesh_path(path) -> Path:
    """The path with `DEFAULT_SUFFIX` appended when it has no extension."""
    path = Path(path)
    return path if path.suffix else path.with_suffix(DEFAULT_SUFFIX)


def mesh_format(path: Path) -> str | None:
    """meshio's format name for the path's extension (e.g. .vtu -> "vtu", .msh -> "gmsh"), or
    None if meshio does not know the extension."""
    suffix = "".join(path.suffixes[-2:]).lower()
    names = meshio.extension_to_filetypes.get(suffix) or meshio.extension_to_filetypes.get(path.suffix.lower())
    if not names:
        return None
    return next((n for n in PREFERRED_FORMATS if n in names), names[0])


# meshio formats without point and cell data: a fish written there could not be read back
GEOMETRY_ONLY = ("stl", "obj", "off", "ply", "wavefront-obj")


def writable_format(path) -> str:
    """meshio's format for writing a fish to ``path`` (``mesh_path`` applied); ConfigError (one
    line) for an unknown extension or a format that cannot carry the fish's data. Checked when
    the config is validated, so a bad name fails before anything is meshed or written."""
    path = mesh_path(path)
    fmt = mesh_format(path)
    if fmt is None:
        raise ConfigError(f"cannot write a mesh as {path.name}: unknown extension {path.suffix!r}; "
                          "use a meshio extension such as .vtu, .msh or .xdmf")
    if fmt in GEOMETRY_ONLY:
        raise ConfigError(f"{path.suffix} files keep only the triangles, not the fish's surface order, length and "
                          "muscles that `fishsim simulate fish.mesh_file=...` needs; use .vtu, .vtk, .msh or .xdmf")
    return fmt


def write_mesh(mesh: FishMesh, path, cell_data: dict[str, np.ndarray] | None = None) -> Path:
    """Write `mesh` to `path` (format from the extension, .vtu if none; parent folders are
    created) and return the path written. cell_data: extra per-element float fields [T] (e.g.
    the muscle layer's muscle_top, muscle_bottom fractions)."""
    path = mesh_path(path)
    fmt = writable_format(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meshio.write(path, to_meshio(mesh, cell_data), file_format=fmt)
    return path


def to_meshio(mesh: FishMesh, cell_data: dict[str, np.ndarray] | None = None) -> meshio.Mesh:
    """The meshio.Mesh of the layout in this module's docstring (with the extra cell fields)."""
    extra = {k: [np.asarray(v, np.float64).reshape(mesh.n_elements)] for k, v in (cell_data or {}).items()}
    surface_order = np.full(mesh.n_nodes, -1, dtype=np.int32)
    surface_order[mesh.surface] = np.arange(len(mesh.surface), dtype=np.int32)
    points = np.column_stack([mesh.points, np.zeros(mesh.n_nodes)])
    return meshio.Mesh(
        points, [("triangle", mesh.triangles.copy())],            # a copy: editing the result leaves mesh alone
        point_data={SURFACE_KEY: surface_order, LENGTH_KEY: np.full(mesh.n_nodes, mesh.length)},
        cell_data={ACTUATOR_KEY: [mesh.actuator.astype(np.int8)], **extra},
    )


def read_mesh(path) -> FishMesh:
    """Read a mesh written by `write_mesh` and check it (`check_mesh`).

    Raises InputFileError (one line: what is wrong, how to fix it) for a missing file, a file
    meshio cannot read, a mesh without triangles or without the fishsim data, or a mesh that
    fails `check_mesh`.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"mesh file not found: {path}; {MAKE_ONE}")
    m = _read_meshio(path)
    try:
        mesh = from_meshio(m, path)
        check_mesh(mesh)
    except MeshError as err:
        raise InputFileError(f"{path}: {err}") from err
    return mesh


def _read_meshio(path: Path) -> meshio.Mesh:
    """meshio.read, with any failure turned into a one-line InputFileError. meshio prints a
    failed read's reason and calls sys.exit; its output is captured and becomes the reason."""
    fmt = mesh_format(path)
    if fmt is None:
        raise InputFileError(f"{path} is not a mesh file (unknown extension {path.suffix!r}); "
                             f"use .vtu, .msh or .xdmf, or {MAKE_ONE}")
    said = io.StringIO()
    try:
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            return meshio.read(path, file_format=fmt)
    except (Exception, SystemExit) as err:  # ReadError, XML, struct, Unicode errors, sys.exit
        lines = [ln for ln in said.getvalue().splitlines() if ln.strip() and "Couldn't read" not in ln]
        lines += [] if isinstance(err, SystemExit) else [str(err) or type(err).__name__]
        reason = " ".join(" ".join(lines).split())[:200]
        detail = f" ({reason})" if reason else ""
        raise InputFileError(f"{path} is not a readable {fmt} mesh file{detail}; {MAKE_ONE}") from err


def from_meshio(m: meshio.Mesh, path: Path) -> FishMesh:
    """FishMesh from a meshio.Mesh in this module's layout; InputFileError if data are missing."""
    blocks = [i for i, c in enumerate(m.cells) if c.type == "triangle"]
    if len(blocks) != 1:
        raise InputFileError(f"{path} has {len(blocks)} triangle blocks, fishsim needs exactly one; {MAKE_ONE}")
    missing = [k for k in (SURFACE_KEY, LENGTH_KEY) if k not in m.point_data]
    missing += [ACTUATOR_KEY] if ACTUATOR_KEY not in m.cell_data else []
    if missing:
        raise InputFileError(f"{path} is a mesh without the fishsim data ({', '.join(missing)}); {MAKE_ONE}")
    points = _planar_points(m.points, path)
    return FishMesh(
        points=points,
        triangles=np.asarray(m.cells[blocks[0]].data, dtype=np.int64),
        surface=_surface_from_order(m.point_data[SURFACE_KEY], path),
        actuator=np.rint(m.cell_data[ACTUATOR_KEY][blocks[0]]).astype(np.int8).ravel(),
        length=_length(m.point_data[LENGTH_KEY], path),
    )


def _planar_points(points: np.ndarray, path: Path) -> np.ndarray:
    """(X, Y) [N, 2] float64 (native byte order) from [N, 2] or [N, 3] points with Z = 0."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (2, 3) or (points.shape[1] == 3 and np.any(points[:, 2] != 0)):
        raise InputFileError(f"{path} is not a planar mesh (points {points.shape}, Z must be 0); {MAKE_ONE}")
    return np.ascontiguousarray(points[:, :2])


def _surface_from_order(order: np.ndarray, path: Path) -> np.ndarray:
    """Surface nodes [S] int64 from surface_order [N] (k >= 0 for the k-th surface node)."""
    order = np.rint(np.asarray(order, dtype=np.float64)).astype(np.int64).ravel()
    nodes = np.flatnonzero(order >= 0)
    nodes = nodes[np.argsort(order[nodes], kind="stable")]
    if not np.array_equal(order[nodes], np.arange(len(nodes))):
        raise InputFileError(f"{path}: surface_order must number the surface nodes 0..S-1 once each; {MAKE_ONE}")
    return nodes


def _length(values: np.ndarray, path: Path) -> float:
    """The body length L (m) from the constant fishsim_length point data."""
    values = np.asarray(values, dtype=np.float64).ravel()
    if values.size == 0 or not np.all(values == values[0]):
        raise InputFileError(f"{path}: fishsim_length must be one constant value; {MAKE_ONE}")
    return float(values[0])

"""netCDF-style conventions for the trajectory file, so that xarray (engine h5netcdf) and other
HDF5 tools see named dimensions, units and descriptions:

* every dataset carries ``units`` and ``long_name`` attributes (``META``);
* every dimension of every dataset has an HDF5 dimension scale attached, a root-level dataset
  named after the dimension (``DIMS``): frame, fluid_frame (growing with the run), fish, node,
  xy, element, corner, surface_node, muscle, and the fluid grid's y, x (cell centres, m) and
  y_vertex, x_vertex (m);
* attribute names are snake_case (``snake``).

    import xarray as xr
    xr.open_dataset("trajectory.h5", engine="h5netcdf", group="solid")   # q (frame, fish, node, xy)
"""

from __future__ import annotations

import re

import h5py
import numpy as np

#: dataset -> (units, long_name); a group's entry covers its datasets not listed themselves
META = {
    "solid/q": ("m", "node positions"),
    "solid/qdot": ("m/s", "node velocities"),
    "solid/f_ext": ("N/m", "fluid force on each node (per unit depth)"),
    "controller/activation": ("1", "muscle contraction"),
    "controller/frequency": ("Hz", "controller frequency"),
    "controller/amplitude": ("1/m", "controller amplitude C"),
    "controller/wave_number": ("rad/m", "body-wave number gamma"),
    "controller/youngs_modulus": ("Pa", "Young's modulus E"),
    "fluid/p": ("Pa", "pressure at cell centres"),
    "fluid/vx": ("m/s", "x velocity at cell centres"),
    "fluid/vy": ("m/s", "y velocity at cell centres"),
    "fluid/mask": ("1", "solid fraction b (1 = solid)"),
    "fluid/a": ("m^2/s", "stream function (vector potential) at cell vertices"),
    "fluid/frame": ("1", "frame index of each stored fluid frame"),
    "mesh/points": ("m", "rest positions of the nodes (material frame, X = 0 at the tail)"),
    "mesh/triangles": ("1", "node indices of each triangle (counter-clockwise)"),
    "mesh/surface": ("1", "node indices of the surface polyline (counter-clockwise)"),
    "mesh/actuator": ("1", "muscle side of each triangle (0 none, 1 top, 2 bottom)"),
    "mesh/muscles": ("1", "triangle index of each muscle"),
    "metrics/time": ("s", "time at the end of each frame"),
    "metrics/head_x": ("m", "x of the head (nose) node"),
    "metrics/head_y": ("m", "y of the head (nose) node"),
    "metrics/tail_y": ("m", "y of the tail tip node"),
    "metrics/centroid_x": ("m", "x of the mass centroid"),
    "metrics/centroid_y": ("m", "y of the mass centroid"),
    "metrics/thrust_x": ("N/m", "total x force of the fluid on the fish"),
    "metrics/force_y": ("N/m", "total y force of the fluid on the fish"),
    "metrics/power": ("W/m", "power the fish gives to the fluid (in the water's rest frame)"),
    "metrics/tunnel_u": ("m/s", "swim tunnel: speed of the water past the fish (0 outside a tunnel)"),
}

#: dataset -> its dimension names (first match: the dataset, then its group's "*")
DIMS = {
    "solid/*": ("frame", "fish", "node", "xy"),
    "controller/activation": ("frame", "fish", "muscle"),
    "controller/*": ("fish",),
    "fluid/a": ("fluid_frame", "fish", "y_vertex", "x_vertex"),
    "fluid/frame": ("fluid_frame",),
    "fluid/*": ("fluid_frame", "fish", "y", "x"),
    "metrics/time": ("frame",),
    "metrics/*": ("frame", "fish"),
    "mesh/points": ("node", "xy"),
    "mesh/triangles": ("element", "corner"),
    "mesh/surface": ("surface_node",),
    "mesh/actuator": ("element",),
    "mesh/muscles": ("muscle",),
}

GROWING = ("frame", "fluid_frame")


def lookup(table: dict, name: str):
    """``table[name]``, else ``table["<group>/*"]``, else None."""
    return table.get(name, table.get(name.split("/")[0] + "/*"))


def snake(name: str) -> str:
    """An attribute name in snake_case: "head distance [m]" -> "head_distance_m"."""
    return re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_")


def describe(f: h5py.File, name: str, dx: float | None) -> None:
    """Give dataset ``name`` its units, long_name and dimension scales (made on first use)."""
    ds = f[name]
    meta = lookup(META, name)
    if meta is not None:
        ds.attrs["units"], ds.attrs["long_name"] = meta
    dims = lookup(DIMS, name)
    if dims is None or len(dims) != ds.ndim:
        return
    for axis, dim in enumerate(dims):
        ds.dims[axis].attach_scale(_scale(f, dim, ds.shape[axis], dx))


def _scale(f: h5py.File, dim: str, n: int, dx: float | None) -> h5py.Dataset:
    if dim in f:
        return f[dim]
    if dim in GROWING:
        scale = f.create_dataset(dim, shape=(0,), maxshape=(None,), dtype="i8", chunks=(1024,))
        scale.attrs["long_name"] = "frame index" if dim == "frame" else "frame index of each stored fluid frame"
    else:
        scale = f.create_dataset(dim, data=_values(dim, n, dx))
        if dim in ("y", "x", "y_vertex", "x_vertex") and dx:
            scale.attrs["units"] = "m"
    scale.make_scale(dim)
    return scale


def _values(dim: str, n: int, dx: float | None) -> np.ndarray:
    if dim == "xy":
        return np.array([b"x", b"y"])
    if dx and dim in ("y", "x"):
        return (np.arange(n) + 0.5) * dx
    if dx and dim in ("y_vertex", "x_vertex"):
        return np.arange(n) * dx
    return np.arange(n)


def grow(f: h5py.File) -> None:
    """Extend the growing scales to their datasets' length, writing only the new entries: frame
    to 0..frames-1 (/metrics/time's length), fluid_frame to /fluid/frame's values."""
    for dim, source in (("frame", "metrics/time"), ("fluid_frame", "fluid/frame")):
        if dim not in f or source not in f:
            continue
        old, new = f[dim].shape[0], f[source].shape[0]
        if new > old:
            f[dim].resize(new, axis=0)
            f[dim][old:] = np.arange(old, new) if dim == "frame" else f[source][old:new]

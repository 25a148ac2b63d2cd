"""Scalar fields to colour-map, their fixed colour limits, and the force-arrow scale.

All functions take and return numpy arrays; nothing here draws or touches files.
"""

from __future__ import annotations

import numpy as np

from fishsim.errors import InputFileError
from fishsim.render.data import RenderData

DIVERGING = {"pressure": True, "vorticity": True, "speed": False}
COLORMAPS = {"pressure": "RdBu_r", "vorticity": "PuOr_r", "speed": "viridis"}
UNITS = {"pressure": "Pa", "vorticity": "1/s", "speed": "m/s"}


def vorticity(vx: np.ndarray, vy: np.ndarray, dx: float) -> np.ndarray:
    """omega = d(vy)/dx - d(vx)/dy [1/s] by central differences (one-sided at the edges);
    arrays [..., H, W] with rows = y, columns = x."""
    return np.gradient(vy, dx, axis=-1) - np.gradient(vx, dx, axis=-2)


def speed(vx: np.ndarray, vy: np.ndarray) -> np.ndarray:
    """|v| = sqrt(vx^2 + vy^2) [m/s]."""
    return np.hypot(vx, vy)


def field_frames(data: RenderData, name: str) -> np.ndarray:
    """The named field for every stored fluid frame, [n_f, H, W]."""
    fl = data.fluid
    if name == "pressure":
        return fl["p"]
    if "vx" not in fl or "vy" not in fl:
        raise InputFileError(f"{data.path} stores no fluid velocity (/fluid/vx, /fluid/vy); "
                             f"render field=pressure instead of field={name}")
    if name == "vorticity":
        return vorticity(fl["vx"], fl["vy"], data.grid[2]).astype(np.float32)
    return speed(fl["vx"], fl["vy"])


def normalised(frames: np.ndarray) -> np.ndarray:
    """Each frame divided by its own max |value| (frames of zeros stay zero)."""
    peak = np.abs(frames).max(axis=(-2, -1), keepdims=True)
    return frames / np.where(peak > 0, peak, 1.0)


def colour_limits(frames: np.ndarray, name: str, percentile: float = 99.0,
                  mask: np.ndarray | None = None) -> tuple[float, float]:
    """Fixed colour limits for a whole run: the ``percentile`` of |field| over all frames and
    fluid cells (mask < 0.5); symmetric around 0 for diverging fields, from 0 for speed."""
    values = frames if mask is None or not (mask < 0.5).any() else frames[mask < 0.5]
    top = float(np.nanpercentile(np.abs(values), percentile)) if values.size else 0.0
    top = top if np.isfinite(top) and top > 0 else 1e-12
    return (-top, top) if DIVERGING[name] else (0.0, top)


def arrow_forces(f_ext: np.ndarray, surface: np.ndarray, n_arrows: int) -> tuple[np.ndarray, np.ndarray]:
    """Forces drawn as about ``n_arrows`` arrows: the surface polyline cut into runs of
    k = ceil(S / n_arrows) consecutive nodes, each run's total force [F, A, 2] (N/m, so the
    arrows add up to the fish's total) at its middle node (mesh indices [A]); n_arrows <= 0 or
    >= S: one arrow per surface node."""
    S = len(surface)
    k = 1 if n_arrows <= 0 or n_arrows >= S else -(-S // n_arrows)
    starts = np.arange(0, S, k)
    ends = np.minimum(starts + k, S)
    return surface[(starts + ends - 1) // 2], np.add.reduceat(f_ext[:, surface], starts, axis=1)


def force_scale(forces: np.ndarray, percentile: float = 95.0) -> float:
    """The ``percentile`` of the arrows' force magnitude over the run [N/m] (robust against a
    few spikes); 0 if there are no forces."""
    mags = np.linalg.norm(forces, axis=-1)
    return float(np.nanpercentile(mags, percentile)) if mags.size else 0.0

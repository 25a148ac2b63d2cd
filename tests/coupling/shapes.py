"""Closed ccw test outlines on the paper's 2.5 mm grid (float64 numpy -> torch)."""

from __future__ import annotations

import numpy as np
import torch

L = 0.2  # fish length (m), docs/physics.md section 2


def ellipse(n: int, centre=(0.2, 0.125), axes=(0.05, 0.02), phase: float = 0.0) -> torch.Tensor:
    """n nodes of an ellipse, counter-clockwise, [1, n, 2]; exact area pi a b."""
    t = phase + 2 * np.pi * np.arange(n) / n
    q = np.stack([centre[0] + axes[0] * np.cos(t), centre[1] + axes[1] * np.sin(t)], -1)
    return torch.tensor(q)[None]


def fish_half_width(X: np.ndarray) -> np.ndarray:
    """Kern & Koumoutsakos profile w(s), s = L - X (docs/physics.md section 2)."""
    s = L - X
    wh = sb = 0.04 * L
    st, wt = 0.95 * L, 0.01 * L
    nose = np.sqrt(np.clip(2 * wh * s - s ** 2, 0, None))
    body = wh - (wh - wt) * ((s - sb) / (st - sb)) ** 2
    tail = wt * (L - s) / (L - st)
    return np.where(s < sb, nose, np.where(s < st, body, tail))


def fish_outline(n: int = 200, origin=(0.2, 0.125)) -> torch.Tensor:
    """Fish outline resampled to n nodes equally spaced in arc length, ccw, [1, n, 2]."""
    X = L * (1 - np.cos(np.linspace(0, np.pi / 2, 4001))) ** 1.0
    X = np.unique(np.concatenate([np.linspace(0, L, 4001), L - (L - X) ** 2 / L]))
    w = fish_half_width(X)
    bottom = np.stack([X, -w], -1)
    top = np.stack([X[::-1], w[::-1]], -1)[1:-1]
    dense = np.concatenate([bottom, top])
    seg = np.linalg.norm(np.diff(dense, axis=0, append=dense[:1]), axis=1)
    arc = np.concatenate([[0], np.cumsum(seg)])
    closed = np.concatenate([dense, dense[:1]])
    u = np.linspace(0, arc[-1], n, endpoint=False)
    q = np.stack([np.interp(u, arc, closed[:, 0]), np.interp(u, arc, closed[:, 1])], -1)
    return torch.tensor(q + np.asarray(origin))[None]


def polyline_signed_distance(points: torch.Tensor, qs: torch.Tensor) -> torch.Tensor:
    """Brute-force signed distance (negative inside) from points [P, 2] to the closed polyline
    qs [S, 2], independent of fishsim (reference for the tests), [P]."""
    a, b = qs[None], torch.roll(qs, -1, 0)[None]
    x = points[:, None]
    t = (((x - a) * (b - a)).sum(-1) / ((b - a) ** 2).sum(-1)).clamp(0, 1)
    dist = (x - a - t[..., None] * (b - a)).norm(dim=-1).amin(1)
    ya, yb = a[..., 1], b[..., 1]
    cross = ((ya > x[..., 1]) != (yb > x[..., 1])) & (
        x[..., 0] < a[..., 0] + (x[..., 1] - ya) * (b[..., 0] - a[..., 0]) / (yb - ya))
    inside = cross.sum(1) % 2 == 1
    return torch.where(inside, -dist, dist)

"""The fish mesh: plain data shared by the solid, the coupling and the outputs."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ACTUATOR_NONE, ACTUATOR_TOP, ACTUATOR_BOTTOM = 0, 1, 2


@dataclass(frozen=True)
class FishMesh:
    """A triangulated 2D fish in its material frame (docs/physics.md section 2).

    points: [N, 2] float64 node positions (X, Y) in metres; X in [0, L] along the body with
        X = 0 at the tail and X = L at the head, Y lateral (top: Y > 0).
    triangles: [T, 3] int64 node indices, counter-clockwise.
    surface: [S] int64 indices of the boundary nodes, one closed counter-clockwise polyline
        (first node not repeated).
    actuator: [T] int8 per element: 0 none, 1 top muscle, 2 bottom muscle.
    length: body length L in metres.
    """

    points: np.ndarray
    triangles: np.ndarray
    surface: np.ndarray
    actuator: np.ndarray
    length: float

    @property
    def n_nodes(self) -> int:
        return len(self.points)

    @property
    def n_elements(self) -> int:
        return len(self.triangles)

    @property
    def actuated(self) -> np.ndarray:
        """Indices of actuated elements (top and bottom), [n_act]."""
        return np.flatnonzero(self.actuator != ACTUATOR_NONE)

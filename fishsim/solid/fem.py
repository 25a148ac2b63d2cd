"""Finite-element quantities of a triangle mesh: rest shapes, areas, F = G q and lumped masses.

Linear triangles, one quadrature point each (constant deformation gradient). For element e with
nodes (0, 1, 2), rest positions X_k and current positions x_k (both [2] metres):

    Dm = [X_1 - X_0, X_2 - X_0]   (rest shape matrix, [2, 2], columns are edges)
    Ds = [x_1 - x_0, x_2 - x_0]
    F  = Ds Dm^-1                  ([2, 2], F_aj = dx_a / dX_j, dimensionless)

F is linear in the element's node positions, F_aj = sum_k x_ka g_kj with shape-function
gradients g [3, 2] in 1/m (g_0 = -g_1 - g_2). The same operator acts on the x and the y
coordinate (the "per-axis split"), so it is stored once as a sparse matrix G [2T, N]: row j T + e,
column node k, value g_kj; (G @ q[:, a])[j T + e] is F_aj of element e.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from fishsim.errors import MeshError
from fishsim.linalg.banded import BandLayout
from fishsim.mesh.fish_mesh import FishMesh


@dataclass(frozen=True)
class CscPattern:
    """Sparsity of sum_e (element 6x6 blocks) in CSC form: entry (e, r, c) of the stacked element
    matrices [T, 6, 6] is added to data[slot[e, r, c]] (so assembly is one bincount); the
    diagonal entry of DOF k is data[diagonal[k]]."""

    slot: np.ndarray
    indices: np.ndarray
    indptr: np.ndarray
    diagonal: np.ndarray
    size: int

    def assemble(self, Ke: np.ndarray, diagonal: np.ndarray | None = None) -> sp.csc_matrix:
        """Sparse [size, size] matrix sum_e P_e^T Ke[e] P_e (+ diag(diagonal) if given) from element
        matrices Ke [T, 6, 6]; canonical CSC (sorted indices, no duplicates)."""
        data = np.bincount(self.slot, weights=Ke.ravel(), minlength=len(self.indices))
        if diagonal is not None:
            data[self.diagonal] += diagonal
        K = sp.csc_matrix((data, self.indices, self.indptr), shape=(self.size, self.size))
        K.has_canonical_format = True
        return K


@dataclass(frozen=True)
class NewtonBand:
    """Where the element entries of the solid's [2N, 2N] Newton matrices land in its padded band
    [rows, cols] (banded.BandLayout of the mesh's pattern): slot [T, 6, 6], the flat index of
    each element matrix entry (-1 above the diagonal, which the band omits); diagonal [2N], that
    of each DOF's diagonal entry. One per mesh (SolidModel.newton_band)."""

    layout: BandLayout
    slot: np.ndarray
    diagonal: np.ndarray

    @classmethod
    def of(cls, pattern: CscPattern) -> NewtonBand:
        layout = BandLayout.of(pattern.indptr, pattern.indices)
        flat = np.full(len(pattern.indices), -1)
        flat[layout.lower] = layout.column * layout.cols + layout.offset
        return cls(layout, flat[pattern.slot].reshape(-1, 6, 6), flat[pattern.diagonal])


@dataclass(frozen=True)
class FemQuantities:
    """Per-element and per-node FEM data of one mesh (numpy, float64, SI units).

    Dm_inv: [T, 2, 2] inverse rest shape matrices (1/m).
    area: [T] rest areas (m^2).
    grad: [T, 3, 2] shape-function gradients g_kj (1/m).
    G: [2T, N] sparse CSR deformation-gradient operator (row j T + e, 1/m).
    mass: [N] lumped nodal masses (kg per unit depth).
    centroid_X: [T] material X of each element's centroid (m).
    element_G: [T, 4, 6] dense G_e: vec(F) (row 2a + j) from the element DOFs (column 2k + a).
    pattern: CsrPattern of the [2N, 2N] element-assembled matrices (DOF 2i + a).
    """

    Dm_inv: np.ndarray
    area: np.ndarray
    grad: np.ndarray
    G: sp.csr_matrix
    mass: np.ndarray
    centroid_X: np.ndarray
    element_G: np.ndarray
    pattern: CscPattern

    @property
    def n_nodes(self) -> int:
        return self.G.shape[1]

    @property
    def n_elements(self) -> int:
        return len(self.area)


def rest_shapes(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse rest shape matrices Dm^-1 [T, 2, 2] and areas |det Dm| / 2 [T] of ccw triangles."""
    X = points[triangles]                                        # [T, 3, 2]
    Dm = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]], axis=2)  # columns are edges
    det = Dm[:, 0, 0] * Dm[:, 1, 1] - Dm[:, 0, 1] * Dm[:, 1, 0]
    if np.any(det <= 0):
        raise MeshError(f"{int(np.sum(det <= 0))} triangles are degenerate or clockwise; "
                        "the solid needs counter-clockwise triangles with positive area")
    return np.linalg.inv(Dm), det / 2


def shape_gradients(Dm_inv: np.ndarray) -> np.ndarray:
    """g [T, 3, 2] with F = sum_k x_k g_k^T: g_1 = row 0 of Dm^-1, g_2 = row 1, g_0 = -g_1 - g_2."""
    return np.stack([-Dm_inv[:, 0] - Dm_inv[:, 1], Dm_inv[:, 0], Dm_inv[:, 1]], axis=1)


def deformation_gradient_operator(triangles: np.ndarray, grad: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """Sparse G [2T, N]: (G @ x)[j T + e] = sum_k g_ekj x[tri_ek] = F_aj of element e for axis x."""
    T = len(triangles)
    rows = (np.arange(T)[:, None, None] + T * np.arange(2)[None, None, :]).repeat(3, axis=1)
    cols = np.broadcast_to(triangles[:, :, None], (T, 3, 2))
    return sp.csr_matrix((grad.ravel(), (rows.ravel(), cols.ravel())), shape=(2 * T, n_nodes))


def element_operators(grad: np.ndarray) -> np.ndarray:
    """G_e [T, 4, 6]: vec(F)_{2a + j} = sum_k g_kj x_{ka}, element DOF 2k + a."""
    T = len(grad)
    Ge = np.zeros((T, 2, 2, 3, 2))                           # [e, a, j, k, a']
    for a in range(2):
        Ge[:, a, :, :, a] = grad.transpose(0, 2, 1)
    return Ge.reshape(T, 4, 6)


def csc_pattern(triangles: np.ndarray, n_nodes: int) -> CscPattern:
    """CSC pattern of matrices assembled from 6x6 element blocks over DOFs 2i + a."""
    T = len(triangles)
    dofs = (2 * triangles[:, :, None] + np.arange(2)).reshape(T, 6)
    rows = np.broadcast_to(dofs[:, :, None], (T, 6, 6)).ravel()
    cols = np.broadcast_to(dofs[:, None, :], (T, 6, 6)).ravel()
    size = 2 * n_nodes
    keys, slot = np.unique(cols * size + rows, return_inverse=True)    # sorted by (col, row)
    indptr = np.searchsorted(keys // size, np.arange(size + 1))
    diagonal = np.searchsorted(keys, np.arange(size) * (size + 1))
    return CscPattern(slot.ravel(), (keys % size).astype(np.int32), indptr.astype(np.int32), diagonal, size)


def lumped_masses(triangles: np.ndarray, area: np.ndarray, n_nodes: int, density: float) -> np.ndarray:
    """m_i = sum over triangles e containing i of density * area_e / 3 (kg per unit depth)."""
    return np.bincount(triangles.ravel(), weights=np.repeat(density * area / 3, 3), minlength=n_nodes)


def fem_quantities(mesh: FishMesh, density: float) -> FemQuantities:
    """All FEM data of `mesh` for a solid of `density` (kg/m^3, per unit area in 2D)."""
    points = np.asarray(mesh.points, np.float64)
    tris = np.asarray(mesh.triangles, np.int64)
    Dm_inv, area = rest_shapes(points, tris)
    grad = shape_gradients(Dm_inv)
    G = deformation_gradient_operator(tris, grad, len(points))
    mass = lumped_masses(tris, area, len(points), density)
    if np.any(mass <= 0):
        raise MeshError(f"{int(np.sum(mass <= 0))} mesh nodes belong to no triangle; remove them")
    return FemQuantities(Dm_inv, area, grad, G, mass, points[tris].mean(axis=1)[:, 0],
                         element_operators(grad), csc_pattern(tris, len(points)))

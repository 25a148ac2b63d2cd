"""Pressure recovered from a step's velocities: the pressure that best satisfies the momentum
equation on the fluid faces (HydroNet's forces with ``HydroNetFluid(pressure="recovered")``).

Why. HydroNet's physics loss constrains its pressure output only through grad p in the fluid
residual, and a network trained on it alone (the model shipped before 2026-11-26, the
measurements below) has a pressure that lags its own velocities: on the 5 Hz fish scene the L_p-optimal
pressure for the network's velocities gives ~3x the thrust and ~4x the lateral force of the
network's own pressure (close to the numerical solver's) and a 40 % lower L_p. The velocities are
the better half of the surrogate, so the pressure is recovered from them.

What. With R(p) the IMEX momentum residual (``fishsim.fluid.residual``, central advection) of
v_t -> v_t+1 in Pa/m and w_f = 1 - b_f the fluid face weights (zero on the box-wall faces),

    p = argmin_p  1/2 sum_f [ w_f (R(0)_f + (grad p)_f)^2 + eps (grad p)_f^2 ]

(R(p) = R(0) + grad p), i.e. the weighted least-squares fit of grad p to -R(0) on the fluid
faces, with a small weight eps on every face (target grad p = 0) so that the body interior,
where w ~ 0, is determined. Normal equations (grad^T = -div):

    A p = f,   A p = -div((w + eps) grad p),   f = div(w R(0))              (mean-free p)

solved by conjugate gradients with a two-level preconditioner (``SchwarzPreconditioner``): the DCT
Neumann Poisson solve (exact for w = const) and an exact sparse solve on the low-weight cells and
a few cells around them (the body and the tank walls, where w + eps ~ eps and the DCT solve is
1/eps off), applied in turn (symmetric multiplicative Schwarz). eps
trades conditioning for bias: the solid faces' grad p = 0 target pulls the
pressure jump across a thin tail down. Measured on the 5 Hz fish scene (mean thrust / lateral
force amplitude, numerical solver 98.6 / 1005 mN/m; the network's own pressure 31 / 233):
eps 1e-2: 49 / 656, 37 iterations; eps 1e-3: 60 / 924; eps 1e-4: 62 / 957, 178 iterations.
The force is converged at a relative residual of 1e-2 (60.0 / 913 vs 60.2 / 923 at 1e-3, 23 vs
56 iterations), hence eps = 1e-3. The default tol = 1e-6 is set by the gradient, not the force: a
solve stopped at 1e-2 depends on its warm start (below), a dependence the implicit gradient does
not see, and over a 100-frame swim (5 Hz, full scale, float64) autograd gave -1.7e-3 m/Hz against
central differences of -4.7e-3; at 1e-6 (26 iterations a solve instead of 9.5, no measurable
change in the frame's time) the distance moves by 0.4 % and autograd agrees within 2 %. With the
DCT solve alone, the adjoint solves took 35-55 iterations on this scene; with the subdomain solve
added (additive, the low-weight cells only), 10-14. (These counts predate the multiplicative
form with overlap of 2026-11-29, which solves the recovery of the 5 Hz fish to 1e-6 in 8
iterations instead of 22, and 6.8 with the overlap of 12 cells, ``SCHWARZ_OVERLAP``.)

Differentiable by implicit differentiation (``WeightedPoisson``): with lambda = A^+ dL/dp,
dL/df = lambda and dL/dw_f = -(grad lambda)_f (grad p)_f; one more solve per backward.
The gradient is the exact gradient of the converged solve (use a tight ``tol`` where it must
match finite differences, e.g. in float64 tests).

Warm start. Consecutive frames have similar pressures, so the forward PCG starts from the
previous frame's pressure (the fluid state's p), or from a given guess (a checkpoint
recomputation passes the forward's solution, which then needs no iteration). The start changes
the result only within ``tol`` and is detached (the solution, not the start, is differentiated).
The adjoint solve starts from zero, so a backward pass does not depend on earlier ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from fishsim.compiled import jit
from fishsim.fields import Grid
from fishsim.fluid.grid import Faces, divergence, gradient
from fishsim.fluid.residual import fluid_face_masks, momentum_residual
from fishsim.linalg.banded import BandedCholesky, BandLayout
from fishsim.linalg.banded import factor as banded_factor
from fishsim.linalg.banded import solve as banded_solve
from fishsim.linalg.dct import inverse_sample, neumann_inverse, solve_neumann_poisson
from fishsim.linalg.pcg import pcg


@dataclass(frozen=True)
class RecoveryConfig:
    """eps: weight of the solid faces (relative to 1 in the fluid); tol: relative residual
    |f - A p| / |f| at which PCG stops; max_iter: PCG iteration cap."""

    eps: float = 1e-3
    tol: float = 1e-6
    max_iter: int = 500


def _mean_free(x: Tensor) -> Tensor:
    return x - x.mean(dim=(-2, -1), keepdim=True)


SCHWARZ_OVERLAP = 12
"""Cells by which S grows beyond the low-weight cells (``SchwarzPreconditioner``). Measured on the
swimming fish (5 Hz, 40 frames; the joint solves to 1e-3): overlap 2 / 4 / 6 / 8 / 12 / 16 took
5.7 / 4.7 / 4.0 / 3.6 / 3.1 / 2.7 iterations a solve on 3560 / 3920 / 4290 / 4680 / 5500 / 6380
cells of S; per step the larger band costs less than the iterations it saves up to 12-16 (the
frequency study 13.4-14.5 s at 12, 14.1-14.7 at 16, 16.1-16.3 at 24, against 15.4-15.5 s at 4,
one thread; Table 1 forward / backward 11.3-12.5 / 14.3-15.8 s against 12.6-13.2 / 15.9-17.4 s);
HydroNet's pressure recovery 6.8 iterations a solve against 8.2 at 4."""


class SchwarzPreconditioner:
    """r -> z, the symmetric multiplicative Schwarz preconditioner of A = -div(w grad .) (symmetric
    positive semi-definite) from two solvers: B_S = R^T A_S^-1 R, an exact solve on the subdomain S
    (Dirichlet truncation: A_S the rows and columns of A on S, R the restriction to S), and L^+,
    the DCT Neumann Poisson solve of -laplacian (exact where w = 1):

        z1 = B_S r,   z2 = z1 + L^+ (r - A z1),   z = z2 + B_S (r - A z2).

    S is every cell whose face weights are all < ``threshold`` (the body, its band and the tank
    walls), the parts not joined to the box's edge grown by ``overlap`` cells (``SCHWARZ_OVERLAP``;
    the walls' ring, grown by 4, would double S: 6918 cells instead of 3910 on the fish's tank,
    for 8 iterations instead of 9 to 1e-6). Measured with overlap 4 on the fish's joint
    penalisation solves (``NumericalFluid(implicit=True)``, PCG to 1e-6; 5 Hz, n = 4) and its
    pressure recovery (HydroNet, ``fluid.pressure=recovered``): 8-9 / 8 iterations a solve, where
    the additive form L^+ r + B_S r on the cells with weights < 0.5 took 20 / 22 (and 16-17 with
    the same overlap).
    The banded Cholesky factors of A_S (one per sample, on the CPU; ``subdomain``: S, its reverse
    Cuthill-McKee order and the band in one compiled pass, ~1 ms on the fish's tank where scipy's
    labelling, dilation, sparse assembly and ordering took ~4 ms; the factorisation ~0.4 ms at
    overlap 4, ~1.8 ms at 12, whose band is twice as wide) are built on first use, so a solve that
    starts converged costs nothing."""

    def __init__(self, weights: Faces, dx: float, threshold: float = 0.99, overlap: int = SCHWARZ_OVERLAP):
        self.weights, self.dx, self.threshold, self.overlap = weights, dx, threshold, overlap
        H, W = weights[0].shape[-2], weights[1].shape[-1]
        self.inverse = neumann_inverse(H, W, dx, weights[0].device, weights[0].dtype)
        self.subdomains: list | None = None

    def factored(self, batch: int) -> list:
        """The samples' (cells of S, banded Cholesky factor of A_S or None), factorised on first use."""
        if self.subdomains is None:
            self.subdomains = [self._factor(b) for b in range(batch)]
        return self.subdomains

    def __call__(self, r: Tensor) -> Tensor:
        self.factored(r.shape[0])
        z = self._local(r)
        z = z - solve_neumann_poisson(r - self.apply(z), self.dx, self.inverse)
        z = z + self._local(r - self.apply(z))
        return _mean_free(z)

    def apply(self, p: Tensor) -> Tensor:
        """A p = -div(w grad p), the operator this preconditions."""
        return -divergence(tuple(w * g for w, g in zip(self.weights, gradient(p, self.dx))), self.dx)

    def _local(self, r: Tensor) -> Tensor:
        """B_S r: A_S^-1 r on each sample's subdomain, 0 elsewhere."""
        z = torch.zeros_like(r)
        flat = z.view(z.shape[0], -1)
        for b, (cells, factor) in enumerate(self.subdomains):
            if factor is None:
                continue
            local = factor.solve(r[b].flatten()[cells].to("cpu", torch.float64).numpy())
            flat[b, cells] = torch.from_numpy(local).to(z)
        return z

    def _factor(self, b: int) -> tuple[Tensor, object]:
        """(flat indices of S [n], banded Cholesky factor of A_S) for sample b (``subdomain``)."""
        wx, wy = (w[b, 0].to("cpu", torch.float64).numpy() for w in self.weights)
        cells, factor = subdomain(wx, wy, self.dx, self.threshold, self.overlap)
        return torch.as_tensor(cells, device=self.weights[0].device), factor


def subdomain(wx: np.ndarray, wy: np.ndarray, dx: float, threshold: float = 0.99,
              overlap: int = SCHWARZ_OVERLAP) -> tuple[np.ndarray, BandedCholesky | None]:
    """(flat indices of S [n], banded Cholesky factor of A_S) of one sample's face weights wx [H,
    W+1], wy [H+1, W] (float64; ``SchwarzPreconditioner``); the factor is None when S is empty
    (then only the DCT part acts). One compiled call (``_subdomain_band``)."""
    cells, perm, row, L, width = _subdomain_band(wx, wy, 1 / dx**2, threshold, overlap)
    if len(cells) == 0 or banded_factor(L, width, 0.0) <= 0:
        return cells, None
    return cells, BandedCholesky(BandLayout.ordered(perm, row, width), L)


@jit(inline="always")
def _face_weights(wx, wy, i, j):
    """(west, east, south, north) face weights of cell (i, j), the box's faces as 0."""
    H, W = wx.shape[0], wy.shape[1]
    return (wx[i, j] if j > 0 else 0.0, wx[i, j + 1] if j < W - 1 else 0.0,
            wy[i, j] if i > 0 else 0.0, wy[i + 1, j] if i < H - 1 else 0.0)


@jit
def _subdomain_cells(wx, wy, threshold, overlap):
    """S of ``SchwarzPreconditioner`` as an [H, W] bool mask: the cells whose four face weights
    (interior faces; the box's count as 0) are all < threshold; the parts of them not joined
    (by faces) to the box's edge, grown by ``overlap`` cells (Manhattan distance)."""
    H, W = wx.shape[0], wy.shape[1]
    inside = np.zeros((H, W), np.bool_)
    for i in range(H):
        for j in range(W):
            west, east, south, north = _face_weights(wx, wy, i, j)
            inside[i, j] = max(max(west, east), max(south, north)) < threshold
    if overlap == 0:
        return inside
    walls = np.zeros((H, W), np.bool_)           # the parts of inside joined to the box's edge
    queue = np.empty(H * W, np.int64)
    m = 0
    for i in range(H):
        for j in range(W):
            if inside[i, j] and (i == 0 or i == H - 1 or j == 0 or j == W - 1):
                walls[i, j] = True
                queue[m] = i * W + j
                m += 1
    k = 0
    while k < m:
        i, j = queue[k] // W, queue[k] % W
        k += 1
        for ii, jj in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
            if 0 <= ii < H and 0 <= jj < W and inside[ii, jj] and not walls[ii, jj]:
                walls[ii, jj] = True
                queue[m] = ii * W + jj
                m += 1
    grown = np.zeros((H, W), np.bool_)           # the rest, grown layer by layer
    m = 0
    for i in range(H):
        for j in range(W):
            if inside[i, j] and not walls[i, j]:
                grown[i, j] = True
                queue[m] = i * W + j
                m += 1
    start = 0
    for _ in range(overlap):
        end = m
        for k in range(start, end):
            i, j = queue[k] // W, queue[k] % W
            for ii, jj in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
                if 0 <= ii < H and 0 <= jj < W and not grown[ii, jj]:
                    grown[ii, jj] = True
                    queue[m] = ii * W + jj
                    m += 1
        start = end
    return walls | grown


@jit
def _cuthill_mckee(seed, cells, index, degree, order, placed, depth, m):
    """Cuthill-McKee from ``seed``: breadth-first over S's cells (neighbours by faces, each cell's
    new neighbours by rising degree), appended to order from m, with each cell's depth (levels
    from seed); returns the new m. placed marks the cells ordered so far (all of seed's component
    on return)."""
    H, W = index.shape
    placed[seed] = True
    depth[seed] = 0
    order[m] = seed
    m += 1
    k = m - 1
    while k < m:
        p = order[k]
        i, j = cells[p] // W, cells[p] % W
        k += 1
        first = m
        for ii, jj in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
            if 0 <= ii < H and 0 <= jj < W:
                q = index[ii, jj]
                if q >= 0 and not placed[q]:
                    placed[q] = True
                    depth[q] = depth[p] + 1
                    order[m] = q
                    m += 1
        for a in range(first + 1, m):                # insertion sort of the (<= 4) new ones
            b = a
            while b > first and degree[order[b]] < degree[order[b - 1]]:
                order[b], order[b - 1] = order[b - 1], order[b]
                b -= 1
    return m


@jit
def _peripheral(seed, cells, index, degree):
    """A pseudo-peripheral cell of seed's component (George and Liu): move to a cell of least
    degree in the last level of a breadth-first search from the current one while the number of
    levels grows."""
    n = cells.shape[0]
    order, placed, depth = np.empty(n, np.int64), np.zeros(n, np.bool_), np.zeros(n, np.int64)
    levels = -1
    while True:
        placed[:] = False
        m = _cuthill_mckee(seed, cells, index, degree, order, placed, depth, 0)
        last = depth[order[m - 1]]
        if last <= levels:
            return seed
        levels, seed = last, order[m - 1]
        for k in range(m - 1, -1, -1):
            if depth[order[k]] != last:
                break
            if degree[order[k]] < degree[seed]:
                seed = order[k]


@jit
def _subdomain_band(wx, wy, inv_dx2, threshold, overlap):
    """``subdomain``'s cells [n] (flat, row-major), their order perm [n] (band row k is the cell
    cells[perm[k]]: ``_reverse_cuthill_mckee``), its inverse row [n] (cell k's band row) and A_S's
    band [rows, cols] in
    fishsim.linalg.banded's layout with its half-bandwidth, unfactored: diagonal (west + east +
    south + north) / dx^2 (every face's weight, the box's 0: the Dirichlet truncation), -w_f / dx^2
    between two cells of S."""
    H, W = wx.shape[0], wy.shape[1]
    index = np.full((H, W), -1, np.int64)
    cells = np.flatnonzero(_subdomain_cells(wx, wy, threshold, overlap))
    n = cells.shape[0]
    for k in range(n):
        index[cells[k] // W, cells[k] % W] = k
    perm = _reverse_cuthill_mckee(cells, index)
    row = np.empty(n, np.int64)
    row[perm] = np.arange(n)
    width = 0
    for k in range(n):
        i, j = cells[k] // W, cells[k] % W
        for ii, jj in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
            if 0 <= ii < H and 0 <= jj < W and index[ii, jj] >= 0:
                width = max(width, abs(row[k] - row[index[ii, jj]]))
    rows = -(-n // 4) * 4
    L = np.zeros((max(rows, 4), width + 4))
    L[n:rows, 0] = 1.0
    for k in range(n):
        i, j = cells[k] // W, cells[k] % W
        west, east, south, north = _face_weights(wx, wy, i, j)
        faces = ((i, j - 1, west), (i, j + 1, east), (i - 1, j, south), (i + 1, j, north))
        diagonal = 0.0
        for ii, jj, w in faces:
            diagonal += w
            if 0 <= ii < H and 0 <= jj < W and index[ii, jj] >= 0 and row[index[ii, jj]] > row[k]:
                L[row[k], row[index[ii, jj]] - row[k]] = -w * inv_dx2
        L[row[k], 0] = diagonal * inv_dx2
    return cells, perm, row, L, width


@jit
def _reverse_cuthill_mckee(cells, index):
    """perm [n] of the cells of S (index [H, W]: each cell's number, -1 off S): Cuthill-McKee by
    components, each from a pseudo-peripheral cell (``_peripheral``), reversed. On the fish's tank
    its half-bandwidth is 16 where scipy's reverse_cuthill_mckee (from a cell of least degree)
    gives 24."""
    H, W = index.shape
    n = cells.shape[0]
    degree = np.zeros(n, np.int64)
    for k in range(n):
        i, j = cells[k] // W, cells[k] % W
        for ii, jj in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
            if 0 <= ii < H and 0 <= jj < W and index[ii, jj] >= 0:
                degree[k] += 1
    order, placed, depth = np.empty(n, np.int64), np.zeros(n, np.bool_), np.empty(n, np.int64)
    m = 0
    for seed in range(n):
        if not placed[seed]:
            start = _peripheral(seed, cells, index, degree)
            m = _cuthill_mckee(start, cells, index, degree, order, placed, depth, m)
    return order[::-1].copy()


def local_solver(cells: np.ndarray, factor: BandedCholesky | None) -> tuple:
    """The arguments (cells, band, width, perm, inverse, local) of the compiled preconditioner
    (``_precondition_sample``) for ``subdomain``'s result; placeholders and local False when the
    factor is None."""
    if factor is None:
        return (np.zeros(0, np.int64), np.zeros((1, 1)), 0, np.zeros(0, np.int64), np.zeros(0, np.int64), False)
    lay = factor.layout
    return (np.asarray(cells, np.int64), factor.factor, lay.width, lay.perm, lay.inverse, True)


# --------------------------------------------------------------------------------------------
# The CPU's PCG, compiled: the same iteration as fishsim.linalg.pcg with the preconditioner above
# --------------------------------------------------------------------------------------------


@jit
def _apply_sample(wx, wy, p, inv_dx2, out):
    """out = A p = -div(w grad p) of one sample [H, W] (no flux through the box's faces)."""
    H, W = p.shape
    for i in range(H):
        for j in range(W):
            c = p[i, j]
            s = 0.0
            if j > 0:
                s += wx[i, j] * (c - p[i, j - 1])
            if j < W - 1:
                s += wx[i, j + 1] * (c - p[i, j + 1])
            if i > 0:
                s += wy[i, j] * (c - p[i - 1, j])
            if i < H - 1:
                s += wy[i + 1, j] * (c - p[i + 1, j])
            out[i, j] = s * inv_dx2


@jit
def _local_sample(r, cells, band, width, perm, inverse, out):
    """out = B_S r (``SchwarzPreconditioner._local``) of one sample: the banded solve on the cells
    of S (float64), 0 elsewhere."""
    flat_r, flat = r.reshape(-1), out.reshape(-1)
    flat[:] = 0.0
    n = cells.shape[0]
    rhs, z, scratch = np.empty(n), np.empty(n), np.empty(n)
    for k in range(n):
        rhs[k] = flat_r[cells[k]]
    banded_solve(band, width, perm, inverse, rhs, z, scratch, 0.0)
    for k in range(n):
        flat[cells[k]] = z[k]


@jit
def _precondition_sample(wx, wy, r, inv_dx2, pivots, dx, cells, band, width, perm, inverse, local, z, t):
    """z = M r (``SchwarzPreconditioner.__call__``) of one sample; t: scratch."""
    if local:
        _local_sample(r, cells, band, width, perm, inverse, z)
    else:
        z[:] = 0.0
    _apply_sample(wx, wy, z, inv_dx2, t)
    z -= inverse_sample(r - t, pivots, dx)
    if local:
        _apply_sample(wx, wy, z, inv_dx2, t)
        correction = np.empty_like(z)
        _local_sample(r - t, cells, band, width, perm, inverse, correction)
        z += correction
    z -= z.mean()


@jit
def _dot(a, b) -> float:
    """sum a b over one sample's cells, in float64 (four partial sums: independent chains)."""
    fa, fb = a.reshape(-1), b.reshape(-1)
    n = fa.shape[0]
    s0 = s1 = s2 = s3 = 0.0
    k = 0
    while k + 3 < n:
        s0 += float(fa[k]) * float(fb[k])
        s1 += float(fa[k + 1]) * float(fb[k + 1])
        s2 += float(fa[k + 2]) * float(fb[k + 2])
        s3 += float(fa[k + 3]) * float(fb[k + 3])
        k += 4
    while k < n:
        s0 += float(fa[k]) * float(fb[k])
        k += 1
    return (s0 + s1) + (s2 + s3)


@jit
def _pcg_sample(wx, wy, f, x, inv_dx2, pivots, dx, cells, band, width, perm, inverse, local, tol, max_iter):
    """Preconditioned conjugate gradients for A x = f (f mean free) of one sample from x (the
    start, overwritten with the solution), stopping at |f - A x| <= tol |f|: the iteration of
    fishsim.linalg.pcg, dots in float64; returns the iterations taken."""
    target = tol * np.sqrt(_dot(f, f))
    if target == 0.0:
        x[:] = 0.0
        return 0
    Ax, t = np.empty_like(x), np.empty_like(x)
    _apply_sample(wx, wy, x, inv_dx2, Ax)
    r = f - Ax
    if np.sqrt(_dot(r, r)) <= target:
        return 0
    z = np.empty_like(x)
    _precondition_sample(wx, wy, r, inv_dx2, pivots, dx, cells, band, width, perm, inverse, local, z, t)
    d = z.copy()
    rz = _dot(r, z)
    Ad = np.empty_like(x)
    for it in range(1, max_iter + 1):
        _apply_sample(wx, wy, d, inv_dx2, Ad)
        dAd = _dot(d, Ad)
        if dAd <= 0.0:
            return it
        step = x.dtype.type(rz / dAd)
        x += step * d
        r -= step * Ad
        if np.sqrt(_dot(r, r)) <= target:
            return it
        _precondition_sample(wx, wy, r, inv_dx2, pivots, dx, cells, band, width, perm, inverse, local, z, t)
        rz_new = _dot(r, z)
        d *= x.dtype.type(rz_new / rz)
        d += z
        rz = rz_new
    return max_iter


def _solve_cpu(weights: Faces, f: Tensor, dx: float, tol: float, max_iter: int, start: Tensor | None,
               precondition: SchwarzPreconditioner) -> tuple[Tensor, int]:
    """``solve_weighted_poisson`` on the CPU: ``_pcg_sample`` per sample (f mean free, start mean
    free or None)."""
    subdomains = precondition.factored(f.shape[0])
    rhs = f.detach().numpy()
    wx, wy = (w.detach().to(f.dtype).expand(f.shape[0], 1, *w.shape[-2:]).numpy() for w in weights)
    x = np.zeros_like(rhs) if start is None else start.numpy().copy()
    inverse, iterations = precondition.inverse, 0
    for b, (cells, factor) in enumerate(subdomains):
        its = _pcg_sample(wx[b, 0], wy[b, 0], rhs[b, 0], x[b, 0], rhs.dtype.type(1 / dx**2), inverse.pivots,
                          inverse.dx, *local_solver(cells.numpy(), factor), tol, max_iter)
        iterations = max(iterations, its)
    return _mean_free(torch.from_numpy(x)), iterations


def solve_weighted_poisson(weights: Faces, f: Tensor, dx: float, tol: float, max_iter: int,
                           start: Tensor | None = None,
                           precondition: SchwarzPreconditioner | None = None) -> tuple[Tensor, int]:
    """Mean-free p [B, 1, H, W] with -div(weights grad p) = f - mean(f), by PCG with the
    SchwarzPreconditioner of these weights, stopping at |f - A p| <= tol |f - mean(f)| per
    sample; returns (p, iterations of the slowest sample). On the CPU the iteration runs compiled
    (``_pcg_sample``, a sample at a time; on the fish's joint solves ~0.6 ms an iteration against
    ~2 ms in torch calls), elsewhere as fishsim.linalg.pcg. weights: positive face weights (x, y)
    [B, 1, ., .]; start: initial guess (None: 0); precondition: a SchwarzPreconditioner of the
    same weights, shared by several solves (None: built for this one)."""
    if precondition is None:
        precondition = SchwarzPreconditioner(weights, dx)
    f = _mean_free(f)
    start = None if start is None else _mean_free(start.detach().to(f.dtype))
    if f.device.type == "cpu":
        return _solve_cpu(weights, f, dx, tol, max_iter, start, precondition)
    p, _, iterations = pcg(precondition.apply, precondition, f, lambda r: r.flatten(1).norm(dim=1), tol, max_iter, start)
    return _mean_free(p), iterations


class WeightedPoisson(torch.autograd.Function):
    """p = A(w)^+ f with A(w) p = -div(w grad p), differentiable in w (faces) and f (module
    docstring); forward and backward are PCG solves to ``tol`` and ``adjoint_tol`` (None: ``tol``),
    the forward started from ``start`` (None: from zero), the backward from zero. The forward
    uses ``precondition`` (a SchwarzPreconditioner of these weights shared by the solves of one
    step) or builds its own; the backward builds its own, so no factors are held from the forward
    until the backward."""

    @staticmethod
    def forward(ctx, wx: Tensor, wy: Tensor, f: Tensor, dx: float, tol: float, max_iter: int,
                start: Tensor | None = None, precondition: SchwarzPreconditioner | None = None,
                adjoint_tol: float | None = None) -> Tensor:
        p, _ = solve_weighted_poisson((wx, wy), f, dx, tol, max_iter, start, precondition)
        ctx.save_for_backward(wx, wy, p)
        ctx.settings = (dx, tol if adjoint_tol is None else adjoint_tol, max_iter)
        return p

    @staticmethod
    def backward(ctx, grad_p: Tensor):
        wx, wy, p = ctx.saved_tensors
        dx, tol, max_iter = ctx.settings
        lam, _ = solve_weighted_poisson((wx, wy), grad_p, dx, tol, max_iter)
        (gl_x, gl_y), (gp_x, gp_y) = gradient(lam, dx), gradient(p, dx)
        return -gl_x * gp_x, -gl_y * gp_y, _mean_free(lam), None, None, None, None, None, None


def recover_pressure(v_old: Faces, v_new: Faces, mask: Tensor, rho: Tensor | float, mu: Tensor | float,
                     h: float, grid: Grid, cfg: RecoveryConfig = RecoveryConfig(),
                     start: Tensor | None = None) -> Tensor:
    """The pressure [B, 1, H, W] (Pa, mean free) of the module docstring for the step
    v_old -> v_new (face velocities, m/s) with the soft mask ``mask`` [B, 1, H, W]; ``start``
    (e.g. the previous frame's pressure) is PCG's initial guess."""
    r0 = momentum_residual(v_old, v_new, torch.zeros_like(mask), rho, mu, h, grid)
    w = fluid_face_masks(mask)
    f = divergence(tuple(wi * ri for wi, ri in zip(w, r0)), grid.dx)
    wx, wy = (wi + cfg.eps for wi in w)
    return WeightedPoisson.apply(wx, wy, f, grid.dx, cfg.tol, cfg.max_iter, start)

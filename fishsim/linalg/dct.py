"""DCT-II and its inverse with torch.fft (any device, differentiable), and the Neumann Poisson
solve they diagonalise (``NeumannPoisson``; on the CPU a DCT along x and tridiagonal solves along
y).

The 5-point Laplacian on cell centres with mirror (homogeneous Neumann) walls,
``grid.laplacian_centres``, has the eigenvectors cos(pi k (n + 1/2) / N) along each axis, i.e. the
DCT-II basis, with eigenvalues -(4/dx^2) [sin^2(pi k / 2H) + sin^2(pi l / 2W)].  Solving is two
transforms and a division: exact to round-off, O(N log N).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import rocket_fft  # noqa: F401  (scipy.fft inside compiled code: ``inverse_sample``)
import scipy.fft as sfft
import torch
from numba import prange
from torch import Tensor

from fishsim.compiled import each_sample, jit


def _phase(N: int, sign: float, like: Tensor) -> Tensor:
    k = torch.arange(N, device=like.device, dtype=like.dtype)
    return torch.polar(torch.ones_like(k), sign * math.pi * k / (2 * N))


def dct(x: Tensor, dim: int = -1) -> Tensor:
    """Unnormalised DCT-II along ``dim``: X_k = sum_n x_n cos(pi k (2n + 1) / (2N)).

    Makhoul's N-point algorithm: reorder v = (x_0, x_2, ..., x_3, x_1), V = FFT(v),
    X_k = Re(exp(-i pi k / 2N) V_k).
    """
    x = x.movedim(dim, -1)
    N = x.shape[-1]
    v = torch.cat([x[..., ::2], x[..., 1::2].flip(-1)], -1)
    X = (torch.fft.fft(v) * _phase(N, -1.0, x)).real
    return X.movedim(-1, dim)


def idct(X: Tensor, dim: int = -1) -> Tensor:
    """Inverse of ``dct``: V_k = exp(i pi k / 2N) (X_k - i X_{N-k}) (X_N = 0), v = IFFT(V),
    then undo the even/odd reordering."""
    X = X.movedim(dim, -1)
    N = X.shape[-1]
    X_rev = torch.cat([torch.zeros_like(X[..., :1]), X[..., 1:].flip(-1)], -1)
    V = _phase(N, 1.0, X) * torch.complex(X, -X_rev)
    v = torch.fft.ifft(V).real
    half = (N + 1) // 2
    even, odd = v[..., :half], v[..., half:].flip(-1)
    if N % 2:
        odd = torch.cat([odd, torch.zeros_like(odd[..., :1])], -1)
    x = torch.stack([even, odd], -1).flatten(-2)[..., :N]
    return x.movedim(-1, dim)


def neumann_eigenvalues(H: int, W: int, dx: float, device=None, dtype=torch.float64) -> Tensor:
    """Eigenvalues [H, W] of ``grid.laplacian_centres`` on the DCT-II modes (k along y, l along x)."""
    k = torch.arange(H, device=device, dtype=dtype)
    l = torch.arange(W, device=device, dtype=dtype)
    sy = torch.sin(math.pi * k / (2 * H)) ** 2
    sx = torch.sin(math.pi * l / (2 * W)) ** 2
    return -(4 / dx**2) * (sy[:, None] + sx[None, :])


@dataclass(frozen=True)
class NeumannInverse:
    """The pseudo-inverse L^+ of ``grid.laplacian_centres`` on an H x W grid (build once with
    ``neumann_inverse``, pass to ``solve_neumann_poisson``).

    inv [H, W]: 1 / eigenvalue of every DCT-II mode, 0 for the constant one (the 2D transform
        solve, any device).
    pivots [H, W] (numpy, inv's dtype): the CPU solve's Thomas factors (``_tridiagonal_sample``),
        computed in float64."""

    inv: Tensor
    pivots: np.ndarray
    dx: float


@functools.lru_cache(maxsize=16)
def neumann_inverse(H: int, W: int, dx: float, device=None, dtype=torch.float64) -> NeumannInverse:
    """L^+ of ``grid.laplacian_centres`` (``NeumannInverse``) in ``dtype`` on ``device``; one per
    grid, device and dtype, built once (its tensors are shared: read them, never write)."""
    lam = neumann_eigenvalues(H, W, dx, device, dtype)
    inv = torch.where(lam < 0, 1 / torch.where(lam < 0, lam, -torch.ones_like(lam)), torch.zeros_like(lam))
    pivots = _thomas_pivots(H, W, dx).astype(torch.empty(0, dtype=dtype).numpy().dtype)
    return NeumannInverse(inv, pivots, dx)


def _thomas_pivots(H: int, W: int, dx: float) -> np.ndarray:
    """1 / pivot [H, W] of Thomas' elimination of A_l = T + lambda_l I for each x-mode l >= 1 (column
    0 unused): T the 1D Neumann Laplacian along y (diagonal -2/dx^2, -1/dx^2 in the end rows,
    off-diagonals 1/dx^2), lambda_l = -(4/dx^2) sin^2(pi l / 2W). A_l is strictly diagonally
    dominant for l >= 1, so the elimination is stable without pivoting."""
    off = 1 / dx**2
    lam = -(4 * off) * np.sin(np.pi * np.arange(W) / (2 * W)) ** 2
    diag = np.full((H, W), -2 * off) + lam
    diag[[0, -1]] += off
    inv_pivot = np.zeros((H, W))
    inv_pivot[0, 1:] = 1 / diag[0, 1:]
    for i in range(1, H):
        inv_pivot[i, 1:] = 1 / (diag[i, 1:] - off * off * inv_pivot[i - 1, 1:])
    return inv_pivot


@jit
def _tridiagonal_sample(f, inv_pivot, dx):
    """Solves, in place, A_l phi_l = f[:, l] for every x-mode l of one sample ([H, W], the x-DCT of
    the right-hand side): Thomas' sweeps over the rows, vectorised over l >= 1; l = 0 (A_0 = T,
    singular: the constant) by integrating twice, phi_0[0] = 0, mean-free right-hand side, then the
    mean removed (the minimum-norm solution, as the 2D transform's)."""
    H, W = f.shape
    off, dx2 = 1.0 / (dx * dx), dx * dx
    col = np.empty(H)
    mean = 0.0
    for i in range(H):
        mean += f[i, 0]
    mean /= H
    flux, phi, total = 0.0, 0.0, 0.0
    for i in range(H):                  # (phi[i+1] - phi[i]) / dx^2 = sum_{j <= i} (f_j - mean)
        col[i] = phi
        total += phi
        flux += dx2 * (f[i, 0] - mean)
        phi += flux
    off_f = f.dtype.type(off)          # the sweeps in f's dtype (a float64 factor would convert every entry)
    for k in range(1, W):
        f[0, k] *= inv_pivot[0, k]
    for i in range(1, H):
        for k in range(1, W):
            f[i, k] = (f[i, k] - off_f * f[i - 1, k]) * inv_pivot[i, k]
    for i in range(H - 2, -1, -1):
        for k in range(1, W):
            f[i, k] -= off_f * inv_pivot[i, k] * f[i + 1, k]
    for i in range(H):
        f[i, 0] = col[i] - total / H


@jit
def inverse_sample(f, inv_pivot, dx):
    """L^+ f of one sample [H, W]: scipy.fft's DCT-II along x (compiled through rocket-fft, bit for
    bit scipy's), ``_tridiagonal_sample``'s sweeps along y, the inverse DCT; a new array of f's
    dtype. Compiled, so that a compiled loop solves its Poisson equations without returning to
    Python (``fluid.kernels.SplitStep``); ``inverse_array`` runs it over a batch."""
    F = sfft.dct(f, 2, None, -1)
    _tridiagonal_sample(F, inv_pivot, dx)
    return sfft.idct(F, 2, None, -1)


@jit
def _inverse_serial(x, inv_pivot, dx, out):
    for n in range(x.shape[0]):
        out[n] = inverse_sample(x[n], inv_pivot, dx)


@jit(parallel=True)
def _inverse_parallel(x, inv_pivot, dx, out):
    for n in prange(x.shape[0]):
        out[n] = inverse_sample(x[n], inv_pivot, dx)


def solve_neumann_poisson(f: Tensor, dx: float, inverse: NeumannInverse | None = None) -> Tensor:
    """The mean-free phi [B, C, H, W] with lap phi = f - mean(f) (5-point, Neumann walls).

    ``inverse`` (from ``neumann_inverse``, in f's dtype) may be passed to reuse it.
    """
    if inverse is None:
        inverse = neumann_inverse(f.shape[-2], f.shape[-1], dx, f.device, f.dtype)
    return NeumannPoisson.apply(f, inverse)


class NeumannPoisson(torch.autograd.Function):
    """phi = L^+ f (``apply_inverse``). L^+ is symmetric, so the backward is the same solve."""

    @staticmethod
    def forward(ctx, f: Tensor, inverse: NeumannInverse) -> Tensor:
        ctx.inverse = inverse
        return apply_inverse(f, inverse)

    @staticmethod
    def backward(ctx, grad: Tensor):
        return apply_inverse(grad, ctx.inverse), None


def apply_inverse(f: Tensor, inverse: NeumannInverse) -> Tensor:
    """L^+ f (no autograd), f [..., H, W]. On the CPU ``inverse_array``: the DCT-II along x, a
    tridiagonal solve along y per x-mode, the inverse DCT, compiled (0.1-0.16 ms per 100 x 300 in
    float32; the same from Python with scipy's transforms took 0.15-0.3 ms, scipy's 2D transforms
    with a division 0.7 ms and the FFT-based ``dct`` / ``idct`` above 0.85 ms: they serve other
    devices, as 2D transforms)."""
    if f.device.type == "cpu":
        y = inverse_array(f.detach().reshape(-1, *f.shape[-2:]).numpy(), inverse)
        return torch.from_numpy(y).reshape(f.shape)
    inv = inverse.inv
    return idct(idct(dct(dct(f, -1), -2) * inv, -2), -1)


def inverse_array(x: np.ndarray, inverse: NeumannInverse) -> np.ndarray:
    """``apply_inverse`` on numpy arrays (CPU): L^+ x for x [N, H, W], a new C-contiguous array of
    x's dtype (x is not changed): ``inverse_sample`` for each sample, over numba's threads for a
    batch (``compiled.each_sample``: one sample, or a thread of ``in_sample_chunks``, serially)."""
    x = np.ascontiguousarray(x)
    out = np.empty_like(x)
    each_sample(_inverse_serial, _inverse_parallel, x, inverse.pivots, inverse.dx, out)
    return out

"""DCT-II and its inverse with torch.fft (any device, differentiable), and the Neumann Poisson
solve they diagonalise (on the CPU through scipy.fft's native DCTs, ``NeumannPoisson``).

The 5-point Laplacian on cell centres with mirror (homogeneous Neumann) walls,
``grid.laplacian_centres``, has the eigenvectors cos(pi k (n + 1/2) / N) along each axis, i.e. the
DCT-II basis, with eigenvalues -(4/dx^2) [sin^2(pi k / 2H) + sin^2(pi l / 2W)].  Solving is two
transforms and a division: exact to round-off, O(N log N).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft as sfft
import torch
from torch import Tensor


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


def neumann_inverse(H: int, W: int, dx: float, device=None, dtype=torch.float64) -> Tensor:
    """1 / eigenvalue [H, W] of every DCT-II mode, 0 for the constant one: the pseudo-inverse of
    ``grid.laplacian_centres`` in that basis (compute once, pass to ``solve_neumann_poisson``)."""
    lam = neumann_eigenvalues(H, W, dx, device, dtype)
    return torch.where(lam < 0, 1 / torch.where(lam < 0, lam, -torch.ones_like(lam)), torch.zeros_like(lam))


def solve_neumann_poisson(f: Tensor, dx: float, inverse: Tensor | None = None) -> Tensor:
    """The mean-free phi [B, C, H, W] with lap phi = f - mean(f) (5-point, Neumann walls).

    ``inverse`` (from ``neumann_inverse``, in f's dtype) may be passed to reuse it.
    """
    if inverse is None:
        inverse = neumann_inverse(f.shape[-2], f.shape[-1], dx, f.device, f.dtype)
    return NeumannPoisson.apply(f, inverse)


class NeumannPoisson(torch.autograd.Function):
    """phi = L^+ f, diagonal in the DCT-II basis (``inv`` = 1 / eigenvalue, 0 for the mean).

    L^+ is symmetric, so the backward is the same solve. On the CPU the transforms are
    scipy.fft's native DCT-II / DCT-III (measured 0.20 ms per 100 x 300 solve against 0.85 ms for
    the FFT-based ``dct`` / ``idct`` above, which serve other devices)."""

    @staticmethod
    def forward(ctx, f: Tensor, inv: Tensor) -> Tensor:
        ctx.save_for_backward(inv)
        return _apply_inverse(f, inv)

    @staticmethod
    def backward(ctx, grad: Tensor):
        (inv,) = ctx.saved_tensors
        return _apply_inverse(grad, inv), None


def _apply_inverse(f: Tensor, inv: Tensor) -> Tensor:
    if f.device.type == "cpu":
        x = f.detach().numpy()
        workers = torch.get_num_threads()
        y = sfft.idctn(sfft.dctn(x, type=2, axes=(-2, -1), workers=workers) * inv.numpy(), type=2, axes=(-2, -1),
                       workers=workers)
        return torch.from_numpy(np.ascontiguousarray(y, dtype=x.dtype))
    return idct(idct(dct(dct(f, -1), -2) * inv, -2), -1)

"""Batched preconditioned conjugate gradients (torch, any device): the solid's iterative adjoint
(solid/solve.py, ``backward_method=pcg|auto``) and the pressure recovery's Poisson solves
(fluid/pressure.py) both run this one."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor


def pcg(apply_A: Callable[[Tensor], Tensor], precondition: Callable[[Tensor], Tensor], b: Tensor,
        norm: Callable[[Tensor], Tensor], rtol: float, max_iter: int,
        x0: Tensor | None = None) -> tuple[Tensor, Tensor, int]:
    """x [B, ...] with norm(b - A x) <= rtol norm(b) for each sample b (the leading dimension), A
    symmetric positive (semi-)definite per sample on the range b lies in.

    apply_A, precondition: [B, ...] -> [B, ...] (the preconditioner symmetric positive definite);
    norm: [B, ...] -> [B], the stopping norm; x0: the start (None: 0; a sample with b = 0 starts,
    and stays, at its solution 0 whatever x0 says). Each sample stops on its
    own, its x then frozen: converged at the tolerance, or failed when a search direction has
    d^T A d <= 0 (A not positive definite for it). Returns (x, converged [B] bool, iterations of
    the slowest sample)."""
    dot = lambda u, v: (u * v).flatten(1).sum(1)
    per_sample = lambda s: s.view(-1, *[1] * (b.ndim - 1))
    target = rtol * norm(b)
    x = torch.zeros_like(b) if x0 is None else x0 * per_sample(target > 0).to(b.dtype)
    r = b.clone() if x0 is None else b - apply_A(x)
    done = norm(r) <= target
    failed = torch.zeros_like(done)
    z = precondition(r)
    d, rz = z, dot(r, z)
    iterations = 0
    while iterations < max_iter:
        active = ~(done | failed)
        if not bool(active.any()):
            break
        iterations += 1
        Ad = apply_A(d)
        dAd = dot(d, Ad)
        failed |= active & (dAd <= 0)
        active &= ~failed
        step = torch.where(active, rz / torch.where(active, dAd, torch.ones_like(dAd)), torch.zeros_like(dAd))
        x, r = x + per_sample(step) * d, r - per_sample(step) * Ad
        done |= active & (norm(r) <= target)
        z = precondition(r)
        rz_new = dot(r, z)
        beta = torch.where(active, rz_new / torch.where(rz != 0, rz, torch.ones_like(rz)), torch.zeros_like(rz))
        d, rz = z + per_sample(beta) * d, rz_new
    return x, done, iterations

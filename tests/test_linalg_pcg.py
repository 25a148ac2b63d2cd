"""The shared batched PCG (fishsim.linalg.pcg) solves SPD systems per sample to its tolerance,
flags a sample whose matrix is indefinite without disturbing the others, and starts from x0."""

import torch

from fishsim.linalg.pcg import pcg


def _systems(B: int = 3, n: int = 40, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    Q = torch.linalg.qr(torch.randn(B, n, n, generator=g, dtype=torch.float64)).Q
    eig = torch.logspace(0, 3, n, dtype=torch.float64).expand(B, n).clone()
    eig[2, :5] *= -1                                            # sample 2 indefinite
    A = Q @ torch.diag_embed(eig) @ Q.transpose(1, 2)
    b = torch.randn(B, n, generator=g, dtype=torch.float64)
    jacobi = torch.diagonal(A, dim1=1, dim2=2).abs()
    return A, b, lambda x: (A @ x.unsqueeze(-1)).squeeze(-1), lambda r: r / jacobi


def test_pcg_solves_each_sample_and_flags_an_indefinite_one():
    A, b, apply_A, precondition = _systems()
    norm = lambda r: r.norm(dim=1)
    x, converged, iterations = pcg(apply_A, precondition, b, norm, 1e-10, 500)
    assert converged.tolist() == [True, True, False] and iterations < 500
    exact = torch.linalg.solve(A[:2], b[:2].unsqueeze(-1)).squeeze(-1)
    assert float((x[:2] - exact).norm(dim=1).max() / exact.norm(dim=1).min()) < 1e-7
    assert bool((norm(b[:2] - apply_A(x)[:2]) <= 1e-10 * norm(b[:2])).all())


def test_pcg_from_the_solution_takes_no_iteration():
    A, b, _, _ = _systems()
    A, b = A[:2], b[:2]                                         # the SPD samples
    exact = torch.linalg.solve(A, b.unsqueeze(-1)).squeeze(-1)
    x, converged, iterations = pcg(lambda x: (A @ x.unsqueeze(-1)).squeeze(-1), lambda r: r, b,
                                   lambda r: r.norm(dim=1), 1e-8, 500, x0=exact)
    assert iterations == 0 and bool(converged.all()) and torch.equal(x, exact)


def test_a_sample_with_zero_right_hand_side_stays_at_zero_whatever_its_start():
    A, b, _, _ = _systems()
    A, b = A[:2], b[:2].clone()
    b[1] = 0.0
    x, converged, _ = pcg(lambda x: (A @ x.unsqueeze(-1)).squeeze(-1), lambda r: r, b,
                          lambda r: r.norm(dim=1), 1e-8, 500, x0=torch.ones_like(b))
    assert bool(converged.all()) and float(x[1].abs().max()) == 0.0

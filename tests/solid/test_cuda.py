"""CUDA parity: the solid accepts CUDA tensors (it solves on the CPU) and returns them there."""

import pytest
import torch

from fishsim.solid import PDOptions, SolidModel, pd_step, rest_state

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


def test_cuda_matches_cpu_forward_and_backward(tiny_mesh):
    model = SolidModel(tiny_mesh, options=PDOptions(atol=1e-9, backward_rtol=1e-12))
    results = {}
    for device in ("cpu", "cuda"):
        q, qdot = rest_state(model, 2, device=device)
        u = torch.full((2, model.n_muscles), 0.1, device=device, requires_grad=True)
        E = torch.tensor([6e5, 5e5], dtype=torch.float64, device=device, requires_grad=True)
        for _ in range(3):
            q, qdot = pd_step(model, q, qdot, u, None, E)
        assert q.device.type == device
        (q[..., 1].sum() + qdot.pow(2).sum()).backward()
        results[device] = [t.detach().cpu() for t in (q, qdot, u.grad, E.grad)]
    for a, b in zip(results["cpu"], results["cuda"]):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-8)

"""The optimisers, all in the normalised space z in [0, 1]^P (fishsim.optimize.problem), all
maximising J through the same ask / tell interface so the command treats them alike:

- a gradient method: any ``torch.optim`` optimiser by name (adam, sgd, rmsprop, ...), one
  candidate per iteration, its gradient dJ/dz by autograd through the checkpointed rollout; after
  each step z is clamped to [0, 1] (projected gradient ascent).
- cma: CMA-ES (pycma) as the gradient-free baseline; each generation's population is one batched
  rollout (B = population size); failed members get a loss worse than every finite one.

``state()`` / ``load()`` carry everything needed to continue exactly (optimiser moments, the CMA-ES
distribution and the random generator it draws from).
"""

from __future__ import annotations

import pickle

import numpy as np
import torch
from torch import Tensor

from fishsim.errors import ConfigError

GRADIENT_FREE = ("cma",)


#: torch.optim optimisers that cannot take one dense gradient per step: LBFGS needs a closure that
#: re-evaluates J (an episode per line-search point), SparseAdam sparse gradients.
UNSUPPORTED = ("lbfgs", "sparseadam")


def torch_optimizer(name: str) -> type:
    """The torch.optim class called ``name`` (case-insensitive), one that steps on a dense gradient."""
    table = {k.lower(): v for k, v in vars(torch.optim).items()
             if isinstance(v, type) and issubclass(v, torch.optim.Optimizer) and v is not torch.optim.Optimizer
             and k.lower() not in UNSUPPORTED}
    if name.lower() not in table:
        raise ConfigError(f"unknown optimiser '{name}' (choose cma or a torch.optim optimiser: "
                          f"{', '.join(sorted(table))})")
    return table[name.lower()]


class GradientMethod:
    """Projected gradient ascent on J with a torch.optim optimiser (one candidate)."""

    uses_gradient = True

    def __init__(self, name: str, z0: list[float], lr: float, options: dict | None = None):
        self.z = torch.tensor([z0], dtype=torch.float64, requires_grad=True)
        self.optimizer = torch_optimizer(name)([self.z], lr=lr, **(options or {}))

    def ask(self) -> Tensor:
        return self.z.detach().clone()

    def tell(self, z: Tensor, J: Tensor, grad_z: Tensor) -> None:
        self.optimizer.zero_grad()
        self.z.grad = -grad_z.to(self.z)                 # minimise -J
        self.optimizer.step()
        with torch.no_grad():
            self.z.clamp_(0.0, 1.0)

    def mean(self) -> Tensor:
        return self.z.detach()[0].clone()

    def state(self) -> dict:
        return {"z": self.z.detach().clone(), "optimizer": self.optimizer.state_dict()}

    def load(self, state: dict) -> None:
        with torch.no_grad():
            self.z.copy_(state["z"])
        self.optimizer.load_state_dict(state["optimizer"])


class CMAES:
    """CMA-ES (pycma) on z in [0, 1]^P with initial step ``sigma`` (in z units)."""

    uses_gradient = False

    def __init__(self, z0: list[float], sigma: float, popsize: int | None, seed: int):
        import cma

        options = {"bounds": [0.0, 1.0], "seed": seed + 1, "verbose": -9}  # pycma: seed 0 means "random"
        if popsize is not None:
            options["popsize"] = popsize
        if len(z0) == 1:      # pycma's std cap (a third of the bounds) fails in 1-D; the bounds still hold
            options["maxstd"] = float("inf")
        self.es = cma.CMAEvolutionStrategy(list(z0), sigma, options)
        self._asked: list | None = None

    @property
    def popsize(self) -> int:
        return self.es.popsize

    def ask(self) -> Tensor:
        self._asked = self.es.ask()
        return torch.tensor(np.array(self._asked), dtype=torch.float64)

    def tell(self, z: Tensor, J: Tensor, grad_z: Tensor | None = None) -> None:
        loss = -J.double().numpy()
        bad = ~np.isfinite(loss)
        if bad.any():
            worst = loss[~bad].max() if (~bad).any() else 0.0
            loss[bad] = worst + abs(worst) + 1.0
        self.es.tell(self._asked, loss.tolist())

    def mean(self) -> Tensor:
        return torch.tensor(self.es.mean, dtype=torch.float64)

    def state(self) -> dict:
        return {"es": pickle.dumps(self.es), "numpy_rng": np.random.get_state()}

    def load(self, state: dict) -> None:
        self.es = pickle.loads(state["es"])
        np.random.set_state(state["numpy_rng"])


def make_method(name: str, z0: list[float], lr: float, sigma: float, popsize: int | None, seed: int,
                options: dict | None = None):
    """The optimiser called ``name`` (cma or a torch.optim name) started at z0."""
    if name == "cma":
        np.random.seed(seed)
        return CMAES(z0, sigma, popsize, seed)
    return GradientMethod(name, z0, lr, options)

"""Differentiable projective-dynamics solid (docs/physics.md section 3; DiffPD, Du et al. 2021).

    model = SolidModel(mesh, SolidMaterial(), h=0.01)
    q, qdot = rest_state(model, batch=B)
    q, qdot = pd_step(model, q, qdot, contraction, f_ext, E)     # [B, N, 2] each

`controller.muscle_contraction` turns the paper's travelling-wave controller into `contraction`.
"""

from fishsim.solid.fem import FemQuantities, fem_quantities
from fishsim.solid.model import PDOptions, SolidMaterial, SolidModel
from fishsim.solid.solve import ForwardInfo
from fishsim.solid.step import pd_step, predicted_start, rest_state

__all__ = [
           "FemQuantities",
           "ForwardInfo",
           "PDOptions",
           "SolidMaterial",
           "SolidModel",
           "fem_quantities",
           "pd_step",
           "predicted_start",
           "rest_state",
]

"""The swimming stroke converges under mesh refinement with the muscle layer and does not with the
paper's station muscles (issue of the mesh-dependent muscles). Reduced size of the README's study
(benchmarks/study_solid_convergence.py): 3, 2 and 1.4 mm edges, 70 frames at 5 Hz in vacuum, tail
peak-to-peak over the last 35 frames, the muscle layer on the default graded mesh (6 elements
across the rear body) and on the paper's uniform mesh, the stations on the uniform mesh."""

import numpy as np
import pytest
import torch

from fishsim.mesh import make_fish_mesh
from fishsim.solid import SolidModel, pd_step, predicted_start, rest_state
from fishsim.solid.controller import WaveController, calibrated_amplitude
from fishsim.solid.muscles import layer_muscles

FRAMES = 70


def _tail_stroke(edge_length: float, muscles: str, across: float) -> float:
    mesh = make_fish_mesh(edge_length=edge_length, elements_across=across)
    model = SolidModel(mesh, muscles=layer_muscles(mesh, 0.3) if muscles == "layer" else None)
    ctrl = WaveController.default(mesh.length, C=calibrated_amplitude(muscles))
    surface = mesh.points[mesh.surface]
    tail = int(mesh.surface[np.argmin(np.hypot(surface[:, 0], surface[:, 1]))])
    q, qdot = rest_state(model)
    qdot_prev, ys = qdot, []
    with torch.no_grad():
        for k in range(FRAMES):
            start = predicted_start(q, qdot, qdot_prev, model.h)
            qdot_prev, (q, qdot) = qdot, pd_step(model, q, qdot, ctrl.contraction(model, (k + 1) * model.h),
                                                 start=start)
            ys.append(float(q[0, tail, 1]))
    ys = np.array(ys[FRAMES // 2:])
    return float(ys.max() - ys.min())


@pytest.fixture(scope="module")
def strokes():
    runs = {"graded": ("layer", 6), "uniform": ("layer", 2), "paper": ("paper", 2)}
    return {k: [_tail_stroke(e, m, n) for e in (3e-3, 2e-3, 1.4e-3)] for k, (m, n) in runs.items()}


def test_layer_stroke_converges_on_the_graded_mesh(strokes):
    coarse, default, fine = strokes["graded"]
    assert max(abs(coarse / fine - 1), abs(default / fine - 1)) < 0.015   # within 1.5 % from 3 mm on
    assert 0.14 * 0.2 < default < 0.16 * 0.2                              # the calibrated 0.15 L stroke


def test_layer_stroke_converges_slowly_on_the_uniform_mesh(strokes):
    coarse, default, fine = strokes["uniform"]
    assert coarse < default < fine                                    # converging from below (stiff triangles)
    assert fine - default < 0.6 * (default - coarse)                  # the changes shrink, slowly
    assert default < strokes["graded"][1] < fine + 0.6 * (fine - default)  # towards the graded mesh's


def test_station_muscles_do_not_converge(strokes):
    coarse, default, fine = strokes["paper"]
    assert coarse > 1.4 * default and default > 1.4 * fine            # the stroke shrinks with the elements

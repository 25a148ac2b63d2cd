"""fishsim validate suite=convergence: the observed order and Richardson estimate against an
exact sequence, and the suite on a small tank."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from fishsim.cli import app
from fishsim.commands.validate import run
from fishsim.config import load_config
from fishsim.swim_study import observed_order
from fishsim.swim_study_config import Knob

runner = CliRunner()
SMALL = ["fluid=numerical", "tank.H=32", "tank.W=96", "fish.length=0.06", "fish.edge_length=4e-3",
         "origin=[0.05,0.04]"]


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_order_and_richardson_of_an_exact_sequence(p):
    values = [2.0, 4.0, 8.0]
    d = np.array([[10 + 3 * v ** -p, -5 - 7 * v ** -p] for v in values])      # d(v) = d_inf + c v^-p
    o = observed_order(values, d)
    np.testing.assert_allclose(o["order"], [p, p], rtol=1e-12)
    np.testing.assert_allclose(o["richardson"], [10, -5], rtol=1e-12)
    down = observed_order([8e-6, 4e-6, 2e-6], np.array([[1 + v * 1e5] for v in (8e-6, 4e-6, 2e-6)]))
    assert down["order"][0] == pytest.approx(1.0) and down["richardson"][0] == pytest.approx(1.0)
    oscillating = observed_order(values, np.array([[1.0], [2.0], [1.5]]))
    assert np.isnan(oscillating["order"][0])
    slow = observed_order(values, np.array([[0.3600], [0.3528], [0.3460]]))      # the grid study's 3 Hz fish
    assert 0 < slow["order"][0] < 0.1 and np.isnan(slow["richardson"][0])


def test_validate_convergence_small(tmp_path):
    cfg = load_config("validate", ["suite=convergence", "convergence.frequencies=[6]", "convergence.frames=6",
                                   f"out_dir={tmp_path}"])
    cfg.convergence.overrides = SMALL
    cfg.convergence.knobs = {"substeps": Knob("fluid.substeps", [2, 4, 8], 4, limit=["fluid.substeps=16"]),
                             "penalization": Knob("fluid.penalization_iterations", [1, 3], None, frames=4,
                                                  base=["fluid.implicit=false"], limit=["fluid.implicit=true"]),
                             "grid": Knob("fluid.refinement", [1, 2], 1, frames=4),
                             "frame_step": Knob("h", [0.01, 0.005], 0.01, finer="down", frames=4)}
    run(cfg)
    m = json.loads((tmp_path / "metrics.json").read_text())["knobs"]
    assert np.asarray(m["substeps"]["displacement_mm"]).shape == (3, 1)
    assert len(m["substeps"]["default_error_vs_finest"]) == 1 and m["grid"]["frames"] == 4
    assert m["frame_step"]["episode_frames"] == [4, 8] and m["grid"]["episode_frames"] == [4, 4]   # the same 0.04 s
    limit = m["substeps"]["limit"]
    error = (m["substeps"]["displacement_mm"][1][0] - limit["displacement_mm"][0]) / abs(limit["displacement_mm"][0])
    assert m["substeps"]["default_error_vs_limit"][0] == pytest.approx(error) and "limit" not in m["grid"]
    passes = m["penalization"]            # the split passes (base) against the default joint stage (limit)
    assert passes["base"] == ["fluid.implicit=false"] and passes["limit"]["overrides"] == ["fluid.implicit=true"]
    assert passes["displacement_mm"][1] != passes["limit"]["displacement_mm"]
    assert "default_error_vs_finest" not in passes and "default_error_vs_limit" not in passes
    # one run per resolved config: the default at 4 frames serves three knobs (wall times shared)
    assert m["grid"]["wall_s"][0] == m["frame_step"]["wall_s"][0] == passes["limit"]["wall_s"]
    assert (tmp_path / "convergence.png").exists()


def test_knob_values_must_go_coarse_to_fine(tmp_path):
    result = runner.invoke(app, ["validate", "suite=convergence", "convergence.knobs.substeps.values=[16,8,4]",
                                 f"out_dir={tmp_path}"])
    assert result.exit_code == 2 and "coarse to fine" in result.output


def test_a_knob_deleted_on_the_command_line_stays_deleted():
    """``~convergence.knobs.<name>`` runs the suite without that knob: the schema's default knobs
    must not come back over the composed config (they did: the deletion was silently ignored)."""
    knobs = load_config("validate", ["suite=convergence", "~convergence.knobs.substeps",
                                     "~convergence.knobs.frame_step"]).convergence.knobs
    assert sorted(knobs) == ["coupling_passes", "grid", "grid_short", "kernel", "penalization"]
    assert isinstance(knobs["grid"], Knob) and knobs["grid"].values == [1, 2]
    assert "substeps" in load_config("validate", ["suite=convergence"]).convergence.knobs

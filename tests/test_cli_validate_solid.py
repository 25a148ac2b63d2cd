"""`fishsim validate suite=solid` end to end through the CLI at a reduced size (coarse meshes, a
short episode, a coarse beam), and its config errors (exit code 2, one line)."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from fishsim.cli import app

runner = CliRunner()

SMALL = ["suite=solid", "solid.edges=[5e-3,4e-3]", "solid.frames=12", "solid.beam_across=[1,2]"]


def test_validate_solid_writes_metrics_table_and_plot(tmp_path):
    result = runner.invoke(app, ["validate", *SMALL, f"out_dir={tmp_path}"])
    assert result.exit_code == 0, result.output
    data = json.loads((tmp_path / "metrics.json").read_text())
    assert [(r["muscles"], r["edge_mm"]) for r in data["stroke"]] == [
        ("layer", 5.0), ("layer", 4.0), ("paper", 5.0), ("paper", 4.0)]
    assert all(r["tail_p2p_mm"] > 0 and np.isfinite(r["head_dx_mm"]) for r in data["stroke"])
    finest = [r for r in data["stroke"] if r["edge_mm"] == 4.0]
    assert all(r["tail_dev"] == 0 for r in finest)
    assert [r["across"] for r in data["beam"]] == [1, 2]
    assert abs(data["beam"][1]["static_err"]) < abs(data["beam"][0]["static_err"])   # refinement helps
    assert set(data["summary"]) == {"layer", "paper", "beam"}
    assert (tmp_path / "solid_convergence.png").stat().st_size > 10_000
    assert "solid mesh convergence" in result.output and "Euler-Bernoulli" in result.output


@pytest.mark.parametrize("override, words", [
    ("solid.edges=[2e-3]", "at least 2"),
    ("solid.edges=[2e-3,0.05]", "(0, 0.02)"),
    ("solid.muscles=[stations]", "layer and/or paper"),
    ("solid.fluid=water", "solid.fluid"),
    ("solid.frames=2", "solid.frames"),
    ("solid.beam_across=[0]", "solid.beam_across"),
])
def test_validate_solid_config_errors_are_one_line(tmp_path, override, words):
    result = runner.invoke(app, ["validate", "suite=solid", override, f"out_dir={tmp_path}"])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and "Traceback" not in result.output, result.output
    assert words in lines[0]

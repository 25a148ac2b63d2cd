"""`fishsim mesh` end to end through the CLI, and its bad-input paths (exit code 2, one line)."""

import numpy as np
from typer.testing import CliRunner

from fishsim.cli import app
from fishsim.io.mesh_io import read_mesh

runner = CliRunner()


def test_mesh_command_writes_mesh_and_preview(tmp_path):
    result = runner.invoke(app, ["mesh", "fish.edge_length=5e-3", f"out_dir={tmp_path}", "output=small.msh"])
    assert result.exit_code == 0, result.output
    mesh = read_mesh(tmp_path / "small.msh")
    assert (tmp_path / "small.png").stat().st_size > 10_000
    assert mesh.n_elements > 100 and (mesh.actuator == 1).any() and (mesh.actuator == 2).any()
    assert np.isclose(mesh.points[:, 0].max() - mesh.points[:, 0].min(), 0.2)
    assert f"{mesh.n_nodes}" in result.output


def test_mesh_command_shows_and_writes_the_muscle_layer(tmp_path):
    """With the default fish.muscles=layer the file carries the layer's area fractions and the
    table counts the layer's elements; with fish.muscles=paper only the stations are written."""
    import meshio

    from fishsim.solid.muscles import layer_muscles

    result = runner.invoke(app, ["mesh", "fish.edge_length=5e-3", f"out_dir={tmp_path}", "output=layer.vtu"])
    assert result.exit_code == 0, result.output
    m = meshio.read(tmp_path / "layer.vtu")
    top, bottom = m.cell_data["muscle_top"][0], m.cell_data["muscle_bottom"][0]
    layout = layer_muscles(read_mesh(tmp_path / "layer.vtu"), 0.3)
    assert np.allclose((top + bottom)[layout.elements], layout.fraction)
    assert "muscle layer (top)" in result.output and "actuated (top)" not in result.output
    result = runner.invoke(app, ["mesh", "fish.edge_length=5e-3", "fish.muscles=paper", f"out_dir={tmp_path}",
                                 "output=paper.vtu", "preview=false"])
    assert result.exit_code == 0, result.output
    assert "muscle_top" not in meshio.read(tmp_path / "paper.vtu").cell_data
    assert "actuated (top)" in result.output


def _one_error_line(result) -> str:
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2, result.output
    assert len(lines) == 1 and "Traceback" not in result.output
    return lines[0]


def test_mesh_command_bad_file(tmp_path):
    junk = tmp_path / "junk.vtu"
    junk.write_text("this is not a mesh")
    line = _one_error_line(runner.invoke(app, ["mesh", f"fish.mesh_file={junk}", f"out_dir={tmp_path}"]))
    assert "junk.vtu" in line and "fishsim mesh" in line


def test_mesh_command_impossible_profile(tmp_path):
    # a polynomial half-width that is negative along the body cannot be meshed
    line = _one_error_line(runner.invoke(
        app, ["mesh", "fish.profile=polynomial", "fish.poly_coeffs=[0.01,-0.1]", f"out_dir={tmp_path}"]))
    assert "width" in line


def test_mesh_formats_that_lose_the_fish_are_refused(tmp_path):
    for name in ("fish.stl", "fish.obj", "fish.ply", "fish.off"):
        line = _one_error_line(runner.invoke(app, ["mesh", f"output={name}", "preview=false", f"out_dir={tmp_path}"]))
        assert "keep only the triangles" in line and ".vtu" in line
        assert not (tmp_path / name).exists()


def test_infinite_amplitude_is_one_line(tmp_path):
    result = runner.invoke(app, ["simulate", "controller.amplitude=inf", f"out_dir={tmp_path}"])
    assert result.exit_code == 2 and "finite" in result.output and "nan" not in result.output

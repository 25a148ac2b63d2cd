"""Fish mesh files (fishsim.io.mesh_io) and the preview picture (fishsim.render.mesh_preview)."""

import meshio
import numpy as np
import pytest

from fishsim.errors import InputFileError
from fishsim.io.mesh_io import read_mesh, to_meshio, write_mesh
from fishsim.mesh import ACTUATOR_TOP, FishMesh, make_fish_mesh
from fishsim.render.mesh_preview import FACE_COLORS, plot_mesh


@pytest.fixture(scope="module")
def mesh() -> FishMesh:
    return make_fish_mesh(edge_length=4e-3)


def _assert_same(a: FishMesh, b: FishMesh) -> None:
    for name in ("points", "triangles", "surface", "actuator"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert np.array_equal(x, y), name
    assert a.length == b.length


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".xdmf"])
def test_round_trip_is_exact(mesh, tmp_path, monkeypatch, suffix):
    monkeypatch.chdir(tmp_path)  # XDMF writes a sibling .h5: keep everything in tmp_path
    path = write_mesh(mesh, tmp_path / f"fish{suffix}")
    _assert_same(mesh, read_mesh(path))


def test_default_format_is_vtu(mesh, tmp_path):
    path = write_mesh(mesh, tmp_path / "out" / "fish")
    assert path.name == "fish.vtu" and path.is_file()
    _assert_same(mesh, read_mesh(path))


def _one_line_error(path, match):
    with pytest.raises(InputFileError, match=match) as info:
        read_mesh(path)
    assert "\n" not in str(info.value)
    return str(info.value)


def test_missing_file(tmp_path):
    msg = _one_line_error(tmp_path / "nope.vtu", "not found")
    assert "fishsim mesh" in msg


@pytest.mark.parametrize("name", ["notes.vtu", "notes.txt", "notes.msh"])
def test_text_file_is_not_a_mesh(tmp_path, name):
    path = tmp_path / name
    path.write_text("this is not a mesh\n")
    msg = _one_line_error(path, r"not a (readable \w+ )?mesh file")
    assert "fishsim mesh" in msg


def test_mesh_without_triangles(tmp_path):
    path = tmp_path / "lines.vtu"
    meshio.write(path, meshio.Mesh(np.zeros((2, 3)), [("line", np.array([[0, 1]]))]))
    _one_line_error(path, "0 triangle blocks")


def test_mesh_without_fishsim_data(mesh, tmp_path):
    path = tmp_path / "plain.vtu"
    points = np.column_stack([mesh.points, np.zeros(mesh.n_nodes)])
    meshio.write(path, meshio.Mesh(points, [("triangle", mesh.triangles)]))
    msg = _one_line_error(path, "without the fishsim data")
    assert "fishsim mesh" in msg


def test_file_with_inverted_element(mesh, tmp_path):
    m = to_meshio(mesh)
    m.cells[0].data[3] = m.cells[0].data[3, [0, 2, 1]]
    path = tmp_path / "inverted.vtu"
    meshio.write(path, m)
    _one_line_error(path, "element 3 is inverted")


def test_preview_png(mesh, tmp_path):
    path = plot_mesh(mesh, tmp_path / "mesh.png", title="test fish")
    assert path.is_file() and path.stat().st_size > 10_000
    from matplotlib.image import imread

    rgb = imread(path)[..., :3]
    assert rgb.std() > 0.05  # not blank
    red = np.array([int(FACE_COLORS[ACTUATOR_TOP][k:k + 2], 16) / 255 for k in (1, 3, 5)])
    assert np.sum(np.all(np.abs(rgb - red) < 0.02, axis=-1)) > 50  # top muscles drawn in red


def test_preview_of_the_muscle_layer(mesh, tmp_path):
    from matplotlib.image import imread

    from fishsim.render.mesh_preview import LAYER_COLORS

    rgb = imread(plot_mesh(mesh, tmp_path / "layer.png", layer=(0.3, (0.05, 0.95))))[..., :3]
    colour = lambda c: np.array([int(c[k:k + 2], 16) / 255 for k in (1, 3, 5)])
    for c in LAYER_COLORS:                                           # full-fraction top and bottom elements
        assert np.sum(np.all(np.abs(rgb - colour(c)) < 0.02, axis=-1)) > 50
    assert np.sum(np.all(np.abs(rgb - colour(FACE_COLORS[2])) < 0.02, axis=-1)) < 10    # no station colours


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".xdmf"])
def test_extra_cell_data_is_written_and_ignored_on_read(mesh, tmp_path, monkeypatch, suffix):
    monkeypatch.chdir(tmp_path)
    fraction = np.linspace(0, 1, mesh.n_elements)
    path = write_mesh(mesh, tmp_path / f"fish{suffix}", cell_data={"muscle_top": fraction})
    _assert_same(mesh, read_mesh(path))
    assert np.allclose(np.ravel(meshio.read(path).cell_data["muscle_top"][0]), fraction)


def test_unknown_output_extension(mesh, tmp_path):
    from fishsim.errors import ConfigError

    with pytest.raises(ConfigError, match="unknown extension"):
        write_mesh(mesh, tmp_path / "fish.xyz")

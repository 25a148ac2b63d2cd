"""``fishsim render`` end to end: PNG frames, video, comparison, folders, bad and incomplete files."""

import subprocess
import sys
import textwrap

import h5py
import imageio.v2 as imageio
import numpy as np
import pytest

from fishsim.errors import ConfigError, InputFileError
from fishsim.render.config import RenderConfig
from fishsim.render.run import run
from fishsim.render.synthetic import write_synthetic_trajectory


def _cfg(path, out, **kw):
    kw = {"width": 320, "progress": False, "stride": 1, **kw}       # every frame unless a test says otherwise
    return RenderConfig(path=str(path), out_dir=str(out), **kw)


def test_frames_and_mp4(traj, tmp_path):
    (summary,) = run(_cfg(traj, tmp_path, stride=2, fps=5)).values()
    pngs = sorted((tmp_path / "frames").glob("*.png"))
    assert summary["frames"] == len(pngs) == 6
    assert imageio.imread(pngs[0]).shape[:2] == (summary["size"][1], summary["size"][0])
    reader = imageio.get_reader(summary["video"])
    assert summary["video"].endswith(".mp4")
    assert reader.count_frames() == 6
    assert reader.get_meta_data()["fps"] == pytest.approx(5)
    frame = reader.get_data(3)
    assert frame.shape == (summary["size"][1], summary["size"][0], 3) and frame.std() > 5


def test_gif(traj, tmp_path):
    (summary,) = run(_cfg(traj, tmp_path, video="gif", pngs=False, start=2, stop=7)).values()
    assert summary["video"].endswith(".gif") and summary["pngs"] is None
    assert len(imageio.mimread(summary["video"])) == 5


def test_comparison_side_by_side_and_overlay(traj, other, tmp_path):
    (summary,) = run(_cfg(traj, tmp_path, compare=str(other), video="none", stop=4, width=640)).values()
    assert "fish vs other" in summary["title"]
    for key in ("compare_normalised", "compare_overlay"):
        img = imageio.imread(summary[key])
        assert img.shape[0] > 100 and img[..., :3].std() > 5
    # the overlay draws the first run in red and the second in blue
    overlay = imageio.imread(summary["compare_overlay"])[..., :3].astype(int)
    assert ((overlay[..., 0] - overlay[..., 2]) > 100).sum() > 50
    assert ((overlay[..., 2] - overlay[..., 0]) > 100).sum() > 50
    assert summary["compare_frame"] == 10                     # last fluid frame stored in both
    assert len(list((tmp_path / "frames").glob("fish_vs_other_*.png"))) == 4


def test_folder_renders_every_trajectory_and_skips_bad_ones(traj, other, tmp_path):
    folder = tmp_path / "runs"
    folder.mkdir()
    for p in (traj, other):
        (folder / p.name).write_bytes(p.read_bytes())
    (folder / "junk.h5").write_text("not a trajectory")
    results = run(_cfg(folder, tmp_path / "out", video="none", stop=2))
    assert sorted(k.rsplit("/", 1)[1] for k in results) == ["fish.h5", "junk.h5", "other.h5"]
    assert "error" in results[str(folder / "junk.h5")]
    assert len(list((tmp_path / "out" / "fish" / "frames").glob("*.png"))) == 2
    assert len(list((tmp_path / "out" / "other" / "frames").glob("*.png"))) == 2


def test_not_a_trajectory_is_one_clear_error(tmp_path):
    text = tmp_path / "notes.h5"
    text.write_text("hello")
    other_h5 = tmp_path / "other.h5"
    with h5py.File(other_h5, "w") as f:
        f["x"] = np.zeros(3)
    for bad in (text, other_h5, tmp_path / "missing.h5"):
        with pytest.raises(InputFileError) as err:
            run(_cfg(bad, tmp_path / "out"))
        assert "\n" not in str(err.value) and str(bad.name) in str(err.value)
    with pytest.raises(ConfigError, match="field must be one of"):
        run(_cfg(other_h5, tmp_path / "out", field="temperature"))


def test_incomplete_file_renders_what_is_there(tmp_path, capsys):
    path = write_synthetic_trajectory(tmp_path / "killed.h5", n_frames=7, complete=False)
    (summary,) = run(_cfg(path, tmp_path / "out", video="none")).values()
    assert summary["frames"] == 7 and not summary["complete"]
    assert "incomplete" in summary["title"]
    assert "incomplete" in capsys.readouterr().err


def test_vtk_series_loads_back(traj, tmp_path):
    import meshio
    import pyvista as pv

    (summary,) = run(_cfg(traj, tmp_path, vtk=True, video="none", pngs=False, stride=3)).values()
    fish = pv.get_reader(summary["vtk"]["fish"])
    assert fish.time_values == pytest.approx([0.0, 0.03, 0.06, 0.09])
    with h5py.File(traj) as f:
        n_nodes, n_tris = len(f["mesh/points"]), len(f["mesh/triangles"])
        q3, p6 = f["solid/q"][3, 0], f["fluid/p"][3, 0]
    vtu = meshio.read(tmp_path / "vtk" / "fish" / "fish_000003.vtu")
    assert len(vtu.points) == n_nodes and len(vtu.cells_dict["triangle"]) == n_tris
    np.testing.assert_allclose(vtu.points[:, :2], q3)
    assert set(vtu.point_data) == {"velocity", "force"}
    with h5py.File(traj) as f:
        np.testing.assert_array_equal(vtu.cell_data["actuator"][0], f["mesh/actuator"][()])
    fluid = pv.get_reader(summary["vtk"]["fluid"])
    assert fluid.time_values == pytest.approx([0.0, 0.06])           # fluid frames 0 and 6
    fluid.set_active_time_value(0.06)
    grid = fluid.read()[0]
    assert grid.n_cells == 20 * 60 and grid.n_points == 21 * 61
    assert grid.spacing == pytest.approx((2.5e-3,) * 3) and grid.origin == pytest.approx((0, 0, 0))
    assert {"p", "velocity", "mask", "vorticity"} <= set(grid.cell_data.keys())
    np.testing.assert_allclose(np.asarray(grid.cell_data["p"]).reshape(20, 60), p6, rtol=1e-6)


def test_renders_without_any_display_or_gl(traj, tmp_path):
    """The renderer is pure Agg: it never loads an OpenGL (VTK rendering) module, so a missing GL
    context cannot crash it. Checked in a clean subprocess with no display."""
    script = textwrap.dedent(f"""
        import sys
        from fishsim.render.config import RenderConfig
        from fishsim.render.run import run
        run(RenderConfig(path={str(traj)!r}, out_dir={str(tmp_path)!r}, width=320, stop=2, stride=1,
                         video="none", progress=False))
        gl = [m for m in sys.modules if "OpenGL" in m or m.startswith("pyvista")]
        assert not gl, gl
    """)
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120,
                          check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert len(list((tmp_path / "frames").glob("*.png"))) == 2


def test_a_folder_of_run_folders_finds_every_trajectory(tmp_path):
    from fishsim.errors import InputFileError
    from fishsim.render.run import trajectory_paths

    for folder in ("2026-01-01_00-00-00", "2026-01-01_00-00-00_2"):
        write_synthetic_trajectory(tmp_path / "simulate" / folder / "trajectory.h5", n_frames=2)
    assert [p.parent.name for p in trajectory_paths(tmp_path / "simulate")] == ["2026-01-01_00-00-00",
                                                                               "2026-01-01_00-00-00_2"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputFileError, match="or its subfolders"):
        trajectory_paths(tmp_path / "empty")


def test_default_stride_renders_the_frames_whose_fluid_was_stored(tmp_path):
    from fishsim.render.run import frame_indices

    path = write_synthetic_trajectory(tmp_path / "t.h5", n_frames=12, fluid_every=3)
    (summary,) = run(_cfg(path, tmp_path / "out", video="none", stride=None)).values()
    assert summary["frames"] == 4                                 # frames 0, 3, 6, 9 hold fluid
    cfg = _cfg(path, tmp_path / "o2", video="none", stride=None)
    assert frame_indices(12, cfg, None) == list(range(12))      # no fluid: every frame

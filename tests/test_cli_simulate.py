"""`fishsim simulate` end to end on a small config: a valid trajectory that round-trips, crash
safety (a killed run leaves a readable, incomplete-marked file), and the CLI's error path."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from fishsim.cli import app
from fishsim.config import load_config
from fishsim.errors import Terminated, stops_surface
from fishsim.io.trajectory import read_trajectory

runner = CliRunner()
SMALL = ["fish.edge_length=5e-3", "tank.H=40", "tank.W=120", "tank.dx=5e-3", "origin=[0.15,0.1]",
         "tank.wall_x=3", "tank.wall_y=2"]
NUMERICAL = [*SMALL, "fluid=numerical"]  # the reference solver: deterministic, no model file


def test_simulate_writes_valid_trajectory(tmp_path):
    result = runner.invoke(app, ["simulate", *NUMERICAL, "frames=6", "fluid_stride=2", f"out_dir={tmp_path}",
                                 "batch.frequency=[4,6]"])
    assert result.exit_code == 0, result.output
    tr = read_trajectory(tmp_path / "trajectory.h5")
    assert tr.complete and tr.n_frames == 6
    B, N = 2, len(tr["mesh/points"])
    assert tr["solid/q"].shape == (6, B, N, 2)
    assert tr["fluid/p"].shape == (3, B, 40, 120) and list(tr["fluid/frame"]) == [1, 3, 5]
    np.testing.assert_allclose(tr["controller/frequency"], [4.0, 6.0])
    np.testing.assert_allclose(tr["metrics/time"], 0.01 * np.arange(1, 7))
    assert np.isfinite(tr["solid/f_ext"]).all() and np.abs(tr["solid/f_ext"]).max() > 0
    assert tr.attrs["grid_w"] == 120
    # the stored config reproduces the run's config
    from omegaconf import OmegaConf
    assert OmegaConf.create(tr.config_yaml).tank.W == 120
    assert load_config("simulate", SMALL).tank.W == 120


def test_simulate_killed_leaves_incomplete_readable_file(tmp_path):
    args = ["simulate", *NUMERICAL, "frames=2000", "flush_every=1", f"out_dir={tmp_path}"]
    proc = subprocess.Popen([sys.executable, "-m", "fishsim.cli", *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    path = tmp_path / "trajectory.h5.part"          # renamed to trajectory.h5 only when the run ends
    deadline = time.time() + 120
    while time.time() < deadline:
        time.sleep(1.0)
        if path.exists() and read_trajectory(path, load_fluid=False).n_frames >= 3:
            break
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    tr = read_trajectory(path)
    assert not tr.complete and not (tmp_path / "trajectory.h5").exists()
    assert 3 <= tr.n_frames < 2000
    assert np.isfinite(tr["solid/q"][: tr.n_frames]).all()
    import h5py
    with h5py.File(path, "r") as f:                  # plain HDF5 opens it: no h5clear needed
        assert f["metrics/time"].shape[0] == f.attrs["n_frames"] == tr.n_frames


def test_simulate_bad_config_exit_code_2(tmp_path):
    result = runner.invoke(app, ["simulate", "origin=[0.7,0.1]", f"out_dir={tmp_path}"])
    assert result.exit_code == 2
    assert "outside" in result.output and "Traceback" not in result.output
    result = runner.invoke(app, ["simulate", *NUMERICAL, "controller.amplitude=1000", f"out_dir={tmp_path}"])
    assert result.exit_code == 2 and "(a muscle would vanish); use amplitude <" in result.output


def _tiny_hydronet(path):
    """An (untrained) HydroNet saved the way train-hydronet saves best.pt."""
    from dataclasses import asdict

    import torch

    from fishsim.fluid.hydronet import HydroNet, NetConfig
    from fishsim.io.atomic import atomic_save

    torch.manual_seed(0)
    net = HydroNet(NetConfig(hidden=4, depth=2))
    atomic_save({"model": net.state_dict(), "net": asdict(net.cfg), "iteration": 0, "val": 0.0}, path)
    return path


def test_simulate_with_a_hydronet_model_file(tmp_path):
    model = _tiny_hydronet(tmp_path / "net.pt")
    result = runner.invoke(app, ["simulate", *SMALL, "fluid=hydronet", f"fluid.model_file={model}", "frames=3",
                                 "fluid_stride=1", f"out_dir={tmp_path}"])
    assert result.exit_code == 0, result.output
    tr = read_trajectory(tmp_path / "trajectory.h5")
    assert tr.complete and tr["fluid/p"].shape == (3, 1, 40, 120) and np.isfinite(tr["fluid/p"]).all()
    assert np.abs(tr["fluid/p"][-1]).max() > 0 and np.abs(tr["solid/f_ext"][-1]).max() > 0


def test_simulate_missing_or_corrupt_hydronet_exit_code_2(tmp_path):
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    for path, words in ((tmp_path / "absent.pt", "not found"), (tmp_path / "junk.pt", "not a readable HydroNet")):
        result = runner.invoke(app, ["simulate", *SMALL, "fluid=hydronet", f"fluid.model_file={path}", "frames=2",
                                     f"out_dir={tmp_path / 'out'}"])
        assert result.exit_code == 2 and words in result.output and "fishsim train-hydronet" in result.output


def test_simulate_writes_an_xdmf_that_vtk_reads_as_the_trajectory(tmp_path):
    """The XDMF sidecar (fishsim/io/xdmf.py) points into trajectory.h5: VTK's XDMF reader (the one
    ParaView has) gives, for every fish of the batch, the nodes, velocities and actuators of the
    file at a frame, and every stored fluid frame's cells with the file's pressure."""
    import h5py
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    args = ["simulate", *NUMERICAL, "frames=6", "fluid_stride=2", "batch.frequency=[3,5]", f"out_dir={tmp_path}"]
    assert runner.invoke(app, args).exit_code == 0
    reader = vtk.vtkXdmfReader()
    reader.SetFileName(str(tmp_path / "trajectory.xdmf"))
    reader.UpdateInformation()
    reader.UpdateTimeStep(0.04)                      # frame 3 (t = 0.01 (t + 1)), a stored fluid frame
    out = reader.GetOutputDataObject(0)
    names = [out.GetMetaData(i).Get(vtk.vtkCompositeDataSet.NAME()) for i in range(out.GetNumberOfBlocks())]
    assert names == ["fish_0", "fluid_0", "fish_1", "fluid_1"]
    with h5py.File(tmp_path / "trajectory.h5", "r") as f:
        k = list(f["fluid/frame"][()]).index(3)
        for i, name in enumerate(names):
            block, b = out.GetBlock(i), int(name[-1])
            if name.startswith("fish"):
                np.testing.assert_array_equal(vtk_to_numpy(block.GetPoints().GetData())[:, :2], f["solid/q"][3, b])
                np.testing.assert_array_equal(vtk_to_numpy(block.GetPointData().GetArray("velocity"))[:, :2],
                                              f["solid/qdot"][3, b])
                np.testing.assert_array_equal(vtk_to_numpy(block.GetCellData().GetArray("actuator")), f["mesh/actuator"][()])
            else:
                np.testing.assert_array_equal(vtk_to_numpy(block.GetCellData().GetArray("p")), f["fluid/p"][k, b].ravel())
                x0, x1, y0, y1, _, _ = block.GetCell(1).GetBounds()   # cell (row 0, column 1)
                dx = f.attrs["grid_dx"]
                np.testing.assert_allclose([x0, x1, y0, y1], [dx, 2 * dx, 0, dx], atol=1e-12)


def _meshio_series(path):
    """Everything meshio's XDMF time-series reader gives for ``path``: (points, cells, steps)."""
    import meshio

    with meshio.xdmf.TimeSeriesReader(path) as reader:
        points, cells = reader.read_points_cells()
        return points, cells, [reader.read_data(k) for k in range(reader.num_steps)]


def test_simulate_writes_an_xdmf_per_fish_that_meshio_reads_as_the_trajectory(tmp_path, monkeypatch):
    """trajectory_fish<b>.xdmf (fishsim/io/xdmf.py) is one fish's time series that meshio reads:
    the mesh (frame 0's positions, the triangles) and, per frame, the time, the positions,
    velocities and forces of the file and the actuators; VTK reads it moving. The views it needs
    are virtual datasets: the file grows by their metadata only, and writing the sidecars again
    changes nothing."""
    import h5py
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    from fishsim.commands import simulate
    from fishsim.io.xdmf import write_xdmf

    sizes = []

    def measured(path):                               # the trajectory's size before and after
        sizes.append(path.stat().st_size)
        out = write_xdmf(path)
        sizes.append(path.stat().st_size)
        return out

    monkeypatch.setattr(simulate, "write_xdmf", measured)
    args = ["simulate", "fluid=none", "fish.edge_length=5e-3", "frames=3", "batch.frequency=[3,5]",
            f"out_dir={tmp_path}"]
    assert runner.invoke(app, args).exit_code == 0
    path = tmp_path / "trajectory.h5"
    with h5py.File(path, "r") as f:
        for b in range(2):
            points, cells, steps = _meshio_series(tmp_path / f"trajectory_fish{b}.xdmf")
            np.testing.assert_array_equal(points, f["solid/q"][0, b])
            assert [c.type for c in cells] == ["triangle"]
            np.testing.assert_array_equal(cells[0].data, f["mesh/triangles"][()])
            assert len(steps) == 3
            for t, (time_, point_data, cell_data) in enumerate(steps):
                assert time_ == f["metrics/time"][t]
                for name, series in (("position", "q"), ("velocity", "qdot"), ("force", "f_ext")):
                    np.testing.assert_array_equal(point_data[name], f[f"solid/{series}"][t, b])
                np.testing.assert_array_equal(cell_data["actuator"][0], f["mesh/actuator"][()])
        views, groups = [], []
        f["xdmf"].visititems(lambda n, o: (views if isinstance(o, h5py.Dataset) else groups).append(o))
        assert len(views) == 3 * 2 * 3                # q, qdot, f_ext; 2 fish; 3 frames
        assert all(v.is_virtual and v.id.get_storage_size() == 0 for v in views)
        assert {s.file_name for v in views for s in v.virtual_sources()} == {"."}   # this file, whatever its name
        moved = f["solid/q"][2, 1]
    assert sizes[1] - sizes[0] <= 1024 * (len(views) + len(groups) + 1)   # metadata: ~0.5 kB a view, ~1 kB a group
    xml = (tmp_path / "trajectory_fish1.xdmf").read_text()
    write_xdmf(path)
    assert path.stat().st_size == sizes[1] and (tmp_path / "trajectory_fish1.xdmf").read_text() == xml
    assert "xdmf/solid/q/0/000000" not in read_trajectory(path).data
    reader = vtk.vtkXdmfReader()                      # VTK reads a fish's own file too, moving
    reader.SetFileName(str(tmp_path / "trajectory_fish1.xdmf"))
    reader.UpdateInformation()
    reader.UpdateTimeStep(0.03)
    np.testing.assert_array_equal(vtk_to_numpy(reader.GetOutputDataObject(0).GetPoints().GetData())[:, :2], moved)


def test_meshio_reads_the_fish_and_the_fluid_of_a_run_with_a_fluid(tmp_path):
    """With a fluid, trajectory_fluid<b>.xdmf is fish b's fluid as meshio reads it: the grid's
    cells as quadrilaterals and, per stored fluid frame, its time and the file's fields."""
    import h5py

    args = ["simulate", *NUMERICAL, "frames=3", "fluid_stride=2", f"out_dir={tmp_path}"]
    assert runner.invoke(app, args).exit_code == 0
    with h5py.File(tmp_path / "trajectory.h5", "r") as f:
        _, _, steps = _meshio_series(tmp_path / "trajectory_fish0.xdmf")
        assert len(steps) == 3
        np.testing.assert_array_equal(steps[2][1]["force"], f["solid/f_ext"][2, 0])
        points, cells, steps = _meshio_series(tmp_path / "trajectory_fluid0.xdmf")
        dx = f.attrs["grid_dx"]
        assert [c.type for c in cells] == ["quad"] and len(cells[0].data) == 40 * 120
        np.testing.assert_allclose(points[cells[0].data[121]], [[dx, dx], [2 * dx, dx], [2 * dx, 2 * dx],
                                                                [dx, 2 * dx]], atol=1e-12)   # cell (1, 1)
        assert len(steps) == 1 and steps[0][0] == f["metrics/time"][f["fluid/frame"][0]]
        for name in ("p", "vx", "vy", "mask"):
            np.testing.assert_array_equal(steps[0][2][name][0], f[f"fluid/{name}"][0, 0].ravel())
        assert np.abs(steps[0][2]["p"][0]).max() > 0


def test_xdmf_of_a_growing_trajectory_has_views_of_its_flushed_frames_only(tmp_path):
    """The sidecars of a file still being written name only its flushed frames; written again
    after more frames, they have those too (the views already there are kept), and the writer
    appends to and closes the file as before."""
    from fishsim.io.trajectory import TrajectoryWriter, trajectory_series
    from fishsim.io.xdmf import write_xdmf

    triangles = np.array([[0, 1, 2], [1, 3, 2]])
    static = {"mesh/points": np.arange(8.0).reshape(4, 2), "mesh/triangles": triangles,
              "mesh/actuator": np.array([1, 2], np.int8)}
    writer = TrajectoryWriter(tmp_path / "t.h5", trajectory_series(4, 1, 1, ["head_x"]), static, "", h=0.01,
                              flush_every=2)

    def frame(t):
        writer.append({"solid/q": np.full((1, 4, 2), t + 0.5), "solid/qdot": np.full((1, 4, 2), -t),
                       "solid/f_ext": np.zeros((1, 4, 2)), "controller/activation": np.zeros((1, 1)),
                       "metrics/head_x": np.zeros(1), "metrics/time": 0.01 * (t + 1)})
        writer.end_frame()

    for t in range(3):                                 # frames 0, 1 flushed; 2 in memory
        frame(t)
    write_xdmf(writer.partial)
    assert len(_meshio_series(tmp_path / "t.h5_fish0.xdmf")[2]) == 2
    for t in range(3, 5):
        frame(t)                                       # frames 2, 3 flushed
    write_xdmf(writer.partial)
    points, _, steps = _meshio_series(tmp_path / "t.h5_fish0.xdmf")
    assert len(steps) == 4
    np.testing.assert_array_equal(points, np.full((4, 2), 0.5))
    for t, (time_, point_data, _) in enumerate(steps):
        assert time_ == pytest.approx(0.01 * (t + 1))
        np.testing.assert_array_equal(point_data["position"], np.full((4, 2), t + 0.5))
        np.testing.assert_array_equal(point_data["velocity"], np.full((4, 2), -t))
    writer.close(complete=True)
    tr = read_trajectory(tmp_path / "t.h5")
    assert tr.complete and tr.n_frames == 5 and not any(k.startswith("xdmf") for k in tr.data)
    write_xdmf(tmp_path / "t.h5")
    assert len(_meshio_series(tmp_path / "t_fish0.xdmf")[2]) == 5


def test_render_a_real_simulation(tmp_path):
    """`fishsim render` on `fishsim simulate` output: an MP4 with one frame per frame, and the
    fish drawn along its surface polyline (pixels under the outline nodes) where the trajectory
    says it is in the last frame."""
    import imageio.v2 as imageio

    from fishsim.render.config import RenderConfig
    from fishsim.render.data import load_render_data
    from fishsim.render.scene import FrameFigure
    from tests.render.test_scene import _is_fish, _pixels

    assert runner.invoke(app, ["simulate", *NUMERICAL, "frames=8", f"out_dir={tmp_path}"]).exit_code == 0
    result = runner.invoke(app, ["render", str(tmp_path / "trajectory.h5"), f"out_dir={tmp_path / 'r'}", "stride=1"])
    assert result.exit_code == 0, result.output
    assert imageio.get_reader(next((tmp_path / "r").glob("*.mp4"))).count_frames() == 8
    data = load_render_data(tmp_path / "trajectory.h5")
    fig = FrameFigure([data], RenderConfig(path=str(tmp_path / "trajectory.h5"), width=1920, arrows=False))
    fig.update(7)
    q, rgb = data.q[7], fig.rgb()
    centroid = q[data.triangles].mean(1)                    # each outline node's adjacent elements
    inward = np.stack([centroid[(data.triangles == k).any(1)].mean(0) for k in data.surface]) - q[data.surface]
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)  # 1 mm ~ 2.6 pixels at this width
    just_in, just_out = q[data.surface] + 0.8e-3 * inward, q[data.surface] - 2e-3 * inward
    assert _is_fish(_pixels(fig, rgb, just_in)).mean() > 0.9
    assert _is_fish(_pixels(fig, rgb, just_out)).mean() < 0.2


def test_simulate_blow_up_exit_code_2_and_partial_file_kept(tmp_path, monkeypatch):
    """A fluid that goes non-finite at frame 4: one line naming the frame and the quantity, exit
    code 2, and the frames before it kept in a readable file marked incomplete with the reason."""
    import torch

    from fishsim.fields import FluidState
    from fishsim.fluid.numerical import NumericalFluid

    real, calls = NumericalFluid.step, {"n": 0}

    def failing(self, state, boundary, params, start=None):
        calls["n"] += 1
        new = real(self, state, boundary, params, start)
        return FluidState(new.a, new.p * torch.nan) if calls["n"] == 4 else new

    monkeypatch.setattr(NumericalFluid, "step", failing)
    result = runner.invoke(app, ["simulate", *NUMERICAL, "frames=10", "flush_every=1", f"out_dir={tmp_path}"])
    assert result.exit_code == 2
    err = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(err) == 1 and "frame 4" in err[0] and "fluid pressure p" in err[0] and "incomplete" in err[0]
    tr = read_trajectory(tmp_path / "trajectory.h5")
    assert not tr.complete and tr.n_frames == 3 and "blew up" in tr.attrs["message"]
    assert np.isfinite(tr["solid/q"][:3]).all()


THRESHOLD = 0.1  # m/s: the 6 Hz fish's surface passes it from the 6th step, the 3 Hz fish's never (8 frames)


def test_a_batch_carries_on_past_a_fish_that_blows_up(tmp_path, monkeypatch):
    """In a batch, the fish whose fluid goes non-finite (here the faster one, from frame 4 on) is
    marked failed with its frame and held at rest; the others finish exactly as alone."""
    import json

    import torch

    from fishsim.fields import FluidState
    from fishsim.fluid.numerical import NumericalFluid

    real, steps = NumericalFluid.step, [0]

    def second_fails(self, state, boundary, params, start=None):
        new = real(self, state, boundary, params, start)
        steps[0] += 1
        fast = boundary.velocity[:, :, 5:-5, 10:-10].abs().amax((1, 2, 3)) > THRESHOLD    # the 6 Hz fish, not the walls
        if steps[0] >= 5 and bool(fast.any()):
            p = new.p.clone()
            p[fast] = torch.nan
            return FluidState(new.a, p)
        return new

    args = ["simulate", *NUMERICAL, "frames=8", f"out_dir={tmp_path}"]
    alone = runner.invoke(app, [*args[:-1], "controller.frequency=3", f"out_dir={tmp_path / 'alone'}"])
    assert alone.exit_code == 0, alone.output
    monkeypatch.setattr(NumericalFluid, "step", second_fails)
    result = runner.invoke(app, [*args, "batch.frequency=[3,6]"])
    assert result.exit_code == 0, result.output
    assert "fish 1 blew up at frame" in result.output
    tr = read_trajectory(tmp_path / "trajectory.h5")
    assert tr.complete and "1" in json.loads(tr.attrs["failed_fish"])
    ref = read_trajectory(tmp_path / "alone" / "trajectory.h5")
    np.testing.assert_allclose(tr["metrics/head_x"][:, 0], ref["metrics/head_x"][:, 0], rtol=1e-6)
    q1 = tr["solid/q"][-3:, 1]
    assert np.isfinite(q1).all() and np.abs(q1 - q1[0]).max() == 0          # held at rest


def test_batch_summary_has_one_row_per_fish_and_strouhal_over_whole_periods(tmp_path):
    import csv

    result = runner.invoke(app, ["simulate", *NUMERICAL, "frames=30", "batch.frequency=[4,9]", f"out_dir={tmp_path}"])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader((tmp_path / "summary.csv").open()))
    assert [float(r["frequency [Hz]"]) for r in rows] == [4.0, 9.0] and "per fish" in result.output
    assert "simulate: frame 30/30" in result.output          # not a terminal: plain progress lines
    # 30 frames: the second half (15 frames) holds no whole 4 Hz period (25 frames), one 9 Hz period (11)
    assert rows[0]["Strouhal f A / U"] == "nan" and rows[0]["mean speed [m/s]"] == "nan"
    assert float(rows[1]["tail peak-to-peak [m]"]) > 0 and rows[1]["mean speed [m/s]"] != "nan"


def test_a_fish_near_the_wall_is_reported(tmp_path):
    import json

    near = [a if not a.startswith("origin=") else "origin=[0.022,0.1]" for a in NUMERICAL]   # tail by the left wall
    result = runner.invoke(app, ["simulate", *near, "frames=2", f"out_dir={tmp_path}"])
    assert result.exit_code == 0, result.output
    assert "fish 0 came within a body width of the tank wall at frame 1" in " ".join(result.output.split())
    assert json.loads(read_trajectory(tmp_path / "trajectory.h5").attrs["near_wall_frame"]) == {"0": 1}
    far = runner.invoke(app, ["simulate", *NUMERICAL, "frames=2", f"out_dir={tmp_path / 'far'}"])
    assert far.exit_code == 0 and "body width" not in far.output


@pytest.mark.parametrize("sig, code, ignored", [(signal.SIGTERM, 143, False), (signal.SIGINT, 130, True)])
def test_stop_signals_keep_a_marked_partial_file(tmp_path, sig, code, ignored):
    """SIGTERM (timeout, SLURM, docker stop) stops like Ctrl-C: exit 143, the frames so far kept
    in trajectory.h5 marked incomplete with the reason. SIGINT works even when the shell started
    the run in the background with SIGINT ignored."""
    args = ["simulate", *NUMERICAL, "frames=2000", "flush_every=1", f"out_dir={tmp_path}"]
    ignore = "signal.signal(signal.SIGINT, signal.SIG_IGN); " if ignored else ""     # as `cmd &` in a script
    start = f"import runpy, signal, sys; {ignore}sys.argv = ['fishsim', *{args!r}]; runpy.run_module('fishsim.cli', run_name='__main__')"
    proc = subprocess.Popen([sys.executable, "-c", start], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    part = tmp_path / "trajectory.h5.part"
    deadline = time.time() + 120
    while time.time() < deadline:
        time.sleep(0.5)
        if part.exists() and read_trajectory(part, load_fluid=False).n_frames >= 3:
            break
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    tr = read_trajectory(tmp_path / "trajectory.h5")
    assert not tr.complete and 3 <= tr.n_frames < 2000 and "partial results were kept" in err
    assert ("SIGTERM" in tr.attrs["message"]) == (sig == signal.SIGTERM)


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_stop_signal_landing_in_a_finalizer_still_stops_the_run(sig, code):
    """Python drops an exception raised in a ``__del__`` or weakref callback; a stop signal that
    lands there is sent again instead of being lost (a CI run once went on to frame 179)."""
    start = ("import signal, sys, time, typer; from fishsim.cli import _execute\n"
             "class Finalized:\n"
             f"    def __del__(self): signal.raise_signal({int(sig)}); time.sleep(0.01)\n"
             "def run(cfg):\n"
             "    Finalized()\n"
             "    time.sleep(30)\n"
             "try:\n"
             "    _execute('mesh', [], False, run)\n"
             "except typer.Exit as stop:\n"
             "    sys.exit(stop.exit_code)\n")
    proc = subprocess.run([sys.executable, "-c", start], check=False, capture_output=True, text=True, timeout=25)
    assert proc.returncode == code, proc.stderr
    assert "Exception ignored" not in proc.stderr and "partial results were kept" in proc.stderr


def test_debug_preset_is_a_tiny_episode(tmp_path):
    """experiment=debug: the coarse fish in a 40 x 120 tank for 20 frames (seconds)."""
    from fishsim.config import load_config

    cfg = load_config("simulate", ["experiment=debug"])
    assert (cfg.tank.H, cfg.tank.W, cfg.frames, cfg.fish.edge_length) == (40, 120, 20, 5e-3)
    assert load_config("optimize", ["experiment=debug"]).frames == 20


@pytest.mark.parametrize("stop", [KeyboardInterrupt("Ctrl-C"), Terminated("terminated (SIGTERM)")])
def test_a_stop_wrapped_by_compiled_code_surfaces_as_the_stop(stop):
    """A signal landing while numba code calls back into Python reaches Python as a SystemError
    caused by the KeyboardInterrupt (seen once in the suite: a simulate stopped by SIGINT exited 1
    with a traceback instead of 130); ``stops_surface`` raises the stop itself, and lets other
    errors, a SystemError without a stop behind it included, pass unchanged."""
    def wrapped():
        try:
            raise stop
        except KeyboardInterrupt as err:
            raise SystemError("CPUDispatcher(...) returned a result with an exception set") from err

    with pytest.raises(type(stop)) as raised, stops_surface():
        wrapped()
    assert raised.value is stop
    with pytest.raises(SystemError), stops_surface():
        raise SystemError("no stop behind it")
    with pytest.raises(ValueError), stops_surface():
        raise ValueError("not a stop")

"""HDF5 trajectories: round trip, crash safety (readable and marked incomplete), bad files."""

import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest

from fishsim.errors import InputFileError
from fishsim.io.trajectory import TrajectoryWriter, read_trajectory, trajectory_series


def _writer(path, flush_every=2):
    series = trajectory_series(n_nodes=5, batch=2, n_act=3, metrics=["head_x"], fluid_shape=(4, 6))
    static = {"mesh/points": np.arange(10.0).reshape(5, 2)}
    return TrajectoryWriter(path, series, static, "fish:\n  length: 0.2\n", h=0.01, flush_every=flush_every)


def _frame(w, t):
    w.append({"solid/q": np.full((2, 5, 2), t), "solid/qdot": np.zeros((2, 5, 2)),
              "solid/f_ext": np.zeros((2, 5, 2)), "controller/activation": np.zeros((2, 3)),
              "metrics/head_x": np.array([t, 2 * t]), "metrics/time": 0.01 * t})
    if t % 2 == 0:
        w.append({"fluid/p": np.full((2, 4, 6), t), "fluid/frame": t})
    w.end_frame()


def test_round_trip(tmp_path):
    w = _writer(tmp_path / "t.h5")
    for t in range(6):
        _frame(w, t)
    w.close(complete=True)
    tr = read_trajectory(tmp_path / "t.h5")
    assert tr.complete and tr.n_frames == 6
    assert tr["solid/q"].shape == (6, 2, 5, 2)
    np.testing.assert_array_equal(tr["solid/q"][3], np.full((2, 5, 2), 3.0))
    np.testing.assert_array_equal(tr["fluid/frame"], [0, 2, 4])
    np.testing.assert_array_equal(tr["mesh/points"], np.arange(10.0).reshape(5, 2))
    assert "length: 0.2" in tr.config_yaml
    assert tr.attrs["h"] == pytest.approx(0.01)


def test_killed_writer_leaves_readable_incomplete_file(tmp_path):
    path = tmp_path / "killed.h5"
    script = textwrap.dedent(f"""
        import os, signal, numpy as np
        import tests.io.test_trajectory as T
        w = T._writer({str(path)!r}, flush_every=2)
        for t in range(5):
            T._frame(w, t)
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, check=False)
    assert proc.returncode != 0 and not path.exists()
    with pytest.raises(InputFileError, match=r"killed\.h5\.part"):      # the error points at what is left
        read_trajectory(path)
    tr = read_trajectory(path.with_name("killed.h5.part"))
    assert not tr.complete
    assert tr.n_frames == 4  # frames 0-3 were flushed; frame 4 was not
    np.testing.assert_array_equal(tr["metrics/head_x"][3], [3.0, 6.0])


def test_truncated_file_is_refused_at_once(tmp_path):
    import time

    w = _writer(tmp_path / "t.h5", flush_every=1)
    for t in range(6):
        _frame(w, t)
    w.close(complete=True)
    data = (tmp_path / "t.h5").read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 2])
    t0 = time.perf_counter()
    with pytest.raises(InputFileError, match="truncated|not a readable HDF5"):
        read_trajectory(cut)
    assert time.perf_counter() - t0 < 5.0


def test_bad_files(tmp_path):
    with pytest.raises(InputFileError, match="no such trajectory"):
        read_trajectory(tmp_path / "missing.h5")
    junk = tmp_path / "junk.h5"
    junk.write_text("not hdf5")
    with pytest.raises(InputFileError, match="not a readable HDF5"):
        read_trajectory(junk)


def test_xarray_opens_a_trajectory_with_named_dimensions_and_units(tmp_path):
    """netCDF conventions (fishsim/io/conventions.py): named dimensions, units, long names, the
    growing frame scale, snake_case attributes."""
    xr = pytest.importorskip("xarray")
    pytest.importorskip("h5netcdf")
    from typer.testing import CliRunner

    from fishsim.cli import app
    from tests.test_cli_simulate import NUMERICAL

    assert CliRunner().invoke(app, ["simulate", *NUMERICAL, "frames=4", "fluid_stride=2",
                                    "batch.frequency=[3,5]", f"out_dir={tmp_path}"]).exit_code == 0
    path = tmp_path / "trajectory.h5"
    solid = xr.open_dataset(path, engine="h5netcdf", group="solid")
    assert solid["q"].dims == ("frame", "fish", "node", "xy") and solid["q"].attrs["units"] == "m"
    assert solid.sizes["frame"] == 4 and solid.sizes["fish"] == 2
    fluid = xr.open_dataset(path, engine="h5netcdf", group="fluid")
    assert fluid["p"].dims == ("fluid_frame", "fish", "y", "x") and fluid["p"].attrs["units"] == "Pa"
    assert fluid["a"].dims == ("fluid_frame", "fish", "y_vertex", "x_vertex") and fluid.sizes["fluid_frame"] == 2
    root = xr.open_dataset(path, engine="h5netcdf")
    np.testing.assert_array_equal(root["frame"], np.arange(4))
    np.testing.assert_allclose(root["x"][:2], [0.5 * 5e-3, 1.5 * 5e-3])
    with h5py.File(path, "r") as f:
        assert all(k == k.lower() and " " not in k for k in f.attrs)


def test_lazy_read_slices_the_open_file_like_the_eager_read(tmp_path):
    path = tmp_path / "t.h5"
    w = _writer(path)
    for t in range(3):
        _frame(w, t)
    w.close(complete=True)
    eager = read_trajectory(path)
    with read_trajectory(path, lazy=True) as lazy:
        assert isinstance(lazy["solid/q"], h5py.Dataset) and lazy.n_frames == eager.n_frames == 3
        np.testing.assert_array_equal(lazy["solid/q"][2, 0], eager["solid/q"][2, 0])
    assert lazy.file is None


def test_a_reader_holding_the_file_delays_the_writer_without_losing_frames(tmp_path):
    """Another program reading the .part (HDF5's lock, e.g. ParaView or a lazy read) made the
    next flush fail and the run die. Now a flush keeps its frames in memory until the file is
    free, and the run's end waits for the reader, so every frame is written."""
    w = _writer(tmp_path / "t.h5", flush_every=100)
    for t in range(3):
        _frame(w, t)
    assert w.flush()
    hold = "import h5py, sys, time; f = h5py.File(sys.argv[1], 'r'); print('open', flush=True); time.sleep(1.5)"
    reader = subprocess.Popen([sys.executable, "-c", hold, str(w.partial)], stdout=subprocess.PIPE, text=True)
    assert reader.stdout.readline().strip() == "open"
    for t in range(3, 6):
        _frame(w, t)
    assert not w.flush(wait=0.1) and len(w.pending["solid/q"]) == 3      # kept for later
    with pytest.warns(UserWarning, match="open in another program"):
        w.close(complete=True)                                          # waits for the reader
    reader.wait(timeout=30)
    tr = read_trajectory(tmp_path / "t.h5")
    assert tr.complete and tr.n_frames == 6
    np.testing.assert_array_equal(tr["solid/q"][:, 0, 0, 0], np.arange(6.0))

"""`fishsim simulate` end to end on a small config: a valid trajectory that round-trips, crash
safety (a killed run leaves a readable, incomplete-marked file), and the CLI's error path."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
from typer.testing import CliRunner

from fishsim.cli import app
from fishsim.config import load_config
from fishsim.io.trajectory import read_trajectory

runner = CliRunner()
SMALL = ["fish.edge_length=5e-3", "fluid.H=40", "fluid.W=120", "fluid.dx=5e-3", "origin=[0.15,0.1]",
         "fluid.wall_x=3", "fluid.wall_y=2"]


def test_simulate_writes_valid_trajectory(tmp_path):
    result = runner.invoke(app, ["simulate", *SMALL, "frames=6", "fluid_stride=2", f"out_dir={tmp_path}",
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
    assert tr.attrs["grid_W"] == 120
    # the stored config reproduces the run's config
    from omegaconf import OmegaConf
    assert OmegaConf.create(tr.config_yaml).fluid.W == 120
    assert load_config("simulate", SMALL).fluid.W == 120


def test_simulate_killed_leaves_incomplete_readable_file(tmp_path):
    args = ["simulate", *SMALL, "frames=2000", "flush_every=1", f"out_dir={tmp_path}"]
    proc = subprocess.Popen([sys.executable, "-m", "fishsim.cli", *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    path = tmp_path / "trajectory.h5"
    deadline = time.time() + 120
    while time.time() < deadline:
        time.sleep(1.0)
        if path.exists() and read_trajectory(path, load_fluid=False).n_frames >= 3:
            break
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    tr = read_trajectory(path)
    assert not tr.complete
    assert 3 <= tr.n_frames < 2000
    assert np.isfinite(tr["solid/q"][: tr.n_frames]).all()


def test_simulate_bad_config_exit_code_2(tmp_path):
    result = runner.invoke(app, ["simulate", "origin=[0.7,0.1]", f"out_dir={tmp_path}"])
    assert result.exit_code == 2
    assert "outside" in result.output and "Traceback" not in result.output

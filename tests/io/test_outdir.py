"""Output folders: a finished result is never overwritten by accident, default folders are
unique, and a folder another run is writing to is refused."""

import dataclasses
import subprocess
import sys
import time

import pytest
from typer.testing import CliRunner

from fishsim.cli import app
from fishsim.errors import ConfigError
from fishsim.io.outdir import make_out_dir, release_locks
from fishsim.io.trajectory import read_trajectory

runner = CliRunner()
TINY = ["fluid=none", "fish.edge_length=5e-3", "frames=2"]


def test_a_finished_trajectory_is_not_overwritten_unless_asked(tmp_path):
    first = runner.invoke(app, ["simulate", *TINY, f"out_dir={tmp_path}"])
    assert first.exit_code == 0, first.output
    before = (tmp_path / "trajectory.h5").read_bytes()
    again = runner.invoke(app, ["simulate", *TINY, "frames=3", f"out_dir={tmp_path}"])
    assert again.exit_code == 2 and "already exists" in again.output and "overwrite=true" in again.output
    assert (tmp_path / "trajectory.h5").read_bytes() == before
    forced = runner.invoke(app, ["simulate", *TINY, "frames=3", "overwrite=true", f"out_dir={tmp_path}"])
    assert forced.exit_code == 0 and read_trajectory(tmp_path / "trajectory.h5").n_frames == 3


def test_default_folders_are_unique_within_one_second(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    a, b = make_out_dir("simulate", None), make_out_dir("simulate", None)
    assert a != b and a.parent == b.parent and a.is_dir() and b.is_dir()
    (a / "result.txt").write_text("kept")
    release_locks()                                  # b was never written to: removed, a kept
    assert (a / "result.txt").exists() and not b.exists()


def test_a_folder_in_use_by_another_run_is_refused(tmp_path):
    script = ("import time; from pathlib import Path; from fishsim.io.outdir import make_out_dir; "
              f"make_out_dir('x', {str(tmp_path)!r}); print('locked', flush=True); time.sleep(30)")
    other = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().strip() == "locked"
        with pytest.raises(ConfigError, match="in use by another fishsim run"):
            make_out_dir("x", str(tmp_path))
        result = runner.invoke(app, ["simulate", *TINY, f"out_dir={tmp_path}"])
        assert result.exit_code == 2 and "in use" in result.output
    finally:
        other.kill()
        other.wait()
    time.sleep(0.1)
    assert make_out_dir("x", str(tmp_path)) == tmp_path          # free again once the other run is gone
    release_locks()


@pytest.mark.parametrize("make_bad, words", [
    (lambda p: (p / "f").write_text("x") and str(p / "f"), "is a file, not a folder"),
    (lambda p: str(p / "f" / "sub"), "cannot create out_dir"),
])
def test_unusable_out_dir_is_one_line(tmp_path, make_bad, words):
    (tmp_path / "f").write_text("x")
    result = runner.invoke(app, ["simulate", *TINY, f"out_dir={make_bad(tmp_path)}"])
    assert result.exit_code == 2 and words in result.output, result.output


@pytest.mark.parametrize("override", [["tank.H=20000", "tank.W=20000"], ["tank.H=100000", "tank.W=100000"],
                                      ["fish.edge_length=1e-5"]])
def test_a_run_too_large_for_memory_is_refused_up_front(tmp_path, override):
    t0 = time.perf_counter()
    result = runner.invoke(app, ["simulate", "fluid=numerical", *override, f"out_dir={tmp_path}"])
    assert result.exit_code == 2 and "GB of memory" in result.output and "check_resources=false" in result.output
    assert time.perf_counter() - t0 < 10 and not (tmp_path / "trajectory.h5").exists()


def test_a_run_longer_than_its_slurm_job_is_refused_up_front(tmp_path, monkeypatch):
    """Inside a SLURM job the estimated run time is checked against the job's end: a default (200-frame)
    paper-scale run in a job with one second left is refused in one line, nothing written;
    check_resources=false lets a (tiny) run go ahead."""
    monkeypatch.setenv("SLURM_JOB_END_TIME", str(int(time.time()) + 1))
    result = runner.invoke(app, ["simulate", "fluid=numerical", f"out_dir={tmp_path / 'a'}"])
    assert result.exit_code == 2 and "SLURM job ends in" in result.output, result.output
    assert "check_resources=false" in result.output and not (tmp_path / "a" / "trajectory.h5").exists()
    result = runner.invoke(app, ["simulate", *TINY, "check_resources=false", f"out_dir={tmp_path / 'b'}"])
    assert result.exit_code == 0 and (tmp_path / "b" / "trajectory.h5").exists(), result.output


def test_the_time_estimate_scales_with_what_the_run_does():
    """The estimate grows linearly in frames and fish, with the refined grid as r^3 (cells and
    sub-steps), and a gradient run costs more than a forward one; the default numerical
    episode is in the calibration's range (300 frames ~ 6 s on the 2-core CPU)."""
    from fishsim.config import SimulateConfig
    from fishsim.resources import episode_seconds

    cfg = SimulateConfig()
    one = episode_seconds(cfg, 1, 300)
    assert 5 < one < 15
    assert episode_seconds(cfg, 4, 600) == pytest.approx(8 * one)
    refined = dataclasses.replace(cfg, fluid=dataclasses.replace(cfg.fluid, refinement=2))
    fluid_share = one - episode_seconds(dataclasses.replace(cfg, fluid=dataclasses.replace(cfg.fluid, model="none")), 1, 300)
    assert episode_seconds(refined, 1, 300) - one == pytest.approx(7 * fluid_share)
    assert episode_seconds(cfg, 1, 300, gradient=True) > 2 * one

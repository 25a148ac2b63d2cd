"""Interrupted training runs, with real signals sent to real `fishsim train-hydronet` processes:
SIGINT and SIGTERM finish the current iteration, save and exit 130 / 143; a resumed run (also
after SIGKILL, from the last periodic checkpoint) ends bit for bit where an uninterrupted run
ends, and its log.csv holds each iteration once."""

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

ITERATIONS = 100
TINY = ["batch_size=2", "net.hidden=4", "net.depth=2", "pool.size=4", "pool.H=16", "pool.W=32",
        "pool.fish_length=[0.04,0.05]", "pool.obstacle_cells=[2,3]", "val_every=25", "val_scenes=2", "val_steps=4",
        "threads=1", "compile_loss=false", "progress=false", "log_every=1", "ckpt_every=25",
        f"iterations={ITERATIONS}"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).resolve().parents[1])}


def _train(out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "fishsim", "train-hydronet", f"out_dir={out}", *TINY, *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=ENV)


def _finish(proc: subprocess.Popen, timeout: float = 120) -> tuple[int, str]:
    out, _ = proc.communicate(timeout=timeout)
    return proc.returncode, out.decode()


def _wait_for_rows(log: Path, rows: int, proc: subprocess.Popen, timeout: float = 60) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        if log.exists() and len(log.read_text().splitlines()) > rows:
            return
        time.sleep(0.05)
    raise AssertionError(f"training did not reach {rows} logged iterations: {_finish(proc)[1][-2000:]}")


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("straight")
    code, text = _finish(_train(out))
    assert code == 0, text[-2000:]
    return torch.load(out / "ckpt.pt", weights_only=False)


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGKILL, -9)])
def test_a_resumed_run_equals_an_uninterrupted_one(tmp_path, uninterrupted, sig, code):
    out = tmp_path / "run"
    proc = _train(out)
    _wait_for_rows(out / "log.csv", 35, proc)               # past the first periodic checkpoint (25)
    proc.send_signal(sig)
    got, text = _finish(proc)
    assert got == code, text[-2000:]
    stopped = torch.load(out / "ckpt.pt", weights_only=False)["iteration"]
    assert 25 <= stopped < ITERATIONS
    said = text
    got, text = _finish(_train(out, "resume=true"))
    assert got == 0, text[-2000:]
    resumed = torch.load(out / "ckpt.pt", weights_only=False)
    assert resumed["iteration"] == uninterrupted["iteration"] == ITERATIONS
    for name, tensor in uninterrupted["model"].items():
        assert torch.equal(resumed["model"][name], tensor), name
    assert resumed["pool"]["rng"] == uninterrupted["pool"]["rng"]
    assert torch.equal(resumed["pool"]["a"], uninterrupted["pool"]["a"])
    assert torch.equal(resumed["torch_rng"], uninterrupted["torch_rng"])
    iterations = [int(row["iteration"]) for row in csv.DictReader((out / "log.csv").open())]
    assert iterations == list(range(1, ITERATIONS + 1))      # each iteration once, none lost or repeated
    if sig != signal.SIGKILL:
        assert f"checkpoint of iteration {stopped} saved" in said, said[-2000:]

"""Training: exact resume, Ctrl-C, best model, loss decrease, config parsing, DDP (gloo)."""

import os
import signal
import socket
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from fishsim.fields import FluidState
from fishsim.fluid.hydronet import load_hydronet
from fishsim.fluid.hydronet.config import TrainConfig
from fishsim.fluid.hydronet.loss import hydronet_loss
from fishsim.fluid.hydronet.unet import HydroNet, HydroNetFluid
from fishsim.learn import train as T
from fishsim.learn.pool import ScenePool


@pytest.fixture
def cfg(tmp_path, tiny_net, tiny_pool):
    return TrainConfig(out_dir=str(tmp_path / "run"), iterations=6, batch_size=3, net=tiny_net, pool=tiny_pool,
                       bf16=False, channels_last=False, compile_loss=False, log_every=1, ckpt_every=3, ckpt_minutes=1e6,
                       val_every=3, val_scenes=2, val_steps=4, progress=False, seed=3)


def _weights(path):
    return torch.load(path, weights_only=False)["model"]


@pytest.mark.parametrize("fast", [False, True])
def test_resume_continues_exactly(cfg, tmp_path, fast):
    """6 iterations in one go == 3 iterations, stop, resume for 3 more (weights, pool, losses);
    also with the CPU training settings (bf16 autocast, channels_last)."""
    cfg = replace(cfg, bf16=fast, channels_last=fast)
    straight = T.run(cfg)
    half = replace(cfg, out_dir=str(tmp_path / "resumed"), iterations=3)
    T.run(half)
    resumed = T.run(replace(half, iterations=6, resume=True))
    assert resumed["iteration"] == straight["iteration"] == 6
    assert resumed["loss"] == straight["loss"]
    w1, w2 = _weights(tmp_path / "run" / "ckpt.pt"), _weights(tmp_path / "resumed" / "ckpt.pt")
    for k in w1:
        assert torch.equal(w1[k], w2[k]), k
    p1 = torch.load(tmp_path / "run" / "ckpt.pt", weights_only=False)["pool"]
    p2 = torch.load(tmp_path / "resumed" / "ckpt.pt", weights_only=False)["pool"]
    assert torch.equal(p1["a"], p2["a"]) and p1["rng"] == p2["rng"]
    lines = (tmp_path / "resumed" / "log.csv").read_text().splitlines()
    assert len(lines) == 1 + 6  # header + one row per iteration, no duplicates


def test_ema_averages_the_iterates_and_resumes_exactly(cfg, tmp_path, monkeypatch):
    """ema=d: after every step theta_avg <- d theta_avg + (1 - d) theta (the first step's weights
    as the start); validation sees the average, not the iterate; ckpt.pt keeps it, so 6 steps in
    one go and 3 + 3 resumed end with the same average."""
    d = 0.5
    cfg = replace(cfg, ema=d)
    run, net = T.build(cfg, 0, 1, torch.device("cpu"))
    expected = None
    for _ in range(3):
        T.train_step(run, cfg, net)
        theta = {k: v.detach().clone() for k, v in run.model.named_parameters()}
        expected = theta if expected is None else {k: d * expected[k] + (1 - d) * theta[k] for k in theta}
    averaged = dict(run.average.module.named_parameters())
    for k, v in expected.items():
        torch.testing.assert_close(averaged[k], v, rtol=0, atol=1e-7)
        assert not torch.equal(averaged[k], theta[k]) or v.abs().max() == 0
    seen = []
    monkeypatch.setattr(T, "validate", lambda model, c: seen.append(model) or -float(len(seen)))  # always better
    straight = T.run(cfg)
    assert seen and all(p.grad is None for m in seen for p in m.parameters())   # never the iterate (it has grads)
    half = replace(cfg, out_dir=str(tmp_path / "resumed"), iterations=3)
    T.run(half)
    T.run(replace(half, iterations=6, resume=True))
    a1 = torch.load(tmp_path / "run" / "ckpt.pt", weights_only=False)["average"]
    a2 = torch.load(tmp_path / "resumed" / "ckpt.pt", weights_only=False)["average"]
    assert straight["iteration"] == 6 and a1.keys() == a2.keys()
    for k in a1:
        assert torch.equal(a1[k], a2[k]), k
    best = torch.load(tmp_path / "resumed" / "best.pt", weights_only=False)["model"]
    assert all(torch.equal(best[k], a2["module." + k]) for k in best)      # the last validation's average
    shipped = torch.load(T.export_model(tmp_path / "resumed" / "ckpt.pt", tmp_path / "ship.pt", {}),
                         weights_only=False)["model"]                    # exported: the average, not the iterate
    assert shipped.keys() == best.keys() and all(torch.equal(shipped[k], a2["module." + k]) for k in shipped)


def test_trained_weights_on_a_fresh_pool_warm_it_first(cfg, tmp_path, monkeypatch):
    """init_from and a resumed compact checkpoint (no pool) age the new pool by the network
    (warm_pool steps at most) before training; a full checkpoint's pool, a run from scratch and
    warm_pool=0 are left as they are."""
    from fishsim.learn.pool import ScenePool

    calls = []
    monkeypatch.setattr(ScenePool, "warm", lambda self, step, steps, batch: calls.append((steps, batch)))
    cfg = replace(cfg, iterations=2, warm_pool=7)
    T.run(cfg)                                                              # from scratch
    T.run(replace(cfg, iterations=3, resume=True))                          # full checkpoint
    assert calls == []
    T.compact_checkpoint(tmp_path / "run" / "ckpt.pt", tmp_path / "compact" / "ckpt.pt")
    T.run(replace(cfg, out_dir=str(tmp_path / "compact"), iterations=4, resume=True))
    T.run(replace(cfg, out_dir=str(tmp_path / "fine"), init_from=str(tmp_path / "run" / "ckpt.pt")))
    T.run(replace(cfg, out_dir=str(tmp_path / "off"), init_from=str(tmp_path / "run" / "ckpt.pt"), warm_pool=0))
    assert calls == [(7, cfg.batch_size)] * 2
    run, _ = T.build(cfg, 0, 1, torch.device("cpu"))
    state, boundary, params = run.pool.ask(cfg.batch_size)[1:]
    before = {k: v.clone() for k, v in run.model.state_dict().items()}
    new = T.network_step(run, cfg)(state, boundary, params)
    assert new.a.shape == state.a.shape and not new.a.requires_grad and run.model.training
    assert all(torch.equal(before[k], v) for k, v in run.model.state_dict().items())   # BatchNorm's stats too


def test_freeze_norm_trains_the_map_inference_runs(cfg):
    """freeze_norm=true: a training step normalises by the running statistics (its forward is the
    eval-mode forward), leaves them as they were and still trains the weights, BatchNorm's scale
    and shift included; without it the step normalises by the batch and moves the statistics."""
    for frozen in (False, True):
        c = replace(cfg, freeze_norm=frozen)
        run, net = T.build(c, 0, 1, torch.device("cpu"))
        T.train_step(run, c, net)             # running statistics off their initial (0, 1)
        buffers = {k: v.clone() for k, v in run.model.named_buffers()}
        weights = {k: v.detach().clone() for k, v in run.model.named_parameters()}
        _, state, boundary, params = run.pool.ask(c.batch_size)
        out = T.network_forward(net, state, boundary, params, run.pool.grid, c.bf16).a
        run.model.eval()
        with torch.no_grad():
            inference = T.network_forward(net, state, boundary, params, run.pool.grid, c.bf16).a
        run.model.train()
        assert torch.equal(out, inference) == frozen
        T.train_step(run, c, net)
        moved = [k for k, v in run.model.named_buffers() if not torch.equal(v, buffers[k])]
        assert moved == [] if frozen else any("running_mean" in k for k in moved), moved
        bn = [k for k in weights if ".1.weight" in k or ".4.weight" in k]
        assert bn and all(not torch.equal(run.model.get_parameter(k), weights[k]) for k in bn)


def test_compact_checkpoint_resumes_model_and_optimiser(cfg, tmp_path):
    """A pool-less checkpoint (the one committed between sittings) is ~3x smaller and resumes
    the counters, weights and Adam state; training then goes on."""
    T.run(replace(cfg, iterations=3))
    full = tmp_path / "run" / "ckpt.pt"
    moved = T.compact_checkpoint(full, tmp_path / "next" / "ckpt.pt")
    assert moved.stat().st_size < full.stat().st_size and "pool" not in torch.load(moved, weights_only=False)
    c2 = replace(cfg, out_dir=str(tmp_path / "next"), iterations=3, resume=True)
    run, _ = T.build(c2, 0, 1, torch.device("cpu"))
    T.load_checkpoint(run, tmp_path / "next", 0)
    saved = torch.load(full, weights_only=False)
    assert run.iteration == 3 and run.opt.state_dict()["state"][0]["step"] == saved["optimizer"]["state"][0]["step"]
    assert all(torch.equal(v, saved["model"][k]) for k, v in run.model.state_dict().items())
    assert T.run(replace(c2, iterations=5))["iteration"] == 5


def _signalling_step(monkeypatch, at: int, times: int) -> None:
    """train_step sends this process ``times`` SIGINTs as iteration ``at`` + 1 begins."""
    real = T.train_step

    def step(run, c, net):
        if run.iteration == at:
            for _ in range(times):
                os.kill(os.getpid(), signal.SIGINT)
        return real(run, c, net)

    monkeypatch.setattr(T, "train_step", step)


def test_shipping_a_model_file_takes_its_runs_config_and_log_up_to_its_iteration(cfg, tmp_path):
    """ship(a model file the run kept): its weights become the asset, the config is the run's,
    the losses, wall time and log stop at the model's iteration, no optimiser state is left
    beside it (a stale ckpt.pt is removed) and training continues from the asset's weights."""
    import json

    from fishsim.learn.ship import ship

    T.run(replace(cfg, iterations=6, val_every=2))
    run_dir = Path(cfg.out_dir)
    kept = run_dir / "kept.pt"
    torch.save({**torch.load(run_dir / "best.pt", weights_only=False), "iteration": 4}, kept)
    (tmp_path / "val").mkdir()
    (tmp_path / "val" / "metrics.json").write_text(json.dumps({"summary": {}}))
    training = tmp_path / "training"
    training.mkdir()
    (training / "ckpt.pt").write_text("stale")
    lineage = [{"run": "x", "command": f"fishsim train-hydronet out_dir={run_dir} teacher=10 resume=true"}]
    meta = ship(kept, tmp_path / "val", lineage, asset=tmp_path / "hydronet.pt", training=training)
    assert meta["iterations"] == meta["iterations_last_run"] == 4 and meta["train_config"]["batch_size"] == 3
    assert meta["final_losses"]["iterations_averaged"] == "1-4"
    log = (training / "log.csv").read_text().splitlines()
    assert log[0].startswith("iteration") and [int(r.split(",")[0]) for r in log[1:]] == [1, 2, 3, 4]
    assert meta["wall_time_s"] == float(log[-1].split(",")[1])
    assert not (training / "ckpt.pt").exists()
    assert "resume" not in meta["continue"] and f"init_from={tmp_path / 'hydronet.pt'} freeze_norm=true" in meta["continue"]
    shipped = load_hydronet(tmp_path / "hydronet.pt")
    for k, v in torch.load(kept, weights_only=False)["model"].items():
        assert torch.equal(shipped.state_dict()[k], v), k


def test_a_stop_signal_finishes_the_iteration_then_saves(cfg, monkeypatch):
    """SIGINT as an iteration begins: that iteration completes, its end is checkpointed, and the
    run returns interrupted (the CLI then exits 130)."""
    _signalling_step(monkeypatch, at=1, times=1)
    out = T.run(cfg)
    assert out["interrupted"] == "SIGINT" and out["saved"] and out["iteration"] == 2
    assert torch.load(os.path.join(cfg.out_dir, "ckpt.pt"), weights_only=False)["iteration"] == 2


def test_a_second_signal_stops_at_once_keeping_the_last_checkpoint(cfg, monkeypatch):
    """Two SIGINTs: the second raises mid-iteration, so nothing half-done is saved; ckpt.pt stays
    the periodic one of iteration 3 (ckpt_every=3), from which a resume is exact."""
    _signalling_step(monkeypatch, at=4, times=2)
    out = T.run(cfg)
    assert out["interrupted"] == "SIGINT" and not out["saved"]
    assert torch.load(os.path.join(cfg.out_dir, "ckpt.pt"), weights_only=False)["iteration"] == 3


def test_sigterm_saves_and_exits(cfg, tmp_path):
    """``kill PID`` of a background run (SIGINT ignored by the shell): checkpoint, then exit 143."""
    import subprocess
    import sys
    import time

    code = ("import signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
            "from fishsim.cli import main; sys.argv[0] = 'fishsim'; main()\n")
    args = [f"out_dir={tmp_path / 'bg'}", "iterations=100000", "batch_size=2", "net.hidden=4", "net.depth=2",
            "pool.size=4", "pool.H=16", "pool.W=32", "pool.fish_length=[0.04,0.05]", "pool.obstacle_cells=[2,3]",
            "val_every=1000000", "threads=1", "compile_loss=false", "progress=false"]
    proc = subprocess.Popen([sys.executable, "-c", code, "train-hydronet", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    log = tmp_path / "bg" / "log.csv"
    deadline = time.time() + 60
    while time.time() < deadline and (not log.exists() or len(log.read_text().splitlines()) < 3):
        time.sleep(0.2)
    proc.terminate()
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 143, out.decode()[-2000:]          # saved, then the stop is reported
    assert b"interrupted, checkpoint saved" in out and b"SIGTERM" in out
    assert torch.load(tmp_path / "bg" / "ckpt.pt", weights_only=False)["iteration"] >= 2


def test_best_model_loads_as_fluid_model(cfg):
    """best.pt holds the lowest validation loss and loads into a working HydroNetFluid."""
    out = T.run(cfg)
    best = torch.load(os.path.join(cfg.out_dir, "best.pt"), weights_only=False)
    assert best["val"] == out["best_val"] <= out["last_val"]
    assert best["training_range"] == {"rho": list(cfg.pool.rho), "mu": list(cfg.pool.mu), "dx": cfg.pool.dx,
                                      "h": cfg.pool.h, "scene_cells": [cfg.pool.H, cfg.pool.W]}
    fluid = HydroNetFluid(load_hydronet(os.path.join(cfg.out_dir, "best.pt")), cfg.pool.grid)
    _, state, boundary, params = ScenePool(cfg.pool, 2, seed=5).ask(2)
    new = fluid.step(state, boundary, params)
    assert torch.isfinite(new.a).all() and new.p.shape == state.p.shape
    assert os.path.exists(os.path.join(cfg.out_dir, "log.csv")) and os.path.isdir(os.path.join(cfg.out_dir, "tb"))


def test_training_lowers_the_loss_on_a_fixed_scene(cfg):
    """40 Adam steps on pool rollouts lower the loss of a fixed held-out batch (train-mode BN)."""
    torch.manual_seed(0)
    c = replace(cfg, batch_size=4, lr=3e-3)
    run, net = T.build(c, 0, 1, torch.device("cpu"))
    _, state, boundary, params = ScenePool(c.pool, 4, seed=123).ask(4)
    held_out = FluidState(state.a, state.p)

    def loss():
        with torch.no_grad():
            new = FluidState(*run.model(held_out.a, held_out.p, boundary.mask, boundary.velocity, params.rho,
                                        params.mu, c.pool.dx, params.h))
        return hydronet_loss(held_out, new, boundary, params, c.pool.grid).objective.item()

    before = loss()
    for _ in range(40):
        T.train_step(run, c, net)
    assert loss() < before - 1.0  # log-loss: the residual shrinks by e^1 or more


def test_init_from_loads_weights_only(cfg, tmp_path):
    """init_from: a new run (other crop size) starts from trained weights, counters at zero."""
    T.run(replace(cfg, iterations=3))
    bigger = replace(cfg.pool, H=32, W=64)
    c2 = replace(cfg, out_dir=str(tmp_path / "ft"), pool=bigger, iterations=0,
                 init_from=os.path.join(cfg.out_dir, "best.pt"))
    out = T.run(c2)
    assert out["iteration"] == 0
    w1, w2 = _weights(os.path.join(cfg.out_dir, "best.pt")), _weights(tmp_path / "ft" / "ckpt.pt")
    assert all(torch.equal(w1[k], w2[k]) for k in w1)


def test_cli_config_composes_and_validates():
    """`fishsim train-hydronet` overrides reach the TrainConfig (ranges as tuples); bad values fail."""
    from fishsim.config import load_config
    from fishsim.errors import ConfigError

    c = T.train_config(load_config("train-hydronet", ["net.hidden=8", "pool.H=32", "pool.rho=[10,50]",
                                                      "net.condition=true", "bf16=false", "lr=0.0005"]))
    assert c.net.hidden == 8 and c.pool.H == 32 and c.pool.rho == (10.0, 50.0) and not c.bf16 and c.lr == 5e-4
    assert c.net.condition and c == T.train_config(c)
    for bad in (["nonsense=1"], ["pool.rho=[10,50]"], ["lr=-1"], ["pool.size=4", "batch_size=8"], ["pool.mu=[1e-3,1e-4]"],
                ["pool.fish_speed=[-0.1,0.2]"]):
        with pytest.raises(ConfigError):
            load_config("train-hydronet", bad)
    d = T.train_config({"batch_size": 4, "net": {"hidden": 8}, "pool": {"H": 32, "mu": [1.25e-4, 1e-3]}})
    assert d.batch_size == 4 and d.net.hidden == 8 and d.net.depth == 4 and d.pool.mu == (1.25e-4, 1e-3)
    with pytest.raises(ValueError):
        T.train_config({"pool": {"nonsense": 1}})


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_worker(rank: int, world: int, port: int, cfg: TrainConfig) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    T.run(cfg)


def test_ddp_gloo_two_processes(cfg, tmp_path):
    """torch DDP on CPU (gloo), 2 processes, 3 iterations: each rank steps its own pool, the
    averaged gradients keep the weights identical on both ranks, and they did change."""
    import torch.multiprocessing as mp

    c = replace(cfg, iterations=3, ckpt_every=3, val_every=100)
    mp.spawn(_ddp_worker, args=(2, _free_port(), c), nprocs=2, join=True)
    ck = torch.load(tmp_path / "run" / "ckpt.pt", weights_only=False)
    r1 = torch.load(tmp_path / "run" / "ckpt_rank1.pt", weights_only=False)
    assert ck["iteration"] == r1["iteration"] == 3
    assert not torch.equal(ck["pool"]["a"], r1["pool"]["a"])  # different scenes per rank
    names = [n for n, _ in HydroNet(c.net).named_parameters()]
    for n in names:
        torch.testing.assert_close(ck["model"][n], r1["model"][n], rtol=1e-6, atol=1e-7)
    torch.manual_seed(c.seed)
    fresh = HydroNet(c.net).state_dict()
    assert any(not torch.equal(ck["model"][n], fresh[n]) for n in names)


def test_resume_without_a_checkpoint_is_an_error(cfg):
    from dataclasses import replace

    from fishsim.errors import ConfigError

    with pytest.raises(ConfigError, match="no ckpt.pt to continue"):
        T.run(replace(cfg, resume=True))


def test_init_from_a_foreign_or_misshapen_file_is_one_line(cfg, tmp_path):
    from dataclasses import replace

    from fishsim.errors import ConfigError, InputFileError
    from fishsim.fluid.factory import SHIPPED_HYDRONET

    junk = tmp_path / "junk.pt"
    junk.write_text("# not a model")
    with pytest.raises(InputFileError, match="not a readable HydroNet"):
        T.run(replace(cfg, init_from=str(junk)))
    with pytest.raises(ConfigError, match=r"do not fit this network: tensor '.*' is \[16"):
        T.run(replace(cfg, init_from=str(SHIPPED_HYDRONET)))


def test_resume_after_an_architecture_change_is_one_line(cfg):
    """A checkpoint of another network shape: a ConfigError naming the first tensor that differs,
    not a torch traceback."""
    from fishsim.errors import FishsimError

    T.run(replace(cfg, iterations=3))
    wider = replace(cfg, net=replace(cfg.net, hidden=cfg.net.hidden + 4), iterations=6, resume=True)
    with pytest.raises(FishsimError) as err:
        T.run(wider)
    assert "\n" not in str(err.value) and "do not fit this network" in str(err.value)
    assert "set net.* to match" in str(err.value)


def test_teacher_training_moves_the_network_towards_the_solver(cfg):
    """With teacher > 0 each step also fits the numerical solver's step from the same state:
    40 Adam steps lower L_t on a held-out batch, and the log records L_t."""
    from fishsim.fluid.hydronet.loss import teacher_loss

    torch.manual_seed(0)
    c = replace(cfg, batch_size=4, lr=3e-3, teacher=10.0)
    run, net = T.build(c, 0, 1, torch.device("cpu"))
    assert run.teacher is not None
    _, state, boundary, params = ScenePool(c.pool, 4, seed=123).ask(4)
    target = run.teacher.step(state, boundary, params)

    def error():
        with torch.no_grad():
            new = FluidState(*run.model(state.a, state.p, boundary.mask, boundary.velocity, params.rho,
                                        params.mu, c.pool.dx, params.h))
        return teacher_loss(new, target, params, c.pool.grid).mean().item()

    before = error()
    for _ in range(40):
        terms = T.train_step(run, c, net)
    assert terms.teacher is not None and torch.all(terms.total >= c.teacher * terms.teacher)
    assert error() < 0.5 * before


def test_the_teacher_is_the_simulate_default_numerical_fluid(cfg):
    """The teacher steps as `fishsim simulate`'s numerical fluid does (the joint stage, its
    sub-steps and CFL bound), the fluid the frequency study's references are measured with."""
    from fishsim.config import NumericalConfig
    from fishsim.fluid.factory import numerical_stepping

    teacher = T.make_teacher(replace(cfg, teacher=1.0))
    assert teacher.implicit and teacher.refinement == 1
    assert {k: getattr(teacher, k) for k in numerical_stepping(NumericalConfig())} == numerical_stepping(NumericalConfig())


def test_a_batch_the_teacher_cannot_step_is_replaced(cfg):
    """A SimulationBlowUp in the teacher's rollout, or a target faster than RUNAWAY max_speed,
    drops the batch (its scenes reset to rest at t = 0) and draws another; the iteration then
    runs once. TEACHER_RETRIES failures in a row raise."""
    from fishsim.errors import SimulationBlowUp

    torch.manual_seed(0)
    c = replace(cfg, batch_size=2, teacher=1.0)
    run, net = T.build(c, 0, 1, torch.device("cpu"))
    run.pool.a.fill_(1e-6)
    step, calls = run.teacher.step, []

    def flaky(state, boundary, params):
        calls.append(1)
        out = step(state, boundary, params)
        if len(calls) == 1:
            raise SimulationBlowUp("test")
        if len(calls) == 2:
            return FluidState(out.a * 1e6, out.p)        # a runaway target
        return out

    run.teacher.step = flaky
    terms = T.train_step(run, c, net)
    assert len(calls) == 3 and run.iteration == 1 and torch.isfinite(terms.objective)
    reset = [i for i, s in enumerate(run.pool.scenes) if s.t == 0.0 and run.pool.a[i].abs().max() == 0]
    assert len(reset) >= 2                                   # fresh scenes at rest in place of the dropped
    run.teacher.step = lambda *args: (_ for _ in ()).throw(SimulationBlowUp("always"))
    with pytest.raises(SimulationBlowUp):
        T.train_step(run, c, net)


def test_an_unrolled_step_advances_its_scenes_and_follows_the_solvers_rollout(cfg):
    """unroll=3: each iteration steps its scenes 3 h forward (the pool's scene clocks) and its
    teacher targets are the solver's own 3-step rollout from the start state; unroll=1 is the
    one-step training."""
    torch.manual_seed(0)
    c = replace(cfg, batch_size=2, teacher=1.0, unroll=3)
    run, net = T.build(c, 0, 1, torch.device("cpu"))
    before = [s.t for s in run.pool.scenes]
    terms = T.train_step(run, c, net)
    moved = [round((s.t - t0) / c.pool.h) for s, t0 in zip(run.pool.scenes, before)]
    assert sorted(moved)[-2:] == [3, 3] and sorted(moved)[:-2] == [0] * (len(moved) - 2)
    assert terms.teacher.shape == (2,) and torch.isfinite(terms.objective)
    with pytest.raises(Exception, match="unroll must be >= 1"):
        replace(cfg, unroll=0).validate()


def test_a_refined_teacher_steps_its_own_fine_rollout_on_fine_boundaries(cfg):
    """teacher_refinement=2: the teacher is the r = 2 solver; it reads the scenes' bodies sampled
    on its fine cells, keeps its own rollout fine across the unrolled steps, and its targets are
    restricted to the training grid (the pool's states and L_t stay there)."""
    from fishsim.fluid.numerical import RefinedState

    torch.manual_seed(0)
    c = replace(cfg, batch_size=2, teacher=1.0, unroll=3, teacher_refinement=2)
    run, net = T.build(c, 0, 1, torch.device("cpu"))
    assert run.teacher.refinement == 2
    calls, step = [], run.teacher.step

    def spy(state, boundary, params):
        out = step(state, boundary, params)
        calls.append((state, boundary.mask.shape, out))
        return out

    run.teacher.step = spy
    terms = T.train_step(run, c, net)
    H, W = c.pool.H, c.pool.W
    assert [shape for _, shape, _ in calls] == [(2, 1, 2 * H, 2 * W)] * 3
    assert not isinstance(calls[0][0], RefinedState)                       # the pool's state, prolonged
    for (state, _, _), (_, _, previous) in zip(calls[1:], calls[:-1]):
        assert state is previous and state.fine_a.shape[-2:] == (2 * H + 1, 2 * W + 1)
    assert calls[-1][2].a.shape[-2:] == (H + 1, W + 1) and torch.isfinite(terms.objective)
    with pytest.raises(Exception, match="teacher_refinement"):
        replace(cfg, teacher_refinement=0).validate()


def test_energy_term_adds_to_the_teachers_objective_and_its_log_column(cfg, tmp_path):
    """energy=w (with a teacher): L = L_p + L_b + teacher L_t + w L_E, L_E logged; without a
    teacher the config is refused; a log.csv from before the L_E column is resumed with the column
    added (nan in its old rows)."""
    import csv

    from fishsim.errors import ConfigError

    torch.manual_seed(0)
    c = replace(cfg, batch_size=2, teacher=1.0, energy=50.0, iterations=3)
    run, net = T.build(c, 0, 1, torch.device("cpu"))
    terms = T.train_step(run, c, net)
    assert terms.energy.shape == (2,) and torch.all(terms.energy >= 0)
    torch.testing.assert_close(terms.total, c.beta * terms.momentum + c.gamma * terms.boundary
                               + c.teacher * terms.teacher + c.energy * terms.energy)
    with pytest.raises(ConfigError, match="energy must be >= 0 and needs the solver's step"):
        replace(cfg, energy=1.0).validate()
    T.run(c)
    log = tmp_path / "run" / "log.csv"
    rows = list(csv.DictReader(log.open()))
    assert all(float(r["L_E"]) >= 0 for r in rows)
    old = [line.rsplit(",", 1)[0] for line in log.read_text().splitlines()]      # the 9-column log of before
    log.write_text("\n".join(old) + "\n")
    T.run(replace(c, iterations=5, resume=True))
    rows = list(csv.DictReader(log.open()))
    assert [r["L_E"] for r in rows[:3]] == ["nan"] * 3 and float(rows[-1]["L_E"]) >= 0 and len(rows) == 5
    log.write_text("step,error\n1,0.5\n")                                    # some other program's log
    with pytest.raises(ConfigError, match="holds another run's log"):
        T.run(replace(c, iterations=6, resume=True))


def test_swim_check_keeps_the_weights_that_swim_closest_to_the_numerical_fluid(cfg):
    """swim_every=3: at iterations 3 and 6 the network (the shipped one, fine-tuned a few steps)
    swims the frequency study (2 fish, 3 frames, the default tank and fish); swim.csv holds each
    error max |d / d_ref - 1| against the numerical fluid's displacements (swim_reference.json,
    computed once), best_swim.pt the weights of the lower one, and the checkpoint its value."""
    import csv
    import json
    import math

    from fishsim.fluid.factory import SHIPPED_HYDRONET
    from fishsim.fluid.hydronet.config import NetConfig
    from fishsim.learn import swim_check

    cfg = replace(cfg, net=NetConfig(hidden=16), init_from=str(SHIPPED_HYDRONET), lr=1e-4,
                  swim_every=3, swim_frames=3, swim_frequencies=(4.0, 6.0))
    T.run(cfg)
    out = Path(cfg.out_dir)
    ref = json.loads((out / "swim_reference.json").read_text())["displacement_mm"]
    rows = list(csv.DictReader((out / "swim.csv").open()))
    assert [int(r["iteration"]) for r in rows] == [3, 6]
    errors = [float(r["error"]) for r in rows]
    for r, e in zip(rows, errors):
        d = [float(r["d_4Hz_mm"]), float(r["d_6Hz_mm"])]
        assert e == pytest.approx(swim_check.swim_error(d, ref)) and math.isfinite(e)
    best = torch.load(out / "best_swim.pt", weights_only=False)
    assert best["val"] == min(errors) and best["iteration"] == [3, 6][errors.index(min(errors))]
    assert torch.load(out / "ckpt.pt", weights_only=False)["best_swim"] == min(errors)
    load_hydronet(out / "best_swim.pt")                       # a model file like best.pt


def test_swim_reference_is_recomputed_when_the_study_or_its_refinement_changes(cfg, tmp_path, monkeypatch):
    """swim_reference.json is the numerical fluid's at ``swim_refinement`` (fluid.refinement=r),
    reused while the study is the same (a file from before the key counts as r = 1), recomputed
    when the frames, frequencies or refinement change."""
    import json

    from fishsim.learn import swim_check

    runs = []
    monkeypatch.setattr(swim_check, "_episode", lambda overrides, c: runs.append(overrides) or [float(len(runs))] * 2)
    c = replace(cfg, swim_frames=3, swim_frequencies=(4.0, 6.0))
    assert swim_check.reference(tmp_path, c) == [1.0, 1.0]
    assert runs[-1] == ["fluid=numerical", "fluid.refinement=1"]
    old = json.loads((tmp_path / "swim_reference.json").read_text())
    del old["refinement"]
    (tmp_path / "swim_reference.json").write_text(json.dumps(old))
    assert swim_check.reference(tmp_path, c) == [1.0, 1.0] and len(runs) == 1
    assert swim_check.reference(tmp_path, replace(c, swim_refinement=2)) == [2.0, 2.0]
    assert runs[-1] == ["fluid=numerical", "fluid.refinement=2"]
    assert swim_check.reference(tmp_path, replace(c, swim_refinement=2)) == [2.0, 2.0] and len(runs) == 2
    assert swim_check.reference(tmp_path, replace(c, swim_refinement=2, swim_frames=4)) == [3.0, 3.0]


def test_bf16_auto_is_on_only_where_it_is_fast(tmp_path):
    """bf16=auto: on a CPU with AMX (its ``amx_bf16`` flag) bfloat16, elsewhere float32 (without
    AMX the U-Net runs ~10x slower in bf16); true and false are kept as given."""
    from fishsim.fluid.hydronet.config import cpu_has_amx_bf16, resolve_bf16

    amx, avx2 = tmp_path / "amx", tmp_path / "avx2"
    amx.write_text("processor\t: 0\nflags\t\t: fpu sse avx2 avx512f amx_bf16 amx_tile\n")
    avx2.write_text("processor\t: 0\nflags\t\t: fpu sse avx2 fma\n")
    assert cpu_has_amx_bf16(str(amx)) and not cpu_has_amx_bf16(str(avx2))
    assert not cpu_has_amx_bf16(str(tmp_path / "missing"))
    assert resolve_bf16("auto", "cpu") == cpu_has_amx_bf16()
    assert resolve_bf16(True, "cpu") is True and resolve_bf16(False, "cuda") is False
    assert TrainConfig().bf16 == "auto"


def test_pressure_dropout_zeroes_the_inputs_pressure_of_some_samples_only(cfg, monkeypatch):
    """pressure_dropout=q: each unrolled step hands the network p_t = 0 in about a share q of its
    samples and the true p_t in the rest (the loss's own p_t untouched); q = 0 hands it over as it
    is; a probability of 1 or more is refused."""
    seen = []
    forward = T.network_forward
    monkeypatch.setattr(T, "network_forward", lambda net, state, *a: seen.append(state.p.clone()) or forward(net, state, *a))
    state = FluidState(torch.zeros(64, 1, 5, 5), torch.ones(64, 1, 4, 4))
    assert T.dropped_pressure(state, 0.0) is state
    torch.manual_seed(0)
    zeroed = (T.dropped_pressure(state, 0.5).p.flatten(1).amax(1) == 0).float().mean().item()
    assert 0.3 < zeroed < 0.7
    c = replace(cfg, batch_size=3, unroll=2, pressure_dropout=0.9)
    run, net = T.build(c, 0, 1, torch.device("cpu"))
    run.pool.p += 1.0                                          # a nonzero pressure in every stored scene
    torch.manual_seed(1)
    T.train_step(run, c, net)
    first = seen[0].flatten(1).abs().amax(1)
    assert len(seen) == 2 and ((first == 0) | (first == 1)).all() and (first == 0).any()
    with pytest.raises(Exception, match="pressure_dropout"):
        replace(cfg, pressure_dropout=1.0).validate()


def test_the_pressure_value_term_needs_a_teacher(cfg):
    """teacher_pressure weighs a term of L_t: without the solver's step it is refused (one line)."""
    replace(cfg, teacher=1.0, teacher_pressure=1.0).validate()
    with pytest.raises(Exception, match="teacher_pressure"):
        replace(cfg, teacher=0.0, teacher_pressure=1.0).validate()

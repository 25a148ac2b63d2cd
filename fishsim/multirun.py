"""Sweeps: ``fishsim <command> -m key=a,b other=x,y`` runs one job per combination through Hydra's
multirun, with its sweepers and launchers:

    hydra/launcher=basic (default)      jobs one after another in this process
    hydra/launcher=joblib               parallel local processes (hydra.launcher.n_jobs=N)
    hydra/launcher=submitit_slurm       one SLURM job each (hydra.launcher.partition=..., timeout_min=...)
    hydra/launcher=submitit_local       submitit's local executor

(joblib and submitit come with the optional ``sweep`` extra: ``pip install -e '.[sweep]'``).

Folders follow Hydra: ``multirun/<date>/<time>/<job number>/`` (``hydra.sweep.dir`` and
``hydra.sweep.subdir`` change them), each job's outputs and Hydra's ``.hydra/`` record in its
folder, and its summary in ``summary.json`` with its overrides and how it ended (a job that
fails on its input or blows up is recorded as failed; the others carry on). When the sweep ends,
``summary.csv`` in the sweep folder collects every job's summary, one row per job; the command
exits 2 if any job failed.
"""

from __future__ import annotations

import csv
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

from fishsim.errors import ConfigError, FishsimError

SUMMARY = "summary.json"


class SweepFailed(FishsimError):
    """Some jobs of a sweep failed (the others completed and are collected)."""


def first_of_each_sweep(overrides: list[str]) -> list[str]:
    """The overrides with every sweep (a,b / range(...) / choice(...)) reduced to its first value
    and Hydra's own keys left out: one job's overrides, to check the config before launching."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(overrides)
    out = []
    for o, text in zip(parsed, overrides):
        key = o.get_key_element()
        if key.lstrip("+~").startswith(("hydra.", "hydra/")) or key in ("hydra",):
            continue
        if o.is_sweep_override():
            out.append(f"{key}={next(iter(o.sweep_string_iterator()))}")
        else:
            out.append(text)
    return out


def sweep(command: str, overrides: list[str], run: Callable) -> Path:
    """Run ``command``'s ``run(cfg)`` for every job of the sweep ``overrides`` (module docstring);
    returns the sweep folder. ConfigError for a config that is wrong for every job (checked on
    the first combination before anything is launched)."""
    import hydra

    from fishsim.config import config_dir, load_config

    load_config(command, first_of_each_sweep(overrides))          # fail fast, one line
    if any(o.split("=", 1)[0].lstrip("+~") in ("out_dir", "hydra.run.dir") for o in overrides):
        raise ConfigError("a sweep writes to hydra.sweep.dir (default multirun/<date>/<time>), one folder per "
                          "job: drop out_dir=")
    given = [o for o in overrides if o.split("=", 1)[0] == "hydra.sweep.dir"]
    folder = Path(given[-1].split("=", 1)[1]) if given else Path("multirun") / time.strftime("%Y-%m-%d/%H-%M-%S")
    extra = ([] if given else [f"hydra.sweep.dir={folder}"]) + [f"hydra.job.name={command}"]

    @hydra.main(config_path=config_dir(), config_name=command, version_base="1.3")
    def job(raw) -> None:
        run_job(command, raw, run)

    argv = sys.argv
    sys.argv = [f"fishsim-{command}", *overrides, *extra, "--multirun"]
    try:
        job()
    except SystemExit as stop:                   # Hydra reports its own errors and exits
        if stop.code:
            raise ConfigError(f"the sweep stopped (Hydra exit {stop.code}); see the message above") from None
    finally:
        sys.argv = argv
    rows = collect(folder)
    failed = [str(r["job"]) for r in rows if r.get("status") != "complete"]
    if failed:
        raise SweepFailed(f"{len(failed)} of {len(rows)} jobs failed (jobs {', '.join(failed)}); the others "
                          f"completed; every job's status is in {folder / 'summary.csv'}")
    return folder


def run_job(command: str, raw, run: Callable) -> dict:
    """One job of a sweep in Hydra's job folder: the command's run, its summary (or failure)
    written to summary.json there."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    from fishsim.config import to_dataclass
    from fishsim.io.outdir import release_locks

    hc = HydraConfig.get()
    folder = Path(hc.runtime.output_dir)
    record = {"job": hc.job.num, "overrides": " ".join(hc.overrides.task), "status": "complete"}
    try:
        raw = OmegaConf.merge(raw, {"out_dir": str(folder)})
        summary = run(to_dataclass(command, raw)) or {}
        record.update(flat(summary))
    except FishsimError as err:
        record["status"] = f"failed: {err}"
        print(f"job {hc.job.num} failed: {err}", file=sys.stderr)
    finally:
        release_locks()
    folder.mkdir(parents=True, exist_ok=True)
    (folder / SUMMARY).write_text(json.dumps(record, indent=1, default=str))
    return record


def flat(summary: dict, prefix: str = "") -> dict:
    """A command's summary as one CSV row: scalars kept, nested dicts' keys joined with dots
    (``{"adam": {"best": {"frequency": 6.1}}}`` -> ``adam.best.frequency``), anything else dropped."""
    row = {}
    for k, v in summary.items():
        if isinstance(v, dict):
            row.update(flat(v, f"{prefix}{k}."))
        elif isinstance(v, (int, float, str, bool)):
            row[f"{prefix}{k}"] = v
    return row


def collect(folder: Path) -> list[dict]:
    """``summary.csv`` in the sweep folder: every job's summary.json, one row each, by job number;
    returns the rows."""
    rows = [json.loads(p.read_text()) for p in Path(folder).rglob(SUMMARY)]
    rows.sort(key=lambda r: r.get("job", 0))
    keys = list(dict.fromkeys(k for r in rows for k in r))
    path = Path(folder) / "summary.csv"
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    return rows

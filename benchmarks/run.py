"""`make bench`: run every benchmark module's ``run() -> dict`` and write the results as JSON
and as a Markdown table (benchmarks/results.json, benchmarks/results.md), so numbers can be
compared run to run.  Usage: ``python -m benchmarks.run [name ...]`` (default: all)."""

from __future__ import annotations

import importlib
import json
import platform
import sys
import time
from pathlib import Path

import numba
import torch

from fishsim.resources import cpu_fields, cpu_flags

SUITES = ["bench_solid", "bench_fluid", "bench_hydronet", "bench_rollout", "bench_render"]
HERE = Path(__file__).parent


VECTOR_FLAGS = ("avx2", "avx512f", "avx512_bf16", "amx_bf16")
"""The CPU features the timings depend on most: the solid's packs (AVX-512: one register a pack)
and HydroNet in bf16 (~2x faster than fp32 with AVX512-BF16 or AMX, ~10x slower without)."""


def machine() -> dict:
    """What the numbers were measured on (the CPU, its vector features among VECTOR_FLAGS)."""
    fields = cpu_fields()
    cpu, flags = fields.get("model name") or platform.processor() or platform.machine(), cpu_flags()
    return {"cpu": cpu, "cpu_features": [f for f in VECTOR_FLAGS if f in flags],
            "torch_threads": torch.get_num_threads(), "numba_threads": numba.get_num_threads(),
            "torch": torch.__version__,
            "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
            "date": time.strftime("%Y-%m-%d %H:%M")}


def to_markdown(results: dict) -> str:
    lines = ["# fishsim benchmarks\n"]
    machines = results.get("machines", {})
    for suite, rows in results["suites"].items():
        lines += [f"## {suite}\n", f"Machine: {machines.get(suite, results.get('machine'))}\n",
                  "| quantity | value |", "|---|---|"]
        for key, value in _flatten(rows):
            lines.append(f"| {key} | {value:.4g} |" if isinstance(value, float) else f"| {key} | {value} |")
        lines.append("")
    return "\n".join(lines)


def _flatten(d: dict, prefix: str = ""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _flatten(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def main(names: list[str]) -> None:
    """Run the named suites (default: all). Naming suites updates just those in an existing
    results.json (each suite records the machine and threads it ran with). Every suite starts at the machine's default torch thread count (one suite
    changing it does not leak into the next)."""
    path = HERE / "results.json"
    results = {"machines": {}, "suites": {}}
    if names and path.exists():           # the other suites keep their numbers and the machine they ran on
        earlier = json.loads(path.read_text())
        results["suites"] = earlier["suites"]
        results["machines"] = earlier.get("machines") or dict.fromkeys(earlier["suites"], earlier.get("machine"))
    threads = torch.get_num_threads()
    for name in names or SUITES:
        module = importlib.import_module(f"benchmarks.{name}")
        print(f"== {name}", flush=True)
        torch.set_num_threads(threads)
        t0 = time.perf_counter()
        results["machines"][name] = machine()
        results["suites"][name] = module.run()
        print(json.dumps(results["suites"][name], indent=1), f"({time.perf_counter() - t0:.0f} s)", flush=True)
        path.write_text(json.dumps(results, indent=1))  # after every suite: a later failure keeps these
        (HERE / "results.md").write_text(to_markdown(results))
    print(f"wrote {HERE / 'results.json'} and {HERE / 'results.md'}")


if __name__ == "__main__":
    main(sys.argv[1:])

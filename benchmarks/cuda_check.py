"""CPU against CUDA: the full-scale episode's objective and gradient on each device.

    python -m benchmarks.cuda_check --devices cpu cuda             # both fluids, float32 and float64
    python -m benchmarks.cuda_check --devices cuda --frames 100 --out outputs/cuda.json

For each fluid (numerical, HydroNet with its default recovered pressure) and fluid precision
(float32, the default, and float64): J (the head's x displacement after ``--frames`` frames, m)
and dJ/d(frequency) by autograd through the checkpointed episode at ``--frequency`` Hz, on the
default tank and fish. On CUDA, HydroNet in float32 runs twice: with TF32 off (fishsim's setting) and with
TF32 on for convolutions and matrix products (PyTorch's cuDNN default), to show what TF32 does to
HydroNet's gradient. Rows of several runs (``--merge`` other runs' JSON) are compared against the
CPU row of the same fluid and precision. Prints a Markdown table and writes --out (JSON).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from benchmarks.gradcheck import autograd_at
from benchmarks.table import markdown_table


def run(fluid: str, dtype: str, device: str, frames: int, frequency: float, tf32: bool = False) -> dict:
    """One gradient evaluation: J [m], dJ/df [m/Hz] and the wall time of forward + backward."""
    from fishsim.config import load_config
    from fishsim.optimize.problem import Problem, Space

    cfg = load_config("optimize", [f"fluid={fluid}", f"fluid.dtype={dtype}", f"device={device}", f"frames={frames}",
                                   "params.frequency.lower=0.5", "params.frequency.upper=20"])
    space = Space(list(cfg.params), list(cfg.params.values()))
    problem = Problem(cfg, space, cfg.objective)
    if device.startswith("cuda"):
        torch.backends.cudnn.allow_tf32 = tf32
        torch.backends.cuda.matmul.allow_tf32 = tf32
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    J, dJ_df = autograd_at(problem, space, frequency)
    seconds = time.perf_counter() - t0
    return {"fluid": fluid, "dtype": dtype, "device": device, "tf32": tf32, "frames": frames, "frequency": frequency,
            "J": J, "dJ_df": dJ_df, "seconds": seconds,
            "name": torch.cuda.get_device_name() if device.startswith("cuda") else "cpu"}


def compare(rows: list[dict]) -> list[dict]:
    """Each row's relative difference in J and dJ/df from the CPU row of its fluid and precision."""
    cpu = {(r["fluid"], r["dtype"]): r for r in rows if r["device"] == "cpu"}
    for r in rows:
        ref = cpu.get((r["fluid"], r["dtype"]))
        r["J_vs_cpu"] = (r["J"] - ref["J"]) / abs(ref["J"]) if ref else None
        r["grad_vs_cpu"] = (r["dJ_df"] - ref["dJ_df"]) / abs(ref["dJ_df"]) if ref else None
    return rows


def markdown(rows: list[dict]) -> str:
    pct = lambda v: "" if v is None else f"{100 * v:+.3g} %"
    columns = ["fluid", "precision", "device", "TF32", "J [mm]", "dJ/df [mm/Hz]", "J vs CPU", "dJ/df vs CPU",
               "forward + backward [s]"]
    return markdown_table(columns, [[r["fluid"], r["dtype"], r["name"], "on" if r["tf32"] else "off",
                                     f"{1e3 * r['J']:.5g}", f"{1e3 * r['dJ_df']:.5g}", pct(r["J_vs_cpu"]),
                                     pct(r["grad_vs_cpu"]), f"{r['seconds']:.1f}"] for r in rows])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", nargs="+", default=["cpu", "cuda"])
    ap.add_argument("--fluids", nargs="+", default=["numerical", "hydronet"])
    ap.add_argument("--dtypes", nargs="+", default=["float32", "float64"])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--frequency", type=float, default=5.0)
    ap.add_argument("--merge", nargs="*", default=[], help="JSON of earlier runs (e.g. the CPU rows of another machine)")
    ap.add_argument("--out", default="outputs/cuda_check.json")
    args = ap.parse_args()
    rows = [r for path in args.merge for r in json.loads(Path(path).read_text())["rows"]]
    for fluid in args.fluids:
        for dtype in args.dtypes:
            for device in args.devices:
                for tf32 in ([False, True] if device.startswith("cuda") and dtype == "float32" and fluid == "hydronet"
                             else [False]):
                    rows.append(run(fluid, dtype, device, args.frames, args.frequency, tf32))
                    print(rows[-1], flush=True)
    print(markdown(compare(rows)))
    Path(args.out).write_text(json.dumps({"rows": rows}, indent=1))


if __name__ == "__main__":
    main()

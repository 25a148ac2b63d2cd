"""Full-scale gradient check: autograd through the checkpointed episode against central finite
differences at several step sizes, for the objectives `fishsim optimize` offers.

    python -m benchmarks.gradcheck                                     # numerical fluid, distance, 100 frames
    python -m benchmarks.gradcheck --fluid hydronet --objective thrust --frames 300
    python -m benchmarks.gradcheck --param amplitude --points 10 12.1 15 --deltas 1e-3 1e-4 1e-5
    python -m benchmarks.gradcheck --frames 50 100 200 300 --points 5    # growth with the horizon
    python -m benchmarks.gradcheck --frames 300 --objective thrust --trend 0.05 --truncate 0 25 50 100
    python -m benchmarks.gradcheck --table run1.json run2.json              # their trend table, joined
    python -m benchmarks.gradcheck --report @runs.txt                  # the report of the JSON runs listed
    (the speed objective needs frames h >= objective.cycles / 2 Hz, the lowest frequency allowed)

For each parameter point x: J and dJ/dx by autograd (one episode forward and backward), and the
central differences (J(x + d) - J(x - d)) / 2d for every relative step d (one batched episode of
2 x len(deltas) fish). Reported: each difference quotient, its spread over the steps (a flat,
smooth frame map gives the same value at every step) and autograd's error against the
difference quotient at the middle step.

Over long horizons J is rough on scales finer than an optimiser's steps, so its local slope is not
the direction an optimiser wants. ``--trend S`` also fits a line through J at ``--trend-points``
points evenly spread over x (1 +- S) (in the same batched episode as the differences): its slope
(the finite difference of the objective at the scale S, with its standard error from the scatter
about the line), the slope over the middle half (x (1 +- S/2): the two agree when the trend is
well defined) and the scatter's RMS. Each ``--truncate`` window W (frames; 0: full
backpropagation) gives its own autograd row, reported against the middle difference and against
the trend: the bias of truncated backpropagation, measured on the same objective.

With several ``--frames`` horizons T it also fits the growth rate per second of |dJ/dx|
(autograd, and the middle-step difference quotient) as the least-squares slope of ln|dJ/dx|
against T h: a rate well above the objective's own growth is an exponentially ill-conditioned
episode (chaotic flow, or amplification through a network's rollout). ``thrust`` runs the
paper's set-up (fish held in x, averaged forces). The fluid runs in float64
(``fluid.dtype=float32`` as an override checks the default precision; its rounding limits the
steps to >= 1e-3). Writes --out (JSON) and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import torch

from benchmarks.table import markdown_table

DEFAULT_POINTS = {"frequency": [3.0, 5.0, 7.0], "amplitude": [10.0, 12.1, 15.0], "wave_number": [25.0, 31.4, 40.0],
                  "youngs_modulus": [4e5, 6e5, 9e5]}
BOUNDS = {"frequency": (2.0, 20.0), "amplitude": (1.0, 40.0), "wave_number": (5.0, 80.0), "youngs_modulus": (1e5, 5e6)}


def check(fluid: str, objective: str, frames: int, param: str, points, deltas, overrides=(), truncate=(0,),
          trend: float = 0.0, trend_points: int = 9):
    """Yields one row per (point, truncation window), as each is measured."""
    from fishsim.config import load_config
    from fishsim.optimize.problem import Problem, Space

    lo, hi = BOUNDS[param]
    held = ["hold_x=true", "coupling.force_mode=average"] if objective == "thrust" else []
    spec = ([f"params.frequency.lower={lo}", f"params.frequency.upper={hi}"] if param == "frequency"
            else ["~params.frequency", f"+params.{param}={{lower:{lo},upper:{hi}}}"])
    cfg = load_config("optimize", [f"fluid={fluid}", "fluid.dtype=float64", f"objective={objective}",
                                   f"frames={frames}", *held, *spec, *overrides])
    space = Space(list(cfg.params), list(cfg.params.values()))
    problem = Problem(cfg, space, cfg.objective)
    first = True
    for x0 in points:
        t0 = time.perf_counter()
        fd, fit = sampled_slopes(problem, space, x0, deltas, trend, trend_points)
        t_fd = time.perf_counter() - t0
        mid = fd[len(fd) // 2] if fd else float("nan")
        spread = (max(fd) - min(fd)) / abs(mid) if fd and mid else float("nan")
        slope = fit.get("slope", float("nan"))
        for window in truncate:
            t1 = time.perf_counter()
            problem.truncate = window
            J0, autograd = autograd_at(problem, space, x0)
            row = {"fluid": fluid, "objective": objective, "frames": frames, "h": cfg.h, "param": param, "x": x0,
                   "dtype": cfg.fluid.dtype, "overrides": list(overrides),
                   "J": J0, "autograd": autograd, "deltas": list(deltas), "central": fd,
                   "fd_spread": spread, "autograd_error": relative(autograd, mid),
                   "trend": fit, "autograd_vs_trend": relative(autograd, slope),
                   "truncate": window, "seconds_autograd": time.perf_counter() - t1, "seconds_samples": t_fd}
            print(markdown([row], header=first), flush=True)
            first = False
            yield row


def relative(value: float, reference: float) -> float:
    return (value - reference) / abs(reference) if reference and math.isfinite(reference) else float("nan")


def sampled_slopes(problem, space, x0: float, deltas, span: float, n: int) -> tuple[list[float], dict]:
    """The central differences (J(x0 + d) - J(x0 - d)) / 2d for each relative step (d = delta |x0|)
    and, if span > 0, the trend fit over n points across x0 (1 +- span) (``trend_fit``): one
    batched evaluation of 2 len(deltas) + n samples."""
    import numpy as np

    steps = [d * abs(x0) for d in deltas]
    sweep = list(np.linspace(x0 - span * abs(x0), x0 + span * abs(x0), n)) if span > 0 else []
    xs = [x0 + s for s in steps] + [x0 - s for s in steps] + sweep
    if not xs:                                      # windows only (--deltas with no steps, no --trend)
        return [], {}
    J = problem.evaluate(space.to_z(torch.tensor([[x] for x in xs], dtype=torch.float64))).J.numpy()
    k = len(steps)
    fd = [float(J[i] - J[k + i]) / (2 * s) for i, s in enumerate(steps)]
    return fd, (trend_fit(np.array(sweep), J[2 * k:], x0, span) if sweep else {})


def central_differences(problem, space, x0: float, deltas) -> list[float]:
    """(J(x0 + d) - J(x0 - d)) / 2d for each relative step (d = delta |x0|), one batched evaluation."""
    return sampled_slopes(problem, space, x0, deltas, 0.0, 0)[0]


def trend_fit(x, J, x0: float, span: float) -> dict:
    """Least-squares line J ~ a + s x through the finite samples: the slope s, its standard error
    (from the scatter about the line), the slope through the samples within x0 (1 +- span / 2)
    and the scatter's RMS (J's units)."""
    import numpy as np

    ok = np.isfinite(J)
    x, J = x[ok], J[ok]
    if len(x) < 4:
        return {"span": span, "x": x.tolist(), "J": J.tolist(), "slope": float("nan")}
    (s, a), cov = np.polyfit(x, J, 1, cov=True)
    inner = np.abs(x - x0) <= span * abs(x0) / 2 + 1e-12
    s_inner = float(np.polyfit(x[inner], J[inner], 1)[0]) if inner.sum() >= 2 else float("nan")
    return {"span": span, "x": x.tolist(), "J": J.tolist(), "slope": float(s), "stderr": float(np.sqrt(cov[0, 0])),
            "slope_inner": s_inner, "rms": float(np.sqrt(np.mean((J - (a + s * x)) ** 2)))}


def autograd_at(problem, space, x0: float) -> tuple[float, float]:
    """J and dJ/dx by autograd at the point x0 of a one-parameter problem (x physical; the
    Space's z is linear in x between its bounds, so dJ/dx = dJ/dz / (upper - lower))."""
    ev = problem.evaluate(space.to_z(torch.tensor([[x0]], dtype=torch.float64)), gradient=True, isolate=False)
    spec = space.specs[0]
    return float(ev.J[0]), float(ev.grad_z[0, 0]) / (spec.upper - spec.lower)


def growth_rates(rows: list[dict]) -> list[dict]:
    """Per (fluid, objective, param, x, truncation window): the slope of ln|dJ/dx| against the horizon T h (1/s),
    for autograd and the middle-step central difference, over the rows' horizons."""
    import numpy as np

    groups: dict = {}
    for r in rows:
        groups.setdefault((r["fluid"], r["objective"], r["param"], r["x"], r["truncate"]), []).append(r)
    out = []
    for key, rs in groups.items():
        if len({r["frames"] for r in rs}) < 2:
            continue
        t = np.array([r["frames"] * r["h"] for r in rs])
        fit = {name: float(np.polyfit(t, np.log(np.abs([f(r) for r in rs])), 1)[0])
               for name, f in (("autograd", lambda r: r["autograd"]),
                               ("central", lambda r: r["central"][len(r["central"]) // 2]))}
        out.append(dict(zip(("fluid", "objective", "param", "x", "truncate"), key)) | {"horizons": [r["frames"] for r in rs]}
                   | {f"rate_{k}_per_s": v for k, v in fit.items()})
    return out


def print_growth(growth: list[dict]) -> None:
    for g in growth:
        print(f"growth of |dJ/d{g['param']}| ({g['fluid']}, {g['objective']}) at {g['x']:g} (truncate {g['truncate']}) "
              f"over {g['horizons']} frames: autograd {g['rate_autograd_per_s']:.2f} /s, central differences "
              f"{g['rate_central_per_s']:.2f} /s", flush=True)


def markdown(rows: list[dict], header: bool = True) -> str:
    columns = ["fluid", "objective", "frames", "param", "x", "J", "truncate", "autograd dJ/dx",
               "central differences (delta rel.)", "spread", "autograd vs mid", "trend slope (span)", "half-span slope",
               "autograd vs trend"]
    cells = []
    for r in rows:
        t = r["trend"]
        cells.append([r["fluid"], r["objective"], str(r["frames"]), r["param"], f"{r['x']:g}", f"{r['J']:.4g}",
                      str(r["truncate"] or "full"), f"{r['autograd']:.4g}",
                      ", ".join(f"{v:.4g} ({d:g})" for v, d in zip(r["central"], r["deltas"])),
                      f"{100 * r['fd_spread']:.1f} %", f"{100 * r['autograd_error']:+.1f} %",
                      f"{t['slope']:.4g} +- {t.get('stderr', float('nan')):.2g} ({t['span']:g})" if t else "-",
                      f"{t.get('slope_inner', float('nan')):.4g}" if t else "-",
                      f"{100 * r['autograd_vs_trend']:+.1f} %" if t else "-"])
    return markdown_table(columns, cells, header)


def join_runs(rows: list[dict]) -> dict:
    """Rows of several runs joined per point (fluid, objective, frames, param, x), in the order
    first seen: "J" (the first run's), "windows" {truncation window: autograd} (the last run's
    for each), "trend" (the last run that fitted one) and "row", the full-backpropagation row
    whose central differences the report shows (the last run with differences)."""
    groups: dict = {}
    for r in rows:
        g = groups.setdefault((r["fluid"], r["objective"], r["frames"], r["param"], r["x"]), {"J": r["J"], "windows": {}})
        if r.get("trend"):
            g["trend"] = r["trend"]
        window = r.get("truncate", 0)
        g["windows"][window] = r["autograd"]
        if window == 0 and (r["central"] or "row" not in g):
            g["row"] = r
    return groups


def trend_table(rows: list[dict]) -> str:
    """One line per (fluid, objective, frames, param, x): J, the trend slope (+- its standard
    error; the half-span slope) and autograd with each truncation window, with its bias against
    the trend. Rows of several runs join (``join_runs``): a run without ``--trend`` lends its
    windows to one with."""
    groups = join_runs(rows)
    windows = sorted({w for g in groups.values() for w in g["windows"]}, key=lambda w: w or math.inf)
    columns = ["fluid", "objective", "frames", "x", "J", "trend slope +- s.e. (half span)"] + [
        f"W = {w}" if w else "full" for w in windows]
    cells = []
    for (fluid, objective, frames, _, x), g in groups.items():
        t = g.get("trend", {"slope": math.nan})
        trend = f"{t['slope']:.3g} +- {t.get('stderr', math.nan):.2g} ({t.get('slope_inner', math.nan):.3g})"
        cells.append([fluid, objective, str(frames), f"{x:g}", f"{g['J']:.4g}", trend] + [
            f"{g['windows'][w]:.3g} ({100 * relative(g['windows'][w], t['slope']):+.0f} %)" if w in g["windows"] else "-"
            for w in windows])
    return markdown_table(columns, cells)


def report_rows(rows: list[dict]) -> list[dict]:
    """The points of ``join_runs`` that have a full-backpropagation row, ordered by objective,
    horizon, fluid, parameter and x."""
    groups = join_runs(rows)
    order = sorted((k for k in groups if "row" in groups[k]), key=lambda k: (k[1], k[2], k[0], k[3], k[4]))
    return [groups[k] for k in order]


def report_table(rows: list[dict]) -> str:
    """Issue 16's report (``report_rows``), one line per point: J, autograd, the central
    differences at each step, their spread and autograd against the middle one, and the trend
    slope (+- its standard error) where a run measured it."""
    columns = ["objective", "frames", "fluid", "precision", "x", "J", "autograd dJ/dx",
               "central differences (step rel. to x)", "spread", "autograd vs middle", "trend +- s.e. (span)"]
    cells = []
    for g in report_rows(rows):
        r, t = g["row"], g.get("trend")
        cells.append([r["objective"], str(r["frames"]), r["fluid"], r.get("dtype", "float64"), f"{r['x']:g}",
                      f"{r['J']:.4g}", f"{r['autograd']:.4g}",
                      " / ".join(f"{v:.4g} ({d:g})" for v, d in zip(r["central"], r["deltas"])) or "-",
                      f"{100 * r['fd_spread']:.0f} %" if r["central"] else "-",
                      f"{100 * r['autograd_error']:+.1f} %" if r["central"] else "-",
                      f"{t['slope']:.3g} +- {t.get('stderr', math.nan):.2g} ({100 * t['span']:g} %)" if t else "-"])
    return markdown_table(columns, cells)


def write(path: str, rows: list[dict], growth: list[dict]) -> None:
    with open(path, "w") as f:
        json.dump({"rows": rows, "growth": growth}, f, indent=1)


def read_rows(path: str) -> list[dict]:
    with open(path) as f:
        return json.load(f)["rows"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], fromfile_prefix_chars="@")
    ap.add_argument("--fluid", default="numerical", choices=["numerical", "hydronet"])
    ap.add_argument("--objective", default="distance", choices=["distance", "thrust", "speed", "cost_of_transport"])
    ap.add_argument("--frames", type=int, nargs="+", default=[100], help="horizons (several: growth rates)")
    ap.add_argument("--param", default="frequency", choices=list(DEFAULT_POINTS))
    ap.add_argument("--points", type=float, nargs="*")
    ap.add_argument("--deltas", type=float, nargs="*", default=[1e-4, 1e-5, 1e-6])
    ap.add_argument("--truncate", type=int, nargs="+", default=[0], help="backpropagation windows (0: full)")
    ap.add_argument("--trend", type=float, default=0.0, help="relative half-span of the trend fit (0: none)")
    ap.add_argument("--trend-points", type=int, default=9)
    ap.add_argument("--out", default="outputs/gradcheck.json")
    ap.add_argument("--table", nargs="+", metavar="JSON", help="only print the trend table of earlier --out files")
    ap.add_argument("--report", nargs="+", metavar="JSON", help="only print the report table of earlier --out files")
    ap.add_argument("overrides", nargs="*", help="more `fishsim optimize` overrides")
    args = ap.parse_args()
    if args.table:
        print(trend_table([r for path in args.table for r in read_rows(path)]))
        return
    if args.report:
        rows = [r for path in args.report for r in read_rows(path)]
        print(report_table(rows))
        print_growth(growth_rates([g["row"] for g in report_rows(rows) if g["row"]["central"]]))
        return
    rows = []
    for frames in args.frames:
        for row in check(args.fluid, args.objective, frames, args.param, args.points or DEFAULT_POINTS[args.param],
                         args.deltas, args.overrides, args.truncate, args.trend, args.trend_points):
            rows.append(row)
            write(args.out, rows, [])                # each row as it comes: a stopped run keeps what it measured
    growth = growth_rates(rows)
    print_growth(growth)
    write(args.out, rows, growth)
    if args.trend or len(args.truncate) > 1:
        print(trend_table(rows))


if __name__ == "__main__":
    main()

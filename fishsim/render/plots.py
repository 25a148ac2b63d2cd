"""Result plots (matplotlib Agg), each written as PNG and SVG:

* ``plot_optimisation_history``: objective and parameters against iterations and simulated
  fish-frames for several methods on the same axes (paper Fig. 5: gradient vs CMA-ES);
* ``plot_validation``: a quantity (head x-position) against the controller frequency for
  several simulators, optional error bars (paper Fig. 4: HydroNet vs the numerical solver);
* ``plot_solid_convergence``: the tail's stroke against the edge length per muscle model, and
  the cantilever's errors against refinement (``fishsim validate suite=solid``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FormatStrFormatter, LogLocator, NullLocator

MARKERS = "osd^v<>"


def save_png_svg(fig: Figure, path: str | Path) -> list[Path]:
    """Save ``fig`` as <path>.png and <path>.svg (any suffix of ``path`` is replaced)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = [path.with_suffix(".png"), path.with_suffix(".svg")]
    for p in out:
        fig.savefig(p, dpi=150)
    return out


def _figure(rows: int, height: float) -> tuple[Figure, list]:
    fig = Figure(figsize=(6.4, height), layout="constrained")
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(rows, 1, i + 1) for i in range(rows)]
    return fig, axes


def plot_optimisation_history(histories: Mapping[str, Mapping], path: str | Path, objective_label: str = "objective J",
                              units: Mapping[str, str] | None = None) -> list[Path]:
    """The paper's Fig. 5 layout, for several methods on the same axes: the objective (each
    iteration's value, markers; best so far, line) and every parameter, against iterations (left
    column) and against simulated fish-frames (right column), so that methods with different
    costs per iteration compare at equal budget.

    histories: {method: {"objective": [n], "best": [n], "frames": [n] cumulative fish-frames,
    "parameters": {name: [n]}}}.  units: {parameter name: unit} for the axis labels.
    """
    names = list(dict.fromkeys(n for h in histories.values() for n in h["parameters"]))
    rows = 1 + len(names)
    fig = Figure(figsize=(10, 2.4 * rows + 0.6), layout="constrained")
    FigureCanvasAgg(fig)
    axes = [[fig.add_subplot(rows, 2, 2 * r + c + 1) for c in range(2)] for r in range(rows)]
    for i, (method, h) in enumerate(histories.items()):
        obj = np.asarray(h["objective"], float)
        xs = (np.arange(1, len(obj) + 1), np.asarray(h["frames"], float))
        for c, x in enumerate(xs):
            line = axes[0][c].plot(x, obj, MARKERS[i % len(MARKERS)], markersize=3, alpha=0.6)[0]
            axes[0][c].plot(x, np.asarray(h["best"], float), color=line.get_color(), label=method)
            for r, name in enumerate(names, start=1):
                if name in h["parameters"]:
                    axes[r][c].plot(x, np.asarray(h["parameters"][name], float), marker=MARKERS[i % len(MARKERS)],
                                    markersize=3, color=line.get_color(), label=method)
    labels = [objective_label] + [f"{n} [{(units or {}).get(n, '-')}]" for n in names]
    for r, row in enumerate(axes):
        for c, ax in enumerate(row):
            ax.set_ylabel(labels[r])
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
            if r == rows - 1:
                ax.set_xlabel(("iteration", "simulated fish-frames")[c])
    axes[0][0].set_title("against iterations (markers: each iteration, line: best so far)")
    axes[0][1].set_title("against simulated fish-frames")
    return save_png_svg(fig, path)


def plot_validation(frequencies: Sequence[float], values: Mapping[str, Sequence[float]], path: str | Path,
                    errors: Mapping[str, Sequence[float]] | None = None,
                    ylabel: str = "head x-position [m]", xlabel: str = "controller frequency [Hz]",
                    title: str = "travelled distance vs controller frequency") -> list[Path]:
    """values: {simulator: [one value per frequency]}; errors: same keys, error-bar half-widths."""
    fig, (ax,) = _figure(1, 3.8)
    f = np.asarray(frequencies, float)
    for i, (name, v) in enumerate(values.items()):
        err = None if not errors or name not in errors else np.asarray(errors[name], float)
        ax.errorbar(f, np.asarray(v, float), yerr=err, marker=MARKERS[i % len(MARKERS)], capsize=3,
                    label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    return save_png_svg(fig, path)


def plot_fluid_comparison(final: Mapping, path: str | Path, labels: Sequence[str] = ("HydroNet", "numerical"),
                          field: str = "vorticity") -> list[Path]:
    """One row per scene: ``field`` of the two models side by side on shared colour limits
    (99th percentile of |field| over the fluid of the reference), the body in grey.

    final: ``fishsim.learn.evaluate.Evaluation.final`` (names, mask [B,H,W], net/ref
    fields [B,H,W] or [B,H+1,W+1])."""
    names, mask = final["names"], final["mask"]
    fig = Figure(figsize=(10, 1.9 * len(names)), layout="constrained")
    FigureCanvasAgg(fig)
    for n, name in enumerate(names):
        ref = final["ref"][field][n]
        lim = float(np.percentile(np.abs(ref[: mask.shape[1], : mask.shape[2]][mask[n] < 0.5]), 99)) or 1.0
        for col, (key, label) in enumerate(zip(("net", "ref"), labels)):
            ax = fig.add_subplot(len(names), 2, 2 * n + col + 1)
            im = ax.imshow(final[key][field][n], origin="lower", cmap="RdBu_r", vmin=-lim, vmax=lim)
            ax.imshow(np.ma.masked_less(mask[n], 0.5), origin="lower", cmap="Greys", vmin=0, vmax=1.5, alpha=0.8)
            ax.set_title(f"{name}: {label}", fontsize=8)
            ax.set_xticks([]), ax.set_yticks([])
        fig.colorbar(im, ax=ax, shrink=0.8, label=field)
    return save_png_svg(fig, path)


def plot_solid_convergence(rows: Sequence[Mapping], beam_rows: Sequence[Mapping], path: str | Path) -> list[Path]:
    """Left: tail peak-to-peak [mm] against the edge length [mm] (finer to the right), one line
    per muscle model (rows of ``fishsim.solid_study.stroke_study``). Right (if beam_rows):
    |relative error| [%] of the cantilever's tip deflection and first frequency against the
    elements across its thickness, log-log (rows of ``beam_study``)."""
    fig = Figure(figsize=(10 if beam_rows else 5.5, 3.8), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2 if beam_rows else 1, 1)
    for i, model in enumerate(dict.fromkeys(r["muscles"] for r in rows)):
        runs = sorted((r for r in rows if r["muscles"] == model), key=lambda r: -r["edge_mm"])
        ax.plot([r["edge_mm"] for r in runs], [r["tail_p2p_mm"] for r in runs], marker=MARKERS[i % len(MARKERS)],
                label=f"{model} muscles")
    ax.set_xscale("log")
    ax.invert_xaxis()
    edges = sorted({r["edge_mm"] for r in rows})
    ax.set_xticks(edges, [f"{e:g}" for e in edges])
    ax.minorticks_off()
    ax.set_xlabel("edge length [mm]")
    ax.set_ylabel("tail peak-to-peak [mm]")
    fluid = rows[0]["fluid"] if rows else "none"
    ax.set_title(f"stroke under refinement ({'vacuum' if fluid == 'none' else fluid + ' fluid'})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if beam_rows:
        bx = fig.add_subplot(1, 2, 2)
        n = [r["across"] for r in beam_rows]
        for i, (key, label) in enumerate((("static_err", "tip deflection"), ("frequency_err", "first frequency"))):
            bx.loglog(n, [max(100 * abs(r[key]), 1e-3) for r in beam_rows], marker=MARKERS[i], label=label)
        bx.set_xticks(n, [str(k) for k in n])
        bx.xaxis.set_minor_locator(NullLocator())
        bx.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        bx.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        bx.yaxis.set_minor_locator(NullLocator())
        bx.set_xlabel("elements across the thickness")
        bx.set_ylabel("|error| vs Euler-Bernoulli [%]")
        bx.set_title("clamped cantilever")
        bx.grid(alpha=0.3, which="both")
        bx.legend(fontsize=8)
    return save_png_svg(fig, path)


def plot_convergence(results: Mapping[str, Mapping], frequencies: Sequence[float], path: str | Path) -> list[Path]:
    """One panel per numerical knob: the head's displacement against the knob's setting (log
    axis) as a change in % from the default setting's (from the finest where the default is not
    among the settings), one line per frequency, the Richardson estimate dashed, the knob's limit
    (where run) dash-dotted, the default dotted and a +-2 % band shaded. results:
    fishsim.swim_study.convergence_study's output."""
    names = list(results)
    fig = Figure(figsize=(5.0 * min(len(names), 3), 3.4 * math.ceil(len(names) / 3)), layout="constrained")
    FigureCanvasAgg(fig)
    for k, name in enumerate(names):
        r = results[name]
        ax = fig.add_subplot(math.ceil(len(names) / 3), min(len(names), 3), k + 1)
        d = np.asarray(r["displacement_mm"], float)
        values = list(r["values"])
        base = d[values.index(r["default"])] if r["default"] in values else d[-1]
        ax.axhspan(-2.0, 2.0, color="0.9", label="+-2 %")
        for j, f in enumerate(frequencies):
            line = ax.plot(values, 100 * (d[:, j] / base[j] - 1), marker=MARKERS[j % len(MARKERS)],
                           label=f"{f:g} Hz ({base[j]:.3g} mm)")[0]
            rich = r["displacement"]["richardson"][j]
            if np.isfinite(rich):
                ax.axhline(100 * (rich / base[j] - 1), color=line.get_color(), linestyle="--", linewidth=0.8)
            if "limit" in r:
                ax.axhline(100 * (r["limit"]["displacement_mm"][j] / base[j] - 1), color=line.get_color(),
                           linestyle="-.", linewidth=0.8,
                           label=f"limit: {' '.join(r['limit']['overrides'])}" if j == 0 else None)
        if r["default"] is not None:
            ax.axvline(r["default"], color="0.5", linestyle=":", label="default")
        ax.set_xscale("log")
        same = len(set(r.get("episode_frames", [r["frames"]]))) == 1
        runs_with = f", {' '.join(r['base'])}" if r.get("base") else ""
        ax.set_xlabel(f"{r['key']} ({r['frames']} frames{runs_with}{'' if same else ' at the default: the same duration'})")
        ax.set_ylabel("head x displacement vs default [%]")
        ax.set_title(name)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return save_png_svg(fig, path)

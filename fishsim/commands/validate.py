"""``fishsim validate``: comparisons against reference solutions.

The HydroNet being judged is the ``hydronet`` node, a ``HydroNetConfig`` (conf/fluid/hydronet.yaml;
``hydronet.model_file=<a best.pt>``, ``hydronet.bf16``, ``hydronet.pressure``, ...).

suite=hydronet: that HydroNet against the numerical solver on held-out scenes
(``fishsim.learn.evaluate``): metrics.json, a printed table, and a picture of the final
vorticity of both models side by side (comparison.png/.svg).

suite=solid: the solid's mesh convergence and its beam validation (``fishsim.solid_study``,
docs/validation.md): the swimming stroke at several edge lengths with each muscle model, and a
clamped cantilever against Euler-Bernoulli; metrics.json, printed tables, and a plot of the tail
peak-to-peak against the edge length and of the beam's errors against refinement
(solid_convergence.png/.svg).

suite=swim: the paper's frequency study (Fig. 4, ``fishsim.swim_study``): the head's displacement
after 120 frames at 3-7 Hz for HydroNet (own and recovered pressure) and the numerical fluid at
r = 1 and r = 2 (the reference), each fluid one batched rollout; Spearman rank correlation,
argmax, mean mismatch (mm and cells) and runtimes; metrics.json, a printed table and a plot of
displacement against frequency (swim.png/.svg).

suite=convergence: the same study against each numerical knob of the reference (sub-steps,
penalisation iterations, the IBM kernel, the grid, the frame step h over the same duration,
the coupling's passes a frame, explicit against converged; ``fishsim.swim_study.convergence_study``):
displacement and mean thrust per setting, observed orders, Richardson estimates and the
defaults' errors; metrics.json, a table and convergence.png/.svg.
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, replace

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from fishsim.config import SolidStudyConfig, ValidateConfig
from fishsim.io.outdir import make_out_dir


def run(cfg: ValidateConfig) -> dict:
    """Run the chosen suite: evaluate, write metrics.json and the picture, print the tables."""
    if cfg.suite == "solid":
        return run_solid(cfg)
    if cfg.suite == "swim":
        return run_swim(cfg)
    if cfg.suite == "convergence":
        return run_convergence(cfg)
    return run_hydronet(cfg)


def run_convergence(cfg: ValidateConfig) -> dict:
    """suite=convergence (module docstring)."""
    from fishsim.render.plots import plot_convergence
    from fishsim.swim_study import convergence_study

    out_dir = make_out_dir("validate", cfg.out_dir)
    c = cfg.convergence
    columns = (TextColumn("validate convergence: {task.fields[run]}"), BarColumn(), TimeRemainingColumn())
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("runs", total=None, run="")
        results = convergence_study(c, cfg.device, progress=lambda what: bar.update(task, run=what))
    metrics = {"convergence": asdict(c), "knobs": results}
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    pictures = plot_convergence(results, c.frequencies, out_dir / "convergence")
    freqs = [f"{f:g} Hz" for f in c.frequencies]
    table = Table(title=escape(f"convergence of the frequency study: head x displacement [mm] ({', '.join(freqs)})"))
    for label in ("knob", "setting", "displacement [mm]", "mean thrust [mN/m]", "wall [s]"):
        table.add_column(escape(label), justify="left" if label == "knob" else "right")
    fmt = lambda row: " / ".join(f"{v:.1f}" for v in row)
    for name, r in results.items():
        if r["base"]:
            table.add_row(name, "with " + " ".join(r["base"]), "", "", "")
        for i, v in enumerate(r["values"]):
            mark = " (default)" if v == r["default"] else ""
            if r["episode_frames"][i] != r["frames"]:
                mark += f" ({r['episode_frames'][i]} frames)"
            table.add_row(name if i == 0 and not r["base"] else "", f"{r['key']}={v:g}{mark}", fmt(r["displacement_mm"][i]),
                          fmt(r["mean_thrust_mN"][i]), f"{r['wall_s'][i]:.0f}")
        o = r["displacement"]
        table.add_row("", "observed order p", " / ".join(f"{p:.2f}" for p in o["order"]), "", "")
        table.add_row("", "Richardson estimate", fmt(o["richardson"]), "", "")
        if "limit" in r:
            lim = r["limit"]
            table.add_row("", " ".join(lim["overrides"]) + " (limit)", fmt(lim["displacement_mm"]),
                          fmt(lim["mean_thrust_mN"]), f"{lim['wall_s']:.0f}")
        for what in ("finest", "limit"):
            if f"default_error_vs_{what}" in r:
                table.add_row("", f"default vs {what}",
                              " / ".join(f"{100 * e:+.1f} %" for e in r[f"default_error_vs_{what}"]), "", "")
    Console(width=max(Console().width, 130)).print(table)
    Console().print(f"metrics: {out_dir / 'metrics.json'}   picture: {pictures[0]}")
    return metrics


def hydronet_overrides(cfg: ValidateConfig, pressure: bool = False) -> list[str]:
    """`fishsim simulate` overrides that make a study's HydroNet runs (``fluid=hydronet``) run the
    HydroNet being judged, the ``hydronet`` node: its model_file (when set), bf16, pressure_tol,
    strict_range and symmetric, and with ``pressure`` its pressure (suite=solid; suite=swim's fluids set their
    own). Not its rho, mu or dtype: the runs' fluid is the study's (``ValidateConfig``)."""
    net = cfg.hydronet
    out = [f"fluid.model_file={net.model_file}"] if net.model_file else []
    out += [f"fluid.bf16={str(net.bf16).lower()}", f"fluid.pressure_tol={net.pressure_tol!r}",
            f"fluid.strict_range={str(net.strict_range).lower()}", f"fluid.symmetric={str(net.symmetric).lower()}"]
    return out + ([f"fluid.pressure={net.pressure}"] if pressure else [])


def run_swim(cfg: ValidateConfig) -> dict:
    """suite=swim: the frequency study (module docstring)."""
    from fishsim.render.plots import plot_validation
    from fishsim.swim_study import PAPER, frequency_study

    out_dir = make_out_dir("validate", cfg.out_dir)
    s = replace(cfg.swim, hydronet_overrides=[*hydronet_overrides(cfg), *cfg.swim.hydronet_overrides])
    columns = (TextColumn("validate swim: {task.fields[fluid]}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("fluids", total=len(s.fluids), fluid="")
        done = []

        def step(name: str) -> None:
            bar.update(task, completed=len(done), fluid=name)
            done.append(name)

        results = frequency_study(s, cfg.device, progress=step)
    metrics = {"swim": asdict(s), "fluids": results, "paper": PAPER}
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    pictures = plot_validation(s.frequencies, {n: r["displacement_mm"] for n, r in results.items()}, out_dir / "swim",
                               ylabel="head x displacement [mm]",
                               title=f"frequency study, {s.frames} frames (reference: {s.reference})")
    table = Table(title=escape(f"frequency study: head x displacement [mm] after {s.frames} frames (reference {s.reference})"))
    for label in ("fluid", *(f"{f:g} Hz" for f in s.frequencies), "Spearman", "argmax [Hz]", "mismatch [mm]",
                  "mismatch [cells]", "wall [s]", "s / fish-frame"):
        table.add_column(escape(label), justify="left" if label == "fluid" else "right")
    for name, r in results.items():
        table.add_row(name, *(f"{v:.1f}" for v in r["displacement_mm"]), f"{r['spearman']:.2f}", f"{r['argmax_hz']:g}",
                      f"{r['mean_mismatch_mm']:.1f}", f"{r['mean_mismatch_cells']:.1f}", f"{r['wall_s']:.1f}",
                      f"{r['s_per_fish_frame']:.3f}")
    Console(width=max(Console().width, 150)).print(table)
    Console().print(f"paper (Fig. 4, Table 1): argmax {PAPER['argmax_hz']:g} Hz for both, mean mismatch "
                    f"{PAPER['mean_mismatch_mm']:g} mm ({PAPER['mean_mismatch_cells']:g} cells); HydroNet "
                    f"{PAPER['hydronet_forward_s_per_frame']:.2f} s / frame, COMSOL {PAPER['comsol_s_per_frame']:.0f} s / frame")
    drift = ", ".join(f"{n} " + " / ".join(f"{v:.1f}" for v in r["lateral_drift_mm"]) for n, r in results.items())
    Console().print(f"lateral drift [mm] (centroid y) at {' / '.join(f'{f:g}' for f in s.frequencies)} Hz: {drift}")
    for name, r in results.items():
        for f, fail in r["failures"].items():
            Console().print(f"[yellow]{name} {f} Hz blew up at frame {fail['frame']}: {escape(fail['reason'])}[/]")
    Console().print(f"metrics: {out_dir / 'metrics.json'}   picture: {pictures[0]}")
    return metrics


def run_solid(cfg: ValidateConfig) -> dict:
    """suite=solid: the stroke study and the beam check (module docstring)."""
    from fishsim.render.plots import plot_solid_convergence
    from fishsim.solid_study import beam_study, stroke_study, summary

    out_dir = make_out_dir("validate", cfg.out_dir)
    s = cfg.solid
    overrides = ([] if cfg.device == "cpu" else [f"device={cfg.device}"]) + (
        hydronet_overrides(cfg, pressure=True) if s.fluid == "hydronet" else [])
    columns = (TextColumn("validate solid"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("runs", total=len(s.edges) * len(s.muscles))
        rows = stroke_study(tuple(s.edges), tuple(s.muscles), s.fluid, s.frames, overrides,
                            progress=lambda done, total: bar.update(task, completed=done, total=total))
    beam_rows = beam_study(tuple(s.beam_across)) if s.beam_across else []
    result = {"solid": asdict(s), "stroke": rows, "beam": beam_rows, "summary": summary(rows, beam_rows)}
    (out_dir / "metrics.json").write_text(json.dumps(result, indent=2))
    pictures = plot_solid_convergence(rows, beam_rows, out_dir / "solid_convergence")
    _print_solid(rows, beam_rows, s)
    Console().print(f"metrics: {out_dir / 'metrics.json'}   picture: {pictures[0]}")
    return result


def _print_solid(rows: list[dict], beam_rows: list[dict], s: SolidStudyConfig) -> None:
    """The stroke table (deviations from the finest mesh of each muscle model), then the beam's."""
    fluid = "vacuum" if s.fluid == "none" else f"{s.fluid} fluid"
    table = Table(title=f"solid mesh convergence ({fluid}, {s.frames} frames, 5 Hz)")
    for label in ("muscles", "edge [mm]", "nodes", "muscle elements", "tail p2p [mm]", "vs finest",
                  "head dx [mm]", "vs finest", "solid step [ms]"):
        table.add_column(escape(label), justify="left" if label == "muscles" else "right")
    for r in rows:
        table.add_row(r["muscles"], f"{r['edge_mm']:.1f}", str(r["nodes"]), str(r["n_act"]), f"{r['tail_p2p_mm']:.1f}",
                      f"{100 * r['tail_dev']:+.1f} %", f"{r['head_dx_mm']:+.2f}", f"{100 * r['head_dev']:+.1f} %",
                      f"{r['solid_ms_per_step']:.1f}")
    console = Console(width=max(Console().width, 120))
    console.print(table)
    if beam_rows:
        beam = Table(title="clamped cantilever vs Euler-Bernoulli")
        for label in ("elements across", "edge [mm]", "nodes", "tip deflection error", "first frequency error"):
            beam.add_column(escape(label), justify="right")
        for r in beam_rows:
            beam.add_row(str(r["across"]), f"{r['edge_mm']:.3g}", str(r["nodes"]), f"{100 * r['static_err']:+.2f} %",
                         f"{100 * r['frequency_err']:+.2f} %")
        console.print(beam)


def run_hydronet(cfg: ValidateConfig) -> dict:
    """suite=hydronet: evaluate, write metrics.json and the comparison picture, print the table."""
    import torch

    from fishsim.fluid.factory import hydronet_file, make_fluid
    from fishsim.fluid.hydronet.trained_range import check_fluid
    from fishsim.learn.evaluate import energy_checks, evaluate, reference_fluid, summarise
    from fishsim.render.plots import plot_fluid_comparison

    out_dir = make_out_dir("validate", cfg.out_dir)
    s = cfg.scenes
    grid, device = s.tank.grid, torch.device(cfg.device)
    path = hydronet_file(cfg.hydronet)
    net = make_fluid(cfg.hydronet, s.tank, device)     # model_file, bf16, pressure, pressure_tol
    # outside the model's trained range: a warning, as measuring that error is allowed (refused with strict_range)
    check_fluid(net.model, path, s.rho, s.mu, s.tank.dx, s.h, strict=cfg.hydronet.strict_range, key="hydronet")
    columns = (TextColumn("validate hydronet"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("steps", total=None)
        result = evaluate(net, reference_fluid(grid), s, device,
                          progress=lambda done, total: bar.update(task, completed=done, total=total))
        bar.update(task, description="validate hydronet: still fish, kinetic energy")
        checks = energy_checks(net, reference_fluid(grid), s, device)
    summary = {"model_file": str(path), "scenes": asdict(s), "metrics": result.metrics,
               "summary": {**summarise(result.metrics), **checks}}
    (out_dir / "metrics.json").write_text(json.dumps(summary, indent=2))
    pictures = plot_fluid_comparison(result.final, out_dir / "comparison")
    _print(result.metrics, summary["summary"])
    Console().print(f"metrics: {out_dir / 'metrics.json'}   picture: {pictures[0]}")
    return summary


COLUMNS = {"one_step_error_v": "1-step e_v", "one_step_error_p": "1-step e_p", "rollout_error_v": "N-step e_v",
           "rollout_error_p": "N-step e_p", "residual_Lp_net": "L_p net", "residual_Lp_ref": "L_p ref",
           "max_div_net": "max div net", "force_x_net": "F_x net [N]", "force_x_ref": "F_x ref [N]"}


def _print(metrics: dict, summary: dict) -> None:
    """One row per scene (N-step: the rollout length), then the means."""
    table = Table(title="HydroNet vs numerical solver (held-out scenes)")
    table.add_column("scene")
    for label in COLUMNS.values():
        table.add_column(label, justify="right")
    for name, m in metrics.items():
        m = {re.sub(r"^rollout\d+_", "rollout_", k): v for k, v in m.items()}
        table.add_row(name, *(f"{m[k]:.3g}" for k in COLUMNS))
    Console(width=max(Console().width, 150)).print(table)
    Console().print("  ".join(f"{k} {v:.3g}" for k, v in summary.items()))

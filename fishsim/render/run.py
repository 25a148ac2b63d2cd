"""``fishsim render``: trajectory files to PNG frames, a video, comparison pictures and
(optionally) a ParaView series.  ``run(cfg)`` is what the CLI calls.

Output folder (``out_dir``; one sub-folder per file when ``path`` is a folder)::

    frames/<name>_000000.png ...   one PNG per rendered frame
    <name>.mp4 (or .gif)           the same frames as a video
    compare_normalised.png, compare_overlay.png   with ``compare=other.h5``
    vtk/{fish,fluid}.pvd + frames  with ``vtk=true``
"""

from __future__ import annotations

import time
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from fishsim.errors import ConfigError, FishsimError, InputFileError
from fishsim.io.outdir import make_out_dir
from fishsim.render.compare import shared_fluid_frames
from fishsim.render.config import RenderConfig
from fishsim.render.data import RenderData, load_render_data
from fishsim.render.scene import FrameFigure
from fishsim.render.video import VideoWriter, write_png


def trajectory_paths(path: str | Path) -> list[Path]:
    """The file itself, or every ``*.h5`` in a folder and its subfolders (sorted; e.g.
    ``outputs/simulate/`` with one run folder per run)."""
    path = Path(path)
    if path.is_dir():
        files = sorted(path.rglob("*.h5"))
        if not files:
            raise InputFileError(f"no *.h5 trajectories in folder {path} or its subfolders")
        return files
    if not path.exists():
        raise InputFileError(f"no such trajectory file or folder: {path}")
    return [path]


def frame_indices(n_frames: int, cfg: RenderConfig, fluid_frames=None) -> list[int]:
    """``range(start, stop, stride)`` clipped to the frames the file holds; with ``stride``
    null, the frames whose fluid is stored (``fluid_frames``: every frame then shows its own
    fluid, none a stale one), or every frame without fluid."""
    stop = n_frames if cfg.stop < 0 else min(cfg.stop, n_frames)
    start = min(cfg.start, n_frames)
    if cfg.stride is None and fluid_frames is not None and len(fluid_frames):
        return [int(t) for t in fluid_frames if start <= t < stop]
    return list(range(start, stop, cfg.stride or 1))


def run(cfg: RenderConfig) -> dict:
    """Render ``cfg.path`` (a file or a folder); return {file: summary} (see ``render_file``)."""
    cfg.validate()
    paths = trajectory_paths(cfg.path)
    if cfg.compare and len(paths) > 1:
        raise ConfigError("compare=... needs path to be one trajectory file, not a folder")
    out_dir = make_out_dir("render", cfg.out_dir)
    console = Console(stderr=True)
    results = {}
    for p in paths:
        target = out_dir / p.stem if len(paths) > 1 else out_dir
        try:
            results[str(p)] = render_file(p, cfg, target, console)
        except InputFileError as err:
            if len(paths) == 1:
                raise
            console.print(f"[yellow]warning: skipped {p}: {err}[/]")
            results[str(p)] = {"error": str(err)}
    return results


def render_file(path: Path, cfg: RenderConfig, out_dir: Path, console: Console | None = None) -> dict:
    """Render one trajectory (and ``cfg.compare`` beside it) into ``out_dir``; return a summary:
    frames, pngs folder, video path, comparison pictures, vtk files, complete, ms_per_frame."""
    console = console or Console(stderr=True)
    runs = [load_render_data(path, cfg.sample)]
    if cfg.compare:
        runs.append(load_render_data(cfg.compare, cfg.sample))
    for r in runs:
        if not r.complete:
            console.print(f"[yellow]warning: {r.path} is incomplete ({r.n_frames} frames flushed; "
                          f"{r.message or 'the run did not finish'}); rendering what is there[/]")
    out_dir.mkdir(parents=True, exist_ok=True)
    labels = list(cfg.labels) or [r.name for r in runs]
    summary = {"complete": all(r.complete for r in runs), "out_dir": str(out_dir)}
    summary.update(render_frames(runs, labels, cfg, out_dir))
    if len(runs) == 2:
        summary.update(render_comparison(runs, labels, cfg, out_dir))
    if cfg.vtk:
        summary["vtk"] = _write_vtk(runs[0], cfg, out_dir)
    console.print(f"rendered {summary['frames']} frames of {path.name} into {out_dir} "
                  f"({summary['ms_per_frame']:.0f} ms/frame)")
    return summary


def render_frames(runs: list[RenderData], labels: list[str], cfg: RenderConfig, out_dir: Path) -> dict:
    """PNG per frame and the video, from one reused figure."""
    n = min(r.n_frames for r in runs)
    frames = frame_indices(n, cfg, shared_fluid_frames(runs))
    if not frames:
        raise InputFileError(f"{runs[0].path} holds {n} frames: nothing to render for "
                             f"start={cfg.start} stop={cfg.stop}")
    figure = FrameFigure(runs, cfg, labels)
    name = "_vs_".join(r.name for r in runs)
    png_dir = out_dir / "frames"
    if cfg.pngs:
        png_dir.mkdir(exist_ok=True)
    video = VideoWriter(out_dir / name, cfg.video, cfg.fps) if cfg.video != "none" else None
    t0 = time.perf_counter()
    try:
        for t in _progress(frames, cfg.progress):
            figure.update(t)
            rgb = figure.rgb()
            if cfg.pngs:
                write_png(png_dir / f"{name}_{t:06d}.png", rgb)
            if video is not None:
                video.append(rgb)
    finally:
        if video is not None:
            video.close()
    ms = 1e3 * (time.perf_counter() - t0) / len(frames)
    return {"frames": len(frames), "pngs": str(png_dir) if cfg.pngs else None,
            "video": str(video.path) if video else None, "size": figure.size, "clim": figure.clim,
            "title": figure.title, "ms_per_frame": ms}


def render_comparison(runs: list[RenderData], labels: list[str], cfg: RenderConfig, out_dir: Path) -> dict:
    """The normalised pressure fields side by side and their contour overlay at one frame."""
    from fishsim.render.compare import common_fluid_frame, plot_normalised_fields, plot_overlay

    try:
        frame = common_fluid_frame(runs, cfg.overlay_frame)
    except FishsimError as err:
        Console(stderr=True).print(f"[yellow]warning: no comparison overlay: {err}[/]")
        return {}
    return {"compare_frame": frame,
            "compare_normalised": str(plot_normalised_fields(runs, labels, frame, out_dir / "compare_normalised.png")),
            "compare_overlay": str(plot_overlay(runs, labels, frame, out_dir / "compare_overlay.png"))}


def _write_vtk(run: RenderData, cfg: RenderConfig, out_dir: Path) -> dict:
    from fishsim.render.vtk_io import write_vtk_series

    files = write_vtk_series(run, out_dir / "vtk", frame_indices(run.n_frames, cfg, shared_fluid_frames([run])),
                             actuator=run.actuator)
    return {k: str(v) for k, v in files.items()}


def _progress(items: list, show: bool):
    """Iterate with a rich progress bar (on stderr) when ``show``."""
    if not show:
        yield from items
        return
    columns = (TextColumn("rendering"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("frames", total=len(items))
        for item in items:
            yield item
            bar.advance(task)

"""Rendering speed: ms per frame at the paper's grid (H = 100, W = 300) for the Agg figure
alone, with a PNG per frame, with an MP4, and for the whole ``fishsim render`` run."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from fishsim.render.config import RenderConfig
from fishsim.render.data import load_render_data
from fishsim.render.run import render_file
from fishsim.render.scene import FrameFigure
from fishsim.render.synthetic import write_synthetic_trajectory
from fishsim.render.video import VideoWriter, write_png

N_FRAMES = 40


def _per_frame(fn, frames) -> float:
    t0 = time.perf_counter()
    for t in frames:
        fn(t)
    return 1e3 * (time.perf_counter() - t0) / len(frames)


def _figure_timings(data, cfg: RenderConfig, tmp: Path) -> dict:
    """ms/frame for draw only, draw + PNG, draw + MP4 (one reused figure)."""
    fig = FrameFigure([data], cfg)
    fig.update(0)
    fig.rgb()                                   # warm-up (fonts, caches)
    frames = range(data.n_frames)
    out = {"draw": _per_frame(lambda t: (fig.update(t), fig.rgb()), frames)}
    out["draw+png"] = _per_frame(lambda t: (fig.update(t), write_png(tmp / f"f{t}.png", fig.rgb())), frames)
    video = VideoWriter(tmp / "bench", "mp4", 20)
    out["draw+mp4"] = _per_frame(lambda t: (fig.update(t), video.append(fig.rgb())), frames)
    video.close()
    return out


def run() -> dict:
    """Timings (ms per frame) for a 40-frame synthetic run on a 100 x 300 grid."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = write_synthetic_trajectory(tmp / "bench.h5", n_frames=N_FRAMES, H=100, W=300, fluid_every=1)
        cfg = RenderConfig(path=str(path), progress=False)
        data = load_render_data(path)
        results = {"grid": "100 x 300", "frames": N_FRAMES, "width_px": cfg.width}
        results["pressure"] = _figure_timings(data, cfg, tmp)
        results["vorticity_follow"] = _figure_timings(
            data, RenderConfig(path=str(path), field="vorticity", follow=True, progress=False), tmp)
        t0 = time.perf_counter()
        render_file(path, cfg, tmp / "out")
        results["render_file_total_ms_per_frame"] = 1e3 * (time.perf_counter() - t0) / N_FRAMES
    return results


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=1))

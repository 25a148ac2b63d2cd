"""Output folders: every command writes under one folder, by default outputs/<command>/<time>."""

from __future__ import annotations

import time
from pathlib import Path


def make_out_dir(command: str, out_dir: str | None) -> Path:
    """Create and return the output folder (``out_dir`` if given)."""
    path = Path(out_dir) if out_dir else Path("outputs") / command / time.strftime("%Y-%m-%d_%H-%M-%S")
    path.mkdir(parents=True, exist_ok=True)
    return path


def resolve_output(out_dir: Path, name: str) -> Path:
    """An output file path: absolute names are kept, relative ones go into ``out_dir``."""
    p = Path(name)
    return p if p.is_absolute() else out_dir / p

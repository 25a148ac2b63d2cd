"""Output folders: every command writes under one folder, by default a new
outputs/<command>/<time> (made unique: two runs started in the same second get two folders).

While a run writes, it holds an exclusive lock on ``<folder>/.fishsim.lock`` (``fcntl.flock``,
released when the command ends or the process dies), so a second run pointed at the same folder
stops at once with one line instead of corrupting the first one's files.
"""

from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path

from fishsim.errors import ConfigError

LOCK_NAME = ".fishsim.lock"
_held: dict = {}          # folder -> open lock file of this process (released by release_locks)


def make_out_dir(command: str, out_dir: str | None) -> Path:
    """Create (if needed), lock and return the output folder: ``out_dir`` if given, else a new
    outputs/<command>/<YYYY-mm-dd_HH-MM-SS>[_n]. ConfigError (one line) if it cannot be made
    or written, or another run is writing to it."""
    if out_dir:
        path = Path(out_dir)
        if path.exists() and not path.is_dir():
            raise ConfigError(f"out_dir={out_dir} is a file, not a folder (choose another out_dir)")
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ConfigError(f"cannot create out_dir={out_dir}: {err.strerror} (choose a writable folder)") from None
    else:
        path = _new_folder(Path("outputs") / command / time.strftime("%Y-%m-%d_%H-%M-%S"))
    lock(path)
    return path


def _new_folder(base: Path) -> Path:
    """base, or base_2, base_3, ...: the first that did not exist (mkdir is the atomic test)."""
    base.parent.mkdir(parents=True, exist_ok=True)
    for n in range(1, 10_000):
        path = base if n == 1 else base.with_name(f"{base.name}_{n}")
        try:
            path.mkdir()
            return path
        except FileExistsError:
            continue
    raise ConfigError(f"could not find a free output folder next to {base} (give out_dir=...)")


def lock(folder: Path) -> None:
    """Hold an exclusive lock on the folder until release_locks() or the process ends (a folder
    this process already holds stays held: one process runs its commands one after another)."""
    key = str(folder.resolve())
    if key in _held:
        return
    try:
        handle = open(folder / LOCK_NAME, "a+")  # noqa: SIM115 - held open for the whole run
    except OSError as err:
        raise ConfigError(f"cannot write in out_dir={folder}: {err.strerror} (choose a writable folder)") from None
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        raise ConfigError(f"out_dir={folder} is in use by another fishsim run (wait for it, or choose another "
                          "out_dir)") from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    _held[key] = handle


def release_locks() -> None:
    """Release the folders this process locked (the CLI calls it when a command ends)."""
    while _held:
        _, handle = _held.popitem()
        try:
            fcntl.flock(handle, fcntl.LOCK_UN)
        finally:
            handle.close()


def resolve_output(out_dir: Path, name: str) -> Path:
    """An output file path: absolute names are kept, relative ones go into ``out_dir``."""
    p = Path(name)
    return p if p.is_absolute() else out_dir / p

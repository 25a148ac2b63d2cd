"""Output folders: every command writes under one folder, by default a new
outputs/<command>/<time> (made unique: two runs started in the same second get two folders).

While a run writes, it holds an exclusive lock on ``<folder>/.fishsim.lock`` (``fcntl.flock``,
released when the command ends or the process dies), so a second run pointed at the same folder
stops at once with one line instead of corrupting the first one's files.

A run that ends having written nothing (an input error found after the folder was made) leaves
no trace: ``release_locks`` removes the folders and the lock file this process created when they
hold no file, so a failed command never leaves an empty run folder behind.
"""

from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path

from fishsim.errors import ConfigError

LOCK_NAME = ".fishsim.lock"
_held: dict = {}          # folder -> open lock file of this process (released by release_locks)
_created: list = []       # folders (and lock files) this process created, removed again if left unused


def make_out_dir(command: str, out_dir: str | None) -> Path:
    """Create (if needed), lock and return the output folder: ``out_dir`` if given, else a new
    outputs/<command>/<YYYY-mm-dd_HH-MM-SS>[_n]. ConfigError (one line) if it cannot be made
    or written, or another run is writing to it."""
    if out_dir:
        path = _given_folder(Path(out_dir))
    else:
        path = _new_folder(Path("outputs") / command / time.strftime("%Y-%m-%d_%H-%M-%S"))
    lock(path)
    return path


def _given_folder(path: Path) -> Path:
    """``path`` made (with its parents) if missing; ConfigError if it is a file or cannot be made."""
    if path.exists() and not path.is_dir():
        raise ConfigError(f"out_dir={path} is a file, not a folder (choose another out_dir)")
    _mkdirs(path, lambda err: f"cannot create out_dir={path}: {err.strerror} (choose a writable folder)")
    return path


def _mkdirs(path: Path, message) -> None:
    """mkdir -p that remembers which folders it made (``message(OSError)``: the ConfigError's text)."""
    missing = [p for p in (path, *path.parents) if not p.exists()]
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(message(err)) from None
    _created.extend(reversed(missing))        # outermost first; cleaned up innermost first


def _new_folder(base: Path) -> Path:
    """base, or base_2, base_3, ...: the first that did not exist (mkdir is the atomic test)."""
    _mkdirs(base.parent, lambda err: f"cannot create the output folder {base.parent}: {err.strerror} "
                                     "(run from a writable folder or give out_dir=...)")
    for n in range(1, 10_000):
        path = base if n == 1 else base.with_name(f"{base.name}_{n}")
        try:
            path.mkdir()
        except FileExistsError:
            continue
        _created.append(path)
        return path
    raise ConfigError(f"could not find a free output folder next to {base} (give out_dir=...)")


def lock(folder: Path) -> None:
    """Hold an exclusive lock on the folder until release_locks() or the process ends (a folder
    this process already holds stays held: one process runs its commands one after another)."""
    key = str(folder.resolve())
    if key in _held:
        return
    lock_file = folder / LOCK_NAME
    new = not lock_file.exists()
    try:
        handle = open(lock_file, "a+")  # noqa: SIM115 - held open for the whole run
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
    if new:
        _created.append(lock_file)


def folders_written() -> list[Path]:
    """The folders this process holds that a run has written a file in (not just the lock)."""
    return [Path(key) for key in _held if _has_files(Path(key), ignore=Path(key) / LOCK_NAME)]


def release_locks() -> None:
    """Release the folders this process locked (the CLI calls it when a command ends), first
    removing what it created and left unused (``discard_unused``)."""
    discard_unused()
    while _held:
        _, handle = _held.popitem()
        try:
            fcntl.flock(handle, fcntl.LOCK_UN)
        finally:
            handle.close()


def discard_unused() -> None:
    """Remove the lock files and folders this process created that hold no file (innermost
    first, while the lock is still held, so no other run can be writing there)."""
    while _created:
        path = _created.pop()
        if path.name == LOCK_NAME:
            if _only_lock(path.parent):
                path.unlink(missing_ok=True)
        elif str(path.resolve()) in _held:      # a run folder: its own empty sub-folders go with it
            if not _has_files(path):
                _remove_empty_tree(path)
        else:                                   # a parent: only if empty (another run may be starting in it)
            _rmdir(path)


def _only_lock(folder: Path) -> bool:
    return not _has_files(folder, ignore=folder / LOCK_NAME)


def _has_files(folder: Path, ignore: Path | None = None) -> bool:
    """Any file (not a folder) below ``folder`` other than ``ignore``."""
    return any(p != ignore and not p.is_dir() for p in folder.rglob("*"))


def _remove_empty_tree(folder: Path) -> None:
    """rmdir every (empty) folder below and then ``folder`` itself; a file that appeared in the
    meantime (another run) keeps it."""
    for sub in sorted((p for p in folder.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        _rmdir(sub)
    _rmdir(folder)


def _rmdir(folder: Path) -> None:
    try:
        folder.rmdir()
    except OSError:
        pass


def resolve_output(out_dir: Path, name: str) -> Path:
    """An output file path: absolute names are kept, relative ones go into ``out_dir``."""
    p = Path(name)
    return p if p.is_absolute() else out_dir / p


def output_file(out_dir: Path, name: str, example: str) -> Path:
    """``resolve_output`` for a file the command is about to write, refused with one line
    (ConfigError) when it names a folder or its folder cannot be made; ``example``: a good name."""
    path = resolve_output(out_dir, name)
    if path.is_dir():
        raise ConfigError(f"output={name} is a folder; name a file, e.g. output={example}")
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise ConfigError(f"output={name}: {parent} is a file, not a folder (choose another output)")
    _mkdirs(parent, lambda err: f"cannot create the folder of output={name}: {err.strerror} (choose another output)")
    return path

"""The run record, Hydra's run-folder convention: every command run from the CLI leaves beside its
outputs

    .hydra/config.yaml      the resolved config (``fishsim <command> --config .hydra/config.yaml``
                            runs it again)
    .hydra/overrides.yaml   the command-line overrides, as given
    .hydra/fishsim.yaml     command, fishsim version, git commit (and whether the checkout had
                            changes), argv, start and end time, how the run ended
    <command>.log           what the command printed (stdout and stderr, control codes removed,
                            at most MAX_LOG_LINES lines: the first and last halves)

The CLI calls ``begin`` once the config is valid and ``end`` when the command stops, for the
output folders the run wrote files in (a run stopped by an input error writes none, so it still
leaves no folder behind).
"""

from __future__ import annotations

import io
import re
import subprocess
import sys
import time
from pathlib import Path

MAX_LOG_LINES = 4000
_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07")


class _Tee(io.TextIOBase):
    """A text stream writing to ``stream`` and keeping a copy (isatty and encoding are the
    stream's, so progress bars still draw on a terminal)."""

    def __init__(self, stream, copy: io.StringIO):
        self.stream, self.copy = stream, copy

    def write(self, text: str) -> int:
        self.copy.write(text)
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()

    def isatty(self) -> bool:
        return self.stream.isatty()

    @property
    def encoding(self):
        return getattr(self.stream, "encoding", "utf-8")

    def fileno(self) -> int:
        return self.stream.fileno()


_run: dict | None = None


def begin(command: str, config_yaml: str, overrides: list[str]) -> None:
    """Start recording a run: remember its config and overrides, copy stdout and stderr."""
    global _run
    copy = io.StringIO()
    _run = {"command": command, "config": config_yaml, "overrides": list(overrides), "copy": copy,
            "streams": (sys.stdout, sys.stderr), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "argv": list(sys.argv)}
    sys.stdout, sys.stderr = _Tee(sys.stdout, copy), _Tee(sys.stderr, copy)


def end(folders: list[Path], status: str) -> None:
    """Stop recording and write the record into every folder in ``folders``; ``status`` says how
    the run ended ("complete", "error: ...", "interrupted", "terminated")."""
    global _run
    if _run is None:
        return
    run, _run = _run, None
    sys.stdout, sys.stderr = run["streams"]
    if not folders:
        return
    from omegaconf import OmegaConf

    from fishsim import __version__

    commit, dirty = git_commit()
    about = {"command": run["command"], "fishsim_version": __version__, "git_commit": commit,
             "git_dirty": dirty, "argv": run["argv"], "started": run["started"],
             "ended": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "status": status}
    log = log_text(run["copy"].getvalue())
    for folder in folders:
        hydra = Path(folder) / ".hydra"
        hydra.mkdir(exist_ok=True)
        (hydra / "config.yaml").write_text(run["config"])
        (hydra / "overrides.yaml").write_text(OmegaConf.to_yaml(run["overrides"]))
        (hydra / "fishsim.yaml").write_text(OmegaConf.to_yaml(about))
        (Path(folder) / f"{run['command']}.log").write_text(log)


def log_text(raw: str) -> str:
    """Printed text as a log: terminal control codes removed, each carriage-return-overwritten
    line reduced to what was left showing, at most MAX_LOG_LINES lines."""
    lines = [line.rsplit("\r", 1)[-1] for line in _ANSI.sub("", raw).split("\n")]
    if len(lines) > MAX_LOG_LINES:
        half = MAX_LOG_LINES // 2
        lines = lines[:half] + [f"[... {len(lines) - 2 * half} lines left out ...]"] + lines[-half:]
    return "\n".join(lines)


def git_commit() -> tuple[str, bool | None]:
    """(commit hash, whether the checkout has uncommitted changes) of the fishsim source tree;
    ("unknown", None) outside a git checkout (an installed wheel)."""
    where = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True,
                                timeout=5, check=True).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=where,
                                capture_output=True, text=True, timeout=5, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown", None
    return commit, bool(status.strip())

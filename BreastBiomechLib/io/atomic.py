"""Atomic writes: every file the project writes appears whole or not at all.

A file is written under a temporary name beside it (same folder, so the same file system, and
the same extension, so SimpleITK and VTK pick the same format) and renamed over the final name
once complete: a run killed mid-write leaves at most a ``.partial-*`` file that no reader looks
for, never a truncated file under the real name that a resumed run would take as finished. The
temporary name holds the writer's process id and host, so that the next run claiming the folder
removes what a dead writer left (:func:`~BreastBiomechLib.io.claims.claimed`).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
from pathlib import Path

PARTIAL = re.compile(r"^\.partial-(?P<pid>\d+)@(?P<host>[^@/]*)@")  # .partial-PID@HOST@NAME


def partial_path(path: Path) -> Path:
    """The temporary name under which this process writes ``path``."""
    return path.with_name(f".partial-{os.getpid()}@{socket.gethostname()}@{path.name}")


@contextlib.contextmanager
def atomic_path(path: str | Path):
    """``with atomic_path(path) as temporary: write(temporary)``: on leaving without an error the
    written file replaces ``path`` (made with its parent folders), else it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = partial_path(path)
    try:
        yield temporary
        if temporary.exists():
            with open(temporary, "rb+") as stream:  # on disk before the rename makes it visible
                os.fsync(stream.fileno())
        os.replace(temporary, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            temporary.unlink()


def write_text_atomically(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically; returns the path."""
    with atomic_path(path) as temporary:
        temporary.write_text(text)
    return Path(path)


def write_json_atomically(path: str | Path, document, indent: int = 2) -> Path:
    """Write ``document`` as JSON (NaN allowed, numpy scalars as floats) to ``path`` atomically."""
    return write_text_atomically(path, json.dumps(document, indent=indent, default=float) + "\n")

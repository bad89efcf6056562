"""An output folder claimed by the run that writes it, so that a second process pointed at the
same folder (a fit, a study or a diagnosis started twice, or resumed while the first still runs)
is refused instead of interleaving its writes with the first's.

The claim is a file ``.in-use.json`` in the folder, made with O_EXCL and holding the process id,
host, start time and what the run is. It is removed when the run ends, however it ends. A run that
was killed leaves it behind: the next run on the same host sees that the process is gone and takes
the folder over (kill and resume must work); a claim from another host (a shared filesystem) is
never taken over silently: the message says how to clear it. A run that claims a folder removes
the temporary files (:mod:`~BreastBiomechLib.io.atomic`) that writers on this host, no longer
running, left in it or below it when they were killed mid-write.
"""

from __future__ import annotations

import json
import os
import socket
import time
from contextlib import contextmanager
from pathlib import Path

from BreastBiomechLib.io.atomic import PARTIAL

CLAIM_FILE = ".in-use.json"
UNWRITTEN_CLAIM_S = 10.0  # an empty claim older than this was cut short by a kill


class FolderInUse(ValueError):
    """An output folder another running process is writing."""


def holder_of(path: Path) -> dict | None:
    """The record of the claim (or lock) file ``path``, or None where it is empty or cut short."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and "pid" in record else None


def _alive(pid: int) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    except (OverflowError, ValueError):
        return False
    return True


def remove_dead_partials(folder: Path) -> list[Path]:
    """Remove the atomic writes' temporary files in ``folder`` and below whose writer, on this
    host, is no longer running (killed mid-write); those of live writers or other hosts stay.
    The files removed."""
    host, removed = socket.gethostname(), []
    for path in Path(folder).rglob(".partial-*"):
        match = PARTIAL.match(path.name)
        if match and match["host"] == host and not _alive(int(match["pid"])) and path.is_file():
            path.unlink(missing_ok=True)
            removed.append(path)
    return removed


def is_stale(path: Path, holder: dict | None) -> bool:
    """Whether the claim (or lock) file ``path`` whose record is ``holder`` can be taken over: its
    process, on this host, is gone; or it was never written out (killed between making and
    writing it)."""
    if holder is None:
        try:
            return time.time() - path.stat().st_mtime > UNWRITTEN_CLAIM_S
        except FileNotFoundError:
            return True
    return holder.get("host") == socket.gethostname() and not _alive(holder["pid"])


@contextmanager
def claimed(folder: str | Path | None, what: str):
    """Hold ``folder`` (made if missing) for the run described by ``what`` (e.g. "a study")
    while the ``with`` block runs; :class:`FolderInUse` if another live process holds it. A claim
    this process already holds (a fit inside a study writing the same folder) is kept. None: a
    run that writes no folder, nothing to claim."""
    if folder is None:
        yield None
        return
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / CLAIM_FILE
    record = {"pid": os.getpid(), "host": socket.gethostname(), "what": what,
              "started": time.strftime("%Y-%m-%d %H:%M:%S")}
    owner = False
    for _ in range(3):
        try:
            descriptor = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            holder = holder_of(path)
            if holder is not None and holder.get("pid") == os.getpid() and holder.get("host") == record["host"]:
                break  # held by this process already
            if is_stale(path, holder):
                path.unlink(missing_ok=True)
                continue
            who = (f"{holder.get('what', 'a run')} (process {holder['pid']} on {holder.get('host', '?')}, since "
                   f"{holder.get('started', '?')})" if holder else "a run that is starting")
            raise FolderInUse(f"{folder} is in use by {who}: wait for it to end or give another output folder; if "
                              f"that run is no longer going, remove {path}") from None
        with os.fdopen(descriptor, "w") as file:
            file.write(json.dumps(record) + "\n")
        owner = True
        break
    else:
        raise FolderInUse(f"{folder}: could not claim it ({path} keeps coming back); is another run starting there?")
    remove_dead_partials(folder)
    try:
        yield folder
    finally:
        if owner:
            path.unlink(missing_ok=True)

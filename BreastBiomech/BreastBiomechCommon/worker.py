"""Long work out of Slicer's process: a ``breastbiomech`` command run as a child process whose
progress the panel reads while the GUI stays live.

A panel starts :class:`CommandWorker` with the command's arguments (``simulate``, ``optimise``,
``diagnose``; always with ``--progress json``), polls it from a ``qt.QTimer`` (:meth:`poll`
returns the events that arrived since the last call, never blocks) and, when it has ended,
loads the results from the output folder with the same library code a headless run uses.
Cancel terminates the process (:meth:`cancel`); what the command had written is whole (its
files are written atomically) and the same command with ``--resume`` goes on from it. A GPU
fault or an out-of-memory kills the worker, not Slicer: the panel reads :attr:`error`.

The child runs the library of this extension (its folder first on ``PYTHONPATH``) in Slicer's
own Python: ``PythonSlicer`` inside the application (where ``sys.executable`` is Slicer itself),
this interpreter headless. No Qt here: the same class is tested headless and runs in Slicer.
The events are those of ``BreastBiomechLib/cli/events.py``.
"""

from __future__ import annotations

import collections
import json
import os
import queue
import shutil
import subprocess
import sys
import threading
import time

STDERR_LINES = 200  # the end of the child's standard error kept for an error message
POLL_INTERVAL_MS = 250  # how often a panel's timer calls poll()


def python_executable() -> str:
    """The Python to run the library in: Slicer's ``PythonSlicer`` in the application (its
    environment, its packages), else this interpreter."""
    if os.path.basename(sys.executable).lower().startswith("python"):
        return sys.executable
    return shutil.which("PythonSlicer") or sys.executable


def library_folder() -> str:
    """The folder holding ``BreastBiomechLib``: beside the module scripts in a built extension,
    the checkout's root in a source tree."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for folder in (here, os.path.dirname(here)):
        if os.path.isdir(os.path.join(folder, "BreastBiomechLib")):
            return folder
    raise FileNotFoundError(f"BreastBiomechLib is neither in {here} nor in {os.path.dirname(here)}: "
                            "the extension is incomplete; reinstall it")


class CommandWorker:
    """``breastbiomech ARGUMENTS --progress json`` in a child process.

    ``events`` holds every event read so far (dicts), ``last`` the latest progress event,
    ``returncode`` the exit code once ended (negative: killed by that signal), ``error`` the
    reason it failed (None while running or when it succeeded). ``folder``: where the command
    writes (the caller's note, for loading the results)."""

    def __init__(self, arguments: list[str], folder=None, environment: dict | None = None):
        if not arguments:
            raise ValueError("a worker needs a command, e.g. ['simulate', 'case.json', '--out', 'folder']")
        self.arguments = [str(a) for a in arguments]
        if "--progress" not in self.arguments:
            self.arguments += ["--progress", "json"]
        self.folder = folder
        self.environment = environment
        self.events: list[dict] = []
        self.last: dict | None = None
        self.process: subprocess.Popen | None = None
        self.started = self.ended = None
        self.cancelled = False
        self._queue: queue.Queue = queue.Queue()
        self._stderr: collections.deque = collections.deque(maxlen=STDERR_LINES)
        self._readers: list[threading.Thread] = []

    # -- life --------------------------------------------------------------------------------

    def start(self) -> "CommandWorker":
        """Start the child process (returns at once)."""
        if self.process is not None:
            raise RuntimeError("this worker has been started already: make a new one")
        env = dict(os.environ if self.environment is None else self.environment)
        env["PYTHONPATH"] = os.pathsep.join([library_folder(), *filter(None, [env.get("PYTHONPATH")])])
        env["PYTHONUNBUFFERED"] = "1"
        env.setdefault("PYTHONIOENCODING", "utf-8")
        command = [python_executable(), "-m", "BreastBiomechLib", *self.arguments]
        flags = getattr(subprocess, "CREATE_NO_WINDOW", 0)  # no console window on Windows
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                        stdin=subprocess.DEVNULL, env=env, text=True, encoding="utf-8",
                                        errors="replace", creationflags=flags)
        self.started = time.perf_counter()
        for stream, handle in ((self.process.stdout, self._event_line), (self.process.stderr, self._stderr.append)):
            reader = threading.Thread(target=self._read, args=(stream, handle), daemon=True)
            reader.start()
            self._readers.append(reader)
        return self

    @staticmethod
    def _read(stream, handle) -> None:
        for line in iter(stream.readline, ""):
            handle(line.rstrip("\n"))
        stream.close()

    def _event_line(self, line: str) -> None:
        try:
            event = json.loads(line)
        except json.JSONDecodeError:
            event = None
        if not isinstance(event, dict) or "event" not in event:
            self._stderr.append(line)  # not an event (a library printed to standard output): kept as text
            return
        self._queue.put(event)

    def poll(self) -> list[dict]:
        """The events that arrived since the last call (never blocks); also notes the end."""
        new = []
        while True:
            try:
                new.append(self._queue.get_nowait())
            except queue.Empty:
                break
        self.events += new
        progress = [e for e in new if e["event"] == "progress"]
        if progress:
            self.last = progress[-1]
        if self.ended is None and self.process is not None and self.process.poll() is not None \
                and not any(r.is_alive() for r in self._readers):
            self.ended = time.perf_counter()
            self.poll()  # what the readers queued before they ended
        return new

    @property
    def running(self) -> bool:
        return self.process is not None and self.ended is None and (self.process.poll() is None or
                                                                    any(r.is_alive() for r in self._readers))

    @property
    def returncode(self) -> int | None:
        return None if self.process is None else self.process.poll()

    @property
    def succeeded(self) -> bool:
        return self.returncode == 0 and any(e["event"] == "done" for e in self.events)

    @property
    def error(self) -> str | None:
        """Why the command failed, for the panel: its own error sentence, else the end of its
        standard error (a crash, a GPU fault, out of memory), else its exit code."""
        code = self.returncode
        if code is None or self.succeeded:
            return None
        if self.cancelled:
            return "cancelled"
        said = [e["message"] for e in self.events if e["event"] == "error"]
        if said:
            return said[-1]
        tail = "\n".join(list(self._stderr)[-15:]).strip()
        how = f"killed by signal {-code}" if code < 0 else f"exit code {code}"
        return f"breastbiomech {self.arguments[0]} stopped ({how})" + (f":\n{tail}" if tail else "")

    def stderr_text(self) -> str:
        return "\n".join(self._stderr)

    def outputs(self) -> dict:
        """What the command said it wrote (its last event's ``outputs``: {name: value})."""
        return next((e.get("outputs", {}) for e in reversed(self.events) if e["event"] == "done"), {})

    def wait(self, timeout_s: float | None = None, every_s: float = POLL_INTERVAL_MS / 1000.0,
             on_events=None) -> int:
        """Poll until the command ends (``on_events(new events)`` after each poll that brought
        some; a headless caller's loop, a panel uses its timer instead); its exit code. Raises
        TimeoutError after ``timeout_s``."""
        deadline = None if timeout_s is None else time.perf_counter() + timeout_s
        while True:
            new = self.poll()
            if new and on_events is not None:
                on_events(new)
            if not self.running:
                self.poll()
                return self.returncode
            if deadline is not None and time.perf_counter() > deadline:
                raise TimeoutError(f"breastbiomech {self.arguments[0]} still running after {timeout_s} s")
            time.sleep(every_s)

    def cancel(self, grace_s: float = 5.0) -> float:
        """Stop the command: terminate, and kill it if it has not ended after ``grace_s``.
        Returns the seconds from the request to the ended process (0 when it had ended)."""
        if self.process is None or self.process.poll() is not None:
            return 0.0
        asked = time.perf_counter()
        self.cancelled = True
        self.process.terminate()
        try:
            self.process.wait(grace_s)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        for reader in self._readers:
            reader.join(timeout=grace_s)
        self.poll()
        return time.perf_counter() - asked

"""A CPU batch's variants solved side by side on the CPU's cores.

warp runs a CPU kernel in one thread, so a batch of B variants (a fit's population, a diagnosis
round's variants) on a CPU device uses one core however many the machine has. Where a batch holds
more than one variant, :func:`solve_on_cores` splits it into contiguous chunks, one per worker
process, each solved by :func:`~BreastBiomechLib.solver.tled.solve_batch` as a batch of its own;
the solutions come back in the variants' order. A chunk takes the smallest critical step of its
own variants (not of the whole batch), so the results equal the serial solve's within the
relaxation's tolerance, and are the same from run to run for the same number of workers.

How many workers: ``BREASTBIOMECH_CPU_WORKERS`` (a whole number; 1 solves in this process as
before), else the cores this process may use. The workers are started on the first batch
(``spawn``: a fresh interpreter each, which imports warp and loads its kernel cache, about 2 s)
and kept for the next ones, each ending when the process that started them ends (however it
ends: a killed command leaves no worker solving); their standard output goes to standard error,
so that a command's ``--progress json`` stream stays events only. Never from inside the Slicer application's own
process (its executable is not a Python interpreter, and a spawned copy of it would be a second
Slicer): there the batch is solved in one process, as the panels' long runs are in a process of
their own (``PythonSlicer``) where the cores are used. Nor from a daemon process (a Dask cohort's
worker, which may not start processes; the cohort uses the cores by running tasks side by side).

Progress and cancellation cross the processes through shared memory: each chunk writes its
fraction done to its slot, the caller's ``progress`` gets their mean about four times a second,
and when it returns False every chunk stops at its next sample (status "cancelled")."""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import sys
import threading
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool

ENVIRONMENT = "BREASTBIOMECH_CPU_WORKERS"
POLL_S = 0.25  # how often the caller's progress is called while the chunks run

_lock = threading.Lock()  # one batch at a time uses the pool
_pool: ProcessPoolExecutor | None = None
_pool_size = 0
_shared = None  # (fractions: Array of doubles, one per worker; cancel: Value)

# in a worker process: the shared progress slots and cancel flag
_worker_fractions = None
_worker_cancel = None


def cpu_workers(batch: int) -> int:
    """How many worker processes a CPU batch of ``batch`` variants is split over: at most one per
    variant, ``BREASTBIOMECH_CPU_WORKERS`` or the cores this process may use; 1 in the Slicer
    application's process and in a daemon process (a Dask worker's)."""
    value = os.environ.get(ENVIRONMENT, "").strip()
    if value:
        try:
            wanted = int(value)
        except ValueError:
            raise ValueError(f"{ENVIRONMENT} must be a whole number of worker processes (1: no workers), "
                             f"not {value!r}") from None
        if wanted < 1:
            raise ValueError(f"{ENVIRONMENT} must be at least 1 (1: no workers), not {wanted}")
    else:
        wanted = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if not _python_executable() or _in_daemon():
        return 1
    return max(1, min(wanted, batch))


def _in_daemon() -> bool:
    """Whether this process is a daemon, which may not start processes (a Dask worker is one: a
    cohort on the CPU runs its tasks side by side, each in one process)."""
    return bool(multiprocessing.current_process().daemon)


def _python_executable() -> bool:
    """Whether ``sys.executable`` is a Python interpreter that ``spawn`` can start (python3.12,
    PythonSlicer, python.exe), not an application embedding Python (SlicerApp-real)."""
    name = os.path.basename(sys.executable or "").lower()
    return name.startswith("python")


def _start_worker(fractions, cancel) -> None:
    """A worker process's start: its standard output to standard error, the shared slots kept,
    and a watch that ends it when the process that started the pool ends."""
    global _worker_fractions, _worker_cancel
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    _worker_fractions, _worker_cancel = fractions, cancel
    parent = multiprocessing.parent_process()
    if parent is not None:
        threading.Thread(target=_end_with, args=(parent,), daemon=True, name="ends with its parent").start()


def _end_with(parent) -> None:
    """In a worker: wait until ``parent`` (the process that started the pool) has ended, then end
    this process. A command killed mid-batch, or a Slicer panel's run cancelled by ending its
    process, would otherwise leave its workers solving their chunks to the end, orphaned."""
    parent.join()
    os._exit(1)


def _solve_chunk(slot: int, model, materials, plate_displacements, plates, options: dict) -> list:
    """One chunk, in a worker: :func:`~BreastBiomechLib.solver.tled.solve_batch` of its variants
    on the CPU, its progress written to ``slot``, stopped when the caller cancels."""
    from BreastBiomechLib.solver.tled import solve_batch

    def progress(fraction: float) -> bool:
        _worker_fractions[slot] = fraction
        return _worker_cancel.value == 0

    solutions = solve_batch(model, materials, plate_displacements, device="cpu", plates=plates, progress=progress,
                            cpu_workers=1, **options)
    _worker_fractions[slot] = 1.0
    return solutions


def _pool_of(size: int) -> ProcessPoolExecutor:
    """The pool, with at least ``size`` workers: a larger one is kept for a smaller batch (a fit's
    population of 5 after a round of 16 variants does not start new processes)."""
    global _pool, _pool_size, _shared
    if _pool is None or _pool_size < size:
        if _pool is not None:
            _pool.shutdown(wait=True)
        context = multiprocessing.get_context("spawn")
        _shared = (context.Array("d", size, lock=False), context.Value("i", 0, lock=False))
        _pool = ProcessPoolExecutor(size, mp_context=context, initializer=_start_worker, initargs=_shared)
        _pool_size = size
    return _pool


def chunks(batch: int, workers: int) -> list[range]:
    """The variants' indices split into ``workers`` contiguous chunks whose sizes differ by one at
    most (the first ones the larger)."""
    size, extra = divmod(batch, workers)
    out, start = [], 0
    for i in range(workers):
        stop = start + size + (1 if i < extra else 0)
        if stop > start:
            out.append(range(start, stop))
        start = stop
    return out


def solve_on_cores(model, materials: list, plate_displacements: list | None, plates: list | None, workers: int,
                   progress: Callable[[float], bool | None] | None = None, **options) -> list | None:
    """The solutions of the batch (``materials[b]``, optionally ``plate_displacements[b]`` or
    ``plates[b]``) solved in ``workers`` processes, in the variants' order; None when another batch
    of this process is using the pool (the caller solves it here). ``options``: solve_batch's other
    keywords (relaxation, warm start, sampling...), the same for every chunk."""
    if not _lock.acquire(blocking=False):
        return None
    try:
        pool = _pool_of(workers)
        fractions, cancel = _shared
        cancel.value = 0
        parts = chunks(len(materials), workers)  # at most the pool's size: one worker each
        for slot in range(len(fractions)):
            fractions[slot] = 0.0

        def pick(items, part):
            return None if items is None else [items[b] for b in part]

        with _main_hidden():
            futures = {pool.submit(_solve_chunk, slot, model, pick(materials, part), pick(plate_displacements, part),
                                   pick(plates, part), options): part for slot, part in enumerate(parts)}
        pending = set(futures)
        while pending:
            _, pending = wait(pending, timeout=POLL_S, return_when=FIRST_COMPLETED)
            if progress is not None and cancel.value == 0:
                done = sum(fractions[slot] * len(part) for slot, part in enumerate(parts)) / len(materials)
                if progress(done) is False:
                    cancel.value = 1
        solutions: list = [None] * len(materials)
        try:
            for future, part in futures.items():
                for b, solution in zip(part, future.result()):
                    solutions[b] = solution
        except BrokenProcessPool as error:  # a worker died (killed, out of memory): the next batch starts new ones
            _forget_pool()
            raise RuntimeError(f"a CPU worker process solving the batch ended unexpectedly ({error}); set "
                               f"{ENVIRONMENT}=1 to solve in this process") from error
        return solutions
    finally:
        _lock.release()


@contextlib.contextmanager
def _main_hidden():
    """The main module without its file and spec while workers are started: ``spawn`` would run
    the caller's script again in every worker (a script without an ``if __name__ == "__main__"``
    guard would solve its batches there too, or fail); the workers need only this library."""
    main = sys.modules.get("__main__")
    saved = {name: getattr(main, name) for name in ("__file__", "__spec__") if hasattr(main, name)}
    try:
        for name in saved:
            if name == "__spec__":
                main.__spec__ = None
            else:
                delattr(main, name)
        yield
    finally:
        for name, value in saved.items():
            setattr(main, name, value)


def _forget_pool() -> None:
    global _pool, _pool_size
    if _pool is not None:
        _pool.shutdown(wait=False, cancel_futures=True)
    _pool, _pool_size = None, 0

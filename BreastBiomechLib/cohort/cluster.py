"""Where a cohort's tasks run: in this process, on a local Dask cluster made for the run (one
worker process per GPU, each pinned to its GPU; on a machine without one, a worker per core), or
on an existing cluster given by its scheduler's address (``--scheduler``, or the environment
variable ``BREASTBIOMECH_SCHEDULER``): a ``dask scheduler`` started by hand, dask-jobqueue on
Slurm/PBS, dask-cuda, Kubernetes.

Pinning: a local worker sees only its GPU (``CUDA_VISIBLE_DEVICES``), so its tasks solve on
warp's "cuda" device; several workers may share a GPU (``workers`` > GPUs: round robin).
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
from dataclasses import dataclass

import psutil

SCHEDULER_ENVIRONMENT = "BREASTBIOMECH_SCHEDULER"


@dataclass(frozen=True)
class Placement:
    """Where a run's tasks go: an existing cluster's ``scheduler`` address (None: none), the
    number of local ``workers`` (0: every task in this process, one after another), the GPU
    ordinals the local workers are pinned to round robin (empty: CPU workers), and the warp
    device string a task is given (None: warp's default where it runs)."""

    scheduler: str | None
    workers: int
    gpus: tuple[int, ...]
    task_device: str | None

    def describe(self) -> str:
        if self.scheduler:
            return f"the Dask cluster at {self.scheduler}"
        if self.workers == 0:
            return "this process, one task after another"
        if self.gpus:
            used = self.gpus[:self.workers]  # worker i on GPU gpus[i % len(gpus)]
            return (f"a local Dask cluster of {self.workers} worker{'s' * (self.workers != 1)} on GPU"
                    f"{'s' * (len(used) != 1)} {', '.join(map(str, used))}")
        return f"a local Dask cluster of {self.workers} CPU worker{'s' * (self.workers != 1)}"


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _gpu_count() -> int:
    import warp as wp

    wp.init()
    return wp.get_cuda_device_count()


def place(scheduler: str | None = None, workers: int | None = None, device: str | None = None) -> Placement:
    """Decide where tasks run. ``scheduler``: an existing cluster's address (default: the
    environment's ``BREASTBIOMECH_SCHEDULER``); otherwise a local cluster of ``workers`` worker
    processes (None: one per GPU of ``device``, or one per core for the CPU; 0: in this process).
    ``device``: "cpu", "cuda" (every GPU), "cuda:K" (GPU K only) or None (the GPUs where there are
    any, else the CPU). Refuses contradictory or impossible choices with what to do."""
    scheduler = scheduler or os.environ.get(SCHEDULER_ENVIRONMENT) or None
    if workers is not None and workers < 0:
        raise ValueError(f"--workers must be 0 (this process) or more, not {workers}")
    if scheduler:
        if workers is not None:
            raise ValueError(f"--workers sizes a local cluster; with a scheduler ({scheduler}) its cluster has "
                             f"the workers it has: drop --workers or the scheduler (unset {SCHEDULER_ENVIRONMENT})")
        if "://" not in scheduler and ":" not in scheduler:
            raise ValueError(f"a scheduler address looks like tcp://HOST:PORT, not {scheduler!r}")
        return Placement(scheduler, 0, (), device)
    if workers == 0:
        return Placement(None, 0, (), device)
    if device == "cpu":
        gpus: tuple[int, ...] = ()
    elif device is None or device == "cuda":
        count = _gpu_count()
        if device == "cuda" and count == 0:
            raise ValueError("--device cuda: this machine has no CUDA device; use --device cpu")
        gpus = tuple(range(count))
    elif device.startswith("cuda:") and device[5:].isdigit():
        ordinal, count = int(device[5:]), _gpu_count()
        if ordinal >= count:
            raise ValueError(f"--device {device}: this machine has {count} CUDA device(s) (cuda:0 to cuda:{count - 1})")
        gpus = (ordinal,)
    else:
        raise ValueError(f"--device takes cpu, cuda or cuda:K, not {device!r}")
    count = workers if workers is not None else (len(gpus) or _cores())
    return Placement(None, count, gpus, "cuda" if gpus else "cpu")


# Dask's sampling profiler takes the running task's frames from the worker's event-loop thread;
# a frame it still holds when its function returns keeps the function's locals, which are then
# freed in that thread - warp arrays and CUDA graphs among them, released by warp at whatever
# moment, also while the task's thread is opening or closing a CUDA graph capture, where warp's
# own check of "a capture is on" races (CUDA error 906, "operation would make the legacy stream
# depend on a capturing blocking stream", in warp's release_now, then 901 in the task's
# capture: the varied suite lost 4 of 20 cases to it on 2026-12-07). The workers of a local
# cluster run without it; those of a cluster the user starts need the same setting
# (docs/cohorts.md).
WORKER_CONFIG = {"distributed.worker.profile.enabled": False}


def _local_cluster(placement: Placement, dashboard: str | None):
    """A Dask cluster on this machine with ``placement.workers`` single-threaded worker
    processes, worker i pinned to GPU ``gpus[i % len(gpus)]``, host memory and ITK's threads
    shared out evenly."""
    import dask
    from distributed import Nanny, Scheduler, SpecCluster

    memory = int(psutil.virtual_memory().total // placement.workers)
    # the cores shared out too: ITK (SimpleITK's filters) otherwise starts a thread per core in
    # every worker (Dask's nanny already sets OpenMP and BLAS to one thread)
    itk_threads = str(max(1, _cores() // placement.workers))
    workers = {}
    for i in range(placement.workers):
        env = {"ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS": itk_threads}
        if placement.gpus:
            env["CUDA_VISIBLE_DEVICES"] = str(placement.gpus[i % len(placement.gpus)])
        workers[f"breastbiomech-{i}"] = {"cls": Nanny, "options": {"nthreads": 1, "env": env,
                                                                   "memory_limit": memory,
                                                                   "silence_logs": logging.CRITICAL,
                                                                   "config": WORKER_CONFIG}}
    scheduler = {"cls": Scheduler, "options": {"dashboard_address": dashboard or ":0",
                                               "dashboard": dashboard is not None}}
    # a worker is sent a task only when it is free, so a long task never waits in a busy worker's
    # queue while another worker idles (Dask's default, 1.1, queues one more per thread)
    with dask.config.set({"distributed.scheduler.worker-saturation": 1.0}):
        return SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.ERROR)


@contextlib.contextmanager
def cohort_client(placement: Placement, dashboard: str | None = ":8787"):
    """A ``distributed.Client`` for ``placement`` (not for in-process placements): connected to
    its scheduler, or to a local cluster made here and closed on leaving (its workers with it).
    ``dashboard``: where a local cluster serves its dashboard (None: none; it needs bokeh)."""
    from distributed import Client

    if placement.workers == 0 and not placement.scheduler:
        raise ValueError("an in-process placement has no cluster")
    if placement.scheduler:
        try:
            client = Client(placement.scheduler, timeout="20s")
        except OSError as error:
            raise RuntimeError(f"cannot reach the Dask scheduler at {placement.scheduler} ({error}); start it "
                               "(`dask scheduler`, dask-jobqueue) or leave --scheduler out for a local cluster") from None
        with client:
            yield client
        return
    if dashboard is not None and importlib.util.find_spec("bokeh") is None:  # the dashboard needs bokeh
        dashboard = None
    cluster = _local_cluster(placement, dashboard)
    try:
        with Client(cluster) as client:
            yield client
    finally:
        cluster.close(timeout=30)


def dashboard_link(client) -> str | None:
    """The address of the cluster's dashboard, or None where it serves none."""
    try:
        info = client.scheduler_info()
    except Exception:  # noqa: BLE001 - a missing dashboard is not an error
        return None
    if "dashboard" not in info.get("services", {}):
        return None
    return client.dashboard_link

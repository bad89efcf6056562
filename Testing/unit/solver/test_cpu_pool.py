"""A CPU batch split over worker processes (solver/cpu_pool.py): the same solutions as one
process within the relaxation's tolerance, in the variants' order, with progress and cancel
crossing the processes, and the worker count read and checked from the environment."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from BreastBiomechLib.solver import DynamicRelaxation, solve_batch
from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
from BreastBiomechLib.solver import cpu_pool
from BreastBiomechLib.solver.cpu_pool import ENVIRONMENT, chunks, cpu_workers
from BreastBiomechLib.solver.materials import ElementMaterials, Material


def _batch():
    model = hemi_ellipsoid_compression(14.0, compression=0.2)
    n = len(model.mesh.tets)
    materials = [ElementMaterials.uniform(n, Material(E, 0.45)) for E in (4e3, 8e3, 16e3)]
    return model, materials, DynamicRelaxation(load_iterations=300)


def test_a_batch_on_two_processes_is_the_batch_in_one():
    model, materials, relaxation = _batch()
    alone = solve_batch(model, materials, device="cpu", relaxation=relaxation, cpu_workers=1)
    seen = []
    split = solve_batch(model, materials, device="cpu", relaxation=relaxation, cpu_workers=2,
                        progress=lambda fraction: seen.append(fraction))
    assert [s.status for s in split] == ["completed"] * 3
    for one, other in zip(alone, split):  # same order; each chunk at its own smallest critical step
        assert np.abs(one.displacement - other.displacement).max() < 0.02  # mm, the relaxation's 0.01 twice
    # the softer variant moves further from the plates' contact inwards: the order is the variants'
    assert np.abs(split[0].displacement).sum() >= np.abs(split[2].displacement).sum()
    assert seen and 0.0 <= min(seen) and max(seen) <= 1.0
    # the same split again gives the same numbers (the workers are kept, the chunks fixed)
    again = solve_batch(model, materials, device="cpu", relaxation=relaxation, cpu_workers=2)
    for one, other in zip(split, again):
        np.testing.assert_array_equal(one.displacement, other.displacement)


def test_a_smaller_batch_keeps_the_larger_pool():
    """Worker processes are started once: a batch split over fewer of them (a fit's population
    after a larger round) uses the pool as it is."""
    model, materials, relaxation = _batch()
    solve_batch(model, materials, device="cpu", relaxation=relaxation, cpu_workers=3)
    pool = cpu_pool._pool
    split = solve_batch(model, materials[:2], device="cpu", relaxation=relaxation, cpu_workers=2)
    assert cpu_pool._pool is pool and cpu_pool._pool_size == 3
    assert [s.status for s in split] == ["completed"] * 2


def test_a_cancelled_split_batch_stops_every_chunk():
    model, materials, relaxation = _batch()
    split = solve_batch(model, materials, device="cpu", relaxation=relaxation, cpu_workers=2,
                        progress=lambda fraction: False)
    assert [s.status for s in split] == ["cancelled"] * 3


def test_the_worker_count_comes_from_the_environment(monkeypatch):
    monkeypatch.setenv(ENVIRONMENT, "3")
    assert cpu_workers(8) == 3 and cpu_workers(2) == 2 and cpu_workers(1) == 1
    monkeypatch.setenv(ENVIRONMENT, "1")
    assert cpu_workers(8) == 1
    for bad in ("0", "two", "-1"):
        monkeypatch.setenv(ENVIRONMENT, bad)
        with pytest.raises(ValueError, match=ENVIRONMENT):
            cpu_workers(8)
    monkeypatch.delenv(ENVIRONMENT)
    assert cpu_workers(64) >= 1  # the cores this process may use
    monkeypatch.setenv(ENVIRONMENT, "4")
    # none in a daemon process (a Dask worker's: it may not start processes)
    with monkeypatch.context() as patched:
        patched.setattr(cpu_pool, "_in_daemon", lambda: True)
        assert cpu_workers(64) == 1
    # none inside an application that embeds Python (Slicer's own process)
    with monkeypatch.context() as patched:
        patched.setattr("sys.executable", "/opt/Slicer/bin/SlicerApp-real")
        assert cpu_workers(64) == 1
    assert cpu_workers(64) == 4


def test_chunks_are_contiguous_and_even():
    assert [list(c) for c in chunks(7, 3)] == [[0, 1, 2], [3, 4], [5, 6]]
    assert [list(c) for c in chunks(2, 4)] == [[0], [1]]
    assert sum(len(c) for c in chunks(64, 16)) == 64


def test_a_script_without_a_main_guard_is_not_run_again_by_the_workers(tmp_path):
    """``spawn`` starts each worker by importing the caller's main module: a plain script (no
    ``if __name__ == "__main__"``) would run again in every worker. The workers import only the
    library: the script's line is printed once, and its batch is solved; what the workers print
    goes to standard error."""
    import subprocess

    script = tmp_path / "plain_script.py"
    script.write_text(
        "import numpy as np\n"
        "from BreastBiomechLib.solver import DynamicRelaxation, solve_batch\n"
        "from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression\n"
        "from BreastBiomechLib.solver.materials import ElementMaterials, Material\n"
        "model = hemi_ellipsoid_compression(14.0, compression=0.2)\n"
        "n = len(model.mesh.tets)\n"
        "materials = [ElementMaterials.uniform(n, Material(E, 0.45)) for E in (4e3, 8e3)]\n"
        "print('the script runs', flush=True)\n"
        "solutions = solve_batch(model, materials, device='cpu', relaxation=DynamicRelaxation(load_iterations=300),\n"
        "                        cpu_workers=2)\n"
        "print('statuses', [s.status for s in solutions], flush=True)\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("the script runs") == 1, done.stdout
    assert "statuses ['completed', 'completed']" in done.stdout
    # the workers' own output (warp's start-up lines) goes to standard error: a command's
    # --progress json stream on standard output stays events only
    assert done.stdout.count("Warp 1.") <= 1 and done.stderr.count("Warp 1.") >= 2


def _ended(pid: int) -> bool:
    """Whether process ``pid`` has ended (gone, or a zombie nobody has reaped yet)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the process table in /proc")
def test_workers_end_with_the_process_that_started_them(tmp_path):
    """A command killed mid-batch (or a Slicer panel's run cancelled by ending its process) must
    not leave its workers solving, orphaned: each worker ends when the pool's process has."""
    import subprocess
    import time

    script = tmp_path / "parent.py"
    script.write_text(
        "import os, time\n"
        "from BreastBiomechLib.solver import cpu_pool\n"
        "if __name__ == '__main__':\n"
        "    pool = cpu_pool._pool_of(1)\n"
        "    print(pool.submit(os.getpid).result(), flush=True)\n"
        "    pool.submit(time.sleep, 600)\n"
        "    time.sleep(600)\n")
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                              text=True)
    try:
        worker = int(parent.stdout.readline())
        assert not _ended(worker)
    finally:
        parent.kill()
        parent.wait()
    deadline = time.monotonic() + 30.0
    while not _ended(worker) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _ended(worker), f"worker {worker} outlived the process that started it"

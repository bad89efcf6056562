"""Shared fixtures of every test folder (unit/<package>, integration, modules, fuzz; docs/developing.md,
"Tests"): a fresh real MRML scene per test (slicer-core wheel), small phantom cases."""

from __future__ import annotations

from pathlib import Path

import os

import pytest
from images import oblique_direction

# a CPU batch in this process, not split over worker processes (solver/cpu_pool.py): pytest-xdist
# keeps the cores busy already; Testing/unit/solver/test_cpu_pool.py splits batches on purpose
os.environ.setdefault("BREASTBIOMECH_CPU_WORKERS", "1")


# session fixtures that make and fit a whole case (minutes of CPU each), by name: the tests that
# use one run at the head of one pytest-xdist worker's share (pytest_collection_modifyitems)
SHARED_CASES = ("null_case", "friction_case")


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist, put the tests that use each of :data:`SHARED_CASES` at the head of one
    worker's share of the run (``--dist worksteal`` hands worker k the k-th contiguous share and
    steals from a share's end): each worker starts on a case of its own, no worker waits on
    another's case, and the run ends on short tests rather than on a case still being made. The
    rest keep their order. Without workers (``-n 0``) the order is pytest's."""
    workers = int(getattr(config, "workerinput", {}).get("workercount", 1))
    if workers < 2:
        return
    heads, placed = [], set()
    for name in SHARED_CASES:
        heads.append([item for item in items if name in item.fixturenames and id(item) not in placed])
        placed |= {id(item) for item in heads[-1]}
    rest = [item for item in items if id(item) not in placed]
    shares, start = [], 0
    for k in range(workers):  # worksteal's first shares: len(pending) // workers remaining, in turn
        size = (len(items) - sum(len(share) for share in shares)) // (workers - k)
        head = [item for i, h in enumerate(heads) if i % workers == k for item in h]
        body = rest[start:start + max(size - len(head), 0)] if k < workers - 1 else rest[start:]
        start += len(body)
        shares.append(head + body)
    items[:] = [item for share in shares for item in share]
    assert len(items) == len(placed) + len(rest)


@pytest.fixture
def scene():
    """A new vtkMRMLScene with the default colour tables, as the Slicer application sets it up."""
    slicer = pytest.importorskip("slicer", reason="needs the slicer-core wheel (pip install -e .[test])")
    scene = slicer.vtkMRMLScene()
    colors = slicer.vtkMRMLColorLogic()
    colors.SetMRMLScene(scene)
    yield scene
    colors.SetMRMLScene(None)
    scene.Clear(True)


@pytest.fixture
def oblique_geometry():
    """(origin, spacing, direction) with anisotropic spacing and an oblique direction, LPS."""
    return (12.5, -40.25, 7.0), (0.7, 1.3, 2.5), tuple(oblique_direction().ravel())


def made_once(tmp_path_factory, worker_id: str, name: str, make) -> Path:
    """The folder ``name`` in the run's shared temporary folder, made by ``make(folder)`` once for
    the whole run: under pytest-xdist the first worker that needs it makes it while the others
    wait on a lock (a session fixture is otherwise made once per worker)."""
    import fcntl

    base = tmp_path_factory.getbasetemp()
    root = (base if worker_id == "master" else base.parent) / name
    with open(f"{root}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / "done").is_file():
            root.mkdir(exist_ok=True)
            make(root)
            (root / "done").write_text("made\n")
    return root


@pytest.fixture(scope="session")
def compressed_case_dir(tmp_path_factory, worker_id):
    """A small coarse phantom (heterogeneous default truth materials) compressed by 25 % LR on a
    6 mm truth mesh on the CPU by `breastbiomech phantom --compressed`: the case folder (made
    once for the run, :func:`made_once`; tests only read it)."""
    from BreastBiomechLib.cli import main

    def make(root):
        assert main(["phantom", "--seed", "2", "--volume-cm3", "450", "--spacing", "1.5", "1.5", "3", "--compressed",
                     "--compression", "0.25", "--truth-edge-mm", "6", "--device", "cpu", "--no-overview",
                     "--out", str(root / "case")]) == 0

    return made_once(tmp_path_factory, worker_id, "compressed-case", make) / "case"


@pytest.fixture(scope="session")
def two_state_case(compressed_case_dir, tmp_path_factory, worker_id):
    """``compressed_case_dir`` (25 % LR by both plates) with a further measured state "lateral"
    (35 % by the second plate alone, its plate force recorded with an sd of 0.5 N) added by
    `breastbiomech phantom-state`: the case folder (made once for the run, :func:`made_once`;
    tests only read it)."""
    import shutil

    from BreastBiomechLib.cli import main

    def make(root):
        shutil.copytree(compressed_case_dir, root / "case")
        assert main(["phantom-state", str(root / "case"), "--device", "cpu", "--no-overview", "--state", "lateral",
                     "moving-plate=second", "compression=0.35", "force-sd=0.5"]) == 0

    return made_once(tmp_path_factory, worker_id, "two-state-case", make) / "case"


@pytest.fixture(scope="session")
def friction_case(tmp_path_factory, worker_id):
    """(case, fit): the library's small hidden-friction case (``small_friction_case``: a 400 cm^3
    phantom compressed 40 % with plate friction mu = 1 hidden in its truth, copied without its
    truth files, fitted without friction on a 12 mm mesh), which the Breast Discrepancy module's
    in-app self-test makes too: a diagnosis of it takes about 80 s on 2 cores. Made once for the
    run (:func:`made_once`); tests only read it."""
    from discrepancy_cases import small_friction_case

    root = made_once(tmp_path_factory, worker_id, "friction-case", small_friction_case)
    return root / "case", root / "fit"

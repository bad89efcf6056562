"""Shared fixtures of every test folder (unit/<package>, integration, modules, fuzz; docs/developing.md,
"Tests"): a fresh real MRML scene per test (slicer-core wheel), small phantom cases."""

from __future__ import annotations

import pytest
from images import oblique_direction


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


@pytest.fixture(scope="session")
def compressed_case_dir(tmp_path_factory):
    """A small coarse phantom (heterogeneous default truth materials) compressed by 25 % LR on a
    6 mm truth mesh on the CPU by `breastbiomech phantom --compressed`: the case folder."""
    from BreastBiomechLib.cli import main

    out = tmp_path_factory.mktemp("compressed") / "case"
    assert main(["phantom", "--seed", "2", "--volume-cm3", "450", "--spacing", "1.5", "1.5", "3", "--compressed",
                 "--compression", "0.25", "--truth-edge-mm", "6", "--device", "cpu", "--no-overview",
                 "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="session")
def friction_case(tmp_path_factory, worker_id):
    """(case, fit): the library's small hidden-friction case (``small_friction_case``: a 400 cm^3
    phantom compressed 40 % with plate friction mu = 1 hidden in its truth, copied without its
    truth files, fitted without friction on a 12 mm mesh), which the Breast Discrepancy module's
    in-app self-test makes too: a diagnosis of it takes about 80 s on 2 cores. Made once
    for the whole run: under pytest-xdist the first worker that needs it makes it in the run's
    shared temporary folder while the others wait on a lock. Tests only read it."""
    import fcntl

    from discrepancy_cases import small_friction_case

    base = tmp_path_factory.getbasetemp()
    root = (base if worker_id == "master" else base.parent) / "friction-case"
    with open(f"{root}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / "done").is_file():
            small_friction_case(root)
            (root / "done").write_text("made\n")
    return root / "case", root / "fit"

"""Shared fixtures: a fresh real MRML scene per test (slicer-core wheel), small phantom cases."""

from __future__ import annotations

import numpy as np
import pytest


# Seconds each test file took (developer machine, 2 cores, 2026-11-27, `PYTEST_ADDOPTS=--durations=80
# make test`): `make test` starts the longest files first (why: docs/developing.md, "Tests").
# Files not listed follow in collection order; only the order depends on these figures.
LONGEST_FILES = {
    "test_kill_resume_diagnosis.py": 720, "test_discrepancy.py": 490, "test_discrepancy_friction.py": 420,
    "test_anatomy_variants.py": 370, "test_module_breastdiscrepancy.py": 280, "test_phantom.py": 230,
    "test_kill_resume.py": 230, "test_fit_warm_starts.py": 180, "test_optimisation.py": 160, "test_cohort.py": 130,
    "test_friction.py": 90, "test_segmentation.py": 85, "test_coarse_meshes.py": 80, "test_warm_start.py": 80,
    "test_study.py": 65, "test_module_breastoptimization.py": 65, "test_module_breastbiomech.py": 60,
    "test_module_breastsegmentation.py": 55, "test_solver.py": 45, "test_static.py": 45, "test_fit_geometry.py": 45,
    "test_skin.py": 40,
}


def pytest_collection_modifyitems(items):
    """The longest test files first (a stable sort: a file's tests keep their order)."""
    items.sort(key=lambda item: -LONGEST_FILES.get(item.path.name, 0))


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


def oblique_direction() -> np.ndarray:
    """A non-identity, non-axis-aligned rotation (det +1)."""
    a, b = np.radians(30.0), np.radians(-20.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rz @ rx


@pytest.fixture
def oblique_geometry():
    """(origin, spacing, direction) with anisotropic spacing and an oblique direction, LPS."""
    return (12.5, -40.25, 7.0), (0.7, 1.3, 2.5), tuple(oblique_direction().ravel())


def make_image(array: np.ndarray, geometry):
    import SimpleITK as sitk

    image = sitk.GetImageFromArray(array, isVector=array.ndim == 4)
    origin, spacing, direction = geometry
    image.SetOrigin(origin)
    image.SetSpacing(spacing)
    image.SetDirection(direction)
    return image


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
    """(case, fit): the test phantom compressed 40 % with plate friction mu = 1 hidden in its
    truth, copied without its truth files, fitted without friction (``fit_coarse``). Made once
    for the whole run: under pytest-xdist the first worker that needs it makes it in the run's
    shared temporary folder while the others wait on a lock. Tests only read it."""
    import fcntl

    from discrepancy_cases import fit_coarse, without_truth

    from BreastBiomechLib.cli import main

    base = tmp_path_factory.getbasetemp()
    root = (base if worker_id == "master" else base.parent) / "friction-case"
    with open(f"{root}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / "done").is_file():
            root.mkdir(exist_ok=True)
            assert main(["phantom", "--seed", "2", "--volume-cm3", "450", "--spacing", "1.5", "1.5", "3",
                         "--compressed", "--compression", "0.4", "--truth-edge-mm", "6", "--device", "cpu",
                         "--no-overview", "--friction", "1.0", "--out", str(root / "made")]) == 0
            case = without_truth(root / "made", root / "case")
            fit_coarse(case, root / "fit")
            (root / "done").write_text("made\n")
    return root / "case", root / "fit"

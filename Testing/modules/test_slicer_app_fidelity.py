"""What the desktop Slicer app does that slicer-core cannot show, checked where it can be:
one requirements list with minimum versions, no install when a panel opens, every action that
needs a package asks for it first, the solver package builds models without warp, self-tests skip
without their packages, the modules' metadata (translatable, Slicer-module dependencies), the
Resources layout Slicer looks for, the CMake template, the Extensions Index entry, and the
"Breast phantom" sample loadable from a script.
"""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
import textwrap
import tomllib
import unittest
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MODULE_DIR = ROOT / "BreastBiomech"
MODULES = sorted(p.stem for p in MODULE_DIR.glob("*.py"))

import BreastBiomechCommon  # noqa: E402  (BreastBiomech/ is on the test path)
from BreastBiomechCommon import dependencies  # noqa: E402


def _tree(module: str) -> ast.Module:
    return ast.parse((MODULE_DIR / f"{module}.py").read_text())


def _classes(tree, suffix: str):
    return [node for node in tree.body if isinstance(node, ast.ClassDef) and node.name.endswith(suffix)]


def _calls(node) -> list[str]:
    """Names of the functions called in ``node`` (``f(...)`` and ``x.f(...)``), in source order."""
    names = []
    for sub in ast.walk(node):
        if isinstance(sub, ast.Call):
            func = sub.func
            names.append(func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else "")
    return names


# -- one list of requirements ---------------------------------------------------------------------

def test_requirements_are_one_list_read_by_pyproject_and_the_modules():
    requirements = dependencies.read_requirements()
    assert {"numpy", "scipy", "SimpleITK", "tetgen", "warp", "cma", "matplotlib"} <= set(requirements)
    assert "vtk" not in requirements, "Slicer brings VTK: it must not be a requirement the modules install"
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "dependencies" in pyproject["project"]["dynamic"] and "dependencies" not in pyproject["project"]
    assert pyproject["tool"]["setuptools"]["dynamic"]["dependencies"]["file"] == [
        str(Path(dependencies.REQUIREMENTS_FILE).relative_to(ROOT))]
    extras = pyproject["project"]["optional-dependencies"]
    assert any(spec.startswith("vtk") for spec in extras["headless"])
    assert "breastbiomech[headless]" in extras["test"]


def test_every_package_a_module_names_is_in_the_requirements():
    requirements = dependencies.read_requirements()
    for module in MODULES:
        for node in _tree(module).body:
            if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id.endswith("DEPENDENCIES")
                                                    for t in node.targets):
                names = ast.literal_eval(node.value)
                assert set(names) <= set(requirements), f"{module}: {set(names) - set(requirements)} not in requirements.txt"


def test_requirements_refuse_lines_pip_and_the_check_would_read_differently(tmp_path):
    path = tmp_path / "requirements.txt"
    path.write_text("# comment\nnumpy>=1.26  # inline\n\nwarp-lang>=1.8\n")
    assert {n: str(r) for n, r in dependencies.read_requirements(str(path)).items()} == {
        "numpy": "numpy>=1.26", "warp": "warp-lang>=1.8"}
    path.write_text("scipy==1.13\n")
    with pytest.raises(ValueError, match="requirements.txt:1: 'scipy==1.13' is not of the form name>=version"):
        dependencies.read_requirements(str(path))


def test_version_minimums_are_checked_not_only_importability():
    assert dependencies.version_tuple("2.5.2.post1") == (2, 5, 2)
    assert dependencies.version_tuple("1.8rc1") == (1, 8)
    assert dependencies.version_tuple("1.19.0") > dependencies.version_tuple("1.8")
    Requirement = dependencies.Requirement
    fake = {"numpy": Requirement("numpy", "999.0"), "nothere": Requirement("breastbiomech-no-such-package", "1.0"),
            "scipy": Requirement("scipy", "1.0")}
    unmet = dependencies.unmet_requirements(["numpy", "nothere", "scipy"], fake)
    assert [u.requirement.pip_name for u in unmet] == ["numpy", "breastbiomech-no-such-package"]
    assert "installed" in str(unmet[0]) and "not installed" in str(unmet[1])
    with pytest.raises(KeyError, match="add it there with its minimum version"):
        dependencies.unmet_requirements(["torch"], fake)


def test_headless_a_missing_package_is_an_error_that_names_the_install_command(monkeypatch):
    monkeypatch.setattr(dependencies, "read_requirements",
                        lambda path=None: {"numpy": dependencies.Requirement("numpy", "999.0")})
    with pytest.raises(BreastBiomechCommon.MissingDependencies, match=r"numpy>=999.0 .* pip install 'numpy>=999.0'"):
        BreastBiomechCommon.ensure_dependencies(["numpy"], "Breast Test")


def test_a_panel_action_is_told_false_when_a_package_is_missing(monkeypatch):
    """``dependencies_ready`` shows the error and answers False (``slicer.util.tryWithErrorDisplay``
    would show it and raise it again, so an action never saw False); the dialog itself is Qt's,
    recorded here."""
    util = pytest.importorskip("slicer.util", reason="needs the slicer-core wheel's slicer.util")

    shown = []
    monkeypatch.setattr(dependencies, "read_requirements",
                        lambda path=None: {"numpy": dependencies.Requirement("numpy", "999.0"),
                                           "scipy": dependencies.Requirement("scipy", "1.0")})
    monkeypatch.setattr(util, "errorDisplay", lambda text, **kwargs: shown.append((text, kwargs)))
    assert BreastBiomechCommon.dependencies_ready(["numpy"], "Breast Test") is False
    [(text, kwargs)] = shown
    assert "Breast Test cannot go on" in text and "numpy>=999.0" in kwargs["detailedText"]
    assert BreastBiomechCommon.dependencies_ready(["scipy"], "Breast Test") is True and len(shown) == 1


# -- when and where packages are installed ---------------------------------------------------------

@pytest.mark.parametrize("module", MODULES)
def test_every_widget_defines_what_its_base_calls(module):
    """``ModuleWidgetBase.setup`` loads ``UI/<Module>.ui`` and makes ``<Module>Logic`` (Slicer's
    own naming): each module's file holds the Widget on that base, the Logic of that name and the
    panel (test_ui_bindings checks the panel's bound widgets and buttons)."""
    tree = _tree(module)
    (widget,) = _classes(tree, "Widget")
    assert widget.name == f"{module}Widget"
    assert [b.id for b in widget.bases if isinstance(b, ast.Name)] == ["ModuleWidgetBase"]
    assert [c.name for c in _classes(tree, "Logic")] == [f"{module}Logic"]
    assert (MODULE_DIR / "Resources" / "UI" / f"{module}.ui").is_file()


@pytest.mark.parametrize("module", MODULES)
def test_panels_install_nothing_when_they_open(module):
    for widget in _classes(_tree(module), "Widget"):
        for method in widget.body:
            if isinstance(method, ast.FunctionDef) and method.name in ("setup", "__init__", "enter", "connectGUI",
                                                                        "createLogic"):
                called = set(_calls(method))
                assert not called & {"dependencies_ready", "ensure_dependencies", "pip_install", "pip_ensure"}, (
                    f"{module}Widget.{method.name} installs packages: install on the first action that needs them")


@pytest.mark.parametrize("module", MODULES)
def test_every_action_checks_its_packages_before_using_the_logic(module):
    """Each button's handler (``on...Button``, the segmentation steps' ``onStep``, a fit's
    ``start...``) calls ``dependencies_ready`` (itself or through ``ModuleWidgetBase.runAction``)
    before it touches the Logic, so a missing package is offered for install instead of surfacing
    as "No module named ..."."""
    handlers = 0
    for widget in _classes(_tree(module), "Widget"):
        for method in widget.body:
            if not (isinstance(method, ast.FunctionDef) and re.fullmatch(r"on\w*Button|onStep|start\w+", method.name)):
                continue
            uses_logic = any(isinstance(n, ast.Attribute) and n.attr == "logic" for n in ast.walk(method))
            steps = "step" in [a.arg for a in method.args.args]
            if not (uses_logic or steps):
                continue  # e.g. Cancel: touches nothing that needs a package
            handlers += 1
            first = method.body[0]
            assert {"dependencies_ready", "runAction"} & set(_calls(first)), (
                f"{module}Widget.{method.name} must start with `if not dependencies_ready(...): return` or run "
                "through `self.runAction(packages, ...)`")
    assert handlers >= 1


def test_model_building_needs_no_warp_and_solving_names_it():
    """"Default materials" and "Place plates" (and a compressed case's plates) build a model
    without warp, tetgen or cma installed; only the solve imports warp."""
    script = textwrap.dedent("""
        import sys
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("warp", "tetgen", "cma"):
                    raise ImportError(f"{name} is blocked for this test")
        sys.meta_path.insert(0, Block())
        import slicer
        import BreastSimulation
        from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh
        from BreastBiomechLib.mrml import tetmesh_to_model_node
        from BreastBiomechLib.phantom.compressed_files import read_compressed  # Breast Optimization's Load case
        scene = slicer.vtkMRMLScene()
        logic = BreastSimulation.BreastSimulationLogic(scene)
        p = logic.getParameterNode()
        p.set_reference("inputMesh", tetmesh_to_model_node(hemi_ellipsoid_mesh((50, 40, 45), 12.0), scene, "Breast"))
        logic.chooseDefaultNodeSets(p)
        logic.createDefaultMaterials(p)
        logic.createCompressionPlates(p)
        assert len(p.references("plates")) == 2
        assert not [m for m in sys.modules if m.split(".")[0] in ("warp", "tetgen", "cma")]
        try:
            from BreastBiomechLib.solver import solve
        except ImportError as error:
            print("solve:", error)
        """)
    pytest.importorskip("slicer")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(MODULE_DIR)]))
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "solve: warp is blocked for this test" in done.stdout


# -- self-tests on a fresh Slicer ------------------------------------------------------------------

@pytest.mark.parametrize("module", MODULES)
def test_self_tests_skip_without_their_packages(module):
    (test,) = _classes(_tree(module), "Test")
    assert [b.id for b in test.bases if isinstance(b, ast.Name)][:1] == ["ModuleTestMixin"]
    assert any(isinstance(n, ast.Assign) and n.targets[0].id == "REQUIRES" for n in test.body)


def test_a_self_test_without_its_packages_is_skipped_with_the_reason(monkeypatch):
    monkeypatch.setattr(dependencies, "read_requirements",
                        lambda path=None: {"tetgen": dependencies.Requirement("tetgen", "999.0")})
    shown, ran = [], []

    class MeshTest(BreastBiomechCommon.ModuleTestMixin, unittest.TestCase):
        REQUIRES = ("tetgen",)

        def delayDisplay(self, message):
            shown.append(message)

        def test_mesh(self):
            ran.append(True)

    case = MeshTest("test_mesh")
    with pytest.raises(unittest.SkipTest, match=r"needs tetgen>=999.0 .*slicer.util.pip_install"):
        case.setUp()
    # what slicer.selfTests[...]() calls: shows the skip and raises it, so that it is not taken for a pass
    with pytest.raises(unittest.SkipTest, match="needs tetgen>=999.0"):
        case.runTest()
    assert not ran and shown and "MeshTest skipped: needs tetgen>=999.0" in shown[0]
    # and a runner counts it as a skip, not a success
    result = unittest.TestResult()
    MeshTest("runTest").run(result)
    assert len(result.skipped) == 1 and result.wasSuccessful() and not ran


def test_the_discrepancy_self_test_makes_the_headless_tests_case():
    """The in-app self-test of Breast Discrepancy diagnoses the case the headless test validates
    (BreastBiomechLib.cli.examples.small_friction_case, conftest's friction_case) on the CPU with
    the same candidates and refinement, not a set-up of its own."""
    source = (MODULE_DIR / "BreastDiscrepancy.py").read_text()
    test = source[source.index("class BreastDiscrepancyTest"):]
    assert "small_friction_case(" in test and 'device="cpu"' in test
    assert 'p["effects"], p["refineIterations"], p["device"] = "", 1, "cpu"' in test
    conftest = (ROOT / "Testing" / "conftest.py").read_text()
    assert '"friction-case", small_friction_case)' in conftest
    module_test = (ROOT / "Testing" / "modules" / "test_module_breastdiscrepancy.py").read_text()
    assert 'EFFECTS = ""' in module_test and '= EFFECTS, 1, "cpu"' in module_test


# -- module metadata and layout --------------------------------------------------------------------

@pytest.mark.parametrize("module", MODULES)
def test_module_metadata_is_translatable_and_names_the_slicer_modules_used(module):
    """The module sets its own title, help and acknowledgement as ``_(...)``; the category (translated),
    the Slicer modules used and the contributors come from ``BreastBiomechCommon.ModuleBase``."""
    def assigned_in(cls):
        assigned = {}
        for node in ast.walk(cls):
            if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Attribute):
                assigned[node.targets[0].attr] = node.value
        return assigned

    (cls,) = [c for c in _classes(_tree(module), "") if c.name == module]
    assert [b.id for b in cls.bases if isinstance(b, ast.Name)] == ["ModuleBase"]
    assigned = assigned_in(cls)
    for text in ("title", "helpText", "acknowledgementText"):
        value = assigned[text]
        assert isinstance(value, ast.Call) and getattr(value.func, "id", "") == "_", f"{module}: {text} is not _(...)"
    common = ast.parse((MODULE_DIR / "BreastBiomechCommon" / "__init__.py").read_text())
    (base,) = [c for c in common.body if isinstance(c, ast.ClassDef) and c.name == "ModuleBase"]
    inherited = assigned_in(base)
    assert "translate" in _calls(inherited["categories"])
    assert "SLICER_MODULES" in ast.dump(inherited["dependencies"]), "parent.dependencies must name the Slicer modules used"
    assert {"Segmentations", "Markups", "Models"} <= set(BreastBiomechCommon.SLICER_MODULES)


def test_tetgen_licence_is_stated_before_it_is_installed():
    source = (MODULE_DIR / "BreastMesh.py").read_text()
    help_text = source[source.index("self.parent.helpText"):source.index("self.parent.acknowledgementText")]
    help_text = " ".join(help_text.split())  # as shown: HTML, where line breaks are spaces
    assert "Affero General Public License" in help_text and "AGPL" in help_text
    assert "by installing it you accept its licence" in help_text


def test_resources_lie_beside_the_module_scripts_where_slicer_looks():
    # the top level's Resources/ holds the extension's own (icon, screenshots), none of a module's
    top = {path.relative_to(ROOT / "Resources").parts[0] for path in (ROOT / "Resources").rglob("*") if path.is_file()}
    assert top <= {"Icons", "Screenshots", "README.md"}, top
    assert not (ROOT / "Resources" / "UI").exists(), "Slicer looks for a module's panel beside its script"
    for module in MODULES:
        # ScriptedLoadableModule: <folder of the script>/Resources/Icons/<Module>.png; "Edit UI": .../UI/<Module>.ui
        assert (MODULE_DIR / "Resources" / "Icons" / f"{module}.png").is_file()
        assert (MODULE_DIR / "Resources" / "UI" / f"{module}.ui").is_file()
        assert BreastBiomechCommon.resource_path(f"UI/{module}.ui") == str(MODULE_DIR / "Resources" / "UI" / f"{module}.ui")
    cmake = (MODULE_DIR / "CMakeLists.txt").read_text()
    for pattern in ("Resources/Icons/*.png", "Resources/UI/*.ui", "Resources/SampleData/*", "Resources/requirements.txt"):
        assert pattern in cmake
    for helper in sorted((MODULE_DIR / "BreastBiomechCommon").glob("*.py")):  # every helper is built and installed
        assert f"BreastBiomechCommon/{helper.name}" in cmake, helper.name


def test_no_module_code_prepends_to_sys_path():
    for path in [*MODULE_DIR.glob("*.py"), *MODULE_DIR.glob("BreastBiomechCommon/*.py")]:
        assert "sys.path.insert" not in path.read_text(), f"{path.name}: append to sys.path, never prepend"


def test_cmake_follows_the_slicer_5_10_extension_template():
    top = (ROOT / "CMakeLists.txt").read_text()
    assert top.startswith("cmake_minimum_required(VERSION 3.20.6...3.22.6 FATAL_ERROR)")
    glob = re.search(r"file\(GLOB_RECURSE BREASTBIOMECH_LIBRARY_SCRIPTS[^)]*\)", (MODULE_DIR / "CMakeLists.txt").read_text())
    assert glob and "CONFIGURE_DEPENDS" in glob.group()


# -- the Extensions Index entry --------------------------------------------------------------------

# Slicer's catalog-entry schema v1.0.2 (Schemas/ in Slicer's repository), its rules written out here
CATALOG_ENTRY_SCHEMA = {
    "$schema": "http://json-schema.org/draft-07/schema",
    "type": "object",
    "required": ["$schema", "category", "scm_url"],
    "additionalProperties": False,
    "properties": {
        "$schema": {"type": "string"},
        "category": {"type": "string"},
        "scm_url": {"type": "string"},
        "scm_revision": {"type": "string"},
        "scm_type": {"type": "string", "enum": ["git", "local"]},
        "build_dependencies": {"type": "array", "items": {"type": "string"}},
        "dicom_support_rule": {"type": "string"},
        "build_subdirectory": {"type": "string"},
        "enabled": {"type": "boolean"},
        "tier": {"type": "integer", "minimum": 1, "maximum": 5},
    },
}


def test_extensions_index_entry_validates_and_matches_the_extension():
    jsonschema = pytest.importorskip("jsonschema")
    entry = json.loads((ROOT / "ExtensionsIndex" / "BreastBiomech.json").read_text())
    jsonschema.validate(entry, CATALOG_ENTRY_SCHEMA)
    with pytest.raises(jsonschema.ValidationError):  # the rules bite
        jsonschema.validate({**entry, "scm_type": "svn"}, CATALOG_ENTRY_SCHEMA)
    assert entry["$schema"].endswith("slicer-extension-catalog-entry-schema-v1.0.2.json#")
    top = (ROOT / "CMakeLists.txt").read_text()
    assert f'set(EXTENSION_CATEGORY "{entry["category"]}")' in top
    assert entry["scm_url"].removesuffix(".git") == re.search(r'set\(EXTENSION_HOMEPAGE "([^"]+)"\)', top).group(1)
    assert entry["build_subdirectory"] == re.search(r'set\(EXTENSION_BUILD_SUBDIRECTORY "([^"]+)"\)', top).group(1)
    # the icon and screenshot URLs name image files of the top-level Resources/ on the main branch
    for variable in ("EXTENSION_ICONURL", "EXTENSION_SCREENSHOTURLS"):
        url = re.search(rf'set\({variable} "([^"]+)"\)', top).group(1)
        relative = url.split("/BreastBiomech/BreastBiomech/main/", 1)[1]
        assert relative.startswith("Resources/") and relative.endswith(".png"), relative
        assert (ROOT / relative).is_file(), f"{variable} points at {relative}, which is not in the repository"
    # the index's own check (Slicer/ExtensionsIndex scripts/check_description_files.py) accepts
    # only its listed categories; Simulation is one (checked against the index on 2026-12-05)
    assert entry["category"] == "Simulation"
    # the repository name it requires (starting with "Slicer") is for publishing: the README says so
    index_readme = (ROOT / "ExtensionsIndex" / "README.md").read_text()
    assert "SlicerBreastBiomech" in index_readme and "3d-slicer-extension" in index_readme


def _command_line_without(blocked: tuple[str, ...], *argv: str) -> subprocess.CompletedProcess:
    """``breastbiomech ARGV`` in a process where importing the ``blocked`` packages fails."""
    script = textwrap.dedent(f"""
        import sys
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in {blocked!r}:
                    raise ImportError(name + " is blocked for this test")
        sys.meta_path.insert(0, Block())
        from BreastBiomechLib.cli import main
        sys.exit(main({list(argv)!r}))
        """)
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))


def _command_line_without_vtk(*argv: str) -> subprocess.CompletedProcess:
    """``breastbiomech ARGV`` in a process where importing VTK fails, as on a plain install."""
    return _command_line_without(("vtk",), *argv)


def test_command_line_without_vtk_names_the_headless_extra():
    """VTK is only in the headless extra (Slicer brings its own): a plain install says so."""
    done = _command_line_without_vtk("phantom", "--out", "unused")
    assert done.returncode == 2
    assert "pip install 'breastbiomech[headless]'" in done.stderr


def test_solver_benchmark_runs_on_warp_numpy_and_scipy_alone():
    """The solver's benchmark needs only warp, NumPy and SciPy (its hemi-ellipsoid is the solver's
    own mesh), so a GPU machine runs it with warp staged beside what it has: no VTK, SimpleITK,
    TetGen, CMA-ES, Dask or Matplotlib (the parsers of the other commands import none of them); a
    benchmark that meshes still asks for the headless extra."""
    done = _command_line_without(("vtk", "SimpleITK", "tetgen", "cma", "dask", "distributed", "matplotlib"),
                                 "bench", "solver", "--tets", "2000", "--device", "cpu", "--relaxation", "--json")
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    assert figures["benchmark"] == "solver" and figures["status"] == "completed"
    refused = _command_line_without_vtk("bench", "mesh", "--json")
    assert refused.returncode == 2 and "breastbiomech[headless]" in refused.stderr


def test_command_line_parsers_import_no_heavy_package():
    """Building every command's parser (``breastbiomech --help``, and before any command) imports
    none of warp, SciPy, SimpleITK, VTK, TetGen, CMA-ES, Dask or Matplotlib: the choices it lists
    come from light modules, the packages' other names are imported on first use
    (``BreastBiomechLib.lazy``). It took 2.6 s on the developer machine when it imported them."""
    heavy = ("warp", "scipy", "SimpleITK", "vtk", "tetgen", "cma", "dask", "distributed", "matplotlib")
    script = ("import sys\nfrom BreastBiomechLib.cli import build_parser\nbuild_parser()\n"
              f"print(sorted(m for m in {heavy!r} if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]", f"building the parsers imported {done.stdout.strip()}"


def test_lazy_package_names_resolve():
    """Every name a package lists in ``__all__`` resolves, those imported on first use included (a
    slip in a package's map would surface only when a console user or a module asked for that
    name) and is listed by ``dir()`` (the console's completion), and a name it does not export is
    an AttributeError that names the package."""
    import importlib

    for package in ("BreastBiomechLib.phantom", "BreastBiomechLib.discrepancy", "BreastBiomechLib.discrepancy.effects",
                    "BreastBiomechLib.discrepancy.suite", "BreastBiomechLib.solver"):
        module = importlib.import_module(package)
        for name in module.__all__:
            getattr(module, name)
        assert set(module.__all__) <= set(dir(module)), f"{package}: dir() misses names the console should complete"
        with pytest.raises(AttributeError, match=package):
            module.no_such_name

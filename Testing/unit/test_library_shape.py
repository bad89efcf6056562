"""The library's shape as docs/developing.md asks for it: functions a reader can hold in mind, and the
solver's element force written once (issue 79: one copy per kernel had drifted before)."""

from __future__ import annotations

import ast
from pathlib import Path

LIBRARY = Path(__file__).resolve().parents[2] / "BreastBiomechLib"
LONGEST_FUNCTION = 150  # lines, the docstring included


def _functions(tree):
    return [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]


def test_no_function_of_the_library_is_longer_than_150_lines():
    long = [f"{path.relative_to(LIBRARY.parent)}:{f.lineno} {f.name} ({f.end_lineno - f.lineno + 1} lines)"
            for path in sorted(LIBRARY.rglob("*.py")) for f in _functions(ast.parse(path.read_text()))
            if f.end_lineno - f.lineno + 1 > LONGEST_FUNCTION]
    assert not long, "split these into functions of one job each: " + "; ".join(long)


def _calls(node) -> set[str]:
    return {n.func.id for n in ast.walk(node) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}


def test_the_element_force_is_written_once_for_both_element_kernels():
    """The stress of an element (``element_first_piola``) is taken in one function,
    ``model_element_stress``, which both force kernels call; neither kernel reads the material or
    forms the deformation gradient itself."""
    tree = ast.parse((LIBRARY / "solver" / "kernels" / "element.py").read_text())
    functions = {f.name: f for f in _functions(tree)}
    callers = {name for name, f in functions.items() if "element_first_piola" in _calls(f)}
    assert callers == {"model_element_stress"}
    for kernel in ("element_forces", "element_forces_shared"):
        called = _calls(functions[kernel])
        assert "model_element_stress" in called and "add_element_forces" in called, kernel
        assert not called & {"material_of", "deformation_gradient", "mean_slot_change"}, kernel

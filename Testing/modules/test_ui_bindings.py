"""Every module's Qt Designer panel loads headless and holds each widget its code uses.

PySide6's QUiLoader builds the .ui file; Slicer's own widgets (ctk*, qMRML*) fall back to the base
class named in the file's <customwidgets>, which is enough to check names and structure.
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MODULES = sorted(p.stem for p in (ROOT / "BreastBiomech").glob("*.py"))
QT_CLASSES_USED = {"QWidget", "QLabel", "QComboBox", "QSpinBox", "QDoubleSpinBox", "QCheckBox", "QPushButton",
                   "QLineEdit", "QGroupBox", "QTableWidget", "QProgressBar", "QRadioButton", "QToolButton"}


def _used_widget_names(module: str) -> set[str]:
    return set(re.findall(r"self\.ui\.(\w+)", (ROOT / "BreastBiomech" / f"{module}.py").read_text()))


@pytest.fixture(scope="module")
def qt_app():
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    widgets = pytest.importorskip("PySide6.QtWidgets")
    return widgets.QApplication.instance() or widgets.QApplication([])


def test_there_are_modules():
    assert "BreastBiomech" in MODULES


@pytest.mark.parametrize("module", MODULES)
def test_module_has_panel_and_icon(module):
    assert (ROOT / "BreastBiomech" / "Resources" / "UI" / f"{module}.ui").is_file()
    assert (ROOT / "BreastBiomech" / "Resources" / "Icons" / f"{module}.png").is_file()


@pytest.mark.parametrize("module", MODULES)
def test_ui_loads_and_holds_every_widget_the_code_uses(module, qt_app):
    from PySide6.QtUiTools import QUiLoader
    from PySide6.QtWidgets import QWidget

    path = ROOT / "BreastBiomech" / "Resources" / "UI" / f"{module}.ui"
    widget = QUiLoader().load(str(path))
    assert widget is not None, f"{path} did not load"
    present = {w.objectName() for w in widget.findChildren(QWidget)}
    used = _used_widget_names(module)
    assert used, f"{module}.py uses no self.ui widgets"
    missing = sorted(used - present)
    assert not missing, f"{module}.py uses widgets missing from {path.name}: {missing}"

    # every class in the file is a Qt class or declared as a custom widget with a base class
    tree = ET.parse(path)
    custom = {c.findtext("class"): c.findtext("extends") for c in tree.iter("customwidget")}
    assert all(base for base in custom.values())
    root = tree.getroot().find("widget")
    assert root.get("class") == "qMRMLWidget", "the panel's root must be a qMRMLWidget (setMRMLScene)"
    for element in tree.iter("widget"):
        cls = element.get("class")
        assert cls in custom or cls.startswith("Q"), f"{path.name}: unknown widget class {cls}"
    names = {w.get("name") for w in tree.iter("widget")}
    for connection in tree.iter("connection"):
        for end in ("sender", "receiver"):
            assert connection.findtext(end) in names, f"{path.name}: a connection's {end} is not a widget"


# -- each panel's bound widgets (BreastBiomechCommon.bindings) against its Logic ------------------------

def _ui(module: str) -> str:
    return str(ROOT / "BreastBiomech" / "Resources" / "UI" / f"{module}.ui")


def _logic_constant(module: str, name: str):
    """A literal class attribute (``DEFAULTS``, ``ROLES``) of the module's Logic, read from the
    source (the module files import ``slicer``, which the UI tests do not need)."""
    import ast

    tree = ast.parse((ROOT / "BreastBiomech" / f"{module}.py").read_text())
    (cls,) = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == module + "Logic"]
    for node in cls.body:
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name) and node.targets[0].id == name:
            return ast.literal_eval(node.value)
    raise AssertionError(f"{module}Logic has no literal {name}")


KIND_OF_DEFAULT = {bool: ("checked",), int: ("value",), float: ("value",), str: ("choice", "path", "text")}


@pytest.mark.parametrize("module", MODULES)
def test_every_bound_widget_holds_a_parameter_of_its_logic_of_its_kind(module):
    """Each widget the panel binds (``SlicerParameterName``) names a parameter its Logic declares,
    of a type that widget holds: a node selector a role, a check box a bool, a number widget a
    number, a combo box or text field a string; and each panel binds its main inputs."""
    from BreastBiomechCommon.bindings import read_bindings

    declared = read_bindings(_ui(module))
    assert len(declared) >= 7, f"{module}: only {len(declared)} bound widgets"
    defaults, roles = _logic_constant(module, "DEFAULTS"), _logic_constant(module, "ROLES")
    for binding, kind in declared:
        if kind == "node":
            assert binding.parameter in roles, f"{module}: {binding.widget} chooses {binding.parameter!r}, not a role"
            continue
        assert binding.parameter in defaults, f"{module}: {binding.widget} holds {binding.parameter!r}, no parameter"
        held = type(defaults[binding.parameter])
        assert kind in KIND_OF_DEFAULT[held], f"{module}: {binding.widget} ({kind}) holds {binding.parameter!r}: {held}"


@pytest.mark.parametrize("module", MODULES)
def test_no_bound_widget_is_also_wired_by_hand(module):
    """A bound widget's value is connected, shown and stored by the base class: doing any of it
    again in the module is the drift the bindings replace."""
    from BreastBiomechCommon.bindings import read_bindings

    source = (ROOT / "BreastBiomech" / f"{module}.py").read_text()
    for binding, _kind in read_bindings(_ui(module)):
        for written in (".value =", ".checked =", ".currentPath", ".currentText", ".setCurrentNode(", ".text =",
                        ".connect(self.updateParameterNodeFromGUI"):
            assert f"self.ui.{binding.widget}{written}" not in source, f"{module}: {binding.widget}{written}"


def _ui_with(tmp_path, widgets: str) -> str:
    path = tmp_path / "panel.ui"
    path.write_text(f'<ui version="4.0"><widget class="qMRMLWidget" name="panel">{widgets}</widget></ui>')
    return str(path)


def _bound(cls: str, name: str, parameter: str, scale: str = "") -> str:
    extra = f'<property name="BreastBiomechScale" stdset="0"><double>{scale}</double></property>' if scale else ""
    return (f'<widget class="{cls}" name="{name}"><property name="SlicerParameterName" stdset="0">'
            f"<string>{parameter}</string></property>{extra}</widget>")


def test_bindings_are_read_with_their_kind_and_scale_and_mistakes_are_refused(tmp_path):
    from BreastBiomechCommon.bindings import Binding, read_bindings

    ui = _ui_with(tmp_path, _bound("QDoubleSpinBox", "edge", "edgeMm") + '<widget class="QLabel" name="note"/>'
                  + _bound("ctkSliderWidget", "density", "density", "100") + _bound("qMRMLNodeComboBox", "m", "mesh"))
    assert read_bindings(ui) == [(Binding("edge", "edgeMm"), "value"), (Binding("density", "density", 100.0), "value"),
                                 (Binding("m", "mesh"), "node")]
    with pytest.raises(ValueError, match="'go' is a QPushButton, which cannot hold a parameter"):
        read_bindings(_ui_with(tmp_path, _bound("QPushButton", "go", "edgeMm")))
    with pytest.raises(ValueError, match="'edgeMm' is bound to 'a' and 'b'"):
        read_bindings(_ui_with(tmp_path, _bound("QSpinBox", "a", "edgeMm") + _bound("QSpinBox", "b", "edgeMm")))
    with pytest.raises(ValueError, match="only number widgets take a scale"):
        read_bindings(_ui_with(tmp_path, _bound("QCheckBox", "c", "clip", "100")))


@pytest.mark.parametrize("module", MODULES)
def test_every_button_handler_has_its_button_and_none_is_connected_twice(module):
    """``ModuleWidgetBase`` connects each push button ``<name>`` to the Widget's ``on<Name>``: each
    such method has its button in the panel and takes no argument (a click's ``checked`` is not
    passed on), and no module connects that button's click by hand as well."""
    import ast

    from BreastBiomechCommon.bindings import button_names, handler_name

    source = (ROOT / "BreastBiomech" / f"{module}.py").read_text()
    (widget,) = [n for n in ast.parse(source).body if isinstance(n, ast.ClassDef) and n.name == f"{module}Widget"]
    handlers = {n.name: n for n in widget.body
                if isinstance(n, ast.FunctionDef) and re.fullmatch(r"on\w+Button", n.name)}
    buttons = button_names(_ui(module))
    by_handler = {handler_name(b): b for b in buttons}
    for name, method in handlers.items():
        assert name in by_handler, f"{module}Widget.{name} has no button {name[2:3].lower() + name[3:]!r} in the panel"
        assert [a.arg for a in method.args.args] == ["self"], f"{module}Widget.{name} must take no argument"
        assert f"self.ui.{by_handler[name]}.clicked.connect" not in source, f"{module}: {by_handler[name]} twice"
    for button in buttons:  # a button with no handler is wired in connectGUI, or it does nothing
        assert handler_name(button) in handlers or f"self.ui.{button}.clicked.connect" in source, \
            f"{module}: the button {button!r} is connected to nothing"

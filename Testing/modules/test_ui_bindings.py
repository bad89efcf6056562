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

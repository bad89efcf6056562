"""Panel widgets bound to parameter-node entries, declared in the panel's Qt Designer file instead
of three hand-written lists per module (signal connections, parameter node -> panel, panel ->
parameter node) that drift apart.

A widget that holds a parameter carries the dynamic property ``SlicerParameterName`` (the one
Slicer's ``parameterNodeWrapper`` reads: set it in Designer with "+" under Dynamic Properties):
a ``DEFAULTS`` name of the module's Logic, or a ``ROLES`` name for a node selector. Optionally
``BreastBiomechScale`` (a number) multiplies the parameter for the widget (a fraction 0-1 shown in
percent: 100). How a widget shows, stores and signals its value follows from its class in the file
(:data:`KIND_OF_CLASS`), so the bindings are read without Qt: ``ModuleWidgetBase`` binds them in the
application, and the UI tests check each against its Logic's parameters headless.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import NamedTuple


class Binding(NamedTuple):
    widget: str        # object name in the module's .ui file
    parameter: str     # DEFAULTS name, or ROLES name for a node selector
    scale: float = 1.0  # widget value = parameter value * scale (number widgets only)


# how each bindable widget class holds its value: "node" (a node reference), "value" (number),
# "checked" (bool), "choice" (a combo box's text), "path" (a folder or file path), "text"
KIND_OF_CLASS = {
    "qMRMLNodeComboBox": "node",
    "QSpinBox": "value", "QDoubleSpinBox": "value", "ctkDoubleSpinBox": "value", "ctkSliderWidget": "value",
    "QCheckBox": "checked",
    "QComboBox": "choice",
    "ctkPathLineEdit": "path",
    "QLineEdit": "text",
}

# the signal each kind stores the parameter on
SIGNAL_OF_KIND = {"node": "currentNodeChanged", "value": "valueChanged", "checked": "toggled",
                  "choice": "currentIndexChanged", "path": "currentPathChanged", "text": "editingFinished"}


PARAMETER_PROPERTY = "SlicerParameterName"
SCALE_PROPERTY = "BreastBiomechScale"


def _dynamic_property(element, name: str):
    for prop in element.findall("property"):
        if prop.get("name") == name:
            value = prop[0]
            return value.text if value.tag == "string" else float(value.text)
    return None


def read_bindings(ui_path: str) -> list[tuple[Binding, str]]:
    """Each binding declared in a Qt Designer file, with its kind (:data:`KIND_OF_CLASS`), in the
    file's order. A parameter bound twice, a widget of a class that cannot hold a value, or a scale
    on a widget that holds no number is refused, naming the widget and the file."""
    found, seen = [], {}
    for element in ET.parse(ui_path).iter("widget"):
        parameter = _dynamic_property(element, PARAMETER_PROPERTY)
        if parameter is None:
            continue
        widget, cls = element.get("name"), element.get("class")
        if cls not in KIND_OF_CLASS:
            raise ValueError(f"{ui_path}: {widget!r} is a {cls}, which cannot hold a parameter "
                             f"(bindable: {', '.join(sorted(KIND_OF_CLASS))})")
        if parameter in seen:
            raise ValueError(f"{ui_path}: the parameter {parameter!r} is bound to {seen[parameter]!r} and {widget!r}")
        seen[parameter] = widget
        scale = _dynamic_property(element, SCALE_PROPERTY) or 1.0
        if scale != 1.0 and KIND_OF_CLASS[cls] != "value":
            raise ValueError(f"{ui_path}: {widget!r} is a {cls}; only number widgets take a scale")
        found.append((Binding(widget, parameter, scale), KIND_OF_CLASS[cls]))
    return found


def button_names(ui_path: str) -> list[str]:
    """The object names of the push buttons in a Qt Designer file (``ModuleWidgetBase`` connects
    each ``<name>`` to the Widget's ``on<Name>`` where it has one)."""
    return [element.get("name") for element in ET.parse(ui_path).iter("widget")
            if element.get("class") == "QPushButton"]


def handler_name(button: str) -> str:
    """The Widget method a push button's click calls: ``applyButton`` -> ``onApplyButton``."""
    return "on" + button[:1].upper() + button[1:]


def show(widget, kind: str, binding: Binding, parameterNode) -> None:
    """The parameter shown in ``widget`` (PythonQt properties; the application only)."""
    if kind == "node":
        widget.setCurrentNode(parameterNode.reference(binding.parameter))
        return
    value = parameterNode[binding.parameter]
    if kind == "value":
        widget.value = value * binding.scale
    elif kind == "checked":
        widget.checked = value
    elif kind == "choice":
        # a value the list lacks (a scene saved by another version) is added, not shown as the first
        # item: the panel's next change would otherwise store that item in its place, unseen
        index = widget.findText(value)
        if index < 0 and value:
            widget.addItem(value)
            index = widget.findText(value)
        widget.currentIndex = max(index, 0)
    elif kind == "path":
        # set only when it differs: the update after each keystroke would move the cursor to the end
        if widget.currentPath != value:
            widget.currentPath = value
    else:
        widget.text = value


def store(widget, kind: str, binding: Binding, parameterNode) -> None:
    """The widget's value stored in the parameter node (numbers take the parameter's type there)."""
    if kind == "node":
        parameterNode.set_reference(binding.parameter, widget.currentNode())
    elif kind == "value":
        value = widget.value
        parameterNode[binding.parameter] = value / binding.scale if binding.scale != 1.0 else value
    elif kind == "checked":
        parameterNode[binding.parameter] = widget.checked
    elif kind == "choice":
        parameterNode[binding.parameter] = widget.currentText
    elif kind == "path":
        parameterNode[binding.parameter] = widget.currentPath
    else:
        parameterNode[binding.parameter] = widget.text.strip()

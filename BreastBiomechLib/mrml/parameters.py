"""Typed access to a module's parameter node (a singleton vtkMRMLScriptedModuleNode).

The node is saved with the scene, so a module's settings and its input/output node choices come
back when a scene is reloaded. Values are stored as strings in the node and typed by the default
given for each parameter (bool, int, float or str); node choices are node references.
"""

from __future__ import annotations


class ParameterNode:
    """The parameter node of ``module_name`` in ``scene`` (created on first use).

    ``defaults`` maps parameter names to default values; ``roles`` names the node references."""

    def __init__(self, scene, module_name: str, defaults: dict, roles: tuple[str, ...] = ()):
        self.defaults = dict(defaults)
        self.roles = tuple(roles)
        node = scene.GetSingletonNode(module_name, "vtkMRMLScriptedModuleNode")
        if node is None:
            node = scene.CreateNodeByClass("vtkMRMLScriptedModuleNode")
            node.UnRegister(None)
            node.SetSingletonTag(module_name)
            node.SetModuleName(module_name)
            node.SetName(f"{module_name} parameters")
            node = scene.AddNode(node)
        # Slicer's ScriptedLoadableModuleLogic and parameterNodeWrapper find a module's parameter
        # node by this attribute (a scene close can drop it: set it again)
        if node.GetAttribute("ModuleName") != module_name:
            node.SetAttribute("ModuleName", module_name)
        self.node = node
        for name, value in self.defaults.items():
            if not node.GetParameter(name):
                node.SetParameter(name, self._to_text(value))

    @staticmethod
    def _to_text(value) -> str:
        """Booleans as "True"/"False" (as Slicer's parameterNodeWrapper writes them), floats by repr."""
        return str(bool(value)) if isinstance(value, bool) else repr(value) if isinstance(value, float) else str(value)

    def _check(self, name: str) -> None:
        if name not in self.defaults:
            raise KeyError(f"unknown parameter {name!r}; known: {sorted(self.defaults)}")

    def __getitem__(self, name: str):
        self._check(name)
        text = self.node.GetParameter(name)
        default = self.defaults[name]
        try:
            if isinstance(default, bool):
                return text.strip().lower() in ("true", "1", "yes")
            return type(default)(text)
        except ValueError:
            raise ValueError(f"parameter {name!r} holds {text!r}, not a {type(default).__name__}") from None

    def __setitem__(self, name: str, value) -> None:
        self._check(name)
        default = self.defaults[name]
        if not isinstance(default, bool) and isinstance(default, (int, float)):
            value = type(default)(value)  # raises a clear ValueError for text that is no number
        self.node.SetParameter(name, self._to_text(value))

    def reference(self, role: str):
        """The node chosen for ``role`` (or None)."""
        self._check_role(role)
        return self.node.GetNodeReference(role)

    def set_reference(self, role: str, node) -> None:
        self._check_role(role)
        self.node.SetNodeReferenceID(role, node.GetID() if node is not None else None)

    def references(self, role: str) -> list:
        """All nodes chosen for a role that takes several (e.g. the plates), in order."""
        self._check_role(role)
        return [self.node.GetNthNodeReference(role, i) for i in range(self.node.GetNumberOfNodeReferences(role))]

    def set_references(self, role: str, nodes) -> None:
        self._check_role(role)
        self.node.RemoveNodeReferenceIDs(role)
        for node in nodes:
            self.node.AddNodeReferenceID(role, node.GetID())

    def _check_role(self, role: str) -> None:
        if role not in self.roles:
            raise KeyError(f"unknown node role {role!r}; known: {list(self.roles)}")

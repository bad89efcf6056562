"""Package names imported on first use, so that importing a package (or one of its light
submodules, which imports the package first) does not import its heavy dependencies.

The command line builds every command's parser before it runs one, and the parsers list
choices that live in packages whose other modules import warp, SciPy or SimpleITK: with those
packages' names resolved on first use, ``breastbiomech --help`` and ``breastbiomech bench
solver`` import only what they run (the solver's benchmark then needs warp, NumPy and SciPy
alone)."""

from __future__ import annotations

import importlib
import sys


def exports(package: str, module_of: dict[str, str]):
    """A module-level ``__getattr__`` and ``__dir__`` for ``package`` (its ``__name__``): name ``n``
    is ``package.<module_of[n]>.n``, imported on first access, and listed by ``dir()`` (so the
    Python console completes it) before it is; any other name is an AttributeError (Python then
    imports a submodule of that name where one is asked for by ``from package import
    submodule``). Use: ``__getattr__, __dir__ = exports(__name__, {...})``."""

    def __getattr__(name: str):
        module = module_of.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{module}"), name)

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(module_of))

    return __getattr__, __dir__

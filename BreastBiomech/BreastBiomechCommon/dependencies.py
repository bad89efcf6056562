"""The Python packages the BreastBiomech modules need, checked against their minimum versions and
installed into Slicer's Python on the first action that needs them.

The requirements live in one file, ``Resources/requirements.txt`` beside the module scripts:
pyproject.toml reads the same file as the library's dependencies, so the modules and a pip
install ask for the same minimums. VTK is not listed: Slicer brings its own (a headless install
takes it from the library's ``headless`` extra).

Nothing is installed when a panel opens, nor while Slicer runs its tests (``--testing``): an
action then stops with a message that names the packages and how to install them.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import logging
import os
import re
from dataclasses import dataclass

REQUIREMENTS_FILE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "Resources",
                                 "requirements.txt")

# pip name -> import name, where they differ
IMPORT_NAMES = {"warp-lang": "warp"}


class MissingDependencies(ImportError):
    """Packages a step needs are not installed, or older than the minimum BreastBiomech needs."""


@dataclass(frozen=True)
class Requirement:
    """One line of requirements.txt: ``pip_name>=minimum``."""

    pip_name: str
    minimum: str

    @property
    def import_name(self) -> str:
        return IMPORT_NAMES.get(self.pip_name, self.pip_name)

    def __str__(self) -> str:
        return f"{self.pip_name}>={self.minimum}"


@dataclass(frozen=True)
class Unmet:
    """A requirement and what is installed of it (None: not installed)."""

    requirement: Requirement
    installed: str | None

    def __str__(self) -> str:
        found = "not installed" if self.installed is None else f"{self.installed} installed"
        return f"{self.requirement} ({found})"


def read_requirements(path: str = REQUIREMENTS_FILE) -> dict[str, Requirement]:
    """The requirements by import name. Each line is ``name>=version`` (comments and blank lines
    ignored); anything else is refused, so the file stays readable by both pip and this check."""
    requirements = {}
    with open(path, encoding="utf-8") as file:
        for number, line in enumerate(file, start=1):
            text = line.split("#", 1)[0].strip()
            if not text:
                continue
            match = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)\s*>=\s*([0-9][0-9.]*)", text)
            if match is None:
                raise ValueError(f"{path}:{number}: {text!r} is not of the form name>=version")
            requirement = Requirement(match.group(1), match.group(2))
            requirements[requirement.import_name] = requirement
    return requirements


def version_tuple(version: str) -> tuple[int, ...]:
    """The leading numeric release of a version string: "2.5.2.post1" -> (2, 5, 2), "1.8rc1" -> (1, 8)."""
    parts = []
    for piece in version.split("."):
        digits = re.match(r"\d+", piece)
        if digits is None:
            break
        parts.append(int(digits.group()))
        if digits.group() != piece:
            break
    return tuple(parts)


def installed_version(pip_name: str) -> str | None:
    """The installed distribution's version, or None where it is not installed."""
    try:
        return importlib.metadata.version(pip_name)
    except importlib.metadata.PackageNotFoundError:
        return None


def unmet_requirements(import_names, requirements: dict[str, Requirement] | None = None) -> list[Unmet]:
    """The requirements among ``import_names`` that are not installed or older than their minimum."""
    requirements = read_requirements() if requirements is None else requirements
    unmet = []
    for name in import_names:
        if name not in requirements:
            raise KeyError(f"{name!r} is not in {REQUIREMENTS_FILE}; add it there with its minimum version")
        requirement = requirements[name]
        version = installed_version(requirement.pip_name)
        if version is None or version_tuple(version) < version_tuple(requirement.minimum):
            unmet.append(Unmet(requirement, version))
    return unmet


def install_command(unmet: list[Unmet]) -> str:
    """The pip command that installs what is unmet (quoted for a shell)."""
    return "pip install " + " ".join(f"'{u.requirement}'" for u in unmet)


def console_install_command(unmet: list[Unmet]) -> str:
    """The line for Slicer's Python console that installs what is unmet."""
    return f"slicer.util.pip_install({[str(u.requirement) for u in unmet]!r})"


def _pip_ensure():
    """Slicer's own ``pip_ensure`` (Slicer 5.12 and newer), or None on older Slicer."""
    for module in ("slicer.packaging", "slicer.pydeps"):
        try:
            ensure = getattr(importlib.import_module(module), "pip_ensure", None)
        except ImportError:
            continue
        if ensure is not None:
            return ensure
    return None


def ensure_dependencies(import_names, requester: str = "BreastBiomech") -> bool:
    """Make sure the packages ``import_names`` need are installed at their minimum versions.

    In the Slicer application: ask, then install them into Slicer's Python (Slicer 5.12+:
    ``pip_ensure``; Slicer 5.10: ``slicer.util.pip_install`` behind a confirmation and a busy
    progress dialog). Returns False when the user declines. Raises :class:`MissingDependencies`
    where nothing may be installed (headless, or Slicer's testing mode) or the install did not
    give the versions needed."""
    from BreastBiomechCommon import IN_SLICER_APPLICATION

    unmet = unmet_requirements(import_names)
    if not unmet:
        return True
    listing = ", ".join(str(u) for u in unmet)
    if not IN_SLICER_APPLICATION:
        raise MissingDependencies(f"{requester} needs {listing}: {install_command(unmet)}")
    import slicer

    if slicer.app.testingEnabled():
        raise MissingDependencies(
            f"{requester} needs {listing}; Slicer runs in testing mode, where BreastBiomech installs nothing. "
            f"Install them first from Slicer's Python console: {console_install_command(unmet)}")
    ensure = _pip_ensure()
    if ensure is not None:
        from packaging.requirements import Requirement as PipRequirement

        try:
            ensure([PipRequirement(str(u.requirement)) for u in unmet], requester=requester)
        except RuntimeError as error:
            if "declined" in str(error).lower():
                return False
            raise
    else:
        if not slicer.util.confirmOkCancelDisplay(
                f"{requester} needs these Python packages: {listing}.\n"
                "Install them now into Slicer's Python (this downloads them)?",
                f"{requester}: install Python packages"):
            return False
        progress = slicer.util.createProgressDialog(
            labelText=f"Installing {', '.join(u.requirement.pip_name for u in unmet)} into Slicer's Python...",
            maximum=0)
        try:
            slicer.app.processEvents()
            slicer.util.pip_install([str(u.requirement) for u in unmet])
        finally:
            progress.close()
    importlib.invalidate_caches()
    still = unmet_requirements(import_names)
    if still:
        raise MissingDependencies(
            f"{requester} still lacks {', '.join(str(u) for u in still)} after installing. If an older version was "
            "already loaded, restart Slicer; otherwise install from Slicer's Python console: "
            f"{console_install_command(still)}")
    logging.info("%s: installed %s", requester, listing)
    return True


def dependencies_ready(import_names, requester: str = "BreastBiomech") -> bool:
    """For a panel's action (application only): :func:`ensure_dependencies`, any failure shown
    to the user as an error dialog (with the reason in its details). True when the action may
    go on, False when a package is missing or could not be installed. (Not
    ``slicer.util.tryWithErrorDisplay``: it shows the error and raises it again, so the action's
    caller would never see False.)"""
    import slicer

    try:
        return ensure_dependencies(import_names, requester)
    except Exception as error:  # an install that failed, was declined, or a package that will not import
        slicer.util.errorDisplay(f"{requester} cannot go on without its Python packages.", detailedText=str(error))
        return False


def skip_message(unmet: list[Unmet]) -> str:
    """Why a module self-test is skipped, and how to run it."""
    return (f"needs {', '.join(str(u) for u in unmet)}; install them (Slicer's Python console: "
            f"{console_install_command(unmet)}) and run the test again")

"""Command line: ``breastbiomech phantom|segment|mesh|simulate|niftysim|warp|compare|optimise|study|diagnose|design|demo|bench``.

Each sub-command is a thin layer over library functions; results go to files and a short report
on standard output (``--json`` where a machine reads it). One module per command group, each
with its parsers beside its commands (``add_parsers``).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys

from BreastBiomechLib import __version__
from BreastBiomechLib.cli import bench, demo, diagnose, fit, images, mesh, niftysim, phantom, segment, simulate, suite
from BreastBiomechLib.cli.common import end_progress
from BreastBiomechLib.cli.events import open_events


GROUPS = (phantom, fit, diagnose, suite, segment, mesh, simulate, niftysim, images, demo, bench)  # the order `--help` lists them in


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="breastbiomech", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for group in GROUPS:
        group.add_parsers(sub)
    return parser


def _vtk_missing() -> bool:
    try:
        return importlib.util.find_spec("vtk") is None
    except ImportError:
        return True


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # as typed, for reports' provenance
    # Slicer brings VTK; outside it the headless extra does. A command that needs no VTK (a parser's
    # ``needs_vtk``, given the arguments) runs without it
    if getattr(args, "needs_vtk", lambda parsed: True)(args) and _vtk_missing():
        print(f"breastbiomech {args.command}: error: VTK is not installed; outside Slicer install the library with "
              "its headless extra: pip install 'breastbiomech[headless]'", file=sys.stderr)
        return 2
    from BreastBiomechLib.cohort import CohortCancelled

    args.events, restore = open_events(args)
    if getattr(args, "json", False) or args.events is not None:  # standard output is for JSON: no warp banner
        import warp

        warp.config.log_level = warp.LOG_WARNING
    try:
        code, message = args.func(args), None
    except (CohortCancelled, KeyboardInterrupt) as exc:
        code, message = 130, (f"breastbiomech {args.command}: cancelled{': ' + str(exc) if str(exc) else ''}; what "
                              "finished is kept, and the same command resumes")
    except (ValueError, OSError, RuntimeError) as exc:
        code, message = 2, f"breastbiomech {args.command}: error: {_described(exc)}"
    finally:
        restore()  # an unexpected error too gives standard output back (its traceback is on standard error)
    if message is not None:
        end_progress()
        print(message, file=sys.stderr)
    if args.events is not None:  # the last event
        if code == 0:
            args.events.done(code)
        else:
            args.events.error(code, message or f"breastbiomech {args.command} ended with exit code {code}")
    return code


def _described(error: Exception) -> str:
    """The message of a bad input or output: the project's own as it is; an operating-system
    error (a path that is a file, a folder that cannot be made or written) as the path, what is
    wrong with it and what to do."""
    if not isinstance(error, OSError) or error.filename is None:
        return str(error)
    path = error.filename
    if isinstance(error, (FileExistsError, NotADirectoryError)):
        return f"{path} is a file where a folder is needed; give another --out (a new or existing folder)"
    if isinstance(error, IsADirectoryError):
        return f"{path} is a folder where a file is needed"
    if isinstance(error, PermissionError):
        return f"{path}: permission denied; give a path you can write to"
    if isinstance(error, FileNotFoundError):
        return f"{path}: no such file or folder"
    return f"{path}: {error.strerror or error}"


if __name__ == "__main__":
    sys.exit(main())

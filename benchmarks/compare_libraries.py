"""The solver benchmark of several versions of the library, run in turn on one machine (issue 25).

A change to a kernel is judged by ``breastbiomech bench solver`` with and without it on the same
machine, the versions taking turns: two H200s of one kind ran the same code 2 % apart, and the
figures of a replayed kernel alone or of a copy of it need not carry over to the solve
(docs/benchmarks.md, 2026-12-02). Each version is a folder holding a ``BreastBiomechLib``
package; ``--export`` writes a git revision's copy of the package to a folder (where git is; a
lease's copy of the working tree has no history, so export before and carry the folder):

    python benchmarks/compare_libraries.py --export 9909dec .base
    python benchmarks/compare_libraries.py base=.base new=. [--runs "--batch 64" "--batch 16" ""]
                                           [--rounds 2] [--device cuda]

Each run is ``bench solver --relaxation RUN --device DEVICE --json`` in a fresh interpreter that
imports the library from the version's folder (``python -P``, the folder first on ``PYTHONPATH``;
checked before the first run, so an installed copy cannot stand in for it), so its kernels are
built from that version's source. Prints one JSON line per run (the version, the run's
arguments, the round, and the bench's µs per model-step, solve seconds, steps, plate force and
largest displacement, which tell a faster version from one that solved something else), then
one line per run's arguments with each version's median and its ratio to the first version's.
Never asserted anywhere; the bench needs warp, NumPy and SciPy only (``bench solver`` imports
nothing else).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shlex
import statistics
import subprocess
import sys
import tarfile
from pathlib import Path

COMMAND_LINE = "import sys; from BreastBiomechLib.cli import main; sys.exit(main(sys.argv[1:]))"
PACKAGE = "BreastBiomechLib"
REPOSITORY = Path(__file__).resolve().parents[1]
FIGURES = ("us_per_step_per_model", "solve_wall_s", "steps", "plate_force_N", "max_displacement_mm")


def export(revision: str, folder: Path) -> Path:
    """Write ``revision``'s ``BreastBiomechLib`` (of the repository this script is in) into
    ``folder`` (made if missing; refused where it holds the package already, so that no version is
    overwritten unseen)."""
    target = folder / PACKAGE
    if target.exists():
        raise SystemExit(f"{target} exists: remove it or export to another folder")
    archive = subprocess.run(["git", "archive", "--format=tar", revision, PACKAGE], capture_output=True,
                             cwd=REPOSITORY)
    if archive.returncode != 0:
        raise SystemExit(f"git archive {revision}: {archive.stderr.decode().strip()}")
    folder.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
        tar.extractall(folder, filter="data")
    return target


def version_environment(folder: Path) -> dict:
    """The environment of a run of the version in ``folder``: its folder first on PYTHONPATH
    (the packages the bench needs stay reachable through the rest)."""
    env = dict(os.environ)
    rest = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    env["PYTHONPATH"] = os.pathsep.join([str(folder.resolve()), *rest])
    return env


def check_version(name: str, folder: Path) -> None:
    """The interpreter of ``name``'s runs imports the package from ``folder``, not another copy."""
    if not (folder / PACKAGE / "__init__.py").is_file():
        raise SystemExit(f"{name}: {folder} holds no {PACKAGE} package (export one with --export REVISION FOLDER)")
    found = subprocess.run([sys.executable, "-P", "-c", f"import {PACKAGE}; print({PACKAGE}.__file__)"],
                           capture_output=True, text=True, env=version_environment(folder))
    if found.returncode != 0:
        raise SystemExit(f"{name}: importing {PACKAGE} from {folder} failed:\n{found.stderr.strip()}")
    if Path(found.stdout.strip()).resolve().parent != (folder / PACKAGE).resolve():
        raise SystemExit(f"{name}: the interpreter imports {found.stdout.strip()}, not {folder / PACKAGE}")


def bench_run(folder: Path, arguments: str, device: str) -> dict:
    """One ``bench solver --relaxation`` run of the version in ``folder``: its JSON figures."""
    command = [sys.executable, "-P", "-c", COMMAND_LINE, "bench", "solver", "--relaxation", *shlex.split(arguments),
               "--device", device, "--json"]
    done = subprocess.run(command, capture_output=True, text=True, env=version_environment(folder))
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode != 0 or not lines:
        raise SystemExit(f"{shlex.join(command[4:])} with {folder} failed (exit {done.returncode}):\n"
                         f"{done.stderr.strip()[-2000:]}")
    return json.loads(lines[-1])


def version(text: str) -> tuple[str, Path]:
    """NAME=FOLDER, or FOLDER (named by itself)."""
    name, _, folder = text.rpartition("=")
    return (name or folder), Path(folder)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("versions", nargs="*", type=version, metavar="NAME=FOLDER",
                        help="the versions in turn, each a folder holding BreastBiomechLib (the first is the base)")
    parser.add_argument("--export", nargs=2, metavar=("REVISION", "FOLDER"),
                        help="write a git revision's BreastBiomechLib into FOLDER and stop")
    parser.add_argument("--runs", nargs="+", default=["--batch 64", "--batch 16", ""],
                        help="bench solver's arguments of each run, besides --relaxation, --device and --json")
    parser.add_argument("--rounds", type=int, default=2, help="each run this many times, the versions taking turns")
    parser.add_argument("--device", default="cuda", help="the bench's device (cuda, cpu or a warp device name)")
    args = parser.parse_args(argv)
    if args.export:
        print(export(args.export[0], Path(args.export[1])))
        return
    if len(args.versions) < 2:
        parser.error("give two versions or more (NAME=FOLDER), or --export REVISION FOLDER")
    if len({name for name, _ in args.versions}) < len(args.versions):
        parser.error("two versions have one name: name them NAME=FOLDER")
    if args.rounds < 1:
        parser.error("--rounds must be 1 or more")
    for name, folder in args.versions:
        check_version(name, folder)
    figures = {}
    for arguments in args.runs:
        for round_ in range(1, args.rounds + 1):
            for name, folder in args.versions:
                result = bench_run(folder, arguments, args.device)
                line = {"version": name, "run": arguments, "round": round_, **{f: result.get(f) for f in FIGURES}}
                figures.setdefault(arguments, {}).setdefault(name, []).append(result["us_per_step_per_model"])
                print(json.dumps(line), flush=True)
    for arguments, by_version in figures.items():
        base = statistics.median(by_version[args.versions[0][0]])
        summary = {"run": arguments, **{name: {"us_per_step_per_model": values,
                                               "median_to_first": round(statistics.median(values) / base, 4)}
                                        for name, values in by_version.items()}}
        print(json.dumps(summary))


if __name__ == "__main__":
    main()

"""The compressed cases of the seed's Table 1 as cohort tasks: one task per case writes the
phantom and its truth compression into a temporary folder renamed to ``case<N>`` when complete,
so a folder that exists is a finished case (``breastbiomech table1-cases``)."""

from __future__ import annotations

import os
import shutil
from dataclasses import replace
from pathlib import Path

from BreastBiomechLib.cohort import Task
from BreastBiomechLib.phantom.parameters import TABLE1_CASES


def case_folder(out_dir: str | Path, number: int) -> Path:
    return Path(out_dir) / f"case{number}"


def case_done(folder: Path) -> bool:
    from BreastBiomechLib.phantom.truth_files import has_truth

    return has_truth(folder)


def table1_tasks(out_dir: str | Path, numbers, truth_edge_mm: float = 2.0, overview: bool = True) -> list:
    """The tasks (:class:`~BreastBiomechLib.cohort.Task`) of the Table 1 cases ``numbers`` not yet
    in ``out_dir``."""
    unknown = [n for n in numbers if n not in TABLE1_CASES]
    if unknown:
        raise ValueError(f"Table 1 has cases {sorted(TABLE1_CASES)}, not {unknown}")
    return [Task(f"table1/case{n}", make_table1_case, {"number": int(n), "out_dir": str(out_dir),
                                                       "truth_edge_mm": truth_edge_mm, "overview": overview},
                 label=f"case{n}")
            for n in numbers if not case_done(case_folder(out_dir, n))]


def make_table1_case(number: int, out_dir: str, truth_edge_mm: float = 2.0, overview: bool = True, device=None,
                     progress=None) -> dict:
    """A cohort task: Table 1 case ``number`` (its phantom and its truth compression, as
    ``breastbiomech phantom --case N --compressed``) written to ``out_dir/case<N>`` through a
    temporary folder renamed into place. Returns the case's summary figures."""
    from BreastBiomechLib.phantom import generate_phantom, table1_case, write_phantom
    from BreastBiomechLib.phantom.compressed import compress_phantom, table1_truth
    from BreastBiomechLib.phantom.compressed_files import write_compressed

    target = case_folder(out_dir, number)
    if case_done(target):
        return {"case": target.name, "skipped": True}
    temporary = target.with_name(f".{target.name}.{os.getpid()}.partial")
    shutil.rmtree(temporary, ignore_errors=True)
    say = (lambda message: progress(message)) if progress is not None else (lambda message: None)
    say("phantom")
    case = generate_phantom(table1_case(number))
    write_phantom(case, temporary, overview=overview)
    truth = replace(table1_truth(number), edge_mm=truth_edge_mm)
    compressed = compress_phantom(case, truth, device=device, progress=lambda fraction, message: say(message))
    write_compressed(compressed, temporary, overview=overview)
    if target.exists():  # an unfinished case of a run from before cases were written whole
        shutil.rmtree(target)
    os.replace(temporary, target)
    return {"case": target.name, "breast_volume_cm3": case.summary["breast_volume_cm3"],
            "truth_tets": compressed.summary["truth_tets"],
            "max_displacement_mm": compressed.summary["max_displacement_mm"]}

"""A phantom case's truth on disk, for validation and scoring only: the truth model and its
solve's figures (``compressed/truth.json``) and the truth mesh with its displacement
(``compressed/truth_mesh.vtu``); a further state's in its own folder (``states/<name>/``). The fit and the diagnosis never import this module (a test
keeps them from it): what they may read of a case is :mod:`BreastBiomechLib.io.case_layout`'s
measured files."""

from __future__ import annotations

import json
from pathlib import Path

from BreastBiomechLib.io.case_layout import FIRST_STATE, CaseLayout

TRUTH_RECORD = "truth.json"
TRUTH_MESH = "truth_mesh.vtu"


def truth_folder(case_dir: str | Path, state: str = FIRST_STATE) -> Path:
    """The folder of a compressed phantom case's truth files of measured ``state`` (each state
    keeps its own truth)."""
    return CaseLayout(case_dir).state(state).folder


def has_truth(case_dir: str | Path) -> bool:
    """Whether the case folder ``case_dir`` holds a phantom's truth record (a finished phantom case)."""
    return (truth_folder(case_dir) / TRUTH_RECORD).is_file()


def read_truth(case_dir: str | Path, state: str = FIRST_STATE) -> dict:
    """The truth record of measured ``state`` of the compressed phantom case ``case_dir``:
    {"truth": the truth model, "summary": its solve's figures}."""
    path = truth_folder(case_dir, state) / TRUTH_RECORD
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no truth record; only a phantom case made by `breastbiomech phantom "
                                "--compressed` holds one")
    return json.loads(path.read_text())


def truth_mesh_path(case_dir: str | Path, state: str = FIRST_STATE) -> Path:
    """Where the compressed phantom case ``case_dir`` keeps the truth mesh of measured ``state``
    (with its displacement, mm)."""
    return truth_folder(case_dir, state) / TRUTH_MESH

"""The design record a diagnosis folder keeps: design.json (and design.md) written by
:meth:`~BreastBiomechLib.discrepancy.session.DiagnosisSession.design` after a decided round.

One reader for everyone who shows it (the report, the command line, the resume check, the
Breast Discrepancy panel): a record counts only for the round it was made after, so a design
made before a later round never describes that round.
"""

from __future__ import annotations

import json
from pathlib import Path

DESIGN_FILE, DESIGN_MARKDOWN = "design.json", "design.md"


def read_design(folder, round_number: int) -> dict | None:
    """design.json's record in ``folder`` if it was made after round ``round_number``, else None
    (no design made, or one made after another round)."""
    path = Path(folder) / DESIGN_FILE
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    return record if record.get("round") == round_number else None


def not_designed(record: dict) -> str:
    """Why a design (design.json's ``record``) simulated nothing."""
    if record.get("undecided"):
        return (f"the candidates the round could not tell apart ({', '.join(record['undecided'])}) lie outside the "
                "effects chosen for this diagnosis: nothing designed (choose them to design for them).")
    return ("every tested candidate could be told apart with the measured states (none absorbed by the fitted "
            "parameters, none too small to see within its range): no further acquisition is needed for that.")


def design_sentences(record: dict) -> list[str]:
    """The sentences a user reads for a design record: per candidate designed for, which
    acquisition tells it from its closest rival (or that none does); or why nothing was designed."""
    if not record["designed_for"]:
        return [not_designed(record)]
    from BreastBiomechLib.discrepancy.design import Design  # SimpleITK: only where a design is shown

    return Design.from_dict(record).sentences()

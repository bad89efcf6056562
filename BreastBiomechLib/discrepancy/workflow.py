"""The whole workflow on a fitted case: diagnose, add the named effect with its refit, and repeat
until nothing significant remains (or ``rounds`` are done), each step written as it finishes
(:class:`~BreastBiomechLib.discrepancy.session.DiagnosisSession`, whose docstring lists the
output folder) so that an interrupted run resumes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from BreastBiomechLib.discrepancy.diagnosis import DiagnosisSettings
from BreastBiomechLib.discrepancy.observations import NoiseModel
from BreastBiomechLib.discrepancy.registration import RegistrationSettings
from BreastBiomechLib.io.claims import claimed


@dataclass
class DiagnosisRun:
    """A finished workflow: every round's record, the final verdict's round and the folder."""

    rounds: list[dict]
    folder: Path

    @property
    def final(self) -> dict:
        return self.rounds[-1]["diagnosis"]

    @property
    def added(self) -> list[str]:
        return [r["added"] for r in self.rounds if r.get("added")]


def run_diagnosis(case_dir, fit_dir, out_dir, effects=None, rounds: int = 3, noise: NoiseModel | None = None,
                  settings: DiagnosisSettings | None = None, device=None, resume: bool = False,
                  progress: Callable[[str], None] | None = None,
                  registration: RegistrationSettings | None = RegistrationSettings()) -> DiagnosisRun:
    """Diagnose the fit in ``fit_dir`` of the compressed case in ``case_dir`` over the candidate
    ``effects`` (names; default the whole library) for at most ``rounds`` rounds, writing to
    ``out_dir`` (a new folder, or the folder of an interrupted run with ``resume``). Each round
    that names a missing effect adds it (refined by ``settings.refine_iterations``) and the next
    round diagnoses the refitted model; a round that names none ends the run. Each round's
    models are also compared through the residual displacement field of a deformable
    registration (``registration``; None: not made)."""
    from BreastBiomechLib.discrepancy.session import DiagnosisSession, is_open

    if rounds < 1:
        raise ValueError("the diagnosis needs at least one round")
    say = progress or (lambda message: None)
    with claimed(out_dir, "a diagnosis"):
        session = DiagnosisSession(case_dir, fit_dir, out_dir, effects, noise, settings, device, resume, registration,
                                   progress)
        for record in session.rounds:
            say(f"round {record['round']}: {record['diagnosis']['verdict']} (from {session.path(record['round'])})")
        while True:
            last = session.last
            pending = last is not None and is_open(last) and last["diagnosis"]["verdict"] == "missing effect"
            if last is not None and not pending and (not last.get("added") or len(session.rounds) >= rounds):
                break  # a round that added nothing ends the run (on resume: an interrupted add is redone)
            record = session.diagnose()
            if record["diagnosis"]["verdict"] != "missing effect":
                break
            session.add(record["diagnosis"]["effect"])
        return session.run()

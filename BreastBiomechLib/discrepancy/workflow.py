"""The whole workflow on a fitted case: diagnose, add the named effect with its refit, and repeat
until nothing significant remains (or ``rounds`` are done), each step written as it finishes
(:class:`~BreastBiomechLib.discrepancy.session.DiagnosisSession`, whose docstring lists the
output folder) so that an interrupted run resumes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from BreastBiomechLib.discrepancy.diagnosis import DiagnosisSettings
from BreastBiomechLib.discrepancy.observations import NoiseModel
from BreastBiomechLib.discrepancy.registration import RegistrationSettings
from BreastBiomechLib.io.claims import claimed
from BreastBiomechLib.timing import staged


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


@staged("diagnosis")
def run_diagnosis(case_dir, fit_dir, out_dir, effects=None, rounds: int = 3, noise: NoiseModel | None = None,
                  settings: DiagnosisSettings | None = None, device=None, resume: bool = False,
                  progress: Callable[[str], None] | None = None,
                  registration: RegistrationSettings | None = RegistrationSettings(), one_round: bool = False,
                  add: str | None = None, design: tuple[str, ...] | None = None) -> DiagnosisRun:
    """Diagnose the fit in ``fit_dir`` of the compressed case in ``case_dir`` over the candidate
    ``effects`` (names; default the whole library) for at most ``rounds`` rounds, writing to
    ``out_dir`` (a new folder, or the folder of an interrupted run with ``resume``). Each round
    that names a missing effect adds it (refined by ``settings.refine_iterations``) and the next
    round diagnoses the refitted model; a round that names none ends the run. Each round's
    models are also compared through the residual displacement field of a deformable
    registration (``registration``; None: not made).

    A person deciding each round (the Breast Discrepancy panel) takes the steps one at a time:
    ``one_round`` diagnoses the next round (an open one again; at most ``rounds`` in all) and
    stops there, its diagnosis kept for the decision (its confirmation refits not refined);
    ``add`` (a candidate's name, with ``resume``) adds that candidate to the open last round,
    refits, refines by ``settings.refine_iterations``, makes its intervals (``settings.profile``),
    and stops.

    ``design`` (acquisition kinds or names; empty: all): once the run ends, the next measurement
    is designed for the candidates its last round could not tell apart
    (:meth:`~BreastBiomechLib.discrepancy.session.DiagnosisSession.design`; kept on resume where
    it was made after that round already). Not with ``one_round`` or ``add``: a person decides
    the round first."""
    from BreastBiomechLib.discrepancy.session import DiagnosisSession, is_open

    if rounds < 1:
        raise ValueError("the diagnosis needs at least one round")
    if design is not None and (one_round or add is not None):
        raise ValueError("the next measurement is designed once the rounds are decided: not with --one-round or --add")
    if add is not None and (one_round or not resume):
        raise ValueError("adding a candidate decides the open round of an earlier run: give --resume, without "
                         "--one-round")
    say = progress or (lambda message: None)
    settings = settings or DiagnosisSettings()
    if one_round:  # the refit of the effect a person accepts is refined, and its interval made, when it is added
        settings = replace(settings, refine_iterations=0, profile=False)
    with claimed(out_dir, "a diagnosis"):
        session = DiagnosisSession(case_dir, fit_dir, out_dir, effects, noise, settings, device, resume, registration,
                                   progress)
        for record in session.rounds:
            say(f"round {record['round']}: {record['diagnosis']['verdict']} (from {session.path(record['round'])})")
        if add is not None:
            session.add(add, settings.refine_iterations)
            return session.run()
        if one_round:
            last = session.last
            if last is not None and not is_open(last) and len(session.rounds) >= rounds:
                raise ValueError(f"{len(session.rounds)} rounds made, the most allowed ({rounds}): raise the rounds "
                                 "to go on")
            session.diagnose()
            return session.run()
        while True:
            last = session.last
            pending = last is not None and is_open(last) and last["diagnosis"]["verdict"] == "missing effect"
            if last is not None and not pending and (not last.get("added") or len(session.rounds) >= rounds):
                break  # a round that added nothing ends the run (on resume: an interrupted add is redone)
            if pending and session.diagnosis is not None:  # its kept diagnosis: the add goes on from it
                session.add(last["diagnosis"]["effect"])
                continue
            record = session.diagnose()
            if record["diagnosis"]["verdict"] != "missing effect":
                break
            session.add(record["diagnosis"]["effect"])
        if design is not None and not _designed(session):
            session.design(design)
        return session.run()


def _designed(session) -> bool:
    """Whether the session's folder holds the design made after its last round."""
    from BreastBiomechLib.discrepancy.design_record import read_design

    return read_design(session.out, session.last["round"]) is not None

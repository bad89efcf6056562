"""Where each file of a case folder lies: the one module that knows the layout.

::

    CASE/
      mr.nrrd                      the undeformed MR (LPS)
      landmarks.mrk.json           its landmarks (optional; LPS mm)
      seeds_muscle.mrk.json        seed points in the pectoral muscle (the segmentation's)
      seeds_tumour.mrk.json        and in the tumour, where the case has one
      labels.nrrd                  a phantom's truth labels: a fit meshes them only when told to
      compressed/                  the first measured state:
        mr.nrrd                      its MR (its own grid)
        landmarks.mrk.json           its landmarks (present exactly where the case's are)
        plates.json                  the plates' final planes and the scan's posture
        force.json                   optional: the measured plate force (N) and its sd
        truth.json, truth_mesh.vtu   a phantom's truth: read only by phantom.truth_files
      states/<name>/               further measured states of the same breast (another
                                   compression, the other plate moving, plates at another
                                   orientation, another posture): the same files as compressed/

A state's name is letters, digits, "-" and "_". :meth:`CaseLayout.check` validates a folder and
names what is wrong and what to do. A fit uses every state, jointly
(:mod:`BreastBiomechLib.optimisation.states`), or those it is told; the diagnosis stacks the
states its fit used: :meth:`CaseLayout.unused_states_note` names those a run leaves out.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

UNDEFORMED_MR = "mr.nrrd"
REFERENCE_LANDMARKS = "landmarks.mrk.json"
SEEDS_MUSCLE = "seeds_muscle.mrk.json"
SEEDS_TUMOUR = "seeds_tumour.mrk.json"
TRUTH_LABELS = "labels.nrrd"
FIRST_STATE = "compressed"
STATES = "states"
STATE_MR = "mr.nrrd"
STATE_LANDMARKS = "landmarks.mrk.json"
STATE_PLATES = "plates.json"
STATE_FORCE = "force.json"
STATE_NAME = re.compile(r"^[A-Za-z0-9_-]+$")


class CaseLayoutError(ValueError):
    """A case folder that does not follow the layout: the message names the file and what to do."""


@dataclass(frozen=True)
class StateFiles:
    """The files of one measured state ``name`` in ``folder``."""

    name: str
    folder: Path

    @property
    def mr(self) -> Path:
        return self.folder / STATE_MR

    @property
    def landmarks(self) -> Path:
        return self.folder / STATE_LANDMARKS

    @property
    def plates(self) -> Path:
        return self.folder / STATE_PLATES

    @property
    def force(self) -> Path:
        return self.folder / STATE_FORCE


@dataclass(frozen=True)
class PlateForce:
    """A state's measured plate force: ``newtons`` (N, > 0) with its standard deviation ``sd``
    (N, > 0), on the plate named ``plate`` (None: the moving plate, or both where both move)."""

    newtons: float
    sd: float
    plate: str | None = None


@dataclass(frozen=True)
class CaseLayout:
    """The files of the case folder ``root`` (see the module notes)."""

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def mr(self) -> Path:
        return self.root / UNDEFORMED_MR

    @property
    def landmarks(self) -> Path:
        return self.root / REFERENCE_LANDMARKS

    @property
    def seeds_muscle(self) -> Path:
        return self.root / SEEDS_MUSCLE

    @property
    def seeds_tumour(self) -> Path:
        return self.root / SEEDS_TUMOUR

    @property
    def truth_labels(self) -> Path:
        return self.root / TRUTH_LABELS

    def state(self, name: str = FIRST_STATE) -> StateFiles:
        """The state ``name``: ``compressed`` is the first, any other lies under ``states/``."""
        if name == FIRST_STATE:
            return StateFiles(name, self.root / FIRST_STATE)
        if not STATE_NAME.match(name):
            raise CaseLayoutError(f"{name!r} is not a state name: use letters, digits, '-' and '_'")
        return StateFiles(name, self.root / STATES / name)

    def state_names(self) -> list[str]:
        """The measured states present: ``compressed`` (where its folder is) first, then those
        under ``states/`` in name order."""
        names = [FIRST_STATE] if (self.root / FIRST_STATE).is_dir() else []
        extra = self.root / STATES
        if extra.is_dir():
            names += sorted(p.name for p in extra.iterdir() if p.is_dir())
        return names

    def check(self) -> list[StateFiles]:
        """The measured states, validated: the undeformed MR is there, a first state exists, and
        every state holds its MR and plates, a valid name and, where present, a valid force
        record; a further state holds landmarks exactly where the case has reference landmarks
        (the first state's are matched to them by the fit, which says what is missing). Raises
        :class:`CaseLayoutError` (or FileNotFoundError for a missing file) naming the file and
        what to do."""
        if not self.mr.is_file():
            raise FileNotFoundError(f"{self.root}: no undeformed MR ({UNDEFORMED_MR}); a case folder holds the "
                                    "undeformed image and its measured states")
        if not (self.root / FIRST_STATE).is_dir():
            raise FileNotFoundError(f"{self.root}: no measured state ({FIRST_STATE}/ with {STATE_MR} and "
                                    f"{STATE_PLATES}); add the compressed scan there")
        extra = self.root / STATES
        if extra.exists() and not extra.is_dir():
            raise CaseLayoutError(f"{extra} is a file: {STATES}/ holds one folder per further measured state")
        if extra.is_dir():
            for entry in sorted(extra.iterdir()):
                if not entry.is_dir():
                    raise CaseLayoutError(f"{entry}: {STATES}/ holds one folder per measured state, not files; move "
                                          f"it into a state's folder")
                if not STATE_NAME.match(entry.name):
                    raise CaseLayoutError(f"{entry}: a state's name is letters, digits, '-' and '_'; rename it")
        has_landmarks = self.landmarks.is_file()
        states = [self.state(name) for name in self.state_names()]
        for state in states:
            for path, what in ((state.mr, "its MR"), (state.plates, "the plates' final planes")):
                if not path.is_file():
                    raise FileNotFoundError(f"state {state.name!r}: no {path.name} ({what}) in {state.folder}")
            if state.name != FIRST_STATE and state.landmarks.is_file() != has_landmarks:
                raise CaseLayoutError(
                    f"state {state.name!r}: {'landmarks' if state.landmarks.is_file() else 'no landmarks'} "
                    f"({state.landmarks}) while the case has {'reference landmarks' if has_landmarks else 'none'} "
                    f"({self.landmarks}): landmarks count where both images have them; add or remove them")
            if state.force.is_file():
                read_force(state)
        return states

    def unused_states_note(self, used=(FIRST_STATE,), why: str = "") -> str:
        """A sentence naming the measured states of the case beyond ``used`` (names) that a run
        does not use, and ``why`` ("" where it uses them all)."""
        extra = [name for name in self.state_names() if name not in used]
        if not extra:
            return ""
        listed = ", ".join(f"{STATES}/{name}" for name in extra)
        using = ", ".join(f"{name}/" if name == FIRST_STATE else f"{STATES}/{name}" for name in used)
        return (f"{self.root} holds measured states this run does not use ({listed}): it uses {using} only"
                + (f"; {why}" if why else ""))


def read_force(state: StateFiles) -> PlateForce:
    """The measured plate force of ``state`` (its force.json: {"newtons": N, "sd": N, "plate":
    optional name}); a :class:`CaseLayoutError` naming what is wrong otherwise."""
    try:
        record = json.loads(state.force.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise CaseLayoutError(f"{state.force}: not readable as JSON ({error}); write "
                              '{"newtons": 12.5, "sd": 1.0} (N)') from None
    if not isinstance(record, dict):
        raise CaseLayoutError(f"{state.force}: a JSON object {{\"newtons\": ..., \"sd\": ...}} (N), not {record!r}")
    unknown = set(record) - {"newtons", "sd", "plate"}
    if unknown:
        raise CaseLayoutError(f"{state.force}: unknown keys {sorted(unknown)}; it holds newtons, sd and optionally "
                              "plate")
    values = {}
    for key in ("newtons", "sd"):
        value = record.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise CaseLayoutError(f"{state.force}: {key} must be a positive number of newtons, not {value!r}")
        values[key] = float(value)
    plate = record.get("plate")
    if plate is not None:
        try:
            names = [p.get("name") for p in json.loads(state.plates.read_text())["plates"]]
        except (OSError, json.JSONDecodeError, KeyError, TypeError, AttributeError):
            names = []
        if not isinstance(plate, str) or plate not in names:
            known = ", ".join(map(str, names)) if names else f"none readable in {state.plates}"
            raise CaseLayoutError(f"{state.force}: plate names one of the state's plates ({known}), not {plate!r}")
    return PlateForce(values["newtons"], values["sd"], plate)

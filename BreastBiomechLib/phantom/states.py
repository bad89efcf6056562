"""Further measured states of a compressed phantom case: the same breast, truth materials and
hidden effects, compressed again another way (another magnitude, the other plate moving, plates
at another orientation, another posture) and imaged as a further scan, written under
``states/<name>/`` (:mod:`BreastBiomechLib.io.case_layout`). A state may also record the plate
force a load cell would measure (``force.json``: the truth's force with a measurement error).

A state is given as its name and settings, ``NAME KEY=VALUE ...`` (``breastbiomech phantom
--compressed --state ...`` makes them with the case, ``breastbiomech phantom-state CASE --state
...`` adds them to a compressed phantom case made earlier)::

    compression=0.3             the fraction of the breast's thickness the plates close
    axis=SI                     the compression axis (LR or SI)
    moving-plate=second         which plate moves: both, first or second
    compression-gravity=0,0,-9.81
                                the gravity while the plates close (m/s^2, LPS: a posture change;
                                the case's truth needs --gravity)
    force-sd=0.5                record the measured plate force with this sd (N)

Settings left out are the first state's.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from BreastBiomechLib.io.case_layout import FIRST_STATE, STATE_NAME, CaseLayout, CaseLayoutError
from BreastBiomechLib.phantom.compressed import MOVING_PLATES, CompressedCase, TruthModel

AXES = ("LR", "SI")
SETTINGS = ("compression", "axis", "moving-plate", "compression-gravity", "force-sd")
SEED_STRIDE = 7919  # a state's image noise is seeded apart from the first state's (a prime: no overlap)


@dataclass(frozen=True)
class StateSpec:
    """A further state ``name``: the settings that differ from the first state's (None: the
    same); ``force_sd`` (N): record the measured plate force with this sd (None: none)."""

    name: str
    compression: float | None = None
    axis: str | None = None
    moving_plate: str | None = None
    compression_gravity: tuple[float, float, float] | None = None
    force_sd: float | None = None

    def truth(self, first: TruthModel, index: int) -> TruthModel:
        """The truth of this state, the ``index``-th further one (1, 2, ...), from the first
        state's ``first``: its own compression, axis, moving plate and posture, the same
        materials and hidden effects, its own image noise."""
        if self.compression_gravity is not None and first.gravity is None:
            raise ValueError(f"state {self.name!r}: compression-gravity is a posture change from the posture the "
                             "undeformed scan was imaged in; give that with --gravity GX GY GZ")
        changed = {"seed": first.seed + SEED_STRIDE * index}
        for key in ("compression", "axis", "moving_plate"):
            if getattr(self, key) is not None:
                changed[key] = getattr(self, key)
        if self.compression_gravity is not None:
            changed["compression_gravity"] = list(self.compression_gravity)
            changed["recorded_gravity"] = None  # the state's own posture, as given
        return replace(first, **changed)


def parse_state(words: list[str]) -> StateSpec:
    """A :class:`StateSpec` from ``NAME KEY=VALUE ...`` (see the module notes); a ValueError
    that names the word at fault and what it may be otherwise."""
    if not words:
        raise ValueError("--state needs a name, then its settings (KEY=VALUE)")
    name, settings = words[0], words[1:]
    if not STATE_NAME.match(name) or name == FIRST_STATE:
        raise ValueError(f"--state {name!r}: a state's name is letters, digits, '-' and '_', and not "
                         f"{FIRST_STATE!r} (the first state's)")
    values: dict = {}
    for word in settings:
        key, sep, text = word.partition("=")
        if not sep or key not in SETTINGS:
            raise ValueError(f"--state {name}: {word!r} is not a setting; give KEY=VALUE with KEY one of "
                             f"{', '.join(SETTINGS)}")
        if key in values:
            raise ValueError(f"--state {name}: {key} given twice")
        values[key] = _value(name, key, text)
    return StateSpec(name, values.get("compression"), values.get("axis"), values.get("moving-plate"),
                     values.get("compression-gravity"), values.get("force-sd"))


def _value(name: str, key: str, text: str):
    where = f"--state {name}: {key}={text!r}"
    if key == "axis":
        if text not in AXES:
            raise ValueError(f"{where}: the axis is one of {', '.join(AXES)}")
        return text
    if key == "moving-plate":
        if text not in MOVING_PLATES:
            raise ValueError(f"{where}: the moving plate is one of {', '.join(MOVING_PLATES)}")
        return text
    if key == "compression-gravity":
        try:
            vector = tuple(float(v) for v in text.split(","))
        except ValueError:
            vector = ()
        if len(vector) != 3 or not all(math.isfinite(v) for v in vector):
            raise ValueError(f"{where}: three finite numbers separated by commas (m/s^2, LPS), e.g. 0,0,-9.81")
        return vector
    try:
        number = float(text)
    except ValueError:
        number = float("nan")
    if key == "compression" and not 0.0 < number < 0.7:
        raise ValueError(f"{where}: the fraction of the breast's thickness the plates close, between 0 and 0.7")
    if key == "force-sd" and not (math.isfinite(number) and number > 0.0):
        raise ValueError(f"{where}: the force's standard deviation, a positive number of newtons")
    return number


def check_states(specs: list[StateSpec]) -> None:
    """Refuse two states of one name (a CaseLayoutError naming it)."""
    names = [s.name for s in specs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise CaseLayoutError(f"--state {', '.join(twice)} given more than once: each state needs its own name")


def measured_force(compressed: CompressedCase, sd: float, seed: int) -> dict:
    """The plate force a load cell on the moving plate would measure (``force.json``'s record):
    the truth solve's normal force on it (N; with both plates moving, on the first) plus a
    normal measurement error of ``sd`` N drawn from ``seed``; never below a tenth of the truth's."""
    forces = compressed.summary["plate_forces_N"]
    plates = list(forces)
    plate = plates[1] if compressed.truth.moving_plate == "second" and len(plates) > 1 else plates[0]
    truth = float(forces[plate])
    newtons = truth + sd * float(np.random.default_rng(seed).standard_normal())
    return {"newtons": max(newtons, 0.1 * truth), "sd": float(sd), "plate": plate}


def add_states(case_dir: str | Path, specs: list[StateSpec], device=None, overview: bool = True,
               progress: Callable[[str], None] | None = None, phantom_dir: str | Path | None = None) -> list[dict]:
    """Simulate and image each further state of ``specs`` on the compressed phantom case in
    ``case_dir`` (its phantom, its first state's truth model and truth mesh, read back) and write
    it under ``states/<name>/``; a state the case holds already is refused. ``phantom_dir``: where
    the phantom lies when not in ``case_dir`` (the hidden-effect suite keeps it once per anatomy).
    Returns each state's figures: {"name", "truth" (:class:`TruthModel`), "summary", "force"
    (or None), "folder"}."""
    from BreastBiomechLib.io.meshes import read_vtu
    from BreastBiomechLib.mesh.tetmesh import TetMesh
    from BreastBiomechLib.phantom.compressed import compress_phantom
    from BreastBiomechLib.phantom.compressed_files import write_compressed
    from BreastBiomechLib.phantom.files import read_phantom
    from BreastBiomechLib.phantom.truth_files import read_truth, truth_mesh_path

    say = progress or (lambda message: None)
    layout = CaseLayout(case_dir)
    check_states(specs)
    present = layout.state_names()
    taken = [s.name for s in specs if s.name in present]
    if taken:
        raise CaseLayoutError(f"{case_dir} holds the state {', '.join(taken)} already: choose another name, or "
                              f"remove {layout.state(taken[0]).folder} first")
    first = TruthModel(**read_truth(case_dir)["truth"])
    case = read_phantom(case_dir if phantom_dir is None else phantom_dir)
    made = read_vtu(truth_mesh_path(case_dir))
    mesh = TetMesh(made.nodes, made.tets, {k: v for k, v in made.point_data.items() if k != "displacement"},
                   dict(made.cell_data))
    out = []
    for k, spec in enumerate(specs, start=len(present)):
        truth = spec.truth(first, k)
        compressed = compress_phantom(case, truth, device=device, mesh=mesh,
                                      progress=lambda fraction, message: say(f"state {spec.name}: {message}"))
        force = None if spec.force_sd is None else measured_force(compressed, spec.force_sd, truth.seed)
        paths = write_compressed(compressed, case_dir, overview=overview, state=spec.name, force=force)
        out.append({"name": spec.name, "truth": truth, "summary": compressed.summary, "force": force,
                    "folder": paths["measured"].parent})
    return out

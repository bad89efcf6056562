"""The hidden-effect suite's cases: which anatomies, which effect each truth hides, and the verdict
that is right for it.

An anatomy is a phantom of the seed's Table 1 presets (cases 1-5: 464-1364 cm³, glandular
density 12-50 %, one with a tumour). Each hidden effect is a set of :class:`TruthModel` fields
at a realistic size:

==================  ==========================================================  =================
hidden effect       in the truth                                                right verdict
==================  ==========================================================  =================
null                nothing beyond the fitted family                            no significant
friction            Coulomb mu 0.6 on both plates (skin on polycarbonate)       friction
gravity             prone MR, compressed upright (gravity inferior; the         gravity
                    postures are in the case's record)
chest-wall          the chest wall holds the breast along itself: springs of    chest-wall
                    3.4 kPa/mm (fat's shear modulus over a 1 mm layer), where
                    the fitted (the seed's) model lets it slide freely
skin                a 2 mm skin layer of 100 kPa                                skin
friction-per-plate  mu 0.9 on the first plate, 0.3 on the second (made only      friction, then
                    where asked for by name)                                    friction per plate
                                                                                 if it shows
plate-tilt          the first plate tilted 4° about its first tilt axis (the    plate-tilt
                    case records the nominal, parallel plates; where only the
                    second plate moves, that one)
friction+plate-tilt both                                                        both, in rounds
stiff-band          a 15 mm oblique band of 4x stiffer breast tissue the MR     unexplained
                    does not show (not in the library)
chest-wall-shift    the thorax 4 mm anterior at the compressed scan             unexplained
                    (breathing; not in the library)
==================  ==========================================================  =================
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

NONE = "no significant discrepancy"
UNEXPLAINED = "unexplained discrepancy"
MISSING = "missing effect"


@dataclass(frozen=True)
class HiddenEffect:
    """One kind of case: its ``name``, the :class:`~BreastBiomechLib.phantom.compressed.TruthModel`
    fields that hide it (``truth``), the library effects a right diagnosis adds (``expected``,
    empty for the null and the unknown effects), whether the library holds it (``known``) and,
    where a library effect's parameters measure the quantity the truth sets, their true values
    (``values``: {effect name: values in the effect's parameter order and units}), against which
    the suite scores the refitted estimate (not the plate tilt's: which plate the truth tilts
    depends on the case's rig). ``optional``: refinements of an expected effect that the truth
    also holds, at a size the case may or may not show (gravity turned from the recorded posture
    by the drawn lean): right whether named or not, never a false naming."""

    name: str
    truth: dict = field(default_factory=dict)
    expected: tuple[str, ...] = ()
    known: bool = True
    values: dict = field(default_factory=dict)
    optional: tuple[str, ...] = ()

    def added_right(self, added) -> bool:
        """Whether the effects ``added`` over a diagnosis's rounds are this truth's: every
        expected one, and nothing beyond them but :attr:`optional` refinements."""
        added = set(added)
        return set(self.expected) <= added <= set(self.expected) | set(self.optional)

    @property
    def kind(self) -> str:
        """"null", "single", "two" or "unknown"."""
        if not self.known:
            return "unknown"
        return {0: "null", 1: "single"}.get(len(self.expected), "two")

    @property
    def right_verdict(self) -> str:
        return {"null": NONE, "unknown": UNEXPLAINED}.get(self.kind, MISSING)


HIDDEN_EFFECTS: dict[str, HiddenEffect] = {h.name: h for h in (
    HiddenEffect("null"),
    HiddenEffect("friction", {"friction": 0.6}, ("friction",), values={"friction": (0.6,)}),
    HiddenEffect("gravity", {"gravity": [0.0, -9.81, 0.0], "compression_gravity": [0.0, 0.0, -9.81]}, ("gravity",)),
    HiddenEffect("chest-wall", {"chest_wall": "sliding", "chest_wall_stiffness": [0.0, 3400.0]}, ("chest-wall",)),
    HiddenEffect("skin", {"skin": [100e3, 2.0]}, ("skin",)),
    HiddenEffect("plate-tilt", {"plate_tilt_deg": [[4.0, 0.0], [0.0, 0.0]]}, ("plate-tilt",)),
    HiddenEffect("friction+plate-tilt", {"friction": 0.6, "plate_tilt_deg": [[4.0, 0.0], [0.0, 0.0]]},
                 ("friction", "plate-tilt"), values={"friction": (0.6,)}),
    HiddenEffect("stiff-band", {"stiff_band": [4.0, 15.0]}, known=False),
    HiddenEffect("chest-wall-shift", {"chest_wall_shift_mm": [0.0, -4.0, 0.0]}, known=False),
    HiddenEffect("friction-per-plate", {"friction": [0.9, 0.3]}, ("friction",),
                 values={"friction-per-plate": (round(math.log(3.0), 4),)}, optional=("friction-per-plate",)),
)}
# made only where asked for by name (``--hidden``): added after runs were made with the others, and
# left out of the default cases so that those runs' cases stay what they were
BY_REQUEST = ("friction-per-plate",)
DEFAULT_HIDDEN = tuple(name for name in HIDDEN_EFFECTS if name not in BY_REQUEST)

ANATOMIES = (1, 2, 3, 4, 5)


@dataclass(frozen=True)
class SuiteCase:
    """One case: the ``anatomy`` (1-5 the Table 1 presets; the varied suite's also 6-11) and the
    ``hidden`` effect; ``name`` its folder. A case of the varied suite
    (:mod:`~BreastBiomechLib.discrepancy.suite.varied`) has its ``index`` in the run of seed
    ``varied_seed`` and the settings it drew (``draw``: (name, value) pairs of
    :class:`~BreastBiomechLib.discrepancy.suite.runner.SuiteSettings` fields); a fixed suite's
    case has index -1 and draws nothing. ``states``: 1, the case as one scan; 2, also a second
    scan chosen by the design step from the one-scan diagnosis, then both fitted and diagnosed
    jointly (:mod:`~BreastBiomechLib.discrepancy.suite.two_state`)."""

    anatomy: int
    hidden: HiddenEffect
    index: int = -1
    varied_seed: int = 0
    draw: tuple = ()
    states: int = 1

    def __post_init__(self) -> None:
        if self.states not in (1, 2):
            raise ValueError(f"a suite case has one or two measured states, not {self.states}")

    @property
    def name(self) -> str:
        name = (f"varied{self.varied_seed}-{self.index:03d}-anatomy{self.anatomy}-{self.hidden.name}"
                if self.index >= 0 else f"anatomy{self.anatomy}-{self.hidden.name}")
        return name + ("-two-state" if self.states == 2 else "")

    @property
    def seed(self) -> int:
        """The measured image's noise seed: its own per case."""
        if self.index >= 0:
            return 900_000 + 1000 * self.varied_seed + self.index
        return 5000 + 100 * self.anatomy + list(HIDDEN_EFFECTS).index(self.hidden.name)

    @property
    def drawn(self) -> dict:
        """The settings this case drew ({} for a fixed suite's case)."""
        return dict(self.draw)


def suite_cases(anatomies=ANATOMIES, effects=None, states: int = 1) -> list[SuiteCase]:
    """The cases of ``anatomies`` (Table 1 numbers) x ``effects`` (names of :data:`HIDDEN_EFFECTS`,
    default all but :data:`BY_REQUEST`), hidden effect by hidden effect (so that workers running side by side start on
    different anatomies), each of ``states`` measured states (:attr:`SuiteCase.states`)."""
    names = list(DEFAULT_HIDDEN) if effects is None else list(effects)
    unknown = sorted(set(names) - set(HIDDEN_EFFECTS))
    if unknown:
        raise ValueError(f"unknown hidden effects {unknown}; the suite has {list(HIDDEN_EFFECTS)}")
    bad = sorted(set(anatomies) - set(ANATOMIES))
    if bad:
        raise ValueError(f"anatomies {bad}: the suite's anatomies are the Table 1 presets {list(ANATOMIES)} (6-11: the varied suite's)")
    return [SuiteCase(a, HIDDEN_EFFECTS[n], states=states) for n in names for a in anatomies]

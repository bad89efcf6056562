"""The varied suite: cases that each draw what the fixed suite holds constant (issue 77, point 6).

The fixed suite makes every case at 40 % compression, both plates closing, a 6 mm fitting mesh
against a 3 mm truth, a 60-solve fit, 0.35 mm landmark noise and one size per effect, on the five
Table 1 anatomies. A real case differs in each of these, so a verdict rule that holds only at
those settings is a defect. Here case ``k`` of a run draws, from random numbers seeded by
(``seed``, ``k``) and so the same on every machine:

==========================  ================================================================
setting                     drawn from
==========================  ================================================================
anatomy                     the Table 1 presets (1-5) and six more (6-11): three of the
                            segmentation sweep's anatomy variants and three of its tumour
                            variants (spiculated or lobulated tumours in dense gland)
compression                 20-50 % of the breast's thickness
rig                         both plates closing, or only the second (the seed's rig)
landmark noise              0.2-1.0 mm (sd per coordinate)
fit budget                  10, 20, 40, 60, 100 or 200 solves (population a third of it,
                            4-12)
fitting mesh                4, 5, 6, 8 or 10 mm elements
truth mesh                  2 or 3 mm elements
friction                    mu 0.2-1.0
friction per plate          their geometric mean 0.2-1.0, one plate's 2-5 times the other's
                            (only where asked for by name, ``--hidden friction-per-plate``)
plate tilt                  0.5-4 degrees, either sign, about either tilt axis, about a pivot
                            up to 60 mm from the plate's recorded point in its plane and up to
                            20 mm behind it (a paddle turns about its mount)
skin                        20-100 kPa, 1-3 mm thick
gravity                     prone MR; compressed upright, the body leaning 0-30 degrees (the
                            case records "upright": the lean is for the diagnosis to find)
chest-wall hold             springs of 1.7-6.8 kPa/mm
stiff band (unknown)        2.5-6 times stiffer, 10-20 mm thick
chest-wall shift (unknown)  the thorax 2-6 mm anterior
==========================  ================================================================

A third of the cases are null cases, so that a run of 90 holds 30 of them and the false-alarm
rate has a useful interval; the rest cycle through the hidden effects. The truths are made as
the fixed suite's are (:class:`~BreastBiomechLib.phantom.compressed.TruthModel`); the fit and the
diagnosis see only the measured copy.
"""

from __future__ import annotations

import numpy as np

from BreastBiomechLib.discrepancy.suite.cases import ANATOMIES, DEFAULT_HIDDEN, HIDDEN_EFFECTS, HiddenEffect, SuiteCase

# anatomies beyond the Table 1 presets: number -> (sweep family, variant index)
EXTRA_ANATOMIES = {6: ("anatomy", 0), 7: ("tumour", 1), 8: ("anatomy", 3), 9: ("tumour", 4), 10: ("anatomy", 6),
                   11: ("tumour", 9)}
VARIED_ANATOMIES = ANATOMIES + tuple(EXTRA_ANATOMIES)
NULL_SHARE = 3  # every third case is a null case
FIT_BUDGETS = (10, 20, 40, 60, 100, 200)
FIT_EDGES_MM = (4.0, 5.0, 6.0, 8.0, 10.0)
TRUTH_EDGES_MM = (2.0, 3.0)
PIVOT_IN_PLANE_MM, PIVOT_BEHIND_MM = 60.0, 20.0  # a hidden plate turn's pivot from the plate's recorded point
# the settings a case draws, with the bins its scores are tabled by (lower edges; the last open)
SETTING_BINS = {"compression": (0.2, 0.3, 0.4), "moving_plate": None, "landmark_noise_mm": (0.2, 0.5),
                "fit_budget": (10, 40, 100), "fit_edge_mm": (4.0, 6.0, 8.0), "truth_edge_mm": None}


def anatomy_parameters(number: int):
    """The phantom parameters of suite anatomy ``number``: a Table 1 preset (1-5) or one of
    :data:`EXTRA_ANATOMIES` (6-11)."""
    from BreastBiomechLib.phantom.parameters import table1_case
    from BreastBiomechLib.phantom.variants import sweep_variants

    if number in ANATOMIES:
        return table1_case(number)
    if number not in EXTRA_ANATOMIES:
        raise ValueError(f"anatomy {number}: the suite's anatomies are {list(VARIED_ANATOMIES)} (1-5 the Table 1 "
                         "presets, 6-11 sweep variants)")
    family, index = EXTRA_ANATOMIES[number]
    return sweep_variants(index + 1, family)[index]


def sized_effect(name: str, rng: np.random.Generator) -> HiddenEffect:
    """The hidden effect ``name`` of :data:`HIDDEN_EFFECTS` at a size drawn from its range (see
    the module notes), with the true values the suite scores its estimate against."""
    base = HIDDEN_EFFECTS[name]
    truth, values = {}, {}
    for part in name.split("+"):
        if part == "friction":
            mu = round(float(rng.uniform(0.2, 1.0)), 3)
            truth["friction"], values["friction"] = mu, (mu,)
        elif part == "friction-per-plate":
            mu = float(rng.uniform(0.2, 1.0))
            ratio = float(rng.uniform(np.log(2.0), np.log(5.0)) * rng.choice((-1.0, 1.0)))
            pair = [round(mu * np.exp(ratio / 2), 3), round(mu * np.exp(-ratio / 2), 3)]
            truth["friction"], values["friction-per-plate"] = pair, (round(float(np.log(pair[0] / pair[1])), 4),)
        elif part == "plate-tilt":
            angle = round(float(rng.uniform(0.5, 4.0) * rng.choice((-1.0, 1.0))), 2)
            truth["plate_tilt_deg"] = [[angle, 0.0] if rng.random() < 0.5 else [0.0, angle], [0.0, 0.0]]
            pivot = np.r_[rng.uniform(-PIVOT_IN_PLANE_MM, PIVOT_IN_PLANE_MM, 2), -rng.uniform(0.0, PIVOT_BEHIND_MM)]
            truth["plate_pivot_mm"] = [np.round(pivot, 1).tolist(), [0.0, 0.0, 0.0]]
        elif part == "skin":
            truth["skin"] = [round(float(rng.uniform(20e3, 100e3)), -2), round(float(rng.uniform(1.0, 3.0)), 2)]
        elif part == "gravity":
            lean = np.radians(rng.uniform(0.0, 30.0))
            truth["gravity"] = [0.0, -9.81, 0.0]
            truth["compression_gravity"] = [0.0, round(float(-9.81 * np.sin(lean)), 3),
                                            round(float(-9.81 * np.cos(lean)), 3)]
            truth["recorded_gravity"] = [0.0, 0.0, -9.81]  # the case says "upright", not the lean
        elif part == "chest-wall":
            truth["chest_wall"] = "sliding"
            truth["chest_wall_stiffness"] = [0.0, round(float(rng.uniform(1.7e3, 6.8e3)), -1)]
        elif part == "stiff-band":
            truth["stiff_band"] = [round(float(rng.uniform(2.5, 6.0)), 2), round(float(rng.uniform(10.0, 20.0)), 1)]
        elif part == "chest-wall-shift":
            truth["chest_wall_shift_mm"] = [0.0, round(float(-rng.uniform(2.0, 6.0)), 2), 0.0]
        elif part != "null":
            raise ValueError(f"no size range for the hidden effect {part!r}")
    optional = base.optional + (("gravity-direction",) if "recorded_gravity" in truth and truth["recorded_gravity"] !=
                                truth["compression_gravity"] else ())
    return HiddenEffect(base.name, truth, base.expected, base.known, values, optional)


def drawn_settings(rng: np.random.Generator) -> dict:
    """One case's settings (the :class:`~BreastBiomechLib.discrepancy.suite.runner.SuiteSettings`
    fields of :data:`SETTING_BINS`, with the fit's population), drawn from their ranges."""
    budget = int(rng.choice(FIT_BUDGETS))
    return {"compression": round(float(rng.uniform(0.2, 0.5)), 3),
            "moving_plate": str(rng.choice(("both", "second"))),
            "landmark_noise_mm": round(float(rng.uniform(0.2, 1.0)), 2),
            "fit_budget": budget, "fit_population": int(min(12, max(4, budget // 3))),
            "fit_edge_mm": float(rng.choice(FIT_EDGES_MM)), "truth_edge_mm": float(rng.choice(TRUTH_EDGES_MM))}


def varied_cases(count: int, seed: int = 0, anatomies=VARIED_ANATOMIES, effects=None) -> list[SuiteCase]:
    """The first ``count`` cases of the varied suite ``seed``: case ``k`` a null case when k is
    a multiple of :data:`NULL_SHARE`, else the next of ``effects`` (names of :data:`HIDDEN_EFFECTS`
    other than null; default all but those made by request), on the next of ``anatomies``, its
    effect's size and its settings drawn from random numbers seeded by (``seed``, ``k``)."""
    if count < 1:
        raise ValueError("the varied suite needs at least one case")
    names = [n for n in (effects or DEFAULT_HIDDEN) if n != "null"]
    unknown = sorted(set(names) - set(HIDDEN_EFFECTS))
    if unknown:
        raise ValueError(f"unknown hidden effects {unknown}; the suite has {list(HIDDEN_EFFECTS)}")
    bad = sorted(set(anatomies) - set(VARIED_ANATOMIES))
    if bad or not anatomies:
        raise ValueError(f"anatomies {bad}: the varied suite's anatomies are {list(VARIED_ANATOMIES)}")
    cases, effect_turn = [], 0
    for k in range(count):
        rng = np.random.default_rng([seed, k])
        if k % NULL_SHARE == 0 or not names:
            name = "null"
        else:
            name, effect_turn = names[effect_turn % len(names)], effect_turn + 1
        cases.append(SuiteCase(int(anatomies[k % len(anatomies)]), sized_effect(name, rng), index=k, varied_seed=seed,
                               draw=tuple(sorted(drawn_settings(rng).items()))))
    return cases


def setting_bin(name: str, value) -> str:
    """The bin of ``value`` of setting ``name`` in the scores' tables ("0.3-0.4", "100+", "second")."""
    edges = SETTING_BINS.get(name)
    if edges is None:
        return str(value)
    below = [e for e in edges if value >= e]
    if not below:
        return f"<{edges[0]:g}"
    low = below[-1]
    following = [e for e in edges if e > low]
    return f"{low:g}-{following[0]:g}" if following else f"{low:g}+"

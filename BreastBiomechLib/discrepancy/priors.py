"""Prior-data conflict: fitted moduli beyond what published measurements of breast tissue allow.

A fit with the plates' travel prescribed sees only the tissues' moduli relative to one another
(the seed fixes fat at 10 kPa as the reference), so the plausible ranges are ratios to the fit's
fat modulus, taken from studies that measured fat and the other tissue in the same protocol:

- **fibroglandular / fat 0.5-10**: similar at small strain (Samani, Zubovits and Plewes 2007,
  Phys Med Biol 52:1565, 169 ex-vivo samples: fat 3.25 +- 0.91 kPa, fibroglandular 3.24 +- 0.61
  kPa) and up to an order of magnitude stiffer than fat at large precompression (Krouskop et al.
  1998, Ultrasonic Imaging 20:260); the seed's own fits put it below fat in one case of four
  (Han et al. 2012, Table 3).
- **tumour / fat 1-30**: fibroadenomas about twice fibroglandular tissue, malignant tumours 3-6
  times and high-grade invasive ductal carcinoma up to 13 times (Samani 2007); infiltrating
  ductal carcinomas much stiffer than any other breast tissue at large strain, 5-28 times fat
  (Krouskop 1998).
- **pectoral muscle / fat 0.5-20**: relaxed skeletal muscle's shear modulus is a few kPa across its
  fibres and rises several-fold along them and under stretch (supersonic shear imaging in vivo,
  Gennisson et al. 2010, Ultrasound Med Biol 36:789; Eby et al. 2013, J Biomech 46:2381), against
  breast fat's 3-20 kPa above.
- **skin / fat 5-50**: skin 56 +- 16 kPa over adipose and fibroglandular tissue's 3.0 +- 1.2 kPa
  in vivo, by light aspiration on seven volunteers ("In vivo measurement of breast tissues
  stiffness using a light aspiration device", Clinical Biomechanics 2022).

The ranges are wide on purpose (they span the studies, not one study's mean +- sd) and were set
from the sources alone, never from the phantom's truth. A fitted modulus outside its range is a
*prior-data conflict*: a missing effect may be absorbed there (a chest wall that holds the breast
fits as a stiffer pectoral muscle). The diagnosis then tests the candidates again with that
modulus held at the nearest end of its range (:func:`held_in_range`: the residual of the model
solved with the modulus there, in the launch of the round's sensitivities; linearised, the
residual moved by the modulus's sensitivity times the step back, only where that model does not
solve; the modulus taken out of the fitted span), and a candidate that explains the residual
only then is reported as *ambiguous*: that effect, or the modulus outside its plausible range
(one already significant at the fit is the verdict's business, not the conflict's).

Units: moduli in Pa; unit coordinates those of the fit's space (log E).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BreastBiomechLib.discrepancy import statistics

REFERENCE_TISSUE = "fat"


@dataclass(frozen=True)
class PlausibleRange:
    """The plausible Young's modulus of ``tissue`` as a ratio to fat's (``low``-``high``), with
    the sources it rests on."""

    tissue: str
    low: float
    high: float
    sources: str


PLAUSIBLE_E = {r.tissue: r for r in (
    PlausibleRange("glandular", 0.5, 10.0, "Samani et al. 2007; Krouskop et al. 1998; Han et al. 2012"),
    PlausibleRange("tumour", 1.0, 30.0, "Samani et al. 2007; Krouskop et al. 1998"),
    PlausibleRange("muscle", 0.5, 20.0, "Gennisson et al. 2010; Eby et al. 2013; Samani et al. 2007"),
    PlausibleRange("skin", 5.0, 50.0, "in vivo light aspiration, Clinical Biomechanics 2022"),
)}


def prior_conflicts(space, z) -> list[dict]:
    """The fit's free moduli (``space``: the fit's
    :class:`~BreastBiomechLib.optimisation.space.FitSpace`, ``z`` its unit position) outside
    their plausible range relative to fat's modulus at ``z``: {"name" (the space key), "index"
    (in the space's keys), "value" (Pa), "ratio" (to fat), "range" ([low, high] Pa at this fat),
    "bound" (the nearest end, Pa), "z_bound" (its unit coordinate, within the fit's own range),
    "sources"}. Empty where the fit has no fat modulus to refer to."""
    materials = space.materials(z)
    fat = (materials.get(REFERENCE_TISSUE) or {}).get("E")
    if not fat or fat <= 0:
        return []
    out = []
    for index, (parameter, value) in enumerate(zip(space.free, space.values(z).values())):
        plausible = PLAUSIBLE_E.get(parameter.tissue)
        if parameter.name != "E" or plausible is None:
            continue
        low, high = plausible.low * fat, plausible.high * fat
        if low <= value <= high:
            continue
        bound = low if value < low else high
        out.append({"name": parameter.key, "index": index, "value": float(value), "ratio": float(value / fat),
                    "range": [float(low), float(high)], "bound": float(bound),
                    "z_bound": float(np.clip(parameter.to_unit(bound), 0.0, 1.0)), "sources": plausible.sources})
    return out


def held_in_range(whitened: np.ndarray, nuisance: np.ndarray, free: np.ndarray, column: int, step: float,
                  signatures: dict[str, np.ndarray], channels, alpha: float, before: dict[str, float],
                  solved: np.ndarray | None = None) -> dict:
    """The tests again with one fitted parameter held inside its plausible range:
    ``whitened`` (n,) the whitened residual, ``nuisance`` (n, p) the whitened sensitivities of
    the fitted parameters, ``free`` (p,) bool which of them the tests take as free, ``column``
    the parameter held and ``step`` its change (unit coordinates) back to its range's end.
    ``solved`` (n,): the whitened residual of the model solved with the parameter held there;
    without it the residual is linearised (moved by the parameter's sensitivity times ``step``),
    which a large step back (a modulus fitted several times past its range) makes poor.
    ``signatures`` {name: (n, k)} the candidates' whitened sensitivities, ``before`` {name: their
    corrected p at the fit}. Returns {"overall": the overall test per channel, "candidates":
    {name: {"p_adjusted", "explained_fraction", "statistic", "dof"}}, "significant": the names
    significant at ``alpha`` (Bonferroni over the candidates), best first, "explains" those
    of them that were not significant at the fit: what the parameter was taking up, and
    "solved" whether the residual was solved}."""
    residual = whitened - nuisance[:, column] * step if solved is None else np.asarray(solved, float)
    kept = np.asarray(free, bool).copy()
    kept[column] = False
    span = nuisance[:, kept]
    overall = statistics.overall_by_channel(residual, span, channels)
    m = max(len(signatures), 1)
    tests = {}
    for name, signature in signatures.items():
        test = statistics.score_by_channel(residual, span, signature, channels)
        tests[name] = {"p_adjusted": min(1.0, test["p_combined"] * m), "explained_fraction": test["explained_fraction"],
                       "statistic": test["statistic"], "dof": test["dof"]}
    significant = sorted((n for n, t in tests.items() if t["p_adjusted"] < alpha), key=lambda n: tests[n]["p_adjusted"])
    explains = [n for n in significant if before.get(n, 1.0) >= alpha]
    return {"overall": overall, "candidates": tests, "significant": significant, "explains": explains,
            "solved": solved is not None}


def conflict_sentence(conflicts: list[dict], named: str | None, titles: dict[str, str]) -> str:
    """What the prior-data conflicts say after a verdict that named ``named`` (None: no effect),
    each conflict's retest (its "retest" entry, :func:`held_in_range`) included; "" when none."""
    parts = []
    for c in conflicts:
        tissue = c["name"].split(".")[0]
        text = (f"Prior-data conflict: {tissue} E {c['value'] / 1e3:.3g} kPa ({c['ratio']:.3g} x fat) lies beyond "
                f"the published {c['range'][0] / 1e3:.3g}-{c['range'][1] / 1e3:.3g} kPa at this fat modulus "
                f"({c['sources']}): a missing effect may be absorbed here.")
        retest = c.get("retest")
        if retest is not None:
            others = [n for n in retest["explains"] if n != named]
            held = f"held at {c['bound'] / 1e3:.3g} kPa"
            if others:
                best = others[0]
                text += (f" With {tissue} E {held}, {titles.get(best, best)} would explain "
                         f"{retest['candidates'][best]['explained_fraction']:.0%} of the residual (corrected p = "
                         f"{retest['candidates'][best]['p_adjusted']:.2g}): ambiguous: {titles.get(best, best)}, or "
                         f"{tissue} E outside its plausible range.")
            else:
                text += f" With {tissue} E {held}, no further candidate explains the residual."
        parts.append(text)
    return " ".join(parts)

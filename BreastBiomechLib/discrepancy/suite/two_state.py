"""Two-state suite cases (issue 78): the case made, fitted and diagnosed on its first scan; the
next measurement designed from that one-scan diagnosis (:meth:`DiagnosisSession.design`, or over
the whole library where the rounds left nothing undecided) and its recommended acquisition
(:meth:`~BreastBiomechLib.discrepancy.design.Design.choice`) made as a further state of the truth
(:func:`~BreastBiomechLib.phantom.states.add_states`); then both scans fitted jointly and diagnosed.

The acquisition the design names is turned into the phantom's state settings
(:func:`state_spec`): a closure changed by a fraction of the thickness is another compression,
a closure by one plate is that plate moving alone (half as far: at half the first compression),
the plates turned is the other axis. The
choice is the design's, made from the measured scan and the fit: the suite never picks the
state by what its truth hides.

Frames and units: LPS millimetres.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from BreastBiomechLib.phantom.states import StateSpec

COMPRESSION_PREFIX, ONE_PLATE_PREFIX, ROTATED_PREFIX = "compression", "only-", "rotated-"


def state_spec(acquisition: dict, first_compression: float) -> StateSpec:
    """The phantom state (:class:`~BreastBiomechLib.phantom.states.StateSpec`) that makes the
    design's ``acquisition`` (its record in design.json: ``name``, ``planes`` in the case's
    plate order) on a truth compressed by ``first_compression`` (fraction of the thickness).
    The state takes the acquisition's name where it is a state name ("compression+10" becomes
    "compression-up10", "compression-10" "compression-down10"). Raises ValueError for an
    acquisition the phantom cannot make."""
    from BreastBiomechLib.discrepancy.acquisitions import HALF
    from BreastBiomechLib.phantom.states import StateSpec  # the phantom: SimpleITK

    name = acquisition["name"]
    if name.startswith(COMPRESSION_PREFIX):
        change = float(name[len(COMPRESSION_PREFIX):]) / 100.0
        state = f"{COMPRESSION_PREFIX}-{'up' if change > 0 else 'down'}{abs(round(100 * change))}"
        return StateSpec(state, compression=round(first_compression + change, 6))
    if name.startswith(ONE_PLATE_PREFIX):
        plates = [plane["name"] for plane in acquisition["planes"]]
        plate = name[len(ONE_PLATE_PREFIX):].removesuffix(HALF)
        if plate not in plates or len(plates) != 2:
            raise ValueError(f"acquisition {name!r}: no plate {plate!r} among the rig's {plates}")
        half = name.endswith(HALF)
        return StateSpec(name, moving_plate=("first", "second")[plates.index(plate)],
                         compression=round(first_compression / 2, 6) if half else None)
    if name.startswith(ROTATED_PREFIX):
        return StateSpec(name, axis=name[len(ROTATED_PREFIX):])
    raise ValueError(f"acquisition {name!r}: the phantom makes compressions, one plate moving and plates turned; "
                     "not this one")


def designed_acquisition(record: dict) -> dict:
    """The acquisition (its design.json record) a design ``record`` recommends
    (:meth:`~BreastBiomechLib.discrepancy.design.Design.choice`). Raises RuntimeError where the
    design simulated none."""
    from BreastBiomechLib.discrepancy.design import Design

    name = Design.from_dict(record).choice()
    if name is None:
        raise RuntimeError(f"the design simulated no acquisition ({record.get('failed') or 'none in its library'})")
    return next(a for a in record["acquisitions"] if a["name"] == name)


def realised_separations(first_round: dict, second: dict) -> dict:
    """Each effect the design predicted a separation for with the second scan (``second``:
    :func:`~BreastBiomechLib.discrepancy.suite.runner` 's second-state record, with the design's
    ``rivals``): the separation the two-scan diagnosis's first round (``first_round``, its record)
    realised beyond the fitted parameters and the same rival (sigma; None where it did not test
    the effect)."""
    candidates = {c["name"]: c for c in first_round["diagnosis"].get("candidates", []) if not c.get("skipped")}
    out = {}
    for effect in second.get("predicted_sigma", {}):
        rival = (second.get("rivals") or {}).get(effect)
        out[effect] = (candidates.get(effect) or {}).get("separations", {}).get(rival or "")
    return out

"""Solves that retry a model whose element inverted, with a slower load.

Dynamic relaxation seeks the static equilibrium, which the loading speed does not change once it
converges; but a marginal model (an element close to inverting under the load, a batch whose
shared time step differs from the model's own, float32 rounding in the atomic force sums) can
invert on the way there, under the loading's transient. Solved again alone with a load
:data:`SLOWER` times slower, the transient shrinks and such a model passes; a model that still
inverts at :data:`RETRIES` such retries is taken to invert under the load itself (a physical
failure: the parameters, the mesh or the constraints), and its last solution is returned.
"""

from __future__ import annotations

from dataclasses import replace

from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.model import Model, Plate

SLOWER = 4  # each retry applies the load this many times more slowly
RETRIES = 2


def slower(relaxation, factor: int = SLOWER):
    """``relaxation`` (:class:`~BreastBiomechLib.solver.DynamicRelaxation`) with its load
    applied ``factor`` times more slowly (its ``pace``; the iterations allowed grow with it)."""
    return replace(relaxation, pace=factor * relaxation.pace)


def solve_batch_with_retries(model: Model, materials: list[ElementMaterials], relaxation,
                             plates: list[list[Plate]] | None = None, plate_displacements: list | None = None,
                             device=None, retries: int = RETRIES, progress=None, warm_start=None) -> list:
    """:func:`~BreastBiomechLib.solver.solve_batch` of the variants (``materials[b]``, optionally
    ``plates[b]`` or ``plate_displacements[b]``) by dynamic ``relaxation``; then each variant that
    inverted an element is solved again alone, its load :data:`SLOWER` times slower each time,
    ``retries`` times at most. The solutions in the variants' order, each with the number of solves it took (``attempts``); a
    variant that never passes keeps its last solution (status "inverted elements").
    ``progress(fraction)`` follows (and, returning False, cancels) the first, batched solve;
    ``warm_start`` (:class:`~BreastBiomechLib.solver.warm.WarmStart`) starts it, the retries
    start at rest."""
    from BreastBiomechLib.solver import solve_batch

    def one(items, b):
        return None if items is None else [items[b]]

    solutions = solve_batch(model, materials, plate_displacements, device=device, relaxation=relaxation,
                            plates=plates, progress=progress, warm_start=warm_start)
    for b, solution in enumerate(solutions):
        patient, attempts = relaxation, 1
        while solution.status == "inverted elements" and attempts <= retries:
            patient = slower(patient)
            solution = solve_batch(model, [materials[b]], one(plate_displacements, b), device=device,
                                   relaxation=patient, plates=one(plates, b))[0]
            attempts += 1
        solutions[b] = replace(solution, attempts=attempts)
    return solutions

"""Warm starts of dynamic relaxation (solver/warm.py): a solve started at a nearby parameter set's
equilibrium reaches the cold solve's equilibrium, in fewer iterations, and refuses where the
equilibrium depends on the path."""

from dataclasses import replace

import numpy as np
import pytest

from BreastBiomechLib.solver import DynamicRelaxation, solve_batch
from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
from BreastBiomechLib.solver.run_case import CaseVariant, run_variants
from BreastBiomechLib.solver.settings import SolverSettings, UnloadedRequest
from BreastBiomechLib.solver.warm import WarmStart

RELAXATION = DynamicRelaxation(tolerance_mm=0.01)


def softer(materials, factor):
    """The materials with the shear modulus times ``factor`` (the bulk modulus kept: nu changes)."""
    return type(materials)(materials.mu * factor, materials.kappa, materials.eta, materials.fibre, materials.density)


@pytest.fixture(scope="module")
def coarse():
    """The 10 mm benchmark breast and its cold relaxation solve."""
    model = hemi_ellipsoid_compression(10.0, compression=0.25)
    start = solve_batch(model, [model.materials], device="cpu", relaxation=RELAXATION)[0]
    assert start.ok and np.isfinite(start.lowest_eigenvalue) and start.shear_speed_squared > 0
    return model, start


def test_a_warm_start_reaches_the_cold_equilibrium_in_fewer_iterations(coarse):
    model, start = coarse
    materials = [softer(model.materials, 0.5), softer(model.materials, 2.0)]
    travel = np.array([p.displacement for p in model.loading.plates])
    plates = [travel * 1.05, travel * 0.95]  # the plates' travel changes too, by 1 mm
    cold = solve_batch(model, materials, plates, device="cpu", relaxation=RELAXATION)
    warm = solve_batch(model, materials, plates, device="cpu", relaxation=RELAXATION,
                       warm_start=WarmStart.from_solution(start))
    for c, w in zip(cold, warm):
        assert c.ok and w.ok, (c.message, w.message)
        assert np.abs(w.displacement - c.displacement).max() < 0.015  # both within 0.01 mm of rest
        assert np.allclose(w.plate_forces, c.plate_forces, rtol=0.01, atol=1e-3)
        assert w.steps < 0.75 * c.steps
    # started at its own equilibrium a solve stays there
    again = solve_batch(model, [model.materials], device="cpu", relaxation=RELAXATION,
                        warm_start=WarmStart.from_solution(start))[0]
    assert again.ok and np.abs(again.displacement - start.displacement).max() < 0.01


def test_a_warm_start_carries_its_lowest_mode_so_that_a_large_change_does_not_stop_early():
    """Started with its damping from the Rayleigh quotient of the first changes (a start without
    the eigenvalue) the approach to a three times softer tissue is overdamped and the distance
    estimate stops it 0.05 mm from rest; with the start's lowest mode carried it ends as close
    as the cold solve."""
    model = hemi_ellipsoid_compression(7.0, compression=0.25)
    start = solve_batch(model, [model.materials], device="cpu", relaxation=RELAXATION)[0]
    materials = [softer(model.materials, 0.3), softer(model.materials, 0.5)]
    cold = solve_batch(model, materials, device="cpu", relaxation=RELAXATION)
    warm = solve_batch(model, materials, device="cpu", relaxation=RELAXATION, warm_start=WarmStart.from_solution(start))
    for c, w in zip(cold, warm):
        assert c.ok and w.ok, (c.message, w.message)
        assert np.abs(w.displacement - c.displacement).max() < 0.015


def test_warm_starts_refuse_what_they_cannot_do(coarse):
    model, start = coarse
    warm = WarmStart.from_solution(start)
    with pytest.raises(ValueError, match="dynamic relaxation"):
        solve_batch(model, [model.materials], device="cpu", warm_start=warm)
    with pytest.raises(ValueError, match="no initial_displacement"):
        solve_batch(model, [model.materials], device="cpu", relaxation=RELAXATION, warm_start=warm,
                    initial_displacement=start.displacement)
    rough = [[replace(p, friction=0.3) for p in model.loading.plates]]
    with pytest.raises(ValueError, match="friction 0.3.*depends on the loading path"):
        solve_batch(model, [model.materials], device="cpu", relaxation=RELAXATION, warm_start=warm, plates=rough)
    turned = [[replace(p, normal=p.normal + np.array([0.0, 0.1, 0.0])) for p in model.loading.plates]]
    with pytest.raises(ValueError, match="another pose"):
        solve_batch(model, [model.materials], device="cpu", relaxation=RELAXATION, warm_start=warm, plates=turned)
    with pytest.raises(ValueError, match="the warm start has 3 nodes"):
        solve_batch(model, [model.materials], device="cpu", relaxation=RELAXATION,
                    warm_start=WarmStart(np.zeros((3, 3))))
    for settings in (SolverSettings(method="static", device="cpu"),
                     SolverSettings(device="cpu", relaxation=RELAXATION, unloaded=UnloadedRequest((0.0, -9.81, 0.0)))):
        with pytest.raises(ValueError, match="reference-state solve.*solve it cold"):
            run_variants(model, [CaseVariant()], settings, warm_start=warm)
    with pytest.raises(ValueError, match="non-finite"):
        WarmStart(np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="completed solve"):
        WarmStart.from_solution(replace(start, status="inverted elements"))


def test_variants_start_where_they_may_and_end_where_cold_solves_do(coarse, monkeypatch):
    """`solve_variants(..., start=outcome)` (a refinement's trial steps, started at the current
    model's equilibrium): the variants of that model with other materials or plate travel start
    warm, in a launch of their own, and end where their cold solves do; one with plate friction
    (whose equilibrium depends on the path) or of another model object starts at rest."""
    from BreastBiomechLib.discrepancy import variants as variants_module
    from BreastBiomechLib.discrepancy.variants import Variant, solve_variants

    model, _ = coarse
    plates = model.loading.plates
    [current] = solve_variants([Variant(model, model.materials, plates)], model.mesh.nodes, RELAXATION, device="cpu")
    assert current.ok and set(current.starts) == {id(model)}
    further = [replace(p, displacement=p.displacement * 1.05) for p in plates]
    rough = [replace(p, friction=0.3) for p in plates]
    other = replace(model)  # the same loading in another model object (an effect's own model)
    variants = [Variant(model, softer(model.materials, 0.7), plates), Variant(model, model.materials, further),
                Variant(model, model.materials, rough), Variant(other, softer(model.materials, 0.7), plates)]
    cold = solve_variants(variants, model.mesh.nodes, RELAXATION, device="cpu")
    launches, run_variants = [], variants_module.run_variants

    def recorded(model, cases, settings, **options):
        launches.append((model, [c.plates[0].friction for c in cases], options["warm_start"] is not None))
        return run_variants(model, cases, settings, **options)

    monkeypatch.setattr(variants_module, "run_variants", recorded)
    warm = solve_variants(variants, model.mesh.nodes, RELAXATION, device="cpu", start=current)
    assert [(m is model, frictions, started) for m, frictions, started in launches] == [
        (True, [0.0, 0.0], True), (True, [0.3], False), (False, [0.0], False)]
    for c, w in zip(cold, warm):
        assert c.ok and w.ok, (c.message, w.message)
        assert np.abs(w.displacement - c.displacement).max() < 0.015  # both within 0.01 mm of rest
        assert w.attempts == 1
    assert set(warm[3].starts) == {id(other)} and set(warm[0].starts) == {id(model)}


def test_a_warm_start_that_does_not_converge_in_twice_its_start_s_iterations_is_solved_cold(coarse, monkeypatch):
    """A warm start is bounded by twice its start's iterations (on a diagnosis's 12 mm mesh a
    plate pushed 1 mm further set a contact oscillating for 50 000 iterations where the cold
    solve took 2 800): past that it ends "not converged" and `solve_variants` solves it again
    from rest, counting both attempts. Here the start says it took 60 iterations, too few for
    the three times softer tissue to settle."""
    from BreastBiomechLib.discrepancy import variants as variants_module
    from BreastBiomechLib.discrepancy.variants import Variant, solve_variants

    model, start = coarse
    warm = WarmStart.from_solution(start)
    assert warm.iterations == start.steps
    bounded = warm.bounded(RELAXATION)
    assert bounded.max_iterations == 2 * start.steps and RELAXATION.max_iterations == 50_000
    assert WarmStart(start.displacement).bounded(RELAXATION) == RELAXATION  # iterations unknown: unchanged
    short = replace(warm, iterations=60)
    assert short.bounded(RELAXATION).max_iterations == RELAXATION.load_iterations + 1 > 120
    quick = replace(RELAXATION, load_iterations=2)  # a minimum: the cold load still goes at its speed limit
    [stopped] = solve_batch(model, [softer(model.materials, 0.3)], device="cpu", relaxation=quick, warm_start=short)
    assert stopped.status == "not converged" and stopped.steps < start.steps  # (stopped at its next check)
    plates = model.loading.plates
    [current] = solve_variants([Variant(model, model.materials, plates)], model.mesh.nodes, quick, device="cpu")
    current.starts[id(model)] = (model, replace(current.starts[id(model)][1], iterations=60))
    launches, run_variants = [], variants_module.run_variants

    def recorded(model, cases, settings, **options):
        launches.append(options["warm_start"] is not None)
        return run_variants(model, cases, settings, **options)

    monkeypatch.setattr(variants_module, "run_variants", recorded)
    [outcome] = solve_variants([Variant(model, softer(model.materials, 0.3), plates)], model.mesh.nodes, quick,
                               device="cpu", start=current)
    assert launches == [True, False] and outcome.ok and outcome.attempts == 2, outcome.message

"""The model-discrepancy workflow on conftest's small compressed phantom (CPU), fitted with a
coarse mesh of its labels and a few solves: the effects are nested in the fitted model, the
inputs a diagnosis cannot use are refused, and this null case (nothing hidden beyond what the
iso-hetero fit has) raises no alarm. Cases are copies without their truth files: the workflow
never reads them. Hidden friction: the Breast Discrepancy module's test (Testing/modules), on a
case of its own; conftest puts each case's tests at the head of one worker's share."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from discrepancy_cases import fit_coarse, without_truth

@pytest.fixture(scope="module")
def null_case(compressed_case_dir, tmp_path_factory):
    """(case, fit): conftest's phantom (nothing hidden beyond heterogeneous materials, which the
    iso-hetero fit has), without its truth, fitted."""
    root = tmp_path_factory.mktemp("null")
    case = without_truth(compressed_case_dir, root / "case")
    return case, fit_coarse(case, root / "fit")


def test_every_effect_at_its_off_values_is_the_fitted_model(null_case):
    """The fitted model is the nested case: each effect applied at its off values leaves the
    materials, plates and loading as they were."""
    from BreastBiomechLib.discrepancy import ModelState, library, load_fitted_case

    fitted = load_fitted_case(*null_case, device="cpu")
    state = ModelState(fitted, fitted.z)
    base = state.variant()
    for effect in library(fitted):
        if effect.unavailable(fitted):
            continue
        variant = effect.apply(base, effect.off, fitted)
        assert variant.model is base.model, effect.name
        for name in ("mu", "kappa", "eta", "fibre", "density"):
            np.testing.assert_array_equal(getattr(variant.materials, name), getattr(base.materials, name),
                                          err_msg=f"{effect.name} {name}")
        for a, b in zip(variant.plates, base.plates):
            np.testing.assert_array_equal(a.point, b.point)
            np.testing.assert_array_equal(a.normal, b.normal)
            np.testing.assert_array_equal(a.displacement, b.displacement)
            assert a.friction == b.friction
        # and switched on, each changes something
        on = effect.apply(base, np.array([p.stepped(p.off) for p in effect.parameters]), fitted)
        changed = on.model is not base.model or any(
            not np.array_equal(getattr(on.materials, n), getattr(base.materials, n)) for n in ("mu", "eta")) or any(
            a.friction != b.friction or not np.allclose(a.point + a.displacement, b.point + b.displacement)
            or not np.allclose(a.normal, b.normal) for a, b in zip(on.plates, base.plates))
        assert changed, effect.name


def test_friction_per_plate_refines_the_friction_the_model_has(null_case):
    """Friction differing between the plates is a candidate only once the model has friction
    (the one-coefficient candidate first); at its off value it is that model, and its factors
    keep the coefficients' geometric mean."""
    from BreastBiomechLib.discrepancy import ModelState, library, load_fitted_case
    from BreastBiomechLib.discrepancy.effects.friction_per_plate import plate_factors

    fitted = load_fitted_case(*null_case, device="cpu")
    by_name = {effect.name: effect for effect in library(fitted)}
    friction, per_plate = by_name["friction"], by_name["friction-per-plate"]
    state = ModelState(fitted, fitted.z)
    assert "the friction candidate (one mu for all plates) comes first" in per_plate.unavailable_at(fitted, state.added)
    with_friction = state.with_effect(friction, [0.5])
    assert per_plate.unavailable_at(fitted, with_friction.added) is None
    assert "comes first" in per_plate.unavailable_at(fitted, state.with_effect(friction, [0.0]).added)
    base = with_friction.variant()
    assert [p.friction for p in base.plates] == [0.5, 0.5]
    assert [p.friction for p in per_plate.apply(base, per_plate.off, fitted).plates] == [0.5, 0.5]
    ratio = np.log(4.0)
    mu = [p.friction for p in with_friction.variant(values={per_plate.name: (per_plate, [ratio])}).plates]
    np.testing.assert_allclose(mu, [1.0, 0.25])  # four times, the geometric mean kept
    np.testing.assert_allclose(np.prod(plate_factors(np.array([0.3, -1.1]))), 1.0)
    assert per_plate.describe([ratio]) == "plate 1's mu x2, plate 2's mu x0.5"
    with pytest.raises(ValueError, match="one fewer than the plates"):
        per_plate.apply(base, [0.1, 0.2], fitted)


def test_a_secant_model_that_cannot_be_built_at_its_step_is_built_at_the_other_side(null_case):
    """A held plate tilted by the secant's step away from the tissue would never touch it (the
    varied suite's case 7, 2026-12-07: its tilt candidate skipped as "could not be built"); the
    secant model is then the step to the other side, and where neither side builds the first
    reason is given."""
    from BreastBiomechLib.discrepancy import ModelState, load_fitted_case
    from BreastBiomechLib.discrepancy.effects import Effect, EffectParameter
    from BreastBiomechLib.discrepancy.sensitivity import _secant_model

    class Lifting(Effect):
        name, title = "lifting", "a plate lifted"
        parameters = (EffectParameter("lift", "mm", 0.0, -2.0, 2.0, 1.0),)

        def __init__(self, refuse_below: float):
            self.refuse_below = refuse_below

        def apply(self, variant, values, fitted):
            if values[0] > self.refuse_below:
                raise ValueError(f"plate 'right': in that pose it ends {values[0]:.2f} mm short of the tissue")
            return replace(variant, plates=[replace(p, displacement=p.displacement + values[0] * p.normal)
                                            for p in variant.plates])

    fitted = load_fitted_case(*null_case, device="cpu")
    state = ModelState(fitted, fitted.z)
    variant, step = _secant_model(state, Lifting(refuse_below=0.5), 0)
    assert step == -1.0
    np.testing.assert_allclose(variant.plates[0].displacement, fitted.plates[0].displacement - fitted.plates[0].normal)
    assert _secant_model(state, Lifting(refuse_below=5.0), 0)[1] == 1.0  # the usual side where it builds
    with pytest.raises(ValueError, match="ends 1.00 mm short"):
        _secant_model(state, Lifting(refuse_below=-5.0), 0)


def test_a_secant_model_two_candidates_share_is_solved_once(null_case):
    """The plate tilt's offsets move an untilted plate as the plate offset does (the same code):
    their secant models are solved once and both candidates take the columns, which are those
    the plate offset's own solves give."""
    from BreastBiomechLib.discrepancy import ModelState, NoiseModel, load_fitted_case, observations_of
    from BreastBiomechLib.discrepancy.effects import PlateOffset, PlateTilt
    from BreastBiomechLib.discrepancy.sensitivity import sensitivities
    from BreastBiomechLib.io.meshes import read_vtu

    case, fit = null_case
    fitted = load_fitted_case(case, fit, device="cpu")
    observations = observations_of(fitted, read_vtu(fit / "deformed_mesh.vtu").point_data["displacement"],
                                   NoiseModel(floor="fixed"))
    state = ModelState(fitted, fitted.z)
    plates = len(fitted.plates)
    offset = PlateOffset(plates)
    both = sensitivities(state, observations, [PlateTilt(plates, offsets=True), offset])
    alone = sensitivities(state, observations, [offset])
    assert not both.skipped and both.solves == alone.solves + 2 * plates  # the tilt's angles alone added
    np.testing.assert_array_equal(both.effects["plate-offset"], both.effects["plate-tilt"][:, 2::3])
    np.testing.assert_array_equal(both.steps["plate-offset"], both.steps["plate-tilt"][2::3])
    # two sets of solves: on a CPU the current model is solved beside the tilt's cold variants in
    # one and alone in the other, and the offsets start at its equilibrium (the relaxation's
    # tolerance apart: 1e-5 mm per mm here, against columns of up to 0.2)
    np.testing.assert_allclose(both.effects["plate-offset"], alone.effects["plate-offset"], rtol=1e-3, atol=1e-4)
    assert np.abs(both.effects["plate-offset"]).max() > 0.1


def test_the_gravity_effect_unloads_in_the_first_scan_s_posture_and_compresses_in_the_second(null_case):
    """The case records the compressed scan's posture (plates.json ``gravity``; the phantoms are
    prone); the gravity effect estimates the unloaded state under the undeformed scan's gravity
    and compresses under the compressed scan's (here changed to upright: a posture change)."""
    from BreastBiomechLib.discrepancy import ModelState, load_fitted_case
    from BreastBiomechLib.discrepancy.effects.gravity import GravityPrestress

    fitted = load_fitted_case(*null_case, device="cpu")
    np.testing.assert_allclose(fitted.compressed_gravity, [0.0, -9.81, 0.0])
    fitted.compressed_gravity = np.array([0.0, 0.0, -9.81])
    variant = GravityPrestress().apply(ModelState(fitted, fitted.z).variant(), np.array([0.5]), fitted)
    np.testing.assert_allclose(variant.model.prestate.gravity, [0.0, -0.5 * 9.81, 0.0])
    np.testing.assert_allclose(variant.model.loading.gravity, [0.0, 0.0, -0.5 * 9.81])


def test_gravity_turned_from_the_recorded_posture_refines_the_gravity_the_model_has(null_case, monkeypatch):
    """Gravity's direction at the compressed scan is a candidate only once gravity is in the
    model; its turn acts while the plates close (the unloaded shape, estimated from the undeformed
    scan, is shared with the unturned model's: estimated once), by the given angles about axes
    perpendicular to the recorded posture."""
    from BreastBiomechLib.discrepancy import ModelState, library, load_fitted_case
    from BreastBiomechLib.discrepancy.effects.gravity_direction import turn_axes, turned_gravity
    from BreastBiomechLib.solver import unloaded as unloaded_module

    upright = np.array([0.0, 0.0, -9.81])
    axes = turn_axes(upright)
    np.testing.assert_allclose(axes @ axes.T, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(axes @ upright, 0.0, atol=1e-12)
    turned = turned_gravity(upright, [10.0, 0.0])
    assert np.linalg.norm(turned) == pytest.approx(9.81)
    assert np.degrees(np.arccos(turned @ upright / 9.81 ** 2)) == pytest.approx(10.0)
    assert abs(turned @ axes[0]) < 1e-9  # turned about the first axis

    fitted = load_fitted_case(*null_case, device="cpu")
    fitted.compressed_gravity = upright
    by_name = {effect.name: effect for effect in library(fitted)}
    gravity, direction = by_name["gravity"], by_name["gravity-direction"]
    state = ModelState(fitted, fitted.z)
    assert "the gravity candidate comes first" in direction.unavailable_at(fitted, state.added)
    with_gravity = state.with_effect(gravity, [0.5])
    assert direction.unavailable_at(fitted, with_gravity.added) is None
    estimated = []
    original = unloaded_module.unloaded_shape

    def counted(*args, **kwargs):  # the gravity effect imports it where it uses it: each estimate counted
        estimated.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(unloaded_module, "unloaded_shape", counted)
    plain = with_gravity.variant()
    off = with_gravity.variant(values={direction.name: (direction, direction.off)})
    on = with_gravity.variant(values={direction.name: (direction, [0.0, 10.0])})
    assert len(estimated) == 1  # one unloaded shape for the three
    np.testing.assert_array_equal(off.model.mesh.nodes, plain.model.mesh.nodes)
    np.testing.assert_allclose(off.model.loading.gravity, 0.5 * upright)
    np.testing.assert_allclose(on.model.loading.gravity, 0.5 * turned_gravity(upright, [0.0, 10.0]))
    np.testing.assert_allclose(on.model.prestate.gravity, plain.model.prestate.gravity)
    np.testing.assert_array_equal(on.model.mesh.nodes, plain.model.mesh.nodes)


def test_inputs_the_diagnosis_cannot_use_are_refused(null_case, tmp_path, capsys):
    from BreastBiomechLib.cli import main
    from BreastBiomechLib.discrepancy import load_fitted_case

    case, fit = null_case
    # a fit of another case: its recorded fingerprint differs from the case's
    other = Path(shutil.copytree(fit, tmp_path / "other"))
    record = json.loads((other / "case.json").read_text())
    (other / "case.json").write_text(json.dumps({**record, "fingerprint": "0" * 64}))
    with pytest.raises(ValueError, match="fit of another case"):
        load_fitted_case(case, other)
    # a case with no measured image
    bare = Path(shutil.copytree(case, tmp_path / "bare"))
    (bare / "compressed" / "mr.nrrd").unlink()
    assert main(["diagnose", str(bare), "--fit", str(fit), "--out", str(tmp_path / "out1")]) == 2
    assert "no measured compressed image" in capsys.readouterr().err
    # a folder that holds no finished fit
    unfinished = Path(shutil.copytree(fit, tmp_path / "unfinished"))
    (unfinished / "result.json").unlink()
    assert main(["diagnose", str(case), "--fit", str(unfinished), "--out", str(tmp_path / "out2")]) == 2
    assert "not a finished fit" in capsys.readouterr().err
    # an output folder in use
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "x").write_text("")
    assert main(["diagnose", str(case), "--fit", str(fit), "--out", str(tmp_path / "used")]) == 2
    assert "resume it" in capsys.readouterr().err


@pytest.mark.slow
def test_the_null_case_raises_no_alarm(null_case, tmp_path, capsys):
    from BreastBiomechLib.cli import main

    from BreastBiomechLib.discrepancy import DiagnosisCancelled, DiagnosisSession

    case, fit = null_case
    out = tmp_path / "diagnosis"
    # a Cancel at the first message after the floor is measured (as the panel's, which stops at
    # the next progress call): no round is written and the floor is kept ...
    heard = []

    def cancel_once_measured(message):
        heard.append(message)
        return not any(m.startswith("measuring the model-error floor") for m in heard[:-1])

    with pytest.raises(DiagnosisCancelled):
        DiagnosisSession(case, fit, out, device="cpu", registration=None,
                         progress=cancel_once_measured).diagnose(progress=cancel_once_measured)
    assert (out / "floor.json").is_file() and not (out / "round-1.json").exists()
    measured = (out / "floor.json").stat()
    # ... and the run that takes the folder up reads it, not measures it again: the whole library
    # against the measured floor; no residual displacement field (the verdict does not use it; the
    # hidden-friction tests check it)
    from BreastBiomechLib.timing import clocked

    with clocked() as clock:  # where the diagnosis spends its time (`bench diagnose`, `bench demo`)
        assert main(["diagnose", str(case), "--fit", str(fit), "--out", str(out), "--device", "cpu", "--quiet",
                     "--json", "--no-residual-field", "--resume"]) == 0
    assert {"features", "sensitivities", "solving", "statistics"} <= set(clock.stages)
    assert "model-error floor" not in clock.stages  # read back, not measured again
    assert clock.stages["sensitivities"].total_s >= clock.stages["sensitivities"].own_s > 0.0
    assert 0.0 < clock.share("solving") < 1.0 and clock.unstaged_s >= 0.0
    from BreastBiomechLib.cli.bench import staged_figures

    figures = staged_figures(clock, out)  # what `bench demo` prints of a run
    assert figures["verdict"] == {"final": "no significant discrepancy", "added": [], "rounds": 1}
    assert figures["solving_share"] == round(clock.share("solving"), 3) and "statistics" in figures["stages"]
    # the demo's report says, per candidate, whether this case could have shown it (issue 78)
    from BreastBiomechLib.cli.demo import identifiability_effects, identifiability_section
    from BreastBiomechLib.discrepancy.diagnosis import not_identifiable
    from BreastBiomechLib.discrepancy.workflow import DiagnosisRun

    run = DiagnosisRun([json.loads((out / "round-1.json").read_text())], out)
    effects = identifiability_effects(case, fit)
    table = identifiability_section(run, effects)
    for candidate in run.rounds[0]["diagnosis"]["candidates"]:
        [row] = [line for line in table.splitlines() if line.startswith(f"| {candidate['title']} |")]
        if candidate.get("skipped"):
            assert "not tested" in row
        else:
            assert row.endswith("| yes, from that size on |") != not_identifiable(candidate, effects[candidate["name"]])
    again = (out / "floor.json").stat()
    assert (again.st_ino, again.st_mtime_ns) == (measured.st_ino, measured.st_mtime_ns)
    summary = json.loads(capsys.readouterr().out)
    assert summary["final"] == "no significant discrepancy", summary["sentence"]
    assert summary["added"] == []
    # by default against the floor measured from the case (the fitted model solved again on its
    # refined mesh), which the record and the report state: every feature's floor finite and at
    # least the lower bound, one value per region and channel, the estimate not zero (a 10 mm
    # mesh is coarse); a resumed session reads it back (at another lower bound, the same estimate)
    from BreastBiomechLib.discrepancy.floor import MeasuredFloor

    recorded = json.loads((out / "round-1.json").read_text())["floor"]
    assert recorded["rms_mm"] >= recorded["lower_bound_mm"] == 0.5 and recorded["tets"][1] == 8 * recorded["tets"][0]
    assert "model-error floor measured from the case" in (out / "report.md").read_text()
    floor = MeasuredFloor.from_dict(json.loads((out / "floor.json").read_text()), 0.5)
    assert np.all(np.isfinite(floor.floor)) and floor.floor.min() >= 0.5
    assert 0.0 < np.sqrt(np.mean(floor.discretisation ** 2)) < 5.0
    assert floor.summary()["rms_mm"] == pytest.approx(recorded["rms_mm"])
    for name, group in floor.groups.items():
        members = floor.feature_groups == name
        assert members.sum() == group["features"] and np.ptp(floor.floor[members]) == 0.0
    lower = MeasuredFloor.from_dict(json.loads((out / "floor.json").read_text()), 0.2)
    np.testing.assert_array_equal(lower.discretisation, floor.discretisation)
    assert lower.floor.min() >= 0.2 and np.all(lower.floor <= floor.floor)
    # the next measurement, designed once the rounds are done (`--resume --design`) for what the
    # round could not tell apart (the chest-wall hold, which the fitted muscle takes up), with one
    # acquisition (the second plate alone), with the diagnosis's own features and measured floor
    # (the acquisition's floor measured there too), so that its separation in this scan is the one
    # the round recorded: the summary, design.json and the report's section say it; asked again
    # after the same round, it is kept, not made again
    from BreastBiomechLib.discrepancy import ModelState, library, load_fitted_case
    from BreastBiomechLib.discrepancy.design import undecided

    fitted = load_fitted_case(case, fit, device="cpu")
    second = f"only-{ModelState(fitted, fitted.z).variant().plates[1].name}"
    designing = ["diagnose", str(case), "--fit", str(fit), "--out", str(out), "--device", "cpu", "--quiet", "--json",
                 "--no-residual-field", "--resume", "--design", second]
    assert main(designing) == 0
    summary = json.loads(capsys.readouterr().out)
    record = json.loads((out / "design.json").read_text())
    last = json.loads((out / "round-1.json").read_text())["diagnosis"]
    assert summary["final"] == "no significant discrepancy" and record["round"] == 1
    assert summary["design"]["designed_for"] == record["designed_for"] == record["undecided"] == undecided(
        last, {e.name: e for e in library(fitted)})
    assert "chest-wall" in record["designed_for"] and [a["name"] for a in record["acquisitions"]] == [second]
    assert record["noise"]["floor"] == "measured" and record["noise"]["model_sd_mm"] == 0.5  # its lower bound
    hold = next(r for r in record["effects"] if r["effect"] == "chest-wall")
    assert hold["now_sigma"] < hold["detectable_sigma"]  # taken up by the muscle in this scan
    tested = next(c for c in last["candidates"] if c["name"] == "chest-wall")
    assert hold["now_sigma"] == pytest.approx(tested["separations"][hold["rival"] or ""], rel=1e-3)
    assert len(summary["design"]["sentences"]) == len(record["effects"])
    section = (out / "report.md").read_text().split("## The next measurement")[1]
    assert "chest-wall hold" in section and second in section
    made = (out / "design.json").stat().st_mtime_ns
    assert main(designing) == 0 and (out / "design.json").stat().st_mtime_ns == made
    capsys.readouterr()


def _friction_secant(null_case, step: float = 0.3):
    """(state, observed, friction, base, shift, secant_features, sens): the null case's
    fit, its observations, the friction effect and sensitivities whose secant at ``step`` is the
    current solution ``base`` shifted 1 mm posteriorly (``shift``)."""
    from BreastBiomechLib.discrepancy import ModelState, library, load_fitted_case, observations_of
    from BreastBiomechLib.discrepancy.sensitivity import Sensitivities
    from BreastBiomechLib.io.meshes import read_vtu

    case, fit = null_case
    fitted = load_fitted_case(case, fit, device="cpu")
    state = ModelState(fitted, fitted.z)
    base = read_vtu(fit / "deformed_mesh.vtu").point_data["displacement"]
    observed = observations_of(fitted, base)
    friction = next(e for e in library(fitted) if e.name == "friction")
    shift = np.tile([0.0, 1.0, 0.0], (len(base), 1))
    features, secant_features = observed.predicted(base), observed.predicted(base + shift)
    sens = Sensitivities(base, features, [k for k, *_ in state.nuisance()],
                         np.zeros((len(features), len(state.nuisance()))),
                         {"friction": ((secant_features - features) / step)[:, None]},
                         {"friction": (shift / step)[None]}, {"friction": np.array([step])})
    return state, observed, friction, base, shift, secant_features, sens


def test_a_refit_whose_every_trial_fails_falls_back_on_the_solved_secant(null_case, monkeypatch):
    """Friction sticking at a plate's rounded edge can invert an element in every Gauss-Newton
    trial of its refit; the effect's secant model, solved for the sensitivities, then stands as
    the refit (noted), provided it lowers the residual. Here the measurement is made to be that
    secant model (the current solution shifted 1 mm posteriorly), and every trial solve fails."""
    from BreastBiomechLib.discrepancy import refit as refit_module
    from BreastBiomechLib.discrepancy.observations import Observations
    from BreastBiomechLib.discrepancy.variants import Outcome

    step = 0.3
    state, observed, friction, base, shift, secant_features, sens = _friction_secant(null_case, step)

    def failing(variants, *args, **kwargs):
        return [Outcome(base, "inverted elements", "an element inverted at step 900") for _ in variants]

    monkeypatch.setattr(refit_module, "solve_variants", failing)
    measured_as_secant = Observations(observed.labels, observed.channel, secant_features, observed.sigma,
                                      observed.points, observed._parts)
    [result] = refit_module.refit(state, measured_as_secant, sens, [friction])
    assert result.ok and "secant" in result.note
    np.testing.assert_allclose(result.values, [step])
    assert result.rss_after < 1e-6 * result.rss_before
    np.testing.assert_allclose(result.displacement, base + shift)
    assert result.state.added["friction"][1][0] == pytest.approx(step)
    assert result.note.startswith("every Gauss-Newton trial failed to solve")
    # a secant that does not lower the residual is no refit: the failure stands
    [failed] = refit_module.refit(state, observed, sens, [friction])
    assert not failed.ok and failed.rss_after == float("inf") and not failed.note


def test_a_refit_whose_trials_all_raise_the_residual_starts_again_along_the_signature(null_case, monkeypatch):
    """The issue's cases where a highly significant score test refitted to nothing (dBIC +5.9): the
    joint step's trials solve but every one raises the residual (here each moves the tissue the
    wrong way). The effect's secant model, solved for the sensitivities, lowers it: it stands
    (noted), and the effect is not dropped at its off value."""
    from BreastBiomechLib.discrepancy import refit as refit_module
    from BreastBiomechLib.discrepancy.observations import Observations
    from BreastBiomechLib.discrepancy.variants import Outcome

    step = 0.3
    state, observed, friction, base, shift, secant_features, sens = _friction_secant(null_case, step)
    trials = []

    def wrong_way(variants, *args, **kwargs):
        trials.append(len(variants))
        return [Outcome(base - shift, "completed", "") for _ in variants]

    monkeypatch.setattr(refit_module, "solve_variants", wrong_way)
    measured_as_secant = Observations(observed.labels, observed.channel, secant_features, observed.sigma,
                                      observed.points, observed._parts)
    [result] = refit_module.refit(state, measured_as_secant, sens, [friction])
    assert len(trials) == refit_module.HALVINGS + 1  # the full step and every halving raised it
    assert result.ok and result.note.startswith("no Gauss-Newton trial lowered the residual")
    np.testing.assert_allclose(result.values, [step])
    assert result.rss_after < 1e-6 * result.rss_before


def test_a_refit_takes_the_shorter_step_where_the_full_one_overshoots(null_case, monkeypatch):
    """A secant from the off value can overstate the step an effect needs (a chest-wall hold
    saturates): where a trial lowers the residual by less than half of the linearised fall, the
    refit tries the half step too and keeps the best. Here the solved response is 1.8 times the
    linear one, so the full step lands at 1.8x the measured shift (a residual sum of squares of
    0.64 of before: 36 % removed of a predicted 100 %), the half step at 0.9x (0.01 of before,
    above half of its predicted 75 %): the half step stands and no quarter step is solved. Where
    the response is 1.2x (0.04 of before after the full step) the full step stands at once."""
    from BreastBiomechLib.discrepancy import refit as refit_module
    from BreastBiomechLib.discrepancy.observations import Observations
    from BreastBiomechLib.discrepancy.variants import Outcome

    step = 0.3
    state, observed, friction, base, shift, secant_features, sens = _friction_secant(null_case, step)
    measured = Observations(observed.labels, observed.channel, secant_features, observed.sigma,
                            observed.points, observed._parts)
    for gain, taken in ((1.8, 0.5), (1.2, 1.0)):
        solved = []

        def saturating(variants, *args, **kwargs):
            fraction = 0.5 ** len(solved)
            solved.append(fraction)
            return [Outcome(base + gain * fraction * shift, "completed", "") for _ in variants]

        monkeypatch.setattr(refit_module, "solve_variants", saturating)
        [result] = refit_module.refit(state, measured, sens, [friction])
        assert result.ok and not result.note
        assert solved == [1.0, 0.5][:len(solved)] and solved[-1] == taken
        np.testing.assert_allclose(result.values, [step * taken])
        np.testing.assert_allclose(result.displacement, base + gain * taken * shift)
        assert result.rss_after < 0.05 * result.rss_before  # 0.01 and 0.04 of before


@pytest.mark.parametrize("workers, launches", [("1", [[0.0], [0.3], [0.15]]), ("2", [[0.0], [0.3, 0.15]])])
def test_a_gauss_newton_step_and_its_half_are_solved_at_once_where_two_models_cost_one(null_case, monkeypatch,
                                                                                        workers, launches):
    """A refinement's trial step that overshoots (the solved response 2.5 times the linear one)
    is halved. On a CPU with one worker process the half is solved after the full step has
    failed; where a batch's models run side by side (two worker processes, or a GPU) the two are
    solved in one launch; either way the half step stands. Given the solve of the model it starts
    from (the refit's being refined), that model is not solved again."""
    from BreastBiomechLib.discrepancy import refit as refit_module
    from BreastBiomechLib.discrepancy.observations import Observations
    from BreastBiomechLib.discrepancy.variants import Outcome

    step = 0.3
    state, observed, friction, base, shift, secant_features, sens = _friction_secant(null_case, step)
    state = state.with_effect(friction, [0.0])
    keys = [k for k, *_ in state.nuisance()]
    column = (secant_features - observed.predicted(base)) / step
    nuisance = np.zeros((len(column), len(keys)))
    nuisance[:, keys.index("friction:0")] = column
    measured = Observations(observed.labels, observed.channel, secant_features, observed.sigma,
                            observed.points, observed._parts)
    solved = []

    def overshooting(variants, *args, **kwargs):
        mu = [v.plates[0].friction for v in variants]
        solved.append(mu)
        return [Outcome(base + 2.5 * (m / step) * shift, "completed", "") for m in mu]

    def linear(state_, observations, candidates, say=None, current=None):
        return replace(sens, displacement=base, features=observed.predicted(base), nuisance_keys=keys,
                       nuisance=nuisance, effects={}, fields={}, steps={})

    monkeypatch.setenv("BREASTBIOMECH_CPU_WORKERS", workers)
    monkeypatch.setattr(refit_module, "solve_variants", overshooting)
    monkeypatch.setattr(refit_module, "sensitivities", linear)
    refined = refit_module.refine(state, measured, iterations=1)
    assert [np.round(mu, 6).tolist() for mu in solved] == launches
    assert refined.state.added["friction"][1][0] == pytest.approx(0.15)
    # given the solve of the model it starts from (a refit's), it does not solve that again
    solved.clear()
    again = refit_module.refine(state, measured, iterations=1, current=Outcome(base, "completed", ""))
    assert [np.round(mu, 6).tolist() for mu in solved] == launches[1:]
    assert again.state.added["friction"][1][0] == pytest.approx(0.15)


def test_an_effect_is_not_credited_with_what_the_fitted_parameters_alone_remove(null_case, monkeypatch):
    """A fit that has not quite converged on the diagnosis's features lowers its residual by the
    refit's step of the fitted parameters alone; an effect refitted alongside must not be named
    for that. Here the measured features are the current ones shifted 1 mm posteriorly; the
    linearised fitted parameters reach only the landmarks' part of it (so friction's score test,
    with them profiled out, is significant), but their solved step removes it all, as does the
    friction refit's: the nested comparison credits friction with nothing, and the sentence says
    the fitted parameters alone explain it (the old comparison with the unrefitted fit named
    friction, removing 100 %). Without noise the overall test is not significant, so the verdict
    is no significant discrepancy, not "unexplained"."""
    from BreastBiomechLib.discrepancy import diagnosis as diagnosis_module
    from BreastBiomechLib.discrepancy import refit as refit_module
    from BreastBiomechLib.discrepancy.observations import Observations
    from BreastBiomechLib.discrepancy.variants import Outcome

    step = 0.3
    state, observed, friction, base, shift, secant_features, sens = _friction_secant(null_case, step)
    measured = Observations(observed.labels, observed.channel, secant_features, observed.sigma,
                            observed.points, observed._parts)
    landmarks = np.asarray(observed.channel) == "landmarks"
    assert 0 < landmarks.sum() < len(landmarks)
    sens.nuisance[:, 0] = np.where(landmarks, (secant_features - sens.features) / step, 0.0)
    monkeypatch.setattr(diagnosis_module, "sensitivities", lambda *args, **kwargs: sens)
    solved = []

    def every_trial_removes_it(variants, *args, **kwargs):
        solved.append(len(variants))
        return [Outcome(base + shift, "completed", "") for _ in variants]

    monkeypatch.setattr(refit_module, "solve_variants", every_trial_removes_it)
    result = diagnosis_module.diagnose(state, measured, [friction])
    [candidate] = [c for c in result.candidates if c.name == "friction"]
    assert candidate.p_adjusted < 0.01 and solved[0] == 2  # friction's trial and the fitted parameters' alone
    assert candidate.refit["rss_fitted_only"] < 1e-6 * candidate.refit["rss_before"]
    assert candidate.refit["removed"] == 0.0
    # noise-free, the surface's share of the shift is below what the overall test can call
    # significant: no discrepancy at the floor's level, with the fit's lack of convergence said
    assert result.overall["p_combined"] > 0.01
    assert result.verdict == "no significant discrepancy" and result.effect is None
    assert "fitted parameters alone removes 100%" in result.sentence
    assert "friction (removed 0%; " in result.sentence


def test_a_fitted_parameter_at_an_end_of_its_range_is_reported_with_any_verdict(null_case, monkeypatch):
    """A hidden chest-wall hold fits as a pectoral muscle at the top of its range (the suite's
    eighth run); whatever the verdict, the diagnosis lists the fit's parameters at an end of
    their range and says so after the verdict's sentence."""
    from BreastBiomechLib.discrepancy import diagnosis as diagnosis_module
    from BreastBiomechLib.discrepancy.observations import Observations

    state, observed, friction, base, shift, secant_features, sens = _friction_secant(null_case)
    exact = Observations(observed.labels, observed.channel, sens.features, observed.sigma, observed.points,
                         observed._parts)
    monkeypatch.setattr(diagnosis_module, "sensitivities", lambda *args, **kwargs: sens)
    inside = diagnosis_module.diagnose(state, exact, [friction])
    assert inside.verdict == "no significant discrepancy" and inside.edges == []
    assert "range" not in inside.sentence
    keys = state.fitted.space.keys
    z = np.full(len(keys), 0.5)
    z[-1], z[0] = 0.999, 0.001
    at_ends = diagnosis_module.diagnose(type(state)(state.fitted, z), exact, [friction])
    values = state.fitted.space.values(z)
    assert at_ends.verdict == "no significant discrepancy"
    assert at_ends.edges == [{"name": keys[0], "value": values[keys[0]], "end": "bottom", "held": False},
                             {"name": keys[-1], "value": values[keys[-1]], "end": "top", "held": False}]
    assert len(keys) >= 2 and f"{keys[-1]} ({values[keys[-1]]:.4g}) at the top" in at_ends.sentence
    assert at_ends.to_dict()["edges"] == at_ends.edges


def test_an_effect_the_fitted_parameters_reproduce_is_said_hard_to_see_and_found_once_one_is_pushed_out(
        null_case, monkeypatch):
    """Friction's signature made the first fitted parameter's exactly (as a held chest wall is a
    stiffer pectoral muscle to these features), the measured features the friction secant's.
    Inside its range the parameter absorbs it all: no significant discrepancy, and the sentence
    says friction is hard to see at this fit, chiefly through that parameter. At the top of its
    range with the residual asking for more, the parameter is held there: friction's score test
    sees it, and its refit (the solves: friction moves the tissue, the fitted parameters alone
    do not) names it."""
    from BreastBiomechLib.discrepancy import diagnosis as diagnosis_module
    from BreastBiomechLib.discrepancy import refit as refit_module
    from BreastBiomechLib.discrepancy.observations import Observations
    from BreastBiomechLib.discrepancy.variants import Outcome

    step = 0.3
    state, observed, friction, base, shift, secant_features, sens = _friction_secant(null_case, step)
    measured = Observations(observed.labels, observed.channel, secant_features, observed.sigma,
                            observed.points, observed._parts)
    sens.nuisance[:, 0] = sens.effects["friction"][:, 0]
    monkeypatch.setattr(diagnosis_module, "sensitivities", lambda *args, **kwargs: sens)

    def friction_moves_it(variants, *args, **kwargs):
        return [Outcome(base + shift if any(p.friction > 0 for p in v.plates) else base, "completed", "")
                for v in variants]

    monkeypatch.setattr(refit_module, "solve_variants", friction_moves_it)
    keys = state.fitted.space.keys
    # no profile interval: its solves would be real ones of a model whose friction is faked here
    settings = diagnosis_module.DiagnosisSettings(refine_iterations=0, profile=False)
    z = np.full(len(keys), 0.5)
    inside = diagnosis_module.diagnose(type(state)(state.fitted, z), measured, [friction], settings)
    [candidate] = inside.candidates
    assert inside.verdict == "no significant discrepancy" and inside.held == []
    assert candidate.absorbed > 0.999 and candidate.absorbed_by["name"] == keys[0]
    assert candidate.absorbed_by["correlation"] > 0.999
    assert "could not have shown" in inside.sentence and f"chiefly by {keys[0]}" in inside.sentence
    z[0] = 0.999
    pushed = diagnosis_module.diagnose(type(state)(state.fitted, z), measured, [friction], settings)
    [candidate] = pushed.candidates
    assert pushed.held == [keys[0]] and candidate.absorbed < 1e-9 and candidate.p_adjusted < 0.01
    assert pushed.verdict == "missing effect" and pushed.effect == "friction", pushed.sentence
    assert pushed.edges[0] == {"name": keys[0], "value": state.fitted.space.values(z)[keys[0]], "end": "top",
                               "held": True}
    assert "pushes" in pushed.sentence and "could not have shown" not in pushed.sentence
    assert pushed.to_dict()["held"] == [keys[0]]


def test_a_directed_residual_below_the_floor_is_no_discrepancy(null_case, monkeypatch):
    """The demo case's second round on one H200 called "unexplained" a residual whose overall test
    read T/dof 0.18, p = 1, from a directed score test alone. Here the measurement is the current
    features plus friction's signature scaled to a score S of 16 (p 6e-5) with no noise: the score
    test is significant, the overall test (T = S on hundreds of dof) is not, and the refit moves the
    features by less than the model-error floor where it acts: no significant discrepancy at the
    floor's level, and the sentence says why friction was not named."""
    from BreastBiomechLib.discrepancy import diagnosis as diagnosis_module
    from BreastBiomechLib.discrepancy import refit as refit_module
    from BreastBiomechLib.discrepancy import verdicts
    from BreastBiomechLib.discrepancy.observations import Observations
    from BreastBiomechLib.discrepancy.variants import Outcome

    state, observed, friction, base, shift, secant_features, sens = _friction_secant(null_case)
    change = secant_features - sens.features  # the signature of friction at its step: 1 mm posterior
    scale = np.sqrt(16.0 / np.sum((change / observed.sigma) ** 2))
    size = verdicts.effect_size_mm(scale * change)
    assert 0.0 < size < observed.floor_mm == 0.5, (scale, size)
    monkeypatch.setattr(diagnosis_module, "sensitivities", lambda *args, **kwargs: sens)

    def friction_moves_it(variants, *args, **kwargs):
        return [Outcome(base + scale * shift if any(p.friction > 0 for p in v.plates) else base, "completed", "")
                for v in variants]

    monkeypatch.setattr(refit_module, "solve_variants", friction_moves_it)
    measured = Observations(observed.labels, observed.channel, sens.features + scale * change, observed.sigma,
                            observed.points, observed._parts, observed.floor_mm)
    result = diagnosis_module.diagnose(state, measured, [friction],
                                       diagnosis_module.DiagnosisSettings(refine_iterations=0))
    [candidate] = result.candidates
    assert candidate.p_adjusted < 0.01 and result.overall["p_combined"] > 0.5
    # the solved change (the surface distances are not linear in the shift) is near the secant's
    moved = candidate.refit["effect_mm"]
    assert moved == pytest.approx(size, rel=0.2) and moved < 0.5 and candidate.refit["removed"] > 0.9
    assert result.verdict == "no significant discrepancy" and result.effect is None, result.sentence
    assert "at the level of the model floor (0.50 mm) remains" in result.sentence
    assert f"moves the features by {moved:.2f} mm, below 0.50 mm" in result.sentence
    assert "Unexplained" not in result.sentence


def test_an_effect_refitted_to_an_end_of_its_range_is_said_to_be_a_bound():
    """Friction refitted to the top of its range (beyond sticking more changes nothing) is
    said to be a bound the data press against, not an estimate; inside its range nothing is said."""
    from types import SimpleNamespace

    from BreastBiomechLib.discrepancy.diagnosis import _bound_note
    from BreastBiomechLib.discrepancy.effects.friction import PlateFriction

    friction = PlateFriction()
    assert _bound_note(SimpleNamespace(effect=friction, values=np.array([0.6]))) == ""
    note = _bound_note(SimpleNamespace(effect=friction, values=np.array([1.5])))
    assert "mu at the top of its range (1.5)" in note and "not an estimate" in note


def test_a_refitted_effect_has_an_interval_within_its_range():
    """Without a profile, 1.96 sd either side of the refitted value, clipped to the parameter's
    range (friction's mu in [0, 1.5]): an estimate near the top has an interval that ends at the
    top. With one, the profile's interval as it is."""
    from types import SimpleNamespace

    from BreastBiomechLib.discrepancy.diagnosis import interval
    from BreastBiomechLib.discrepancy.effects.friction import PlateFriction

    friction = PlateFriction()

    def refit(value, sd, profile=None):
        return SimpleNamespace(effect=friction, values=np.array([value]), sd=np.array([sd]), profile=profile)

    [(low, high)] = interval(refit(0.6, 0.1))
    assert (low, high) == pytest.approx((0.404, 0.796))
    [(low, high)] = interval(refit(1.45, 0.1))
    assert (low, high) == pytest.approx((1.254, 1.5))
    profiled = [{"key": "friction:0", "estimate": 0.36, "interval": [0.13, 1.5], "open": [False, True]}]
    assert interval(refit(0.36, 0.03, profiled)) == [[0.13, 1.5]]


def test_range_end_names_the_end_a_value_lies_at():
    """Within EDGE (a share of the range) of an end: that end; inside, or an empty range: none
    (before the helper, an empty nuisance range counted as mid-range and must still)."""
    from BreastBiomechLib.discrepancy.diagnosis import EDGE, range_end

    assert range_end(1.5, 0.0, 1.5) == "top" and range_end(1.5 * (1 - EDGE / 2), 0.0, 1.5) == "top"
    assert range_end(0.0, 0.0, 1.5) == "bottom" and range_end(-2.0, -2.0, 8.0) == "bottom"
    assert range_end(0.75, 0.0, 1.5) == "" and range_end(1.5 * (1 - 2 * EDGE), 0.0, 1.5) == ""
    assert range_end(3.0, 3.0, 3.0) == ""


def test_a_cancel_clicked_during_a_round_after_its_save_does_not_undo_what_was_said(null_case, tmp_path):
    """The panel processes events only in the progress calls: a Cancel clicked during a round's
    last stretch lands on the first message after the round is written. That message cannot
    cancel (the round is on disk, and "nothing was changed" would be false); every message before
    the write can, and a Cancel there leaves no round on disk."""
    from BreastBiomechLib.discrepancy import DiagnosisCancelled, DiagnosisSession, NoiseModel

    case, fit = null_case
    out = tmp_path / "clicked-late"
    heard = []

    def cancel_once_saved(message):
        saved = (out / "round-1.json").is_file()
        heard.append((message, saved))
        return not saved

    session = DiagnosisSession(case, fit, out, ["friction"], NoiseModel(floor="fixed"), device="cpu",
                               registration=None)
    record = session.diagnose(progress=cancel_once_saved)
    assert record["round"] == 1 and (out / "round-1.json").is_file()
    assert heard[-1][1] and heard[-1][0].startswith("round 1: No significant discrepancy")
    last_before = [message for message, saved in heard if not saved][-1]
    early = tmp_path / "clicked-early"
    session = DiagnosisSession(case, fit, early, ["friction"], NoiseModel(floor="fixed"), device="cpu",
                               registration=None)
    with pytest.raises(DiagnosisCancelled, match="cancelled while"):
        session.diagnose(progress=lambda message: message != last_before)
    assert not (early / "round-1.json").exists() and session.rounds == []


def test_a_floor_that_cannot_be_measured_falls_back_to_the_fixed_one_and_says_so(null_case, tmp_path, monkeypatch):
    """Where the fitted model on its refined mesh does not solve (an element inverted, as in one
    case of the varied suite), the session uses the fixed floor instead of failing the whole
    diagnosis, says so as it goes, records why (floor.json, each round's record, the report) and a
    resumed session reads that rather than solving again."""
    from BreastBiomechLib.discrepancy import DiagnosisSession
    from BreastBiomechLib.discrepancy import session as session_module
    from BreastBiomechLib.discrepancy.report import _floor_phrase

    def inverted(*args, **kwargs):
        raise RuntimeError("the fitted model on its refined mesh (800 tets) did not solve (inverted elements)")

    monkeypatch.setattr(session_module, "measure_floor", inverted)
    heard = []
    session = DiagnosisSession(*null_case, tmp_path / "dx", device="cpu", registration=None, progress=heard.append)
    assert session.floor is None and "inverted elements" in session.floor_failure
    assert any(m.startswith("the model-error floor could not be measured; the fixed floor (0.5 mm) is used")
               for m in heard)
    np.testing.assert_allclose(session.observations.sigma, session.observations.base_sigma)
    assert "inverted elements" in json.loads((tmp_path / "dx" / "floor.json").read_text())["failed"]

    def not_again(*args, **kwargs):
        raise AssertionError("the floor was measured again")

    monkeypatch.setattr(session_module, "measure_floor", not_again)
    again = DiagnosisSession(*null_case, tmp_path / "dx", device="cpu", registration=None, resume=True)
    assert again.floor is None and again.floor_failure == session.floor_failure
    phrase = _floor_phrase({"floor": {"fixed_mm": 0.5, "not_measured": session.floor_failure},
                            "noise": {"model_sd_mm": 0.5}})
    assert phrase.startswith("model-error floor 0.5 mm (fixed: measuring it from the case failed: the fitted model")


@pytest.mark.slow
def test_the_next_measurement_is_designed_from_the_fit(null_case, tmp_path, capsys):
    """`breastbiomech design`: the library's acquisitions for the case's rig (both plates closing
    25 % LR: the closure 10 and 20 % of the thickness further and less, all of it by either
    plate, the same closure along SI), one of them simulated from the fit (the second plate
    alone), and the chest-wall hold's separation from the fitted parameters now and with that
    acquisition: the fitted muscle modulus takes it up in this scan, the second tells it apart,
    also once the fitted parameters are refitted to the hold's data in both (rivals among candidates, and that a state never lowers a separation:
    Testing/unit/discrepancy/test_discrepancy_design.py); the report's section; a used output
    folder and an acquisition the library does not have are refused."""
    from BreastBiomechLib.cli import main
    from BreastBiomechLib.discrepancy import ModelState, load_fitted_case
    from BreastBiomechLib.discrepancy.acquisitions import acquisition_library, half_push

    case, fit = null_case
    fitted = load_fitted_case(case, fit, device="cpu")
    plates = ModelState(fitted, fitted.z).variant().plates
    acquisitions = {a.name: a for a in acquisition_library(fitted)}
    assert list(acquisitions) == ["compression-20", "compression-10", "compression+10", "compression+20",
                                  f"only-{plates[0].name}", f"only-{plates[1].name}", "rotated-SI"]
    thickness = (plates[1].point - plates[0].point) @ plates[0].normal
    closure = sum(p.displacement @ p.normal for p in plates)

    def gap(acquisition):
        first, second = (np.asarray(p["point"]) for p in acquisition.planes)
        return (second - first) @ np.asarray(acquisition.planes[0]["normal"])

    assert gap(acquisitions["compression+20"]) == pytest.approx(thickness - closure - 0.2 * thickness)
    assert gap(acquisitions[f"only-{plates[0].name}"]) == pytest.approx(thickness - closure)
    np.testing.assert_allclose(acquisitions[f"only-{plates[0].name}"].planes[1]["point"], plates[1].point, atol=1e-9)
    # a longer push than the first scan's: the plates end further from the chest and round more, by
    # as much as the larger travel grew (the library's rule for placing plates); a shorter one keeps them
    first_travel = max(p.displacement @ p.normal for p in plates)
    first_end = plates[0].point @ plates[0].edge.direction + plates[0].edge.distance
    for name, travel in (("compression-10", first_travel), ("compression+20", (closure + 0.2 * thickness) / 2),
                         (f"only-{plates[0].name}", closure)):
        for plane in acquisitions[name].planes:
            edge = plane["edge"]
            grown = max(0.0, travel - first_travel)
            assert edge["radius"] == pytest.approx(plates[0].edge.radius + grown, abs=0.3)
            assert np.asarray(plane["point"]) @ np.asarray(edge["direction"]) + edge["distance"] == pytest.approx(
                first_end - grown, abs=0.3)
    half = half_push(fitted, None, acquisitions[f"only-{plates[0].name}"])  # where the whole push does not solve
    assert half.name == f"only-{plates[0].name}-half" and gap(half) == pytest.approx(thickness - closure / 2)
    np.testing.assert_allclose(half.planes[1]["point"], plates[1].point, atol=1e-9)
    assert half_push(fitted, None, half) is None and half_push(fitted, None, acquisitions["compression+10"]) is None
    asked = acquisition_library(fitted, kinds=(half.name,))  # by name
    assert [a.name for a in asked] == [half.name] and asked[0].planes == half.planes
    out = tmp_path / "design"
    second = f"only-{plates[1].name}"
    command = ["design", str(case), "--fit", str(fit), "--out", str(out), "--effects", "chest-wall",
               "--acquisitions", second, "--device", "cpu", "--json"]
    assert main(command) == 0
    made = json.loads(capsys.readouterr().out)
    assert [a["name"] for a in made["acquisitions"]] == [second] and not made["failed"]
    [hold] = made["effects"]
    assert hold["rival"] is None  # the only candidate: the fitted parameters are its rivals
    [alone] = hold["acquisitions"]
    assert 0.0 < hold["now_sigma"] < hold["detectable_sigma"] < alone["separation_sigma"]
    # checked beyond the linearisation: the fitted parameters refitted to the hold's data in both
    # scans (a stiffer muscle takes some of it up), each step one solve of the model in each scan
    refitted = alone["refitted"]
    assert refitted["steps"] >= 1 and refitted["solves"] >= 2 * refitted["steps"] and refitted["stopped"] is None
    assert min(refitted["rss"][1:]) < 0.2 * refitted["rss"][0] and refitted["moved"]["muscle.E"] > 0
    assert alone["separation_sigma"] == refitted["sigma"] <= 1.05 * alone["linear_sigma"]
    report = (out / "design.md").read_text()
    assert "once the fitted parameters are refitted to what it would show" in report
    assert f"{alone['linear_sigma']:.1f} sigma by the linearisation" in report
    assert report.startswith("## The next measurement") and "To tell chest-wall hold from the fitted" in report
    assert main(command) == 2 and "not empty" in capsys.readouterr().err
    assert main([*command[:4], "--out", str(tmp_path / "again"), "--acquisitions", "sideways", "--device", "cpu"]) == 2
    assert "unknown acquisitions ['sideways']" in capsys.readouterr().err


@pytest.mark.slow
def test_a_design_with_a_measured_floor_measures_each_acquisition_s_or_says_what_stood_in(null_case, monkeypatch):
    """Given the diagnosis's features with a floor measured from the case, the design's
    separations now are in that floor's units (smaller than at the fixed 0.5 mm where the floor
    is larger), and each simulated acquisition's floor is measured there too; where its refined
    model does not solve, the measured states' RMS floor stands in, the acquisition's record says
    so, and it is still ranked. A one-plate push whose model does not solve (made to fail here)
    is said failed and simulated half as far instead."""
    from BreastBiomechLib.discrepancy import ModelState, load_fitted_case
    from BreastBiomechLib.discrepancy import design as design_module
    from BreastBiomechLib.discrepancy import floor as floor_module
    from BreastBiomechLib.discrepancy.design import design
    from BreastBiomechLib.discrepancy.fitted import recorded_solution
    from BreastBiomechLib.discrepancy.observations import observations_of

    case, fit = null_case
    fitted = load_fitted_case(case, fit, device="cpu")
    observations = observations_of(fitted, recorded_solution(fitted))
    floor = np.linspace(0.5, 1.5, len(observations))
    second = f"only-{ModelState(fitted, fitted.z).variant().plates[1].name}"

    def refused(*args, **kwargs):
        raise RuntimeError("the fitted model on its refined mesh did not solve (inverted)")

    real = design_module.sensitivities

    def inverting(state, *args, **kwargs):  # the whole push inverts an element of this model
        if state.fitted.name == second:
            raise RuntimeError("the current model does not solve (inverted elements: 1 element(s) inverted)")
        return real(state, *args, **kwargs)

    monkeypatch.setattr(floor_module, "discretisation_error", refused)
    monkeypatch.setattr(design_module, "sensitivities", inverting)
    made = design(fitted, ["chest-wall"], (second,), observations=observations.with_floor(floor))
    assert list(made.failed) == [second] and "inverted" in made.failed[second]
    [acquisition] = made.acquisitions
    assert acquisition["name"] == f"{second}-half" and "half as far" in acquisition["description"]
    rms = float(np.sqrt(np.mean(floor ** 2)))
    assert acquisition["floor"].startswith(f"the measured states' RMS floor ({rms:.2f} mm)")
    assert "inverted" in acquisition["floor"] and made.noise["floor"] == "measured"
    assert acquisition["solves"] >= 2  # the model and the hold's secant, timed for the bench
    assert 0 < acquisition["seconds"]["sensitivities"] <= acquisition["seconds"]["total"]
    [hold] = made.effects
    assert [a["name"] for a in hold["acquisitions"]] == [f"{second}-half"]
    assert hold["acquisitions"][0]["separation_sigma"] > 0
    fixed = design(fitted, ["chest-wall"], acquisitions=[])  # the fixed 0.5 mm floor, no acquisition
    assert fixed.noise["floor"] == "fixed" and 0.0 < hold["now_sigma"] < fixed.effects[0]["now_sigma"]


def test_a_modulus_beyond_its_published_range_is_retested_on_the_model_solved_at_the_range_s_end(null_case):
    """A fit whose muscle modulus lies beyond its published range (the null case's fit with the
    muscle moved to the top of the fit's range): the round solves the model with the muscle held
    at the range's end in the launch of its sensitivities and retests the candidates on that
    solve's residual, not on the linearised step back (a modulus fitted several times past its
    range is far from where the linearisation holds); the verdict says the conflict."""
    from BreastBiomechLib.discrepancy import ModelState, library, load_fitted_case, priors
    from BreastBiomechLib.discrepancy.diagnosis import diagnose
    from BreastBiomechLib.discrepancy.fitted import recorded_solution
    from BreastBiomechLib.discrepancy.observations import observations_of

    case, fit = null_case
    fitted = load_fitted_case(case, fit, device="cpu")
    observations = observations_of(fitted, recorded_solution(fitted))
    z = fitted.z.copy()
    z[fitted.space.keys.index("muscle.E")] = 1.0
    [expected] = priors.prior_conflicts(fitted.space, z)
    result = diagnose(ModelState(fitted, z), observations, library(fitted, ["anisotropy"]))
    [conflict] = result.conflicts
    assert conflict["name"] == expected["name"] == "muscle.E" and conflict["retest"]["solved"]
    held = result.sensitivities.held["muscle.E"]
    assert held is not None and np.isfinite(held).all()
    assert np.abs(held - result.sensitivities.displacement).max() > 0.1  # the softer muscle moved the breast
    assert "Prior-data conflict: muscle E" in result.sentence


def test_a_design_starts_from_the_model_a_diagnosis_ended_with(null_case, tmp_path):
    """`design --diagnosis DIR` designs from the last round's model (its refitted parameters and
    added effects; the added ones are no longer candidates); a folder without a round, or the
    diagnosis of another fit, is refused."""
    from BreastBiomechLib.discrepancy import load_fitted_case
    from BreastBiomechLib.discrepancy.design import last_round_state

    case, fit = null_case
    fitted = load_fitted_case(case, fit, device="cpu")
    folder = tmp_path / "diagnosis"
    folder.mkdir()
    with pytest.raises(FileNotFoundError, match="no diagnosis round"):
        last_round_state(fitted, folder)
    z = np.clip(fitted.z + 0.05, 0.0, 1.0)
    for number, added in ((1, {"friction": [0.4]}), (2, {"friction": [0.5], "skin": [1.5, 0.0]})):
        (folder / f"round-{number}.json").write_text(json.dumps({"state_after": {"z": z.tolist(), "added": added}}))
    (folder / "diagnosis.json").write_text(json.dumps({"case_dir": str(case), "fit_dir": str(fit)}))
    state = last_round_state(fitted, folder)
    np.testing.assert_allclose(state.z, z)
    assert {name: list(values) for name, (_, values) in state.added.items()} == {"friction": [0.5], "skin": [1.5, 0.0]}
    (folder / "diagnosis.json").write_text(json.dumps({"case_dir": str(case), "fit_dir": str(tmp_path / "other")}))
    with pytest.raises(ValueError, match="is the diagnosis of fit"):
        last_round_state(fitted, folder)

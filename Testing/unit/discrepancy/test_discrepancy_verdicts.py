"""The diagnosis's verdict rules and sentences, fed with numbers on both sides of every threshold:
the verdict follows the rule, and the words say what the numbers show (a sentence that calls the
residual significant quotes a significant test; one that says there is no significant discrepancy
quotes none)."""

from __future__ import annotations

import itertools
import re

import pytest

from BreastBiomechLib.discrepancy import verdicts
from BreastBiomechLib.discrepancy.diagnosis import DiagnosisSettings
from BreastBiomechLib.discrepancy.verdicts import effect_size_mm

SETTINGS = DiagnosisSettings()
FLOOR = 0.5


def _overall(p_combined: float) -> dict:
    """A family whose smallest p is the landmarks' (the combined p three times it)."""
    return {"statistic": 300.0, "dof": 350, "p_value": 0.97, "per_dof": 0.86, "family": 3,
            "p_combined": p_combined,
            "channels": {"landmarks": {"statistic": 80.0, "dof": 57, "p_value": p_combined / 3, "features": 60},
                         "surface": {"statistic": 220.0, "dof": 290, "p_value": 0.99, "features": 300}}}


def _candidate(name="friction", p=1e-6, lr_p=1e-6, dbic=-30.0, localisation=0.8, effect_mm=1.2, removed=0.7,
               refitted=True) -> dict:
    c = {"name": name, "title": name.replace("-", " "), "acts_in": "the contact bands", "statistic": 40.0, "dof": 1,
         "p_value": p / 10, "p_adjusted": p, "localisation": localisation, "skipped": "", "refit": None}
    if refitted:
        c["refit"] = {"status": "completed", "values": [0.5], "sd": [0.05], "described": f"{name} 0.5",
                      "refined_described": f"{name} 0.55", "lr_p_adjusted": lr_p, "delta_bic": dbic,
                      "removed": removed, "effect_mm": effect_mm, "at_range_ends": []}
    return c


def _evidence(p_combined=0.5, candidates=(), correlations=None, alone=0.05) -> verdicts.Evidence:
    return verdicts.Evidence(_overall(p_combined), list(candidates), correlations or {}, 0.42, "contact 1 (surface)",
                             FLOOR, alone)


def _quoted_combined_p(sentence: str) -> float:
    return float(re.search(r"combined p = ([0-9.eE+-]+)", sentence).group(1))


def _agrees(decision: verdicts.Decision, evidence: verdicts.Evidence) -> None:
    """The words agree with the numbers: significance claimed only with a significant test quoted,
    denied only with none."""
    sentence = decision.sentence
    if decision.verdict == verdicts.NONE:
        assert sentence.startswith("No significant discrepancy")
        assert _quoted_combined_p(sentence) >= SETTINGS.alpha
        assert "residual is significant" not in sentence
    if decision.verdict == verdicts.UNEXPLAINED:
        assert sentence.startswith("Unexplained discrepancy: the residual is significant (")
        assert _quoted_combined_p(sentence) < SETTINGS.alpha
        assert "T/dof" in sentence and "landmarks: T = 80.0 on 57 dof" in sentence  # the test that found it
    if decision.verdict == verdicts.AMBIGUOUS:
        assert sentence.startswith("Ambiguous: ")


def test_nothing_significant_is_said_so_with_every_channel_quoted():
    evidence = _evidence(0.5, [_candidate(p=0.2, refitted=False)])
    decision = verdicts.decide(evidence, SETTINGS)
    assert decision.verdict == verdicts.NONE
    assert "landmarks T = 80.0 on 57 dof, p = 0.167" in decision.sentence
    assert "surface T = 220.0 on 290 dof" in decision.sentence and "combined p = 0.5" in decision.sentence
    assert "smallest corrected p = 0.2" in decision.sentence
    _agrees(decision, evidence)


@pytest.mark.parametrize("overall_p", [0.5, 0.001])
def test_each_confirmation_rule_on_both_sides_of_its_threshold(overall_p):
    """One candidate significant by its score test; each rule moved just past its threshold
    alone: on the right side the candidate is named, on the wrong side it is not, the sentence
    names the rule it failed, and the verdict is "unexplained" only where the overall test is
    significant (else a residual at the floor's level: no significant discrepancy)."""
    floor_effect = SETTINGS.min_effect * FLOOR
    sides = {"lr_p": (0.009, 0.011), "dbic": (-10.1, -9.9), "localisation": (0.51, 0.49),
             "effect_mm": (floor_effect + 0.01, floor_effect - 0.01), "removed": (0.41, 0.39)}
    failed_words = {"lr_p": "LR p 0.011", "dbic": "dBIC -9.9 > -10", "localisation": "localisation 0.49 < 0.5",
                    "effect_mm": "moves the features by 0.49 mm, below 0.50 mm", "removed": "removes only 39%"}
    for rule, (good, bad) in sides.items():
        evidence = _evidence(overall_p, [_candidate(**{rule: good})])
        named = verdicts.decide(evidence, SETTINGS)
        assert named.verdict == verdicts.MISSING and named.effect == "friction", rule
        evidence = _evidence(overall_p, [_candidate(**{rule: bad})])
        decision = verdicts.decide(evidence, SETTINGS)
        expected = verdicts.UNEXPLAINED if overall_p < SETTINGS.alpha else verdicts.NONE
        assert decision.verdict == expected and decision.effect is None, rule
        _agrees(decision, evidence)
        if expected == verdicts.NONE:
            assert "at the level of the model floor (0.50 mm) remains, largest in contact 1 (surface)" in decision.sentence
            assert "0.42 mm RMS" in decision.sentence
        if rule != "removed" or expected == verdicts.UNEXPLAINED:
            assert failed_words[rule] in decision.sentence, (rule, decision.sentence)


def test_a_significant_residual_with_no_significant_candidate_is_unexplained_and_says_which_test():
    evidence = _evidence(0.003, [_candidate(p=0.3, refitted=False)])
    decision = verdicts.decide(evidence, SETTINGS)
    assert decision.verdict == verdicts.UNEXPLAINED
    assert "no candidate's score test is significant" in decision.sentence
    _agrees(decision, evidence)


def test_an_unexplained_residual_in_the_landmarks_alone_says_what_marking_error_would_read_the_same():
    """The landmarks' channel significant and the surface not: the sentence adds the other
    reading, landmarks marked less precisely than assumed, with the localisation sd that would
    give their T/dof of 1 at the same floor (here T/dof 80/57 at 0.5 mm and a 0.5 mm floor: 0.67
    mm); with the surface significant too, or no landmark noise known, it does not."""
    evidence = _evidence(0.003, [_candidate(p=0.3, refitted=False)])
    evidence.landmark_noise = (0.5, 0.5)
    decision = verdicts.decide(evidence, SETTINGS)
    assert decision.verdict == verdicts.UNEXPLAINED
    assert ("The landmarks alone carry it (T/dof 1.40; the surface is within its noise): landmarks marked with a "
            "localisation error of about 0.67 mm rather than the assumed 0.5 mm") in decision.sentence
    _agrees(decision, evidence)
    evidence.overall["channels"]["surface"]["p_value"] = 0.001
    assert "landmarks alone" not in verdicts.decide(evidence, SETTINGS).sentence
    evidence.overall["channels"]["surface"]["p_value"] = 0.99
    evidence.landmark_noise = None
    assert "landmarks alone" not in verdicts.decide(evidence, SETTINGS).sentence


def test_unexplained_names_the_nearest_candidate_and_what_it_pressed_against():
    near = _candidate("skin", dbic=-4.0, removed=0.15)
    near["refit"]["at_range_ends"] = ["ln(E_skin/E_tissue) at the top of its range (4)"]
    far = _candidate("plate-tilt", dbic=-2.0, removed=0.05)
    evidence = _evidence(0.001, [near, far])
    decision = verdicts.decide(evidence, SETTINGS)
    assert decision.verdict == verdicts.UNEXPLAINED and decision.alternatives == ["skin"]
    assert "Nearest: skin, at the ln(E_skin/E_tissue) at the top of its range (4)." in decision.sentence
    assert "skin (removed 15%; dBIC -4.0 > -10)" in decision.sentence
    _agrees(decision, evidence)


def test_a_fit_that_had_not_converged_is_said_so():
    """Whether or not the overall test is significant, a nested refit that removes most of the
    residual by itself is said to be an unconverged fit, and no effect is credited with it."""
    for overall_p, verdict in ((0.001, verdicts.UNEXPLAINED), (0.5, verdicts.NONE)):
        evidence = _evidence(overall_p, [_candidate(removed=0.0, dbic=5.0)], alone=0.9)
        decision = verdicts.decide(evidence, SETTINGS)
        assert decision.verdict == verdict
        assert "fitted parameters alone removes 90%" in decision.sentence
        _agrees(decision, evidence)
    quiet = verdicts.decide(_evidence(0.5, [_candidate(removed=0.0, dbic=5.0)], alone=0.3), SETTINGS)
    assert "fitted parameters alone" not in quiet.sentence


def test_ambiguity_on_both_sides_of_its_thresholds():
    best, rival = _candidate("friction", dbic=-30.0), _candidate("skin", dbic=-26.0)
    for correlation, gap, verdict in ((0.91, 4.0, verdicts.AMBIGUOUS), (0.89, 4.0, verdicts.MISSING),
                                      (0.91, 6.1, verdicts.MISSING)):
        rival["refit"]["delta_bic"] = -30.0 + gap
        evidence = _evidence(0.001, [best, rival], {"friction|skin": correlation})
        decision = verdicts.decide(evidence, SETTINGS)
        assert decision.verdict == verdict, (correlation, gap)
        if verdict == verdicts.AMBIGUOUS:
            assert decision.alternatives == ["friction", "skin"]
            assert f"correlate {correlation:.2f}" in decision.sentence and f"differ by {gap:.1f}" in decision.sentence
        else:
            assert decision.effect == "friction"


def test_the_words_agree_with_the_numbers_over_a_grid():
    """Every combination of overall p, score-test p and refit outcome on both sides of the
    thresholds: whatever the verdict, its sentence agrees with the numbers it quotes; a missing
    effect's sentence quotes its size."""
    grid = itertools.product((0.5, 0.02, 0.009, 1e-8), (0.2, 0.011, 0.009, 1e-9), (-30.0, -9.0),
                             (0.1, 0.9), (0.3, 2.0))
    seen = set()
    for overall_p, p, dbic, removed, size in grid:
        candidate = _candidate(p=p, dbic=dbic, removed=removed, effect_mm=size, refitted=p < SETTINGS.alpha)
        evidence = _evidence(overall_p, [candidate])
        decision = verdicts.decide(evidence, SETTINGS)
        seen.add(decision.verdict)
        _agrees(decision, evidence)
        if decision.verdict == verdicts.MISSING:
            sentence = verdicts.missing_effect_sentence(candidate)
            assert f"moving the features by {size:.2f} mm" in sentence and "(friction 0.55)" in sentence
            assert p < SETTINGS.alpha and dbic <= SETTINGS.bic_threshold and removed >= SETTINGS.min_explained
        if overall_p >= SETTINGS.alpha and p >= SETTINGS.alpha:
            assert decision.verdict == verdicts.NONE
    assert seen == {verdicts.NONE, verdicts.UNEXPLAINED, verdicts.MISSING}


def test_a_named_effect_is_said_with_its_interval():
    candidate = _candidate()
    sentence = verdicts.missing_effect_sentence(candidate)
    assert "(friction 0.55). Score test" in sentence  # a record made before intervals: none said
    candidate["refit"]["interval"] = [[0.412, 0.688]]  # a record made before profile intervals
    assert ("(friction 0.55; 95 % linearised interval 0.412 to 0.688). Score test"
            in verdicts.missing_effect_sentence(candidate))
    # a profile interval that reaches the top of the range: the data bound it from below only
    candidate["refit"].update(interval=[[0.132, 1.5]], interval_kind="profile", interval_open=[[False, True]])
    assert ("(friction 0.55; 95 % profile interval 0.132 to 1.5, bounded by the data from below only). Score test"
            in verdicts.missing_effect_sentence(candidate))
    candidate["refit"].update(interval=[[-5.0, 0.2], [-5.0, 5.0]], interval_open=[[True, False], [True, True]])
    assert ("95 % profile interval -5 to 0.2, bounded by the data from above only; -5 to 5, the data do not bound it)"
            in verdicts.missing_effect_sentence(candidate))
    # an interval the model-error floor widened says the data's own beside it
    candidate["refit"].update(interval=[[0.25, 1.5]], interval_open=[[False, True]], data_interval=[[1.05, 1.5]])
    assert ("(friction 0.55; 95 % profile interval 0.25 to 1.5, bounded by the data from below only, the data alone "
            "1.05 to 1.5, the rest within the model-error floor). Score test" in verdicts.missing_effect_sentence(candidate))


def test_an_effect_is_sized_where_it_acts():
    """The RMS of the largest tenth of the changes: an effect confined to 10 of 100 features is
    not diluted by the 90 it leaves alone."""
    change = [0.0] * 90 + [1.0] * 10
    assert effect_size_mm(change) == pytest.approx(1.0)
    assert effect_size_mm([-2.0] * 100) == pytest.approx(2.0)
    assert effect_size_mm([]) == 0.0


def test_a_named_effects_interval_is_conditional_on_a_fit_that_has_not_settled():
    """Where the fitted parameters alone remove ``min_explained`` of the residual or more, the
    named effect's interval holds only for the fitted materials as they are: the sentence says
    so, and says the fit has not converged; below that share it says neither."""
    candidate = _candidate()
    candidate["refit"].update(interval=[[0.294, 0.356]], interval_kind="profile", interval_open=[[False, False]])
    for alone, unsettled in ((SETTINGS.min_explained - 0.01, False), (SETTINGS.min_explained, True), (None, False)):
        sentence = verdicts.missing_effect_sentence(candidate, "", _evidence(alone=alone), SETTINGS)
        assert ("0.294 to 0.356, given the fitted materials, which have not settled)" in sentence) is unsettled
        assert ("the fit has not converged on these features" in sentence) is unsettled, alone
    assert "not settled" not in verdicts.missing_effect_sentence(candidate)  # no evidence given: nothing said


def test_a_residual_far_below_the_noise_model_is_said_to_be_so():
    """A quiet verdict whose landmark channel has T far below its dof (the demo's second round: T
    = 0.6 on 49 dof) says the noise model is larger than this case's noise, naming the channel;
    one near its dof says nothing of the kind. The threshold is chi-square's lower tail at alpha."""
    from scipy.stats import chi2

    evidence = _evidence(0.9)
    evidence.overall["channels"]["surface"]["statistic"] = 290.0  # at its dof: nothing to say of it
    for statistic, said in ((0.6, True), (chi2.ppf(SETTINGS.alpha / 2, 57), True),
                            (chi2.ppf(2 * SETTINGS.alpha, 57), False), (57.0, False)):
        evidence.overall["channels"]["landmarks"].update(statistic=statistic, p_value=0.99)
        decision = verdicts.decide(evidence, SETTINGS)
        assert decision.verdict == verdicts.NONE
        assert decision.sentence.startswith("No significant discrepancy: the residual is within what the noise model")
        assert ("far smaller than the noise model assumes (landmarks T/dof" in decision.sentence) is said, statistic
        assert "surface T/dof" not in decision.sentence


def test_what_this_case_could_not_have_shown_names_absorbed_and_too_small_effects():
    """A quiet round says which candidates it could not have shown: one the fitted parameters
    absorb, and one whose smallest detectable size lies beyond its whole range (friction whose
    test would need mu 2.1 where mu ends at 1.5); one detectable inside its range is not named."""
    from BreastBiomechLib.discrepancy.diagnosis import Candidate, absorbed_sentence, beyond_range
    from BreastBiomechLib.discrepancy.effects.friction import PlateFriction

    friction = PlateFriction()
    absorbed = Candidate("chest-wall", "chest-wall hold", "", absorbed=0.85,
                         absorbed_by={"name": "muscle.E", "correlation": 0.9}, detectable=[0.01])
    small = Candidate("friction", "plate friction", "", absorbed=0.1, detectable=[2.1])
    seen = Candidate("friction", "plate friction", "", absorbed=0.1, detectable=[0.2])
    assert beyond_range(small, {"friction": friction}) == ["mu 2.1, its range 0 to 1.5"]
    assert beyond_range(seen, {"friction": friction}) == []
    assert beyond_range(Candidate("friction", "", "", detectable=[None]), {"friction": friction}) == [
        "mu none, its range 0 to 1.5"]
    sentence = absorbed_sentence([absorbed, small], {"friction": friction})
    assert "chest-wall hold (85% of its signature, chiefly by muscle.E" in sentence
    assert "Too small to see at this case's noise, whatever its size within its range: plate friction (smallest " \
           "size its test would see: mu 2.1, its range 0 to 1.5)" in sentence
    assert absorbed_sentence([seen], {"friction": friction}) == ""
    # too small to see, the larger part of it reproduced: what would take it up is named
    mostly = Candidate("friction", "plate friction", "", absorbed=0.78,
                       absorbed_by={"name": "glandular.E", "correlation": 0.88}, detectable=[2.1])
    assert "(smallest size its test would see: mu 2.1, its range 0 to 1.5; 78% of it would be taken up as " \
           "glandular.E)" in absorbed_sentence([mostly], {"friction": friction})
    assert "taken up" not in absorbed_sentence([small], {"friction": friction})
    assert "such an effect, if present, has been fitted as those parameters" in sentence
    # after an unexplained discrepancy such an effect may be what is missing
    after_unexplained = absorbed_sentence([absorbed], {"friction": friction}, missing=True)
    assert "chest-wall hold (85% of its signature" in after_unexplained
    assert "may be what is missing here, fitted in part as those parameters" in after_unexplained


def test_the_pairs_a_case_cannot_tell_apart_follow_from_their_correlations():
    """Each tested candidate's closest rival is the one whose signature correlates most with its
    own after the fitted parameters (a skipped one is never a rival); the sentence names every
    pair at or above the threshold, strongest first, and says so when there is none."""
    from BreastBiomechLib.discrepancy.diagnosis import INSEPARABLE, closest_rivals, inseparable_sentence

    candidates = [{"name": "friction", "title": "plate friction"}, {"name": "skin", "title": "skin layer"},
                  {"name": "plate-tilt", "title": "plate pose"}, {"name": "gravity", "title": "gravity",
                                                                 "skipped": "no posture"}]
    correlations = {"friction|skin": 0.93, "friction|plate-tilt": 0.41, "skin|plate-tilt": 0.85,
                    "friction|gravity": 0.99}
    assert closest_rivals(candidates, correlations) == {"friction": ("skin", 0.93), "skin": ("friction", 0.93),
                                                        "plate-tilt": ("skin", 0.85)}
    sentence = inseparable_sentence(candidates, correlations)
    assert "plate friction and skin layer (0.93); skin layer and plate pose (0.85)" in sentence
    assert "gravity" not in sentence and "0.41" not in sentence
    just_below = {key: min(value, INSEPARABLE - 1e-6) for key, value in correlations.items()}
    assert inseparable_sentence(candidates, just_below).startswith("No two tested candidates")
    at_threshold = inseparable_sentence(candidates, {**just_below, "skin|plate-tilt": INSEPARABLE})
    assert "skin layer and plate pose (0.80)" in at_threshold and "plate friction and" not in at_threshold

"""The hidden-effect suite: phantom cases whose truth hides one effect, two, none, or one the
candidate library does not hold; each fitted on a mesh of the segmentation of its MR and
diagnosed without its truth; scored against the effect it hides (``breastbiomech
discrepancy-suite``; docs/discrepancy.md)."""

from BreastBiomechLib.discrepancy.suite.cases import ANATOMIES, HIDDEN_EFFECTS, HiddenEffect, SuiteCase, suite_cases
from BreastBiomechLib.discrepancy.suite.runner import MEASURED_FILES, SuiteSettings, measured_copy, run_case, run_suite
from BreastBiomechLib.discrepancy.suite.scores import case_result, scores_markdown, suite_scores

__all__ = ["ANATOMIES", "HIDDEN_EFFECTS", "HiddenEffect", "MEASURED_FILES", "SuiteCase", "SuiteSettings",
           "case_result", "measured_copy", "run_case", "run_suite", "scores_markdown", "suite_cases", "suite_scores"]

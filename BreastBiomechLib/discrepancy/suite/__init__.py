"""The hidden-effect suite: phantom cases whose truth hides one effect, two, none, or one the
candidate library does not hold; each fitted on a mesh of the segmentation of its MR and
diagnosed without its truth; scored against the effect it hides (``breastbiomech
discrepancy-suite``; docs/discrepancy-suite.md)."""

from BreastBiomechLib.discrepancy.suite.cases import ANATOMIES, HIDDEN_EFFECTS, HiddenEffect, SuiteCase, suite_cases
from BreastBiomechLib.lazy import exports

__all__ = ["ANATOMIES", "HIDDEN_EFFECTS", "HiddenEffect", "MEASURED_FILES", "SuiteCase", "SuiteSettings",
           "case_result", "measured_copy", "run_case", "run_suite", "scores_markdown", "suite_cases", "suite_scores"]

# the runner and the scores are imported on first use (see BreastBiomechLib.lazy)
__getattr__, __dir__ = exports(__name__, {"MEASURED_FILES": "runner", "SuiteSettings": "runner",
                                          "measured_copy": "runner", "run_case": "runner", "run_suite": "runner",
                                          "case_result": "scores", "scores_markdown": "scores",
                                          "suite_scores": "scores"})

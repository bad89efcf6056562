"""Small CPU cases for the discrepancy tests: the library's examples
(:mod:`BreastBiomechLib.cli.examples`), which the Breast Discrepancy module's in-app
self-test makes too."""

from BreastBiomechLib.cli.examples import FIT, fit_coarse, small_friction_case, without_truth

__all__ = ["FIT", "fit_coarse", "small_friction_case", "without_truth"]

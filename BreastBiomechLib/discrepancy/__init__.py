"""Model discrepancy: find where the fitted model and the measured case disagree, name the
physical effect that is missing, add it, refit, and show the gap shrink.

Steps, each usable alone from the Python console:

- :func:`~BreastBiomechLib.discrepancy.fitted.load_fitted_case`: a case and its fit;
- :func:`~BreastBiomechLib.discrepancy.observations.observations_of`: the features compared
  (landmarks, the body surface) with their noise;
- :func:`~BreastBiomechLib.discrepancy.effects.library`: the candidate effects;
- :func:`~BreastBiomechLib.discrepancy.diagnosis.diagnose`: one round (sensitivities, score
  tests, refits of the best, the verdict);
- :class:`~BreastBiomechLib.discrepancy.session.DiagnosisSession`: the rounds one step at a
  time (diagnose, add a candidate with its refit, or reject it), each written as it finishes;
- :func:`~BreastBiomechLib.discrepancy.workflow.run_diagnosis`: rounds until nothing
  significant remains, with its report.
"""

from BreastBiomechLib.lazy import exports

__all__ = ["VERDICTS", "Diagnosis", "DiagnosisCancelled", "DiagnosisRun", "DiagnosisSession", "DiagnosisSettings",
           "FittedCase", "ModelState", "NoiseModel", "Observations", "diagnose", "library", "load_fitted_case",
           "observations_of", "run_diagnosis"]

# imported on first use (the modules import warp, SciPy and SimpleITK; see BreastBiomechLib.lazy)
__getattr__, __dir__ = exports(__name__, {
    "VERDICTS": "diagnosis", "Diagnosis": "diagnosis", "DiagnosisSettings": "diagnosis", "diagnose": "diagnosis",
    "library": "effects", "FittedCase": "fitted", "load_fitted_case": "fitted", "NoiseModel": "observations",
    "Observations": "observations", "observations_of": "observations", "DiagnosisCancelled": "session",
    "DiagnosisSession": "session", "ModelState": "state", "DiagnosisRun": "workflow", "run_diagnosis": "workflow"})

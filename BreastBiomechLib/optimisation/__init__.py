"""Material-parameter optimisation (seed section 2.4): parameters that maximise the similarity
between the FE-predicted and the measured compressed MR image, found by the seed's hybrid
search (simulated annealing, then a bounded local search) or by CMA-ES, batched on the device.
"""

from BreastBiomechLib.optimisation.forward import Evaluation, FittingProblem
from BreastBiomechLib.optimisation.run import OptimisationResult, optimise
from BreastBiomechLib.optimisation.space import MODELS, FreeParameter, ParameterSpace

__all__ = ["Evaluation", "FittingProblem", "FreeParameter", "MODELS", "OptimisationResult", "ParameterSpace",
           "optimise"]

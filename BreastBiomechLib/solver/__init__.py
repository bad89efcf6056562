"""GPU explicit nonlinear finite elements (TLED) on NVIDIA warp: four-node tets with average
nodal pressure, neo-Hookean and transversely isotropic neo-Hookean materials, rigid-plate
frictionless contact, prescribed displacements, gravity, batched solves.

Building a model (materials, plates, constraints, loading) needs numpy only; warp is imported on
first use of the solver itself (``solve``, ``solve_batch``; the settings and ``Solution`` are light),
so a Slicer panel can build and show a model before warp is installed."""

from BreastBiomechLib.lazy import exports
from BreastBiomechLib.solver.materials import ElementMaterials, Material, fibre_direction, lame_from_young
from BreastBiomechLib.solver.model import Constraint, Loading, Model, Plate

__all__ = ["Constraint", "DynamicRelaxation", "ElementMaterials", "Loading", "Material", "Model", "Plate", "Solution",
           "SolverSettings", "fibre_direction", "lame_from_young", "solve", "solve_batch"]

__getattr__, __dir__ = exports(__name__, {"DynamicRelaxation": "settings", "SolverSettings": "settings",
                                          "Solution": "solution", "solve": "tled", "solve_batch": "tled"})

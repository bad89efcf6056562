"""GPU explicit nonlinear finite elements (TLED) on NVIDIA warp: four-node tets with average
nodal pressure, neo-Hookean and transversely isotropic neo-Hookean materials, rigid-plate
frictionless contact, prescribed displacements, gravity, batched solves."""

from BreastBiomechLib.solver.materials import ElementMaterials, Material, fibre_direction, lame_from_young
from BreastBiomechLib.solver.model import Constraint, Loading, Model, Plate
from BreastBiomechLib.solver.tled import DynamicRelaxation, Solution, solve, solve_batch

__all__ = ["Constraint", "DynamicRelaxation", "ElementMaterials", "Loading", "Material", "Model", "Plate", "Solution",
           "fibre_direction", "lame_from_young", "solve", "solve_batch"]

"""Deterministic synthetic prone breast MR cases with ground truth (labels, partial-volume
fractions, bias field, 17 landmarks); see :func:`generate_phantom` and :func:`write_phantom`."""

from BreastBiomechLib.phantom.generate import PhantomCase, generate_phantom
from BreastBiomechLib.phantom.files import read_phantom, write_phantom
from BreastBiomechLib.phantom.parameters import TABLE1_CASES, PhantomParameters, table1_case


__all__ = ["PhantomCase", "PhantomParameters", "generate_phantom", "read_phantom", "table1_case",
           "TABLE1_CASES", "write_phantom"]

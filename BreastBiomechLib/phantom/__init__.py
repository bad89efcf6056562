"""Deterministic synthetic prone breast MR cases with ground truth (labels, partial-volume
fractions, bias field, 17 landmarks); see :func:`generate_phantom` and :func:`write_phantom`.

The parameters (:class:`PhantomParameters`, the seed's Table 1 cases) need only the standard
library; the generator and the case files (which import SimpleITK) are imported on first use."""

from BreastBiomechLib.lazy import exports
from BreastBiomechLib.phantom.parameters import TABLE1_CASES, PhantomParameters, table1_case

__all__ = ["PhantomCase", "PhantomParameters", "generate_phantom", "read_phantom", "table1_case",
           "TABLE1_CASES", "write_phantom"]

__getattr__, __dir__ = exports(__name__, {"PhantomCase": "generate", "generate_phantom": "generate",
                                          "read_phantom": "files", "write_phantom": "files"})

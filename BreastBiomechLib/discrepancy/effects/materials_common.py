"""Scaling the stiffness of some elements, shared by the heterogeneity and tumour effects."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from BreastBiomechLib.solver.materials import ElementMaterials


def stiffer(materials: ElementMaterials, elements: np.ndarray, log_ratio: float) -> ElementMaterials:
    """``materials`` with the shear and bulk moduli of ``elements`` (boolean mask, M) multiplied
    by exp(``log_ratio``) (Poisson's ratio kept)."""
    factor = np.where(elements, np.exp(float(log_ratio)), 1.0)
    return replace(materials, mu=materials.mu * factor, kappa=materials.kappa * factor)

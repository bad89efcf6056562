"""Closed triangulated surfaces from tissue label images: extraction (flying edges), smoothing
(windowed sinc), decimation to a target edge length, and topology checks."""

from BreastBiomechLib.surface.checks import SurfaceCheck, check_surface
from BreastBiomechLib.surface.extract import SurfaceSettings, body_surface, tissue_surface
from BreastBiomechLib.surface.trisurface import TriSurface

__all__ = ["SurfaceCheck", "SurfaceSettings", "TriSurface", "body_surface", "check_surface", "tissue_surface"]

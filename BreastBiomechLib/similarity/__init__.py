"""Similarity of the FE-predicted and the measured deformed image: NMI (the seed's eq. (16)) and
normalised cross-correlation, on the device (:class:`Similarity`) or as one-off functions; the
distance of predicted skin points to the measured body surface (:class:`SurfaceDistance`)."""

from BreastBiomechLib.similarity.measures import Similarity, entropies, ncc, nmi
from BreastBiomechLib.similarity.surface import SurfaceDistance

__all__ = ["Similarity", "SurfaceDistance", "entropies", "ncc", "nmi"]

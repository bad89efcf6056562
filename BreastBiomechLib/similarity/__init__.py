"""Similarity of the FE-predicted and the measured deformed image: NMI (the seed's eq. (16)) and
normalised cross-correlation, on the device (:class:`Similarity`) or as one-off functions."""

from BreastBiomechLib.similarity.measures import Similarity, entropies, ncc, nmi

__all__ = ["Similarity", "entropies", "ncc", "nmi"]

"""The FE-predicted deformed MR image and the dense displacement field of an FE solution (seed
section 2.4, step 3): :func:`predict_image`, :func:`displacement_field`, and :class:`ImageWarper`
for repeated warps of one image through one mesh (the optimisation loop)."""

from BreastBiomechLib.warping.predict import ImageWarper, PredictedImage, displacement_field, predict_image

__all__ = ["ImageWarper", "PredictedImage", "displacement_field", "predict_image"]

"""A fixed, reproducible spread of phantom variants for robustness sweeps (``breastbiomech bench
segment --sweep``, ``bench mesh --sweep``): every option of the anatomy the default case does
not make, crossed with image quality and voxel shape.

Each option list is walked with its own stride, so that over the first 20+ variants every value
of every option occurs and the combinations vary; the list is the same on every machine.
"""

from __future__ import annotations

from BreastBiomechLib.phantom.parameters import PhantomParameters

# option -> values; lengths chosen pairwise coprime-ish so the combinations keep changing
_OPTIONS: dict[str, list] = {
    "gland_texture": [0.0, 1.0, 0.5],
    "tumour_site": ["central", "border"],
    "gland_on_muscle": [False, True, False, True, True],
    "thorax": [True, False, True, True, False, True, False],
    "skin_thickness_mm": [1.5, 0.0, 3.0, 0.8, 2.2],
    "spacing_mm": [(1.0, 1.0, 2.5), (1.5, 1.5, 1.5), (0.8, 0.8, 3.0), (1.0, 1.0, 2.0)],
    "snr": [30.0, 15.0, 40.0, 20.0, 25.0, 35.0, 18.0],
    "bias_strength": [0.2, 0.0, 0.35, 0.1, 0.3, 0.25],
    "density": [0.25, 0.12, 0.4, 0.3, 0.18, 0.5],
    "volume_cm3": [450.0, 600.0, 420.0, 750.0, 500.0],
}
TUMOUR_MM = 12.0
SUBVOXEL_MM = 0.7  # 1.5 mm voxels drawn on 4 sub-voxels per axis, not 2: with 2, many truth voxels tie at half
DEFAULT_COUNT = 24


def sweep_variants(count: int = DEFAULT_COUNT) -> list[PhantomParameters]:
    """``count`` phantom variants (seeds 1001...), each with a 12 mm tumour and sub-voxels of at
    most 0.7 mm; variant ``i`` takes value ``i mod len`` of every option list (see the module notes)."""
    if count < 1:
        raise ValueError("a sweep needs at least one variant")
    out = []
    for i in range(count):
        values = {name: options[i % len(options)] for name, options in _OPTIONS.items()}
        out.append(PhantomParameters(seed=1001 + i, tumour_diameter_mm=TUMOUR_MM, subvoxel_mm=SUBVOXEL_MM, **values))
    return out


def describe(params: PhantomParameters) -> str:
    """A short name of a variant's options, for tables."""
    parts = [f"seed {params.seed}", f"{params.volume_cm3:g} cm3", f"density {params.density:g}",
             f"SNR {params.snr:g}", f"bias {params.bias_strength:.0%}",
             "x".join(f"{s:g}" for s in params.spacing_mm) + " mm", f"skin {params.skin_thickness_mm:g} mm"]
    if params.gland_texture:
        parts.append(f"texture {params.gland_texture:g}")
    if params.tumour_site != "central":
        parts.append(f"tumour at {params.tumour_site}")
    if params.gland_on_muscle:
        parts.append("gland on muscle")
    if not params.thorax:
        parts.append("no thorax")
    return ", ".join(parts)

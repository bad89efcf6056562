"""Fixed, reproducible spreads of phantom variants for robustness sweeps (``breastbiomech bench
segment --sweep``, ``bench mesh --sweep``). Two families: ``anatomy``, every option of the
anatomy the default case does not make, crossed with image quality and voxel shape; ``tumour``,
irregular tumours (lobulated or spiculated, 10-20 mm, their T1 signal from well below the gland's
to near it) at the centre of dense glandular tissue, with and without interleaved fat, across
the same image qualities: the tumours a real breast MR holds, harder than the anatomy family's.

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
# the tumour family: dense gland (40-65 %), the tumour central in it; tumour_signal up to 350
# (0.83 of the gland's 420 at fat 1000: a contrast of 70 against noise of 25-67)
_TUMOUR_OPTIONS: dict[str, list] = {
    "tumour_shape": ["spiculated", "lobulated"],
    "tumour_diameter_mm": [15.0, 10.0, 20.0, 12.0, 18.0],
    "tumour_signal": [250.0, 320.0, 290.0, 350.0, 270.0, 335.0, 305.0],
    "density": [0.5, 0.65, 0.4, 0.55, 0.6, 0.45],
    "gland_texture": [0.0, 1.0, 0.5],
    "spacing_mm": [(1.0, 1.0, 2.5), (1.5, 1.5, 1.5), (0.8, 0.8, 3.0), (1.0, 1.0, 2.0)],
    "snr": [30.0, 20.0, 40.0, 25.0, 15.0, 35.0, 18.0],
    "bias_strength": [0.2, 0.35, 0.0, 0.1, 0.3],
    "volume_cm3": [500.0, 700.0, 450.0, 600.0, 800.0],
}
FAMILIES = ("anatomy", "tumour")
TUMOUR_MM = 12.0
SUBVOXEL_MM = 0.7  # 1.5 mm voxels drawn on 4 sub-voxels per axis, not 2: with 2, many truth voxels tie at half
DEFAULT_COUNT = 24


def sweep_variants(count: int = DEFAULT_COUNT, family: str = "anatomy") -> list[PhantomParameters]:
    """``count`` phantom variants of ``family`` (:data:`FAMILIES`), variant ``i`` taking value
    ``i mod len`` of every option list (see the module notes); sub-voxels of at most 0.7 mm.
    ``anatomy``: seeds 1001..., each with a 12 mm tumour; ``tumour``: seeds 3001..., the tumour
    central in the gland."""
    if count < 1:
        raise ValueError("a sweep needs at least one variant")
    if family not in FAMILIES:
        raise ValueError(f"unknown variant family {family!r}; the families are {', '.join(FAMILIES)}")
    options, seed, fixed = ((_OPTIONS, 1001, {"tumour_diameter_mm": TUMOUR_MM}) if family == "anatomy"
                            else (_TUMOUR_OPTIONS, 3001, {"tumour_site": "central"}))
    out = []
    for i in range(count):
        values = {name: values[i % len(values)] for name, values in options.items()}
        out.append(PhantomParameters(seed=seed + i, subvoxel_mm=SUBVOXEL_MM, **fixed, **values))
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
    if params.tumour_diameter_mm > 0:
        parts.append(f"{params.tumour_shape} {params.tumour_diameter_mm:g} mm tumour, signal {params.tumour_signal:g}")
    if params.gland_on_muscle:
        parts.append("gland on muscle")
    if not params.thorax:
        parts.append("no thorax")
    return ", ".join(parts)

"""Parameters of a synthetic breast MR case, and presets spanning the seed paper's Table 1.

All lengths in millimetres, volumes in cm^3, intensities in arbitrary MR units (fat = 1000).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

INTENSITY = {  # T1-weighted, non-fat-suppressed: fat bright, fibroglandular and muscle dark
    "air": 0.0,
    "fat": 1000.0,
    "glandular": 420.0,
    "muscle": 330.0,
    "tumour": 250.0,
    "skin": 560.0,
    "lung": 60.0,
    "rib": 650.0,
}

TUMOUR_SITES = ("central", "border")
TUMOUR_SHAPES = ("lobulated", "spiculated")


@dataclass
class PhantomParameters:
    """Everything that generates one case; the same parameters give the same case bit for bit."""

    seed: int = 1
    volume_cm3: float = 800.0          # breast tissue volume (fat + glandular + tumour + skin)
    density: float = 0.25              # glandular volume / breast volume
    tumour_diameter_mm: float = 0.0    # equivalent-sphere diameter; 0 = no tumour
    skin_thickness_mm: float = 1.5
    muscle_thickness_mm: float = 11.0  # pectoral muscle, mean thickness
    skin_separate: bool = False        # keep skin as its own label; by default folded into fat (seed 2.2.1)
    snr: float = 30.0                  # fat signal / noise standard deviation (Rician noise)
    bias_strength: float = 0.2         # multiplicative bias field spans 1 +- this over the breast and muscle
    spacing_mm: tuple[float, float, float] = (1.0, 1.0, 2.5)  # voxel size along L, P, S
    aspect_si: float = 0.9             # superior-inferior base radius / left-right base radius
    aspect_depth: float = 0.95         # anterior projection / left-right base radius (pendulous > 0.8)
    ptosis: float = 0.12               # inferior droop of the nipple, fraction of the depth
    margin_mm: float = 15.0            # field of view beyond the breast
    subvoxel_mm: float = 0.75          # largest edge of the sub-voxels the tissues are drawn on (voxel =
                                       # their average, truth label = their majority); 0.75 keeps every
                                       # earlier case; finer means fewer exact ties in the truth labels
    # anatomy the default case does not make (all off by default, so older cases stay bit for bit):
    gland_texture: float = 0.0         # 0-1: fat interleaved with the gland at ~1 mm and thin fibrous septa
                                       # (Cooper's ligaments) crossing the subcutaneous fat
    gland_on_muscle: bool = False      # glandular tissue lying on the pectoral fascia with no fat plane between
    tumour_site: str = "central"       # "central": inside the gland; "border": in mixed tissue, touching fat
    tumour_shape: str = "lobulated"    # "lobulated": smooth lobes; "spiculated": lobes with thin radiating spikes
    tumour_signal: float = 250.0       # the tumour's T1 signal (fat 1000, glandular 420): nearer the gland's, harder to see
    thorax: bool = True                # False: air behind the pectoral muscle, field of view ending just behind it
    extra: dict = field(default_factory=dict)  # free-form notes carried into parameters.json

    def __post_init__(self) -> None:
        self.spacing_mm = tuple(float(s) for s in self.spacing_mm)
        checks = [
            (400.0 <= self.volume_cm3 <= 1500.0, "volume_cm3 must lie in 400-1500 cm^3"),
            (0.05 <= self.density <= 0.65, "density (glandular fraction) must lie in 0.05-0.65"),
            (self.tumour_diameter_mm == 0 or 5.0 <= self.tumour_diameter_mm <= 30.0,
             "tumour_diameter_mm must be 0 (none) or 5-30 mm"),
            (0.0 <= self.skin_thickness_mm <= 3.0, "skin_thickness_mm must lie in 0-3 mm (0: no skin layer)"),
            (4.0 <= self.muscle_thickness_mm <= 25.0, "muscle_thickness_mm must lie in 4-25 mm"),
            (self.snr > 2.0, "snr must exceed 2"),
            (0.0 <= self.bias_strength <= 0.45, "bias_strength must lie in 0-0.45"),
            (len(self.spacing_mm) == 3 and all(0.3 <= s <= 4.0 for s in self.spacing_mm),
             "spacing_mm needs three voxel sizes of 0.3-4 mm"),
            (0.2 <= self.subvoxel_mm <= 1.0, "subvoxel_mm must lie in 0.2-1 mm"),
            (0.0 <= self.gland_texture <= 1.0, "gland_texture must lie in 0-1"),
            (self.tumour_site in TUMOUR_SITES, f"tumour_site must be one of {', '.join(TUMOUR_SITES)}"),
            (self.tumour_shape in TUMOUR_SHAPES, f"tumour_shape must be one of {', '.join(TUMOUR_SHAPES)}"),
            (100.0 <= self.tumour_signal <= 400.0,
             "tumour_signal must lie in 100-400 (fat 1000; the glandular tissue's 420 is the upper limit of a visible tumour)"),
            (isinstance(self.gland_on_muscle, bool) and isinstance(self.thorax, bool),
             "gland_on_muscle and thorax are true or false"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(f"phantom parameters: {message}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "PhantomParameters":
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown phantom parameters {sorted(unknown)}; known: {sorted(known)}")
        return cls(**values)


# The five cases of the seed's Table 1 (breast volume, tissue types); densities, tumour size and
# seeds are ours. Compression (19-50 %) is applied by the compressed-case generator.
TABLE1_CASES: dict[int, PhantomParameters] = {
    1: PhantomParameters(seed=101, volume_cm3=1364.0, density=0.18, tumour_diameter_mm=18.0),
    2: PhantomParameters(seed=102, volume_cm3=865.0, density=0.35),
    3: PhantomParameters(seed=103, volume_cm3=464.0, density=0.50, aspect_depth=0.85),
    4: PhantomParameters(seed=104, volume_cm3=1064.0, density=0.12, aspect_depth=1.05),
    5: PhantomParameters(seed=105, volume_cm3=716.0, density=0.28, ptosis=0.05),
}
TABLE1_COMPRESSION = {1: 0.319, 2: 0.389, 3: 0.400, 4: 0.504, 5: 0.194}
PRONE_GRAVITY = (0.0, -9.81, 0.0)  # m/s^2, LPS: the phantoms' posture, a prone MR scan (gravity anterior)


def table1_case(number: int) -> PhantomParameters:
    """A fresh copy of the preset for case ``number`` (1-5) of the seed's Table 1."""
    if number not in TABLE1_CASES:
        raise ValueError(f"case {number}: the presets are cases 1-5 of the seed's Table 1")
    return PhantomParameters.from_dict(TABLE1_CASES[number].to_dict())

"""Generate a synthetic prone breast MR case with ground truth.

The anatomy is evaluated on a fine grid (voxels split about 0.5 mm in-plane) and averaged into the
MR voxels, so the per-tissue fraction images are exact partial volumes of the analytic anatomy and
the MR intensities carry the same partial-volume mixing. A smooth multiplicative bias field and
Rician noise follow. All geometry in ITK physical space (LPS), millimetres.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from BreastBiomechLib import labels as lt
from BreastBiomechLib.landmarks import Landmarks
from BreastBiomechLib.phantom.anatomy import NIPPLE_RADIUS_MM, BreastAnatomy, DuctTree, tumour_phi_factory
from BreastBiomechLib.phantom.parameters import INTENSITY, PhantomParameters
from BreastBiomechLib.phantom.seeds import farthest_points
from BreastBiomechLib.timing import staged

# Fine-grid material codes: the truth tissues plus structures imaged but not modelled.
_LUNG, _RIB, _INTERCOSTAL, _SUBPECTORAL_FAT = 6, 7, 8, 9
_MATERIAL_INTENSITY = np.zeros(10, dtype=np.float32)
for _code, _name in [(1, "fat"), (2, "glandular"), (3, "muscle"), (4, "tumour"), (5, "skin"),
                     (_LUNG, "lung"), (_RIB, "rib"), (_INTERCOSTAL, "muscle"), (_SUBPECTORAL_FAT, "fat")]:
    _MATERIAL_INTENSITY[_code] = INTENSITY[_name]
_FINE_MM = 0.6  # target fine-grid spacing
_SUBPECTORAL_FAT_MM = 2.0  # the thin fat plane between the pectoral muscle and the chest wall
# the body's implicit function is evaluated exactly within this distance (mm) of the surface: twice
# the deepest depth below the skin the phantom tests (8 mm), which covers gradients of the
# approximate distance up to 2 (1 for a true distance)
_EXACT_BAND_MM = 16.0


@dataclass
class PhantomCase:
    """One generated case. Images share one grid (LPS, mm)."""

    parameters: PhantomParameters
    image: sitk.Image                 # MR, float32, arbitrary units (fat about 1000)
    labels: sitk.Image                # uint8, values from the label table
    fractions: dict[str, sitk.Image]  # tissue name -> float32 volume fraction per voxel
    bias_field: sitk.Image            # float32 multiplicative field applied to the image
    landmarks: Landmarks              # 17: 12 internal, 4 skin fiducials, nipple
    summary: dict                     # measured volumes, density, tumour size, timing
    signal: sitk.Image | None = None  # the MR before bias and noise (float32), for deformed cases


class _Grid:
    """Voxel-centre coordinates of an axis-aligned grid, arrays ordered (z, y, x) as in SimpleITK."""

    def __init__(self, origin, spacing, size):
        self.origin = np.asarray(origin, float)
        self.spacing = np.asarray(spacing, float)
        self.size = np.asarray(size, int)  # (nx, ny, nz)

    def axes(self):
        return [self.origin[i] + self.spacing[i] * np.arange(self.size[i]) for i in range(3)]

    def broadcast(self, dtype=np.float64):
        x, y, z = (a.astype(dtype) for a in self.axes())
        return x[None, None, :], y[None, :, None], z[:, None, None]

    def box(self, centre, radius) -> tuple[slice, slice, slice]:
        """Index slices (z, y, x) of the voxels within ``radius`` mm (per axis) of ``centre``."""
        lo = np.floor((np.asarray(centre) - radius - self.origin) / self.spacing).astype(int)
        hi = np.ceil((np.asarray(centre) + radius - self.origin) / self.spacing).astype(int) + 1
        lo, hi = np.clip(lo, 0, self.size), np.clip(hi, 0, self.size)
        return slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0])

    def refined(self, factors):
        factors = np.asarray(factors, int)
        spacing = self.spacing / factors
        origin = self.origin - 0.5 * self.spacing + 0.5 * spacing
        return _Grid(origin, spacing, self.size * factors)

    def index_of(self, points):
        """Nearest voxel index (z, y, x) of LPS points, clipped to the grid."""
        ijk = np.rint((np.atleast_2d(points) - self.origin) / self.spacing).astype(int)
        ijk = np.clip(ijk, 0, self.size - 1)
        return ijk[:, 2], ijk[:, 1], ijk[:, 0]


def _block_mean(fine: np.ndarray, factors) -> np.ndarray:
    fx, fy, fz = factors
    nz, ny, nx = fine.shape[0] // fz, fine.shape[1] // fy, fine.shape[2] // fx
    return fine.reshape(nz, fz, ny, fy, nx, fx).mean(axis=(1, 3, 5), dtype=np.float64).astype(np.float32)


def _upsample2(coarse: np.ndarray, shape) -> np.ndarray:
    """Linear interpolation of a grid sampled at every second fine voxel back onto the fine grid."""
    out = coarse
    for axis, n in enumerate(shape):
        pos = np.arange(n) / 2.0
        i0 = np.minimum(np.floor(pos).astype(int), out.shape[axis] - 1)
        i1 = np.minimum(i0 + 1, out.shape[axis] - 1)
        w = (pos - i0).astype(np.float32)
        view = [None] * out.ndim
        view[axis] = slice(None)
        out = out.take(i0, axis=axis) * (1 - w[tuple(view)]) + out.take(i1, axis=axis) * w[tuple(view)]
    return out


def _body_phi_near_surface(anatomy: BreastAnatomy, xyz) -> np.ndarray:
    """The body's implicit function (float32, mm) on a fine grid given as broadcast coordinate
    arrays ``xyz`` (x, y, z; LPS mm): exact within :data:`_EXACT_BAND_MM` of the surface, elsewhere
    linearly interpolated from every second fine voxel per axis. Beyond the band the phantom reads
    only its sign (inside or not) and that the depth below the skin exceeds the deepest depth it
    tests (the gland's taper, 8 mm), so the result is the full evaluation's at a quarter of its
    cost on a Table 1 breast."""
    x, y, z = xyz
    coarse = anatomy.body_phi(x[..., ::2], y[:, ::2], z[::2]).astype(np.float32)
    phi = _upsample2(coarse, (z.shape[0], y.shape[1], x.shape[2]))
    k, j, i = np.nonzero(np.abs(phi) < _EXACT_BAND_MM)
    phi[k, j, i] = anatomy.body_phi(x[0, 0, i], y[0, j, 0], z[k, 0, 0])
    return phi


def _calibrated_anatomy(params: PhantomParameters, rng_state: int) -> BreastAnatomy:
    """Find the base radius whose breast tissue volume (anterior to the muscle) is the requested
    one, measured on a 1.5 mm grid; four fixed-point updates on volume ~ scale^3."""
    target = params.volume_cm3 * 1000.0
    scale = (target / (2.0 / 3.0 * np.pi * params.aspect_si * params.aspect_depth)) ** (1 / 3) * 0.9
    for _ in range(4):
        anatomy = BreastAnatomy(params, np.random.default_rng(rng_state), scale)
        lo, hi = anatomy.extent(params.margin_mm)  # the image's field of view: the chest layer counts
        step = 1.5
        grid = _Grid(lo, (step, step, step), np.ceil((hi - lo) / step).astype(int) + 1)
        x, y, z = grid.broadcast()
        # sub-voxel occupancy from the (near-distance) implicit values: unbiased on a coarse grid
        phi = anatomy.body_phi(x, y, z)
        gradient = np.sqrt(sum(g**2 for g in np.gradient(phi, step)))
        inside = np.clip(0.5 - phi / np.maximum(gradient, 0.3) / step, 0, 1) * np.clip(
            0.5 + (anatomy.muscle_front_y(x, z) - y) / step, 0, 1)
        volume = inside.sum() * step**3
        scale *= (target / volume) ** (1 / 3)
    return BreastAnatomy(params, np.random.default_rng(rng_state), scale)


def _smooth_noise(rng, shape, sigma_vox) -> np.ndarray:
    field = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), sigma_vox, mode="reflect")
    return field / (field.std() + 1e-12)


def _ray_to_surface(anatomy: BreastAnatomy, start, direction, reach=250.0) -> np.ndarray:
    """First point (LPS mm) where the body surface is crossed going from ``start`` (inside)."""
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    s = np.arange(0.0, reach, 0.05)
    pts = np.asarray(start)[None, :] + s[:, None] * direction[None, :]
    phi = anatomy.body_phi(pts[:, 0], pts[:, 1], pts[:, 2])
    k = int(np.argmax(phi > 0))
    if k == 0:
        raise RuntimeError("phantom: skin fiducial ray did not leave the body")
    t = phi[k - 1] / (phi[k - 1] - phi[k])
    return pts[k - 1] + t * (pts[k] - pts[k - 1])


@staged("phantom")
def generate_phantom(params: PhantomParameters | None = None,
                     progress: Callable[[float, str], None] | None = None) -> PhantomCase:
    """Generate the case described by ``params`` (deterministic in ``params.seed``).

    ``progress(fraction, message)`` is called as the stages finish (for progress bars)."""
    params = params or PhantomParameters()
    report = progress or (lambda fraction, message: None)
    started = time.perf_counter()
    report(0.0, "shaping the breast to the requested volume")
    rng = np.random.default_rng(params.seed)
    variant_rng = np.random.default_rng([params.seed, 27])  # the optional anatomy draws from its own stream
    anatomy = _calibrated_anatomy(params, params.seed)
    tree = anatomy.grow_duct_tree(rng)

    grid, factors, fine, half = _grids(anatomy, params)
    x, y, z = fine.broadcast(np.float32)  # float32 halves the memory traffic of the fine grid

    report(0.1, "body, skin, pectoral muscle and chest wall")
    # --- body, skin, muscle, thorax ------------------------------------------------------------
    phi = _body_phi_near_surface(anatomy, (x, y, z))
    gz, gy, gx = np.gradient(phi, *fine.spacing[::-1])
    depth = -phi / np.maximum(np.sqrt(gx**2 + gy**2 + gz**2), 0.3)  # mm below the skin surface
    del gx, gy, gz
    body = phi < 0
    front = anatomy.muscle_front_y(x, z)
    back = front + anatomy.muscle_thickness(x, z)
    material = np.zeros(phi.shape, dtype=np.uint8)
    breast = body & (y < front)
    material[breast] = 1
    material[body & (y >= front) & (y < back)] = 3
    thorax = body & (y >= back)
    wall = back + _SUBPECTORAL_FAT_MM  # front of the chest wall (ribs and intercostal muscle)
    rib_centre_y = wall + 7.0
    rib_phase = np.mod(z - anatomy.b * 0.37, 24.0) - 12.0
    rib = thorax & ((y - rib_centre_y) ** 2 + rib_phase**2 < 5.5**2)
    material[thorax] = _LUNG
    material[thorax & (y < wall + 14.0)] = _INTERCOSTAL
    material[rib] = _RIB
    material[thorax & (y < wall)] = _SUBPECTORAL_FAT
    if not params.thorax:
        material[thorax] = 0  # nothing imaged behind the muscle, as in the compressed scans
    skin = body & (depth < params.skin_thickness_mm) & (y < back)
    material[skin] = 5
    nip_base, nip_tip = anatomy.nipple_axis()
    nipple = np.zeros_like(body)
    around = fine.box((nip_base + nip_tip) / 2, np.linalg.norm(nip_tip - nip_base) / 2 + NIPPLE_RADIUS_MM + 1.0)
    nipple[around] = anatomy.nipple_phi(x[..., around[2]], y[:, around[1]], z[around[0]]) < 0.5  # none beyond
    nipple &= body & (y < nip_base[1])
    material[nipple] = 5

    # --- tumour in the gland (a tumour at a fat/gland border is placed once the gland exists) ---
    tumour_centre = None
    if params.tumour_diameter_mm > 0 and params.tumour_site == "central":
        depth_frac = rng.uniform(0.35, 0.55)
        tumour_centre = np.array([rng.uniform(-0.25, 0.25) * anatomy.a, -depth_frac * anatomy.d,
                                  rng.uniform(-0.2, 0.2) * anatomy.b - anatomy.droop * depth_frac**2])
        _paint_tumour(material, breast & ~skin, fine, (x, y, z), tumour_centre, params.tumour_diameter_mm, rng,
                      params.tumour_shape)

    report(0.4, "fibroglandular tissue")
    # --- fibroglandular tissue: duct tree + lobules, blurred, thresholded to the density -------
    ducts = np.zeros(half.size[::-1], dtype=np.float32)
    lobules = np.zeros_like(ducts)
    for i in np.flatnonzero(tree.parent >= 0):
        a, b = tree.nodes[tree.parent[i]], tree.nodes[i]
        n = max(2, int(np.linalg.norm(b - a) / 0.5))
        pts = a + np.linspace(0, 1, n)[:, None] * (b - a)
        np.add.at(ducts, half.index_of(pts), 1.0 / (1 + tree.generation[i]))
    # lobules (terminal duct lobular units) cluster around duct ends and side branches
    anchors = tree.nodes[tree.terminal | (tree.generation >= 1)]
    clusters = np.repeat(anchors, 8, axis=0) + rng.normal(0.0, 4.0, (8 * len(anchors), 3))
    np.add.at(lobules, half.index_of(clusters), rng.uniform(0.5, 1.5, len(clusters)))

    def sig(mm):  # a length in mm as Gaussian sigmas in half-grid voxels (z, y, x)
        return mm / half.spacing[::-1]

    field = (ndimage.gaussian_filter(ducts, sig(1.2)) + ndimage.gaussian_filter(lobules, sig(2.0))
             + 0.5 * ndimage.gaussian_filter(lobules, sig(9.0)))
    # log-domain texture: fat lobules interleaved with glandular tissue at a few millimetres
    gland = np.log(field + 1e-4 * field.max()) + 0.9 * _smooth_noise(rng, field.shape, sig(2.5))
    if params.gland_texture > 0:  # fat interleaved with the gland at about a millimetre
        gland += 1.2 * params.gland_texture * _smooth_noise(variant_rng, field.shape, sig(0.6))
    gland -= gland.min()
    del field
    gland = _upsample2(gland, phi.shape)
    clear_of_muscle = np.clip((front - y - 2.0) / 6.0, 0, 1)
    if params.gland_on_muscle:
        on_fascia = _gland_on_fascia(anatomy, (x, y, z), front, variant_rng)
        clear_of_muscle[on_fascia] = 1.0
        gland[on_fascia] = gland.max()
        del on_fascia
    gland *= np.clip((depth - 2.0) / 6.0, 0, 1) * clear_of_muscle
    del clear_of_muscle
    if params.gland_texture > 0:
        material[(material == 1) & _ligaments(half, (x, y, z), phi.shape, depth, front, params, variant_rng)] = 2
    candidate = material == 1
    n_breast = int(np.count_nonzero(np.isin(material, (1, 2, 4, 5))))
    n_gland = int(round(params.density * n_breast)) - int(np.count_nonzero(material == 2))
    values = gland[candidate]
    if n_gland >= np.count_nonzero(values > 0):
        raise ValueError(
            f"phantom: a glandular density of {params.density:.2f} does not fit this breast shape; "
            "lower the density or raise the volume"
        )
    threshold = np.partition(values, len(values) - n_gland)[len(values) - n_gland]
    material[candidate & (gland >= threshold)] = 2
    del gland, values
    if params.tumour_diameter_mm > 0 and params.tumour_site == "border":
        tumour_centre = _border_site(material, grid, factors, params.tumour_diameter_mm, variant_rng)
        _paint_tumour(material, breast & ~skin, fine, (x, y, z), tumour_centre, params.tumour_diameter_mm,
                      variant_rng, params.tumour_shape)

    report(0.7, "partial-volume truth images")
    # --- truth images ----------------------------------------------------------------------------
    fractions = {t.name: _block_mean(material == t.label, factors) for t in lt.TISSUES}
    if not params.skin_separate:
        fractions["fat"] = fractions["fat"] + fractions.pop("skin")
    names = list(fractions)
    stack = np.stack([fractions[n] for n in names])
    label_values = np.array([lt.tissue(n).label for n in names], dtype=np.uint8)
    tissue_total = stack.sum(axis=0)
    labels = np.where(tissue_total >= 0.5, label_values[np.argmax(stack, axis=0)], 0).astype(np.uint8)

    report(0.8, "MR signal, bias field and noise")
    # --- MR signal: partial-volume mix, texture, bias, Rician noise ----------------------------
    texture = _upsample2(_smooth_noise(rng, half.size[::-1], sig(1.5)), phi.shape)
    levels = _MATERIAL_INTENSITY.copy()
    levels[4] = params.tumour_signal
    signal = _block_mean(levels[material] * (1.0 + 0.035 * texture), factors)
    del texture, phi, depth
    bias = _bias_field(grid, labels > 0, params.bias_strength, rng)
    sigma = INTENSITY["fat"] / params.snr
    noisy = np.sqrt((signal * bias + sigma * rng.standard_normal(signal.shape)) ** 2
                    + (sigma * rng.standard_normal(signal.shape)) ** 2).astype(np.float32)

    report(0.95, "landmarks")
    # --- landmarks -------------------------------------------------------------------------------
    landmarks = _landmarks(anatomy, tree, material, fine, tumour_centre, rng)

    case = _phantom_case(params, grid, fractions, labels, noisy, bias, signal, landmarks, summary={
        "base_radius_mm": float(anatomy.a), "duct_tree_nodes": int(len(tree.nodes)),
        "seconds": round(time.perf_counter() - started, 2)})
    report(1.0, "done")
    return case


def _grids(anatomy, params: PhantomParameters) -> tuple:
    """The image grid over the anatomy's extent (``params.spacing_mm``), its per-axis refinement
    factors (even, fine voxels at most ``params.subvoxel_mm``), the fine grid the anatomy is
    painted on and the half-resolution grid of the gland's fields."""
    spacing = np.array(params.spacing_mm)
    lo, hi = anatomy.extent(params.margin_mm)
    size = np.ceil((hi - lo) / spacing).astype(int) + 1
    grid = _Grid(lo, spacing, size)
    factors = np.maximum(1, np.rint(spacing / _FINE_MM)).astype(int)
    factors += factors % 2  # even, so the half-resolution grid below lands on fine voxels
    while np.any(spacing / factors > params.subvoxel_mm):
        factors[spacing / factors > params.subvoxel_mm] += 2
    fine = grid.refined(factors)
    return grid, factors, fine, _Grid(fine.origin, fine.spacing * 2, (fine.size + 1) // 2)


def _phantom_case(params: PhantomParameters, grid, fractions: dict, labels, noisy, bias, signal, landmarks,
                  summary: dict) -> PhantomCase:
    """The :class:`PhantomCase` of the generated arrays (z, y, x) on ``grid``, with its summary
    (volumes in cm^3, glandular density, the tumour's equivalent diameter in mm, the grid, and the
    entries of ``summary``)."""

    def to_image(array, pixel=None):
        img = sitk.GetImageFromArray(array if pixel is None else array.astype(pixel))
        img.SetOrigin(tuple(grid.origin))
        img.SetSpacing(tuple(grid.spacing))
        return img

    voxel_cm3 = float(np.prod(grid.spacing)) / 1000.0
    volumes = {n: float(f.sum() * voxel_cm3) for n, f in fractions.items()}
    breast_cm3 = sum(v for n, v in volumes.items() if n != "muscle")
    seconds = summary.pop("seconds")
    summary = {
        "breast_volume_cm3": breast_cm3,
        "tissue_volumes_cm3": volumes,
        "glandular_density": volumes["glandular"] / breast_cm3,
        "tumour_equivalent_diameter_mm": float((6 * volumes["tumour"] * 1000 / np.pi) ** (1 / 3)),
        "size_voxels": [int(s) for s in grid.size],
        "spacing_mm": [float(s) for s in grid.spacing],
        **summary,
        "seconds": seconds,
    }
    return PhantomCase(
        parameters=params,
        image=to_image(noisy),
        labels=to_image(labels),
        fractions={n: to_image(f) for n, f in fractions.items()},
        bias_field=to_image(bias.astype(np.float32)),
        landmarks=landmarks,
        summary=summary,
        signal=to_image(signal.astype(np.float32)),
    )


def _paint_tumour(material: np.ndarray, allowed: np.ndarray, fine: _Grid, xyz, centre: np.ndarray,
                  diameter_mm: float, rng, shape: str = "lobulated") -> None:
    """Mark (code 4) the fine voxels of ``allowed`` inside a lobulated (or spiculated: ``shape``)
    tumour around ``centre`` (LPS mm) whose equivalent-sphere diameter is ``diameter_mm``
    (calibrated on a 0.25 mm grid, spicules included)."""
    base_phi = tumour_phi_factory(centre, diameter_mm / 2, rng, spicules=shape == "spiculated")
    reach = diameter_mm * (1.25 if shape == "spiculated" else 1.0)
    ax = np.arange(-reach, reach, 0.25)
    vol = (base_phi(centre[0] + ax[None, None, :], centre[1] + ax[None, :, None],
                    centre[2] + ax[:, None, None]) < 0).sum() * 0.25**3
    shrink = (np.pi / 6 * diameter_mm**3 / vol) ** (1 / 3)

    def phi(x_, y_, z_):
        return base_phi(centre[0] + (x_ - centre[0]) / shrink, centre[1] + (y_ - centre[1]) / shrink,
                        centre[2] + (z_ - centre[2]) / shrink) * shrink

    x, y, z = xyz
    box = fine.box(centre, diameter_mm * (2.0 if shape == "spiculated" else 1.5))
    zs, ys, xs = box
    inside = allowed[box] & (phi(x[..., xs], y[:, ys, :], z[zs]) < 0)
    material[box][inside] = 4


def _border_site(material: np.ndarray, grid: _Grid, factors, diameter_mm: float, rng) -> np.ndarray:
    """A tumour centre (LPS mm) where fat and gland mix about evenly within the tumour's radius
    (so it sits in mixed tissue and touches fat on one side), at least 4 mm clear of the skin
    and the muscle."""
    radius = diameter_mm / 2
    breast = _block_mean(np.isin(material, (1, 2)), factors) > 0.5
    gland = _block_mean(material == 2, factors)
    spacing = grid.spacing[::-1]
    share = ndimage.gaussian_filter(gland, radius / spacing) / np.maximum(
        ndimage.gaussian_filter(breast.astype(np.float32), radius / spacing), 1e-3)
    clear = ndimage.distance_transform_edt(breast, sampling=spacing) > radius + 4.0
    candidates = np.argwhere(clear & (share > 0.35) & (share < 0.65))
    if len(candidates) == 0:
        raise ValueError("phantom: no fat/gland border deep enough for a tumour of "
                         f"{diameter_mm:g} mm; make it smaller or use tumour_site='central'")
    k, j, i = candidates[int(rng.integers(len(candidates)))]
    return grid.origin + grid.spacing * np.array([i, j, k])


def _gland_on_fascia(anatomy: BreastAnatomy, xyz, front, rng) -> np.ndarray:
    """Fine voxels of a glandular slab 5 mm thick lying on the pectoral fascia (no retromammary
    fat plane) over a patch of the breast base about 0.9 x its radius across."""
    x, y, z = xyz
    cx, cz = rng.uniform(-0.2, 0.2) * anatomy.a, rng.uniform(-0.2, 0.2) * anatomy.b
    patch = ((x - cx) / (0.45 * anatomy.a)) ** 2 + ((z - cz) / (0.45 * anatomy.b)) ** 2 < 1.0
    gap = front - y
    return patch & (gap > 0) & (gap < 5.0)


def _ligaments(half: _Grid, xyz, shape, depth, front, params: PhantomParameters, rng) -> np.ndarray:
    """Cooper's ligaments: fibrous septa about 0.6 mm thick (the zero level of a smooth random
    field at 8 mm, spaced about a centimetre apart) crossing the fat between the skin and the
    muscle; ``gland_texture`` sets the share of that level set kept."""
    field = _smooth_noise(rng, half.size[::-1], 8.0 / half.spacing[::-1])
    gradient = np.sqrt(sum(g**2 for g in np.gradient(field, *half.spacing[::-1])))
    distance = _upsample2(np.abs(field) / np.maximum(gradient, 1e-6), shape)  # mm to the zero level
    keep = _upsample2(_smooth_noise(rng, half.size[::-1], 12.0 / half.spacing[::-1]), shape)
    x, y, z = xyz
    return ((distance < 0.3) & (keep < np.quantile(keep[::7, ::7, ::7], params.gland_texture))
            & (depth > params.skin_thickness_mm) & (front - y > 1.0))


def _bias_field(grid: _Grid, body: np.ndarray, strength: float, rng) -> np.ndarray:
    """Smooth multiplicative field 1 + strength * f, f a random 2nd-order polynomial in the
    normalised coordinates scaled so that it spans exactly [-1, 1] over the modelled tissues."""
    x, y, z = grid.broadcast()
    u = [(c - c.mean()) / (np.ptp(c) / 2 + 1e-9) for c in (x, y, z)]
    terms = [u[0], u[1], u[2], u[0] * u[1], u[1] * u[2], u[0] * u[2], u[0] ** 2, u[1] ** 2, u[2] ** 2]
    coef = rng.normal(size=len(terms)) * np.array([1, 1, 1, 0.6, 0.6, 0.6, 0.5, 0.5, 0.5])
    f = sum(c * t for c, t in zip(coef, terms))
    f = np.broadcast_to(f, body.shape).astype(np.float64)
    inside = f[body]
    lo, hi = inside.min(), inside.max()
    f = 2.0 * (f - lo) / (hi - lo) - 1.0
    return 1.0 + strength * f


def _landmarks(anatomy: BreastAnatomy, tree: DuctTree, material, fine: _Grid, tumour_centre, rng) -> Landmarks:
    """17 landmarks as in the seed: 12 internal at tissue features, 4 skin fiducials, nipple."""
    positions, labels, descriptions = [], [], []

    def add(p, label, text):
        positions.append(np.asarray(p, float))
        labels.append(label)
        descriptions.append(text)

    internal = []
    if tumour_centre is not None:
        internal.append((tumour_centre, "tumour centre"))
    for sx in (-0.45, 0.45):
        xz = np.array([sx * anatomy.a, 0.15 * anatomy.b])
        p = np.array([xz[0], anatomy.muscle_front_y(xz[0], xz[1]), xz[1]])
        internal.append((p, "pectoral fascia below the breast base"))
    in_gland = material[fine.index_of(tree.nodes)] == 2
    branch = np.intersect1d(tree.branch_points, np.flatnonzero(in_gland))
    lobule = np.flatnonzero(tree.terminal & in_gland)
    pool = np.concatenate([branch, lobule])
    kinds = ["duct branching"] * len(branch) + ["lobule centre"] * len(lobule)
    need = 12 - len(internal)
    if len(pool) < need:
        raise RuntimeError("phantom: too few glandular features for 12 internal landmarks; raise the density")
    chosen = farthest_points(tree.nodes[pool], need, np.array([p for p, _ in internal]))
    internal += [(tree.nodes[pool[k]], kinds[k]) for k in chosen]
    for i, (p, text) in enumerate(internal, start=1):
        add(p, f"L{i:02d}", text)

    mid = np.array([0.0, -0.45 * anatomy.d, -anatomy.droop * 0.2])
    for i, (name, direction) in enumerate(
        [("medial", (-1, 0, 0)), ("lateral", (1, 0, 0)), ("superior", (0, 0, 1)), ("inferior", (0, 0, -1))],
        start=1,
    ):
        add(_ray_to_surface(anatomy, mid, direction), f"F{i}", f"skin fiducial, {name}")
    _, tip = anatomy.nipple_axis()
    add(_ray_to_surface(anatomy, tip, (0, -1, 0)), "nipple", "nipple tip")
    return Landmarks(np.array(positions), labels, descriptions)

"""Analytic anatomy of a prone breast: implicit surfaces for the body, pectoral muscle, nipple and
tumour, and the branching fibroglandular duct tree.

Frame: ITK physical space (LPS), millimetres. The breast base centre sits at the origin on the
anterior surface of the pectoral muscle; the breast points anteriorly (-y, prone: the direction
gravity pulls), the chest wall curves posteriorly (+y) away from the sternum (-x, a left breast).
Implicit functions are negative inside; they approximate signed distances near their zero level.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BreastBiomechLib.phantom.parameters import PhantomParameters

CHEST_LAYER_MM = 3.0   # skin + subcutaneous fat covering the pectoral muscle outside the breast base
NIPPLE_RADIUS_MM = 5.0
NIPPLE_LENGTH_MM = 6.0
THORAXLESS_MARGIN_MM = 3.0  # field of view behind the muscle's most posterior corner when no thorax is imaged


def smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (smooth union of implicit solids) with blend radius ``k`` mm."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


@dataclass
class DuctTree:
    """Ducts from the nipple towards the chest wall: node positions (LPS mm), parent index
    (-1 at roots), generation (0 = main duct) and whether a node ends in a lobule."""

    nodes: np.ndarray
    parent: np.ndarray
    generation: np.ndarray
    terminal: np.ndarray

    @property
    def branch_points(self) -> np.ndarray:
        counts = np.bincount(self.parent[self.parent >= 0], minlength=len(self.nodes))
        return np.flatnonzero(counts >= 2)


class BreastAnatomy:
    """The analytic shape of one case; ``scale`` (mm) sets the left-right base radius."""

    def __init__(self, params: PhantomParameters, rng: np.random.Generator, scale: float):
        self.params = params
        self.a = scale                                # left-right base radius
        self.b = scale * params.aspect_si             # superior-inferior base radius
        self.d = scale * params.aspect_depth          # anterior projection
        self.droop = params.ptosis * self.d           # inferior shift of the nipple
        self.sternum_x = -0.3 * scale
        self.chest_radius_x = 3.0 * scale
        self.chest_radius_z = 6.0 * scale
        self.lobes = rng.normal(0.0, 0.035, size=(3, 2))  # angular shape harmonics k = 2, 3, 4
        self.fullness = 0.10 + 0.05 * rng.random()        # pendulous widening at mid-depth

    # --- surfaces -----------------------------------------------------------------------------
    def muscle_front_y(self, x, z):
        """y (mm) of the anterior pectoral surface (the pectoral fascia) at (x, z)."""
        return ((x - self.sternum_x) ** 2 - self.sternum_x**2) / (2 * self.chest_radius_x) + z**2 / (
            2 * self.chest_radius_z
        )

    def muscle_thickness(self, x, z):
        """Pectoral muscle thickness (mm): thicker medially and superiorly."""
        t = self.params.muscle_thickness_mm
        return t * (1.0 - 0.3 * np.tanh(x / self.a)) * (1.0 + 0.15 * np.tanh(z / self.b))

    def breast_phi(self, x, y, z):
        """Implicit breast mound (ellipsoidal, pendulous, slightly lobed), approx. mm."""
        t = -y / self.d
        tc = np.clip(t, 0.0, 1.0)
        ux = x / self.a
        uz = (z + self.droop * tc**2) / self.b
        theta = np.arctan2(uz, ux)
        lobed = 1.0
        for k, (c, s) in enumerate(self.lobes, start=2):
            lobed = lobed + c * np.cos(k * theta) + s * np.sin(k * theta)
        width = lobed * (1.0 + self.fullness * 4.0 * tc * (1.0 - tc))
        radial = (ux**2 + uz**2) / width**2
        f = radial + np.where(t > 0.0, t, 0.0) ** 2
        scale = (self.a * self.b * self.d) ** (1.0 / 3.0)
        return (np.sqrt(f) - 1.0) * scale

    def nipple_axis(self) -> tuple[np.ndarray, np.ndarray]:
        """Base and tip (LPS mm) of the nipple's central segment."""
        base = np.array([0.0, -self.d + 2.0, -self.droop])
        tip = np.array([0.0, -self.d - NIPPLE_LENGTH_MM + NIPPLE_RADIUS_MM, -self.droop])
        return base, tip

    def nipple_phi(self, x, y, z):
        base, tip = self.nipple_axis()
        ab = tip - base
        s = np.clip(((x - base[0]) * ab[0] + (y - base[1]) * ab[1] + (z - base[2]) * ab[2]) / (ab @ ab), 0, 1)
        dx, dy, dz = x - base[0] - s * ab[0], y - base[1] - s * ab[1], z - base[2] - s * ab[2]
        return np.sqrt(dx**2 + dy**2 + dz**2) - NIPPLE_RADIUS_MM

    def body_phi(self, x, y, z):
        """Implicit body (breast mound, nipple and chest), approx. signed distance in mm."""
        chest = (self.muscle_front_y(x, z) - CHEST_LAYER_MM) - y
        phi = smooth_min(self.breast_phi(x, y, z), chest, 12.0)
        return smooth_min(phi, self.nipple_phi(x, y, z), 3.0)

    def extent(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box (LPS mm, low and high corners) holding the breast with ``margin`` and
        the chest wall behind its base (beyond the base the chest may leave the field of view);
        without a thorax the box ends a few millimetres behind the muscle."""
        lo_x, hi_x = -self.a * 1.15 - margin, self.a * 1.15 + margin
        lo_z, hi_z = -self.b * 1.15 - self.droop - margin, self.b * 1.15 + margin
        lo_y = -self.d - NIPPLE_LENGTH_MM - margin
        corners_x, corners_z = np.meshgrid([-self.a, self.a, self.sternum_x], [-self.b, self.b, 0.0])
        back = self.muscle_front_y(corners_x, corners_z) + self.muscle_thickness(corners_x, corners_z)
        hi_y = float(back.max()) + (22.0 if self.params.thorax else THORAXLESS_MARGIN_MM)
        return np.array([lo_x, lo_y, lo_z]), np.array([hi_x, hi_y, hi_z])

    # --- ducts --------------------------------------------------------------------------------
    def grow_duct_tree(self, rng: np.random.Generator) -> DuctTree:
        """Main ducts from behind the nipple branch towards the chest wall and end in lobules."""
        base, _ = self.nipple_axis()
        start = base + np.array([0.0, 4.0, 0.0])
        nodes, parent, generation, terminal = [], [], [], []
        n_ducts = int(rng.integers(11, 16))
        stack = []
        for i in range(n_ducts):
            angle = 2 * np.pi * (i + rng.random() * 0.6) / n_ducts
            spread = np.radians(rng.uniform(35.0, 65.0))
            direction = np.array([np.sin(spread) * np.cos(angle), np.cos(spread), np.sin(spread) * np.sin(angle)])
            nodes.append(start.copy())
            parent.append(-1)
            generation.append(0)
            terminal.append(False)
            stack.append((len(nodes) - 1, direction, 0))
        step = 0.09 * self.d
        while stack:
            index, direction, gen = stack.pop()
            position = nodes[index]
            for _ in range(int(rng.integers(2, 4))):
                direction = direction + rng.normal(0.0, 0.25, 3)
                direction[1] = abs(direction[1]) * 0.8 + 0.2  # keep heading posteriorly
                direction /= np.linalg.norm(direction)
                candidate = position + step * direction
                inside = self.breast_phi(*candidate) < -6.0
                clear_of_muscle = candidate[1] < self.muscle_front_y(candidate[0], candidate[2]) - 10.0
                if not (inside and clear_of_muscle):
                    break
                nodes.append(candidate)
                parent.append(index)
                generation.append(gen)
                terminal.append(False)
                index, position = len(nodes) - 1, candidate
            if gen < 3 and rng.random() < 0.75:
                for sign in (-1.0, 1.0):
                    kick = np.cross(direction, rng.normal(size=3))
                    kick /= np.linalg.norm(kick) + 1e-12
                    stack.append((index, direction + sign * 0.6 * kick, gen + 1))
            else:
                terminal[index] = True
        return DuctTree(np.array(nodes), np.array(parent), np.array(generation), np.array(terminal))


def tumour_phi_factory(centre: np.ndarray, radius: float, rng: np.random.Generator, spicules: bool = False):
    """An irregular, lobulated mass: a smooth union of offset spheres around ``centre``; with
    ``spicules``, also 8-14 tapering spikes radiating from it (base radius 1.2-2 mm, tip 0.5 mm,
    reaching 1.1-1.9 x ``radius`` from the centre), as a spiculated carcinoma's strands into the
    surrounding tissue, thick enough to hold whole voxels of an MR at 1-1.5 mm.

    Returns ``phi(x, y, z)`` (approx. mm; < 0 inside)."""
    n = int(rng.integers(4, 7))
    offsets = rng.normal(size=(n, 3))
    offsets /= np.linalg.norm(offsets, axis=1, keepdims=True)
    offsets *= radius * rng.uniform(0.25, 0.45, size=(n, 1))
    radii = radius * rng.uniform(0.55, 0.75, size=n)
    spikes = _spicules(radius, rng) if spicules else []

    def phi(x, y, z):
        out = np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2) - 0.6 * radius
        for o, r in zip(offsets, radii):
            c = centre + o
            lobe = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) - r
            out = smooth_min(out, lobe, 0.25 * radius)
        for direction, length, base in spikes:
            out = np.minimum(out, _tapered_segment(x - centre[0], y - centre[1], z - centre[2], direction,
                                                   length, base, 0.5))
        return out

    return phi


def _spicules(radius: float, rng: np.random.Generator) -> list:
    """Directions (unit), lengths from the centre (mm) and base radii (mm) of a tumour's spicules."""
    count = int(rng.integers(8, 15))
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    lengths = radius * rng.uniform(1.1, 1.9, size=count)
    bases = rng.uniform(1.2, 2.0, size=count)
    return list(zip(directions, lengths, bases))


def _tapered_segment(x, y, z, direction: np.ndarray, length: float, base: float, tip: float):
    """Approximate distance (mm; < 0 inside) to a spike along ``direction`` from the origin to
    ``length``, its radius falling linearly from ``base`` to ``tip``."""
    t = np.clip(x * direction[0] + y * direction[1] + z * direction[2], 0.0, length)
    gap = np.sqrt((x - t * direction[0]) ** 2 + (y - t * direction[1]) ** 2 + (z - t * direction[2]) ** 2)
    return gap - (base + (tip - base) * t / length)

"""The finite-element model the solver runs: mesh + element materials + loading.

Inputs in the library's units: node positions and displacements in millimetres (LPS), moduli in
pascal, density kg/m^3, time in seconds, gravity in m/s^2. The solver converts to SI.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.materials import ElementMaterials

FORMULATIONS = ("T4ANP", "T4")
LOAD_SHAPES = ("POLY345", "RAMP", "STEP", "RAMPHOLD", "HILLY")  # NiftySim's load curves, see kernels.load_factor
PENETRATION_TOLERANCE_MM = 1e-3  # slave nodes may start this far behind a plate (round-off)


@dataclass
class PlateEdge:
    """Where a plate's flat face ends: at ``distance`` (mm) from the plate's ``point`` along the
    in-plane unit vector ``direction``, with a rounded edge of ``radius`` (mm) that curves away
    from the tissue (a convex fillet whose centre lies ``radius`` behind the face). Beyond the
    fillet the plate has ended: tissue there is free. A real plate's edge is rounded; a knife
    edge would push the contact nodes in by the full travel next to free nodes, a step that
    inverts the elements between them at large compression."""

    direction: np.ndarray
    distance: float
    radius: float

    def __post_init__(self) -> None:
        direction = np.asarray(self.direction, float).reshape(3)
        norm = np.linalg.norm(direction)
        if norm == 0:
            raise ValueError("a plate edge needs a non-zero in-plane direction")
        self.direction = direction / norm
        self.distance = float(self.distance)
        self.radius = float(self.radius)
        if not self.radius > 0:
            raise ValueError(f"a plate edge's radius must be positive (mm), not {self.radius}")

    def to_dict(self) -> dict:
        return {"direction": self.direction.tolist(), "distance": self.distance, "radius": self.radius}


@dataclass
class Plate:
    """A rigid planar plate in contact with the tissue, frictionless or with Coulomb friction.

    ``point`` (mm) lies on the plate at t = 0 and ``normal`` (unit) points towards the tissue:
    slave nodes are kept on the side ``(x - point) . normal >= 0``. The plate translates by
    ``displacement`` (mm) over the loading with the load curve. ``slave_nodes`` are the node ids
    that may touch it (e.g. the skin surface nodes). ``edge``: where the plate ends, with a
    rounded edge (:class:`PlateEdge`); None: the plate is unbounded. ``friction``: the Coulomb
    coefficient mu (>= 0; 0: frictionless; skin on plastic is about 0.2-1, dry skin ~0.5): a
    contact node sticks to the plate while the tangential force it needs is within mu times its
    normal force, and slips otherwise (:func:`BreastBiomechLib.solver.kernels.touch_plate`)."""

    point: np.ndarray
    normal: np.ndarray
    displacement: np.ndarray
    slave_nodes: np.ndarray
    name: str = "plate"
    edge: PlateEdge | None = None
    friction: float = 0.0

    def __post_init__(self) -> None:
        self.point = np.asarray(self.point, float).reshape(3)
        normal = np.asarray(self.normal, float).reshape(3)
        norm = np.linalg.norm(normal)
        if not np.all(np.isfinite(self.point)) or not np.all(np.isfinite(normal)):
            raise ValueError(f"plate {self.name!r}: its point and normal must be finite numbers (mm)")
        if norm == 0:
            raise ValueError(f"plate {self.name!r}: the normal must not be zero")
        self.normal = normal / norm
        self.displacement = np.asarray(self.displacement, float).reshape(3)
        if not np.all(np.isfinite(self.displacement)):
            raise ValueError(f"plate {self.name!r}: its displacement must be finite (mm)")
        self.friction = float(self.friction)
        if not (np.isfinite(self.friction) and self.friction >= 0):
            raise ValueError(f"plate {self.name!r}: the friction coefficient must be a finite number >= 0 "
                             f"(0: frictionless; skin on plastic is about 0.2-1), not {self.friction}")
        self.slave_nodes = np.unique(np.asarray(self.slave_nodes, dtype=np.int64).ravel())
        if self.edge is not None and abs(self.edge.direction @ self.normal) > 1e-6:
            raise ValueError(f"plate {self.name!r}: its edge direction must lie in the plate's plane "
                             "(perpendicular to the normal)")

    def gaps(self, positions_mm: np.ndarray) -> np.ndarray:
        """Signed distances (mm) of points from the plate's surface at the start, > 0 on the
        tissue side (beyond a rounded edge: from the fillet, positive past the plate's end)."""
        rel = np.asarray(positions_mm, float).reshape(-1, 3) - self.point
        gap = rel @ self.normal
        if self.edge is None:
            return gap
        past = rel @ self.edge.direction - self.edge.distance
        radius = self.edge.radius
        fillet = np.hypot(past, gap + radius) - radius
        return np.where(past <= 0, gap, np.where(gap > -radius, fillet, np.inf))

    def check_clear_of(self, positions_mm: np.ndarray) -> None:
        """Raise a ValueError naming the fix when any of the points (mm) starts behind the plate
        by more than the round-off tolerance, i.e. the plate cuts into the tissue."""
        gap = self.gaps(positions_mm)
        if len(gap) and gap.min() < -PENETRATION_TOLERANCE_MM:
            raise ValueError(
                f"plate {self.name!r} cuts into the tissue at the start: {int(np.sum(gap < -PENETRATION_TOLERANCE_MM))} "
                f"of its contact nodes lie behind it, up to {-gap.min():.2f} mm; move it {-gap.min():.2f} mm "
                "along its normal so that it just touches the skin, and check that the normal points "
                "towards the tissue")


@dataclass
class Constraint:
    """Prescribed displacement components: node ids, a (K, 3) mask of constrained components and
    their final values (mm, applied with the load curve; zeros = fixed). ``load_shape``: this
    constraint's own load curve (one of ``LOAD_SHAPES``, as NiftySim's per-constraint
    ``LoadShape``); None: the loading's."""

    nodes: np.ndarray
    mask: np.ndarray
    values: np.ndarray | None = None
    load_shape: str | None = None

    def __post_init__(self) -> None:
        self.nodes = np.asarray(self.nodes, dtype=np.int64).ravel()
        self.mask = np.broadcast_to(np.asarray(self.mask, bool), (len(self.nodes), 3)).copy()
        values = np.zeros((len(self.nodes), 3)) if self.values is None else self.values
        self.values = np.broadcast_to(np.asarray(values, float), (len(self.nodes), 3)).copy()
        if self.load_shape is not None and self.load_shape not in LOAD_SHAPES:
            raise ValueError(f"a constraint's load_shape must be one of {LOAD_SHAPES} (or None: the loading's), "
                             f"not {self.load_shape!r}")

    @classmethod
    def fixed(cls, nodes, components=(True, True, True)) -> "Constraint":
        """Fix the given components (e.g. (False, True, False): anterior-posterior only)."""
        return cls(nodes, np.asarray(components, bool)[None, :].repeat(len(np.ravel(nodes)), axis=0))


SUPPORT_MODES = ("sliding", "elastic")


@dataclass
class SurfaceSupport:
    """Nodes supported against a surface (e.g. the chest wall) along their local normals
    ``normals`` (K, 3, unit; the direction's sign does not matter), each standing for the surface
    ``areas`` (K,) mm^2 around it. ``mode`` "sliding": zero normal displacement (kinematic,
    bilateral) and free along the surface, or held there by ``tangential_stiffness``; "elastic":
    springs of ``normal_stiffness`` and ``tangential_stiffness`` across and along it (at least
    one > 0; springs along it only where a fixed constraint holds the nodes across it). The
    stiffnesses are per area, Pa/mm (the spring force on a node is the stiffness x its area x its
    displacement's part; 1 kPa/mm holds 1 mm^2 with 1 mN per mm). Fixed supports are
    constraints (:class:`Constraint`); :func:`BreastBiomechLib.solver.supports.chest_wall_support` makes
    either from a node set."""

    nodes: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    mode: str = "sliding"
    normal_stiffness: float = 0.0
    tangential_stiffness: float = 0.0

    def __post_init__(self) -> None:
        self.nodes = np.asarray(self.nodes, dtype=np.int64).ravel()
        normals = np.asarray(self.normals, float).reshape(len(self.nodes), 3)
        length = np.linalg.norm(normals, axis=1)
        if len(self.nodes) and not np.all(length > 0):
            raise ValueError("a surface support needs a non-zero normal at every node")
        self.normals = normals / np.where(length > 0, length, 1.0)[:, None]
        self.areas = np.asarray(self.areas, float).reshape(len(self.nodes))
        if np.any(~np.isfinite(self.areas)) or np.any(self.areas < 0):
            raise ValueError("a surface support's nodal areas must be finite and >= 0 (mm^2)")
        if self.mode not in SUPPORT_MODES:
            raise ValueError(f"support mode must be one of {SUPPORT_MODES} (or a fixed Constraint), not {self.mode!r}")
        for name in ("normal_stiffness", "tangential_stiffness"):
            value = float(getattr(self, name))
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"the support's {name} must be a finite number >= 0 (Pa/mm), not {value}")
            setattr(self, name, value)
        if self.mode == "elastic" and self.normal_stiffness == 0 and self.tangential_stiffness == 0:
            raise ValueError("an elastic support needs a spring (normal or tangential stiffness > 0, Pa/mm)")
        if self.mode == "sliding" and self.normal_stiffness:
            raise ValueError("a sliding support has no normal stiffness (its normal displacement is zero); "
                             "use mode 'elastic' for a spring across the surface")


@dataclass
class Loading:
    """Constraints, plates, surface supports and gravity (m/s^2), applied over ``total_time``
    seconds with ``load_shape``; the solve then continues for ``settle_time`` seconds at full load."""

    constraints: list[Constraint] = field(default_factory=list)
    plates: list[Plate] = field(default_factory=list)
    gravity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    total_time: float = 1.0
    load_shape: str = "POLY345"
    settle_time: float = 0.0
    supports: list[SurfaceSupport] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # how the supports hold the model, for reports

    def __post_init__(self) -> None:
        self.gravity = np.asarray(self.gravity, float).reshape(3)
        if not np.all(np.isfinite(self.gravity)):
            raise ValueError(f"gravity must be three finite numbers (m/s^2, LPS), not {self.gravity.tolist()}")
        if self.total_time <= 0 or self.settle_time < 0:
            raise ValueError("total_time must be positive and settle_time >= 0 (s)")
        if self.load_shape not in LOAD_SHAPES:
            raise ValueError(f"load_shape must be one of {LOAD_SHAPES}")


@dataclass
class ReferenceState:
    """A pre-stressed start: the model's mesh is the stress-free (unloaded) shape, and at t = 0
    the tissue rests at ``displacement`` (N, 3) mm from it, in equilibrium under ``gravity``
    (m/s^2, LPS), e.g. the imaged prone shape (see :mod:`BreastBiomechLib.solver.unloaded`).
    Over the loading gravity changes from this to the loading's gravity (the same: it stays;
    another: a change of posture)."""

    displacement: np.ndarray
    gravity: np.ndarray

    def __post_init__(self) -> None:
        self.displacement = np.asarray(self.displacement, float)
        self.gravity = np.asarray(self.gravity, float).reshape(3)
        if self.displacement.ndim != 2 or self.displacement.shape[1] != 3 or not np.all(np.isfinite(self.displacement)):
            raise ValueError("a reference state's displacement is (N, 3) finite numbers (mm)")
        if not np.all(np.isfinite(self.gravity)):
            raise ValueError(f"gravity must be three finite numbers (m/s^2, LPS), not {self.gravity.tolist()}")


@dataclass
class Model:
    """Mesh (mm, LPS) + per-element materials + loading, and the solver settings.

    ``damping`` is the mass-proportional damping coefficient alpha (1/s) of seed eq. (15);
    ``time_step`` None picks ``safety`` x the critical step. ``prestate``: a pre-stressed start
    (:class:`ReferenceState`; the mesh is then the stress-free shape), None: the mesh's shape is
    stress-free and the tissue starts at rest there. ``anp_across_materials`` (T4ANP): False
    averages each node's pressure over the elements of one material at a time (this project's
    default, see :func:`~BreastBiomechLib.solver.host_setup.anp_slots`); True over all its elements, as
    NiftySim's T4ANP does (what a NiftySim model means; read NiftySim files come back so)."""

    mesh: TetMesh
    materials: ElementMaterials
    loading: Loading
    formulation: str = "T4ANP"
    damping: float = 50.0
    time_step: float | None = None
    safety: float = 0.8
    prestate: ReferenceState | None = None
    anp_across_materials: bool = False

    @property
    def start_positions(self) -> np.ndarray:
        """(N, 3) mm, LPS: where the nodes are at t = 0 (the mesh, or its pre-stressed state)."""
        return self.mesh.nodes if self.prestate is None else self.mesh.nodes + self.prestate.displacement

    def __post_init__(self) -> None:
        if self.formulation not in FORMULATIONS:
            raise ValueError(f"formulation must be one of {FORMULATIONS}")
        m, n = len(self.mesh.tets), len(self.mesh.nodes)
        if len(self.materials.mu) != m:
            raise ValueError(f"materials are given for {len(self.materials.mu)} elements, the mesh has {m}")
        if np.any(self.mesh.volumes <= 0):
            bad = np.flatnonzero(self.mesh.volumes <= 0)[:10]
            raise ValueError(f"elements {bad.tolist()} have zero or negative volume; fix the mesh orientation")
        if self.prestate is not None and self.prestate.displacement.shape != (n, 3):
            raise ValueError(f"the reference state gives {len(self.prestate.displacement)} node displacements, the "
                             f"mesh has {n} nodes")
        for c in self.loading.constraints:
            if len(c.nodes) and (c.nodes.min() < 0 or c.nodes.max() >= n):
                raise ValueError("a constraint refers to nodes outside the mesh")
        for support in self.loading.supports:
            if len(support.nodes) and (support.nodes.min() < 0 or support.nodes.max() >= n):
                raise ValueError("a surface support refers to nodes outside the mesh")
        for p in self.loading.plates:
            if len(p.slave_nodes) and (p.slave_nodes.min() < 0 or p.slave_nodes.max() >= n):
                raise ValueError(f"plate {p.name!r} refers to nodes outside the mesh")
            p.check_clear_of(self.start_positions[p.slave_nodes])
        if self.damping < 0:
            raise ValueError("damping must be >= 0 (1/s)")
        if not 0 < self.safety <= 1:
            raise ValueError("safety factor must lie in (0, 1]")

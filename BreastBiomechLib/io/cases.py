"""Simulation case files (``CASE.json``): a ``.vtu`` mesh plus materials, loading and solver
settings, the input of ``breastbiomech simulate``. Format reference: docs/solver.md.

Geometry in the mesh's frame (LPS mm), moduli in Pa, density kg/m^3, time s, gravity m/s^2.
Node sets are named point arrays of the mesh (nodes where the array is non-zero) or lists of
node ids; materials are keyed by tissue name or label value of :mod:`BreastBiomechLib.labels`
(``"default"`` for a mesh without a ``tissue`` cell array).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from BreastBiomechLib.errors import InputError, reading
from BreastBiomechLib.labels import BY_LABEL, SKIN
from BreastBiomechLib.labels import tissue as lookup_tissue
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.materials import ElementMaterials, Material, default_tissue_materials
from BreastBiomechLib.solver.model import Constraint, Loading, Model, Plate, PlateEdge
from BreastBiomechLib.solver.placement import (PLATE_SIDES, compression_plates, held_plates_touching, plate_contacts,
                                               posed_plate)
from BreastBiomechLib.solver.settings import DynamicRelaxation, SolverSettings, UnloadedRequest
from BreastBiomechLib.solver.supports import chest_wall_support, support_constraints


def _node_set(mesh: TetMesh, spec, what: str, path: Path) -> np.ndarray:
    if isinstance(spec, str):
        try:
            return mesh.node_set(spec)
        except ValueError as error:
            raise ValueError(f"{path}: {what}: {error}") from None
    nodes = np.asarray(spec, dtype=np.int64).ravel()
    if len(nodes) and (nodes.min() < 0 or nodes.max() >= len(mesh.nodes)):
        raise ValueError(f"{path}: {what} lists nodes outside 0..{len(mesh.nodes) - 1}")
    return nodes


def _components(spec, path: Path) -> tuple[bool, bool, bool]:
    if isinstance(spec, str):
        if not spec or set(spec) - set("xyz"):
            raise ValueError(f"{path}: constraint components {spec!r} must be letters of 'xyz'")
        return tuple(axis in spec for axis in "xyz")
    if len(spec) != 3:
        raise ValueError(f"{path}: constraint components need three booleans (x, y, z)")
    return tuple(bool(c) for c in spec)


def _plate_edge(spec, what: str, path: Path) -> PlateEdge | None:
    """A plate's ``edge`` entry: {"direction": in-plane unit vector, "distance": mm from the
    plate's point to where its flat face ends, "radius": mm of its rounded edge}."""
    if spec is None:
        return None
    missing = {"direction", "distance", "radius"} - set(spec)
    if missing:
        raise ValueError(f"{path}: {what}: its edge needs {sorted(missing)} (direction, distance mm, radius mm)")
    try:
        return PlateEdge(spec["direction"], spec["distance"], spec["radius"])
    except ValueError as error:
        raise ValueError(f"{path}: {what}: {error}") from None


PLATE_FIELDS = ("name", "point", "normal", "displacement", "slaves", "edge", "friction", "tilt_deg", "offset_mm")


def _plate(mesh: TetMesh, spec: dict, index: int, path: Path) -> Plate:
    """A case's plate: ``point`` and ``normal`` (towards the tissue) at the start, ``displacement``
    (mm), contact nodes ``slaves``, optional rounded ``edge``, Coulomb ``friction`` (>= 0), and a
    pose change of its final position (:func:`~BreastBiomechLib.solver.placement.posed_plate`):
    ``tilt_deg`` (two angles about its tilt axes, at most 10 degrees) and ``offset_mm`` (along its
    normal, > 0 further in); the posed plate starts just touching its contact nodes."""
    name = spec.get("name", f"plate{index}")
    what = f"plate {name}"
    unknown = set(spec) - set(PLATE_FIELDS)
    if unknown:
        raise ValueError(f"{path}: {what} has unknown fields {sorted(unknown)}; use {list(PLATE_FIELDS)}")
    missing = {"point", "normal"} - set(spec)
    if missing:
        raise ValueError(f"{path}: {what} needs {sorted(missing)} (LPS mm; the normal towards the tissue)")
    slaves = _node_set(mesh, spec.get("slaves", "surface"), what, path)
    edge = _plate_edge(spec.get("edge"), what, path)
    try:
        plate = Plate(_vector(spec["point"], f"{what}: point"), _vector(spec["normal"], f"{what}: normal"),
                      _vector(spec.get("displacement", (0.0, 0.0, 0.0)), f"{what}: displacement"), slaves, name, edge,
                      _number(spec.get("friction", 0.0), f"{what}: friction"))
        if "tilt_deg" in spec or "offset_mm" in spec:
            plate = posed_plate(plate, mesh.nodes, spec.get("tilt_deg", (0.0, 0.0)),
                                _number(spec.get("offset_mm", 0.0), f"{what}: offset_mm"))
    except (TypeError, ValueError) as error:  # the messages name the plate
        raise ValueError(f"{path}: {error}") from None
    return plate


SKIN_FIELDS = ("E", "nu", "density", "thickness_mm", "nodes")


def _skin_layer(mesh: TetMesh, materials: ElementMaterials, spec: dict, path: Path):
    """A case's ``skin``: {"E" (Pa), "nu", optional "density", "thickness_mm", "nodes" (the skin
    surface's node set, default "skin")}. A mesh with skin elements (tissue ``skin``) gives them
    this material; otherwise the elements within ``thickness_mm`` of the skin surface carry it by
    partial-volume weighting (:mod:`BreastBiomechLib.mesh.skin`). Returns the materials and a
    sentence saying which."""
    from BreastBiomechLib.mesh.skin import check_thickness, skin_fraction

    if not isinstance(spec, dict) or set(spec) - set(SKIN_FIELDS) or not {"E", "nu", "thickness_mm"} <= set(spec):
        raise ValueError(f"{path}: skin is {{\"E\": Pa, \"nu\", \"thickness_mm\", optional \"density\", \"nodes\" "
                         "(the skin surface's node set, default \"skin\")}")
    try:
        skin = Material(E=_number(spec["E"], "skin E"), nu=_number(spec["nu"], "skin nu"),
                        density=_number(spec.get("density", 1000.0), "skin density"))
        thickness = _number(spec["thickness_mm"], "skin thickness_mm")
        if not thickness > 0:
            raise ValueError(f"the skin thickness must be positive (mm), not {thickness}")
    except ValueError as error:
        raise ValueError(f"{path}: skin: {error}") from None
    tissue = np.asarray(mesh.cell_data.get("tissue", np.zeros(len(mesh.tets))), dtype=int)
    if np.any(tissue == SKIN.label):
        elements = tissue == SKIN.label
        fraction = elements.astype(float)
        note = f"skin E {skin.E:g} Pa: the mesh's {int(elements.sum())} skin elements"
    else:
        nodes = _node_set(mesh, spec.get("nodes", "skin"), "skin", path)
        try:
            check_thickness(mesh, nodes, thickness)
            fraction = skin_fraction(mesh, nodes, thickness)
        except ValueError as error:
            raise ValueError(f"{path}: skin: {error}") from None
        layer = float(fraction @ mesh.volumes)
        note = (f"skin E {skin.E:g} Pa, {thickness:g} mm: partial-volume weighting of {int(np.sum(fraction > 0))} "
                f"elements ({layer / 1000:.1f} cm^3 of layer)")
    return materials.with_skin(fraction, skin), note


SUPPORT_FIELDS = ("nodes", "kind", "components", "normal_stiffness", "tangential_stiffness", "anchor")


def _support(mesh: TetMesh, spec: dict, index: int, path: Path):
    """A case's surface support (e.g. the chest wall): ``nodes`` (a node set), ``kind`` "fixed"
    (in ``components``, default "y"), "sliding" or "elastic", ``normal_stiffness`` and
    ``tangential_stiffness`` (Pa/mm, per area), ``anchor`` (default true: patches against the
    rigid motion the support leaves free). See
    :func:`~BreastBiomechLib.solver.supports.chest_wall_support`."""
    what = f"support {index}"
    unknown = set(spec) - set(SUPPORT_FIELDS)
    if unknown:
        raise ValueError(f"{path}: {what} has unknown fields {sorted(unknown)}; use {list(SUPPORT_FIELDS)}")
    if "nodes" not in spec:
        raise ValueError(f"{path}: {what} needs its nodes (a node set such as \"chest_wall\")")
    nodes = _node_set(mesh, spec["nodes"], what, path)
    anchor = spec.get("anchor", True)
    if not isinstance(anchor, bool):
        raise ValueError(f"{path}: {what}: anchor must be true or false")
    try:
        return chest_wall_support(mesh, nodes, spec.get("kind", "fixed"), _components(spec.get("components", "y"), path),
                                  _number(spec.get("normal_stiffness", 0.0), f"{what}: normal_stiffness"),
                                  _number(spec.get("tangential_stiffness", 0.0), f"{what}: tangential_stiffness"),
                                  anchor)
    except ValueError as error:
        raise ValueError(f"{path}: {what}: {error}") from None


def _vector(value, field: str, unit: str = "LPS mm") -> np.ndarray:
    try:
        vector = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        vector = None
    if vector is None or vector.shape != (3,):
        raise ValueError(f"{field} must be three numbers ({unit}), not {value!r}")
    return vector


def _number(value, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{field} must be a number, not {value!r}")
    return float(value)


def _material(values: dict, key: str, path: Path) -> Material:
    known = {"E", "nu", "eta", "fibre", "density", "prony"}
    unknown = set(values) - known
    if unknown:
        raise ValueError(f"{path}: material {key!r} has unknown fields {sorted(unknown)}; use {sorted(known)}")
    try:
        return Material(E=float(values["E"]), nu=float(values["nu"]), eta=float(values.get("eta", 0.0)),
                        fibre=tuple(values.get("fibre", (0.0, 0.0, 1.0))),
                        density=float(values.get("density", 1000.0)),
                        prony=tuple(tuple(term) for term in values.get("prony", ())))
    except KeyError as missing:
        raise ValueError(f"{path}: material {key!r} needs {missing} (E in Pa, nu)") from None
    except ValueError as error:
        raise ValueError(f"{path}: material {key!r}: {error}") from None


def _element_materials(mesh: TetMesh, spec: dict, path: Path) -> ElementMaterials:
    if not spec:
        raise ValueError(f"{path}: the case gives no materials")
    if "tissue" not in mesh.cell_data:
        if set(spec) != {"default"}:
            raise ValueError(f"{path}: the mesh has no 'tissue' cell array, so give one material named 'default'")
        return ElementMaterials.uniform(len(mesh.tets), _material(spec["default"], "default", path))
    table = {}
    for key, values in spec.items():
        label = lookup_tissue(int(key) if key.isdigit() else key).label
        table[label] = _material(values, key, path)
    return ElementMaterials.from_tissues(np.asarray(mesh.cell_data["tissue"]).astype(int), table)


def _flag(value, name: str, path: Path) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"{path}: {name} must be true or false, not {value!r}")
    return value


@dataclass
class CaseDescription:
    """A case file's content (``CASE.json``, format in docs/solver.md), typed: the mesh file (relative
    to the case file), materials by tissue, constraints, plates and supports (node sets by name or
    node ids), gravity (m/s^2, LPS), the load's times (s) and curve, an optional skin layer, the
    formulation and solver settings, and an optional ``reference_state`` (start from the unloaded
    shape). :meth:`from_dict` checks the top-level keys (an unknown one is an error that lists the
    known ones, so that a misspelt key is never ignored); :meth:`build` makes the model and
    solver settings on the mesh, checking every entry; :meth:`to_dict` writes the same format."""

    mesh: str | None = None
    materials: dict = field(default_factory=dict)
    constraints: list = field(default_factory=list)
    plates: list = field(default_factory=list)
    supports: list = field(default_factory=list)
    gravity: list | None = None
    total_time: float = 1.0
    settle_time: float = 0.0
    load_shape: str = "POLY345"
    skin: dict | None = None
    formulation: str = "T4ANP"
    damping: float = 50.0
    time_step: float | None = None
    safety: float = 0.8
    anp_across_materials: bool = False
    solver: dict = field(default_factory=dict)
    reference_state: dict | None = None

    @classmethod
    def from_dict(cls, data: dict, path: Path = Path("<case>")) -> CaseDescription:
        """The description of a case dictionary (a case file's JSON content)."""
        if not isinstance(data, dict):
            raise ValueError(f"{path}: a case is a JSON object of {sorted(f.name for f in fields(cls))}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{path}: unknown case entries {unknown}; a case holds {sorted(known)} (docs/solver.md)")
        return cls(**data)

    @classmethod
    def from_json(cls, text: str, path: Path = Path("<case>")) -> CaseDescription:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise InputError(f"{path}: not valid JSON ({error})") from None
        return cls.from_dict(data, path)

    def to_dict(self) -> dict:
        """The case file's JSON content: every entry set (None left out)."""
        return {name: value for name, value in asdict(self).items() if value is not None}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1) + "\n"

    def build(self, mesh: TetMesh, path: Path = Path("<case>")) -> tuple[Model, SolverSettings]:
        """The model and solver settings of this description on ``mesh`` (errors name ``path``)."""
        constraints = []
        for i, c in enumerate(self.constraints):
            nodes = _node_set(mesh, c["nodes"], f"constraint {i}", path)
            mask = np.array(_components(c.get("components", "xyz"), path))
            values = np.zeros(3) if c.get("displacement") is None else np.asarray(c["displacement"], float)
            constraints.append(Constraint(nodes, np.tile(mask, (len(nodes), 1)), np.tile(values, (len(nodes), 1)),
                                          load_shape=c.get("load_shape")))
        plates = [_plate(mesh, p, i, path) for i, p in enumerate(self.plates)]
        supports, notes = [], []
        for i, spec in enumerate(self.supports):
            held, surface, note = _support(mesh, spec, i, path)
            constraints += held
            supports += surface
            notes.append(note)
        gravity = (0.0, 0.0, 0.0) if self.gravity is None else self.gravity
        loading = Loading(constraints, plates, supports=supports, notes=notes,
                          gravity=_vector(gravity, f"{path}: gravity", "m/s^2, LPS"),
                          total_time=float(self.total_time), load_shape=self.load_shape,
                          settle_time=float(self.settle_time))
        materials = _element_materials(mesh, self.materials, path)
        if self.skin is not None:
            materials, note = _skin_layer(mesh, materials, self.skin, path)
            loading.notes.append(note)
        model = Model(mesh, materials, loading, formulation=self.formulation, damping=float(self.damping),
                      time_step=self.time_step, safety=float(self.safety),
                      anp_across_materials=_flag(self.anp_across_materials, "anp_across_materials", path))
        return model, self._settings(path)

    def _settings(self, path: Path) -> SolverSettings:
        solver = dict(self.solver)
        method = solver.pop("method", "relaxation")
        device = solver.pop("device", None)
        steady = solver.pop("steady_state_mm", None)
        increments = solver.pop("increments", None)
        mass_scaling = solver.pop("mass_scaling", False)
        if not isinstance(mass_scaling, bool):
            raise ValueError(f"{path}: solver mass_scaling must be true or false")
        try:
            relaxation = DynamicRelaxation(**solver)
        except TypeError:
            raise ValueError(f"{path}: unknown solver settings {sorted(solver)}; use method, device, steady_state_mm, "
                             "increments, mass_scaling, load_iterations, tolerance_mm, max_iterations, "
                             "update_every") from None
        settings = SolverSettings(method, device, relaxation, None if steady is None else float(steady),
                                  None if increments is None else int(increments), mass_scaling,
                                  _unloaded_request(self.reference_state, path))
        if settings.unloaded is not None and method == "static":
            raise ValueError(f"{path}: the static reference solver starts from the stress-free mesh; a "
                             "reference_state needs the relaxation or physical method")
        return settings


def case_from_dict(data: dict | CaseDescription, mesh: TetMesh,
                   path: Path = Path("<case>")) -> tuple[Model, SolverSettings]:
    """Build the model and solver settings of a case (its JSON content or its
    :class:`CaseDescription`) on ``mesh``."""
    description = data if isinstance(data, CaseDescription) else CaseDescription.from_dict(data, path)
    return description.build(mesh, path)


def _unloaded_request(spec, path: Path) -> UnloadedRequest | None:
    if spec is None:
        return None
    known = {"imaged_gravity", "tolerance_mm", "max_iterations"}
    if not isinstance(spec, dict) or "imaged_gravity" not in spec or set(spec) - known:
        raise ValueError(f"{path}: reference_state is {{\"imaged_gravity\": [gx, gy, gz] (m/s^2, LPS), optional "
                         "\"tolerance_mm\", \"max_iterations\"}")
    try:
        return UnloadedRequest(_vector(spec["imaged_gravity"], "imaged_gravity", "m/s^2, LPS"),
                               _number(spec.get("tolerance_mm", 0.02), "tolerance_mm"),
                               int(_number(spec.get("max_iterations", 30), "max_iterations")))
    except ValueError as error:
        raise ValueError(f"{path}: reference_state: {error}") from None


def read_case(path: str | Path) -> tuple[Model, SolverSettings]:
    """Read ``CASE.json`` and the mesh it names (a path relative to the JSON file)."""
    from BreastBiomechLib.io.meshes import read_vtu

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such case file")
    with reading(path, "case file", "docs/solver.md lists its fields; `breastbiomech mesh` writes one"):
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise InputError(f"{path}: not valid JSON ({error})") from None
        if not isinstance(data, dict) or not isinstance(data.get("mesh"), str):
            raise InputError(f"{path}: the case must name its mesh file (\"mesh\": \"breast.vtu\")")
        description = CaseDescription.from_dict(data, path)
        mesh_path = path.parent / description.mesh
        if not mesh_path.is_file():
            raise InputError(f"{path}: its mesh {description.mesh!r} is not a file ({mesh_path}); give the .vtu's "
                             "path relative to the case file")
        return description.build(read_vtu(mesh_path), path)


def compression_case(mesh: TetMesh, mesh_file: str, axis: str = "LR", compression: float = 0.25,
                     moving: str = "both", total_time: float = 1.0, settle_time: float = 0.25,
                     chest_clearance_mm: float | None = None) -> CaseDescription:
    """The case description of a plate compression of a breast mesh made by
    :func:`BreastBiomechLib.mesh.from_labels.mesh_labels` (node sets ``chest_wall``, ``skin``,
    ``breast_skin``, ``fov_cut``): plates tangent to the breast skin on both sides of ``axis``
    closing by ``compression`` of the thickness between them; the chest wall fixed
    anterior-posteriorly as in the seed; the field-of-view cut faces, where the body continues,
    fixed (without them, the anchor patches of
    :func:`~BreastBiomechLib.solver.supports.support_constraints` stop rigid motion); the
    default tissue materials; dynamic relaxation. ``mesh_file`` is written as the case's mesh.

    ``moving``: "both" plates close (half the travel each), or only the "first" or "second"
    towards the other, held one, which is placed touching the nearest skin it can touch
    (:func:`~BreastBiomechLib.solver.placement.held_plates_touching`). The plates touch the skin
    nodes that start between them and lie more than
    ``chest_clearance_mm`` anterior to the chest (None: the plate travel per side, at least
    5 mm), listed in the case: see :func:`~BreastBiomechLib.solver.placement.plate_contacts`."""
    for name in ("chest_wall", "skin", "breast_skin", "fov_cut"):
        if name not in mesh.point_data:
            raise ValueError(f"the mesh has no {name!r} node set; make it with `breastbiomech mesh`")
    if "tissue" not in mesh.cell_data:
        raise ValueError("the mesh has no 'tissue' cell array; make it with `breastbiomech mesh`")
    skin = mesh.node_set("skin")
    plates = compression_plates(mesh, axis, compression, skin,
                                names=PLATE_SIDES.get(str(axis).upper(), ("plate1", "plate2")), moving=moving,
                                extent_nodes=mesh.node_set("breast_skin"))
    contacts = plate_contacts(mesh, skin, plates, chest_clearance_mm)
    plates = held_plates_touching(mesh.nodes, plates, contacts)
    for plate in plates:
        plate.slave_nodes = contacts
    cut = mesh.node_set("fov_cut")
    if len(cut):
        constraints = [{"nodes": "chest_wall", "components": "y"}, {"nodes": "fov_cut", "components": "xyz"}]
    else:
        constraints = [{"nodes": c.nodes.tolist(), "components": [bool(v) for v in c.mask[0]]}
                       for c in support_constraints(mesh.nodes, mesh.node_set("chest_wall"), (False, True, False))]
    tissues = np.unique(np.asarray(mesh.cell_data["tissue"], dtype=int))
    defaults = default_tissue_materials()
    materials = {BY_LABEL[int(t)].name: {"E": defaults[int(t)].E, "nu": defaults[int(t)].nu} for t in tissues}
    return CaseDescription(
        mesh=mesh_file, materials=materials, constraints=constraints,
        plates=[{"name": p.name, "point": p.point.tolist(), "normal": p.normal.tolist(),
                 "displacement": p.displacement.tolist(), "slaves": p.slave_nodes.tolist(),
                 **({"edge": p.edge.to_dict()} if p.edge else {})} for p in plates],
        total_time=total_time, settle_time=settle_time, solver={"method": "relaxation"})

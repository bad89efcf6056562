"""NiftySim XML model files: write a :class:`~BreastBiomechLib.solver.Model` so the same case runs
in NiftySim (``niftysim -x MODEL.xml``), and read NiftySim's models, its own examples' constructs
included, back into a model with NiftySim's physics.

The file is in SI units, as the solver works internally: node coordinates in metres, moduli in
Pa, density kg/m^3, time s, gravity m/s^2 (the library's models are in millimetres; the reader
converts back). What maps to what, what is converted and what is refused is the table in
docs/solver.md ("NiftySim XML"); in short:

- ``Elements Type`` = the formulation (T4ANP or T4). NiftySim's T4ANP averages the nodal
  pressure over all elements at a node; the project's default averages per material, so a
  T4ANP model of several materials is written only when it says ``anp_across_materials`` (the
  model NiftySim runs), and models read from a file say so.
- One ``ElementSet`` per distinct material: NH / TI (eta > 0) / NHV / TIV (isochoric Prony
  terms). **TI's fibre parameter**: the project's eta is the seed's eq. (8), W_f = eta/2
  (I4bar - 1)^2; NiftySim's code computes the fibre stress of E/4 (I4bar - 1)^2 for its third
  TI parameter E (tledMaterialTI: S_f = J^(-2/3) E (I4bar - 1) (A - I4bar/3 C^-1)), so the file
  holds E = 2 eta (:data:`NIFTYSIM_ETA_PER_ETA`) and the reader halves it. The seed's Table 3
  eta values were NiftySim inputs: in this project's convention they are half as large.
- Constraints: per component and load curve one ``Fix`` (zero values) or ``Disp`` constraint
  (``Magnitudes`` per node); gravity as a ``Gravity`` constraint on every node.
- Plates, two variants (the file's first comment says which): ``ContactPlate`` rectangles
  (NiftySim's GPU build only: its CPU build has no contact), or, given the solved displacement,
  every plate and surface support replaced by the solved displacement of the nodes it holds at
  the end (``Disp`` constraints: any NiftySim build runs it, and its final state is the solved
  equilibrium).
- ``SystemParams``: TimeStep (the stable step, fibres counted), TotalTime (the loading time;
  NiftySim has no settling phase), DampingCoeff, Density.
"""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import numpy as np

from BreastBiomechLib.errors import InputError, reading
from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_faces, check_mesh
from BreastBiomechLib.solver.host_setup import constraint_load_shapes, critical_time_step, merged_constraints
from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.model import LOAD_SHAPES, Constraint, Loading, Model, Plate, PlateEdge

MM = 1e-3
AXES = "012"
NIFTYSIM_ETA_PER_ETA = 2.0  # NiftySim's TI parameter E for this project's eta (see the module docstring)
CONTACT_TOLERANCE_MM = 1e-3  # a slave node this close to its moved plate at the end is in contact
VARIANT_PLATES = "ContactPlate (NiftySim's GPU build; its CPU build has no contact)"
VARIANT_SOLVED = "plates and supports replaced by the solved displacement of the nodes they hold (any NiftySim build)"

# what the reader knows: top-level elements it reads, ignores with a warning, and refuses
READ_ELEMENTS = ("Nodes", "Elements", "ElementSet", "Constraint", "ContactPlate", "SystemParams")
IGNORED_ELEMENTS = {"Output": "output requests (U, F, EKin, ...) do not change the model; this project writes "
                              "its own results"}
SYSTEM_PARAMS_READ = ("TimeStep", "TotalTime", "DampingCoeff", "Density")
SYSTEM_PARAMS_FLAGS = {"DoDeformableCollision": "deformable-deformable contact",
                       "DoSelfCollision": "self-collision contact", "ROM": "reduced-order modelling"}
SYSTEM_PARAMS_IGNORED = {"HGKappa": "hourglass control acts on H8 elements only, not on tetrahedra",
                         "ContactSafetyMargin": "a setting of deformable contact, which is not used",
                         "RateConstraintDistance": "a setting of deformable contact, which is not used",
                         "BVType": "a setting of deformable contact, which is not used",
                         "DoMultiPassContacts": "a setting of deformable contact, which is not used",
                         "DeformableFrictionCoefficient": "a setting of deformable contact, which is not used"}
MATERIAL_PARAMS = {"NH": 2, "NHV": 2, "TI": 6, "TIV": 6}
CONSTRAINT_TYPES = ("Fix", "Disp", "Gravity")


PLAUSIBLE = 1e30  # larger numbers in a model file are mistakes (and overflow once scaled to mm)


class NiftySimFormatError(InputError):
    """A NiftySim file this project cannot read or a model it cannot write: the message names the
    file, the element and what to do."""


class NiftySimExportWarning(UserWarning):
    """The written file differs from the model in a way NiftySim forces (named in the message and
    in the file's first comment)."""


class NiftySimImportWarning(UserWarning):
    """Part of a NiftySim file was ignored because it does not change the model (named in the
    message)."""


def _text(values, per_line: int) -> str:
    values = np.asarray(values).reshape(-1, per_line)
    return "\n" + "\n".join(" ".join(f"{v:.9g}" for v in row) for row in values) + "\n"


def _material_sets(mat: ElementMaterials) -> tuple[np.ndarray, np.ndarray]:
    """Rows of distinct (mu, kappa, eta, fibre, density, Prony) and each element's row."""
    table = np.column_stack([mat.mu, mat.kappa, mat.eta, mat.fibre, mat.density, mat.prony_g, mat.prony_tau])
    return np.unique(table, axis=0, return_inverse=True)


def differs_in_niftysim_anp(model: Model) -> bool:
    """True when NiftySim's T4ANP (pressure averaged across materials) would be another model than
    ``model``: T4ANP averaged per material over more than one bulk modulus."""
    return (model.formulation == "T4ANP" and not model.anp_across_materials
            and len(np.unique(model.materials.kappa)) > 1)


def _solved_holds(model: Model, solved_mm: np.ndarray) -> Constraint | None:
    """The plates' and supports' work as prescribed displacements: every plate's slave node within
    ``CONTACT_TOLERANCE_MM`` of its moved plate at the end and every supported node takes its solved
    displacement (mm), in the components no constraint prescribes already."""
    n = len(model.mesh.nodes)
    solved_mm = np.asarray(solved_mm, float)
    if solved_mm.shape != (n, 3) or not np.all(np.isfinite(solved_mm)):
        raise NiftySimFormatError(f"the solved displacement must be ({n}, 3) finite numbers (mm), the solution of "
                                  f"this model; got an array of shape {solved_mm.shape}")
    held = np.zeros(n, bool)
    final = model.start_positions + solved_mm
    for plate in model.loading.plates:
        gap = plate.gaps(final[plate.slave_nodes] - plate.displacement)
        held[plate.slave_nodes[gap <= CONTACT_TOLERANCE_MM]] = True
    for support in model.loading.supports:
        held[support.nodes] = True
    nodes, mask, _ = merged_constraints(model)
    taken = np.zeros((n, 3), bool)
    taken[nodes] = mask
    ids = np.flatnonzero(held & ~np.all(taken, axis=1))
    if not len(ids):
        return None
    return Constraint(ids, ~taken[ids], solved_mm[ids])


def write_niftysim(path: str | Path, model: Model, drop_settling: bool = False,
                   solved_displacement: np.ndarray | None = None) -> Path:
    """Write ``model`` as a NiftySim XML file (SI units); returns the path.

    Plates become ``ContactPlate`` elements (frictionless, moved with POLY345: friction, other
    load shapes with plates and surface supports are refused), unless ``solved_displacement``
    ((N, 3) mm, this model's solution) is given: then each plate and support is replaced by the
    solved displacement of the nodes it holds at the end, the file NiftySim's CPU build runs (and
    friction, rounded edges and supports are carried by those displacements). NiftySim has no
    settling phase: a model with ``settle_time`` is refused unless ``drop_settling``. A T4ANP
    model of several materials is written only with ``anp_across_materials`` (NiftySim averages
    nodal pressure across materials). A pre-stressed start (``prestate``) is refused. Each lossy
    change warns (:class:`NiftySimExportWarning`) and is listed in the file's first comment."""
    notes = []

    def note(message: str) -> None:
        notes.append(message)
        warnings.warn(message, NiftySimExportWarning, stacklevel=3)

    loading = model.loading
    if model.prestate is not None:
        raise NiftySimFormatError("NiftySim has no pre-stressed start: this model starts from a reference state "
                                  "(unloaded shape under gravity); export the model without its prestate")
    if loading.settle_time:
        if not drop_settling:
            raise NiftySimFormatError(f"NiftySim has no settling phase: this model settles for {loading.settle_time} s "
                                      "after loading; pass drop_settling=True to export the loading only")
        note(f"the settling phase ({loading.settle_time:g} s at full load) is dropped: NiftySim stops at the end of "
             "the loading, so its result is the state at that time, not the settled one")
    if differs_in_niftysim_anp(model):
        raise NiftySimFormatError(
            "NiftySim's T4ANP averages nodal pressure across materials, this model per material (its default, "
            f"{len(np.unique(model.materials.kappa))} bulk moduli here): the file would be a different model. Export "
            "dataclasses.replace(model, anp_across_materials=True), the model NiftySim runs (solve it here first: "
            "across stiff/soft interfaces it may invert), or formulation 'T4'")
    if solved_displacement is None:
        variant = VARIANT_PLATES
        rough = [f"{p.name} (mu {p.friction:g})" for p in loading.plates if p.friction > 0]
        if rough:
            raise NiftySimFormatError(
                f"NiftySim's ContactPlate is frictionless, so plates {', '.join(rough)} cannot be written as they are; "
                "set their friction to 0, or pass the solved displacement to write the plates as prescribed "
                "displacements of the nodes they hold")
        if loading.supports:
            raise NiftySimFormatError(
                "NiftySim has no sliding or elastic surface supports (this model's chest wall); pass the solved "
                "displacement to write them as prescribed displacements of the nodes they hold")
        if loading.plates and loading.load_shape != "POLY345":
            raise NiftySimFormatError("NiftySim moves contact plates with POLY345 only; use that load shape to export "
                                      "plates, or pass the solved displacement")
        written = model
    else:
        variant = VARIANT_SOLVED
        extra = _solved_holds(model, solved_displacement)
        constraints = list(loading.constraints) + ([extra] if extra is not None else [])
        written = replace(model, loading=replace(loading, constraints=constraints, plates=[], supports=[]))
        if loading.plates or loading.supports:
            note(f"{len(loading.plates)} plate(s) and {len(loading.supports)} surface support(s) are written as the "
                 f"solved displacement of the {0 if extra is None else len(extra.nodes)} nodes they hold at the end "
                 "(prescribed over the loading): the final state is the solved equilibrium, the path to it differs")
    path = Path(path)
    root = ET.Element("Model")
    root.append(ET.Comment(f" BreastBiomech export; plates: {variant}; units m, Pa, kg/m^3, s; TI parameter E = "
                           f"{NIFTYSIM_ETA_PER_ETA:g} x eta of the seed's eq. (8)"
                           + "".join(f"; {n}" for n in notes) + " "))
    mesh, mat = written.mesh, written.materials
    ET.SubElement(root, "Nodes", DOF="3", NumNodes=str(len(mesh.nodes))).text = _text(mesh.nodes * MM, 3)
    ET.SubElement(root, "Elements", NumEls=str(len(mesh.tets)), Type=model.formulation).text = _text(mesh.tets, 4)
    _write_element_sets(root, mat)
    _write_constraints(root, written)
    gravity = loading.gravity
    if np.any(gravity):
        c = ET.SubElement(root, "Constraint", NumNodes="all", Type="Gravity", LoadShape=loading.load_shape)
        ET.SubElement(c, "AccelerationMagnitude").text = f"{np.linalg.norm(gravity):.9g}"
        ET.SubElement(c, "AccelerationDirection").text = _text(gravity / np.linalg.norm(gravity), 3)
    for plate in written.loading.plates:
        _write_plate(root, plate, mesh.nodes)
    system = ET.SubElement(root, "SystemParams")
    dt = model.time_step or model.safety * critical_time_step(model, [mat])
    ET.SubElement(system, "TimeStep").text = f"{dt:.9g}"
    ET.SubElement(system, "TotalTime").text = f"{loading.total_time:.9g}"
    ET.SubElement(system, "DampingCoeff").text = f"{model.damping:.9g}"
    ET.SubElement(system, "Density").text = f"{float(np.median(mat.density)):.9g}"
    ET.indent(root)
    path.parent.mkdir(parents=True, exist_ok=True)
    ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)
    return path


def _write_element_sets(root: ET.Element, mat: ElementMaterials) -> None:
    rows, index = _material_sets(mat)
    K = mat.prony_terms
    for r, row in enumerate(rows):
        elements = np.flatnonzero(index.ravel() == r)
        mu, kappa, eta, a1, a2, a3, density = row[:7]
        g, tau = row[7:7 + K], row[7 + K:]
        visco = np.any(g > 0)
        kind = ("TI" if eta > 0 else "NH") + ("V" if visco else "")
        es = ET.SubElement(root, "ElementSet", Size=str(len(elements)))
        m = ET.SubElement(es, "Material", Type=kind)
        params = [mu, kappa] + ([NIFTYSIM_ETA_PER_ETA * eta, a1, a2, a3] if eta > 0 else [])
        ET.SubElement(m, "ElasticParams", NumParams=str(len(params))).text = _text(params, len(params))
        if visco:
            terms = np.column_stack([g[g > 0], tau[g > 0]])
            ET.SubElement(m, "ViscoParams", NumIsoTerms=str(len(terms)), NumVolTerms="0").text = _text(terms, 2)
        ET.SubElement(m, "Density").text = f"{density:.9g}"
        m.tail = _text(elements, 1)


def _write_constraints(root: ET.Element, model: Model) -> None:
    """One Fix constraint per component and one Disp constraint per component and load curve."""
    nodes, mask, values = merged_constraints(model)
    shapes = constraint_load_shapes(model, nodes)
    for axis in range(3):
        on = mask[:, axis]
        fixed = on & (values[:, axis] == 0)
        groups = [("Fix", fixed, None)] + [("Disp", on & ~fixed & (shapes[:, axis] == s), name)
                                           for s, name in enumerate(LOAD_SHAPES)]
        for kind, pick, shape in groups:
            if not np.any(pick):
                continue
            c = ET.SubElement(root, "Constraint", DOF=AXES[axis], NumNodes=str(int(pick.sum())), Type=kind)
            if shape is not None:
                c.set("LoadShape", shape)
            ET.SubElement(c, "Nodes").text = _text(nodes[pick], 1)
            if kind == "Disp":
                ET.SubElement(c, "Magnitudes", Type="DIFFORM").text = _text(values[pick, axis] * MM, 1)


def _write_plate(root: ET.Element, plate: Plate, nodes_mm: np.ndarray) -> None:
    """A ContactPlate with the plate's name and rounded edge as attributes (NiftySim ignores
    them; the reader restores them)."""
    a, b, c = _plate_corners(plate, nodes_mm)
    p = ET.SubElement(root, "ContactPlate", Name=plate.name)
    if plate.edge is not None:
        p.set("EdgeDirection", " ".join(f"{v:.12g}" for v in plate.edge.direction))
        p.set("EdgeDistance", f"{plate.edge.distance * MM:.12g}")
        p.set("EdgeRadius", f"{plate.edge.radius * MM:.12g}")
    for name, corner in (("a", a), ("b", b), ("c", c)):
        ET.SubElement(p, name).text = _text(corner * MM, 3)
    ET.SubElement(p, "Disp").text = _text(plate.displacement * MM, 3)
    ET.SubElement(p, "SlvNodes", NumNodes=str(len(plate.slave_nodes))).text = _text(plate.slave_nodes, 1)


def _plate_corners(plate: Plate, nodes_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corners a, b, c (mm) of a rectangle in the plate's plane covering its slave nodes (with a
    margin), ordered so that (b - a) x (c - a) points along the plate normal. A plate with an
    edge ends where its flat face ends: NiftySim's plates are flat rectangles, so the rounded
    edge is not exported (a warning says so)."""
    n = plate.normal
    if plate.edge is None:
        helper = np.eye(3)[np.argmin(np.abs(n))]
        e1 = np.cross(n, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)  # e1 x e2 = n
    else:
        e2 = plate.edge.direction
        e1 = np.cross(e2, n)  # (e2 x n) x e2 = n for unit e2 perpendicular to n
        warnings.warn(f"plate {plate.name!r}: NiftySim plates are flat rectangles, so its rounded edge (radius "
                      f"{plate.edge.radius:g} mm) is not exported; the rectangle ends where the flat face ends, "
                      "and NiftySim's result will differ near that edge", NiftySimExportWarning, stacklevel=4)
    rel = (nodes_mm[plate.slave_nodes] if len(plate.slave_nodes) else nodes_mm) - plate.point
    s, t = rel @ e1, rel @ e2
    margin = 0.5 * max(np.ptp(s), np.ptp(t), 1.0)
    s0, s1, t0, t1 = s.min() - margin, s.max() + margin, t.min() - margin, t.max() + margin
    if plate.edge is not None:
        t1 = min(t1, plate.edge.distance)
    a = plate.point + s0 * e1 + t0 * e2
    return a, plate.point + s1 * e1 + t0 * e2, plate.point + s0 * e1 + t1 * e2


class _Reader:
    """One NiftySim file being read: its path for messages and the element lookups."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, message: str) -> NiftySimFormatError:
        return NiftySimFormatError(f"{self.path}: {message}")

    def warn(self, message: str) -> None:
        warnings.warn(f"{self.path}: {message}", NiftySimImportWarning, stacklevel=4)

    def numbers(self, element: ET.Element | None, what: str, dtype=float, text: str | None = None) -> np.ndarray:
        if element is None and text is None:
            raise self.fail(f"{what} is missing")
        raw = element.text if text is None else text
        try:
            values = np.array((raw or "").split(), dtype=np.float64)
        except ValueError:
            raise self.fail(f"{what} holds text that is not a number: {(raw or '').strip()[:60]!r}") from None
        if not np.all(np.isfinite(values)):
            raise self.fail(f"{what} holds values that are not finite numbers")
        if np.any(np.abs(values) > PLAUSIBLE):
            raise self.fail(f"{what} holds values beyond {PLAUSIBLE:g}, which no model quantity in SI units reaches")
        if dtype is not float:
            if np.any(np.abs(values) > 2**53):
                raise self.fail(f"{what} holds an index too large to be one: {values[np.abs(values) > 2**53][:3]}")
            if np.any(values != np.round(values)):
                raise self.fail(f"{what} must list whole numbers (indices), not {values[values != np.round(values)][:3]}")
            return values.astype(np.int64)
        return values

    def attribute_number(self, element: ET.Element, name: str, what: str, dtype=float):
        raw = element.get(name)
        try:
            return dtype(raw)
        except (TypeError, ValueError):
            raise self.fail(f"{what}: attribute {name}={raw!r} is not a number") from None

    def listing(self, listed: np.ndarray, size: str | None, total: int, what: str, item: str) -> np.ndarray:
        """NiftySim's index lists: ``size`` "all" (every one of ``total``), the K indices listed,
        or one start index and ``size`` = K (a consecutive run), as its parser reads them."""
        if size == "all":
            return np.arange(total)
        if size is None:
            ids = listed
        else:
            try:
                count = int(size)
            except ValueError:
                raise self.fail(f"{what}: its size {size!r} must be a number of {item}s or \"all\"") from None
            if count < 0:
                raise self.fail(f"{what}: its size {count} is negative")
            if len(listed) == count:
                ids = listed
            elif len(listed) == 1:
                ids = listed[0] + np.arange(count)
            else:
                raise self.fail(f"{what} lists {len(listed)} {item}s but its size says {count}; list all {count}, or "
                                "give one start index for a consecutive run")
        if len(ids) and (ids.min() < 0 or ids.max() >= total):
            raise self.fail(f"{what} refers to {item}s outside 0..{total - 1} (e.g. {ids[(ids < 0) | (ids >= total)][:3]})")
        return ids


def read_niftysim(path: str | Path) -> Model:
    """Read a NiftySim XML model (written by :func:`write_niftysim`, by NiftySim's users or in
    NiftySim's examples) as the model NiftySim runs: geometry back in mm, TI's E halved to the
    project's eta, T4ANP with ``anp_across_materials``, each Disp constraint with its own load
    curve, element sets and node lists given explicitly, by start index + size or "all",
    constraints on the surface facets facing a ``Normal`` (``SpecType="NORMAL"``).
    Negatively oriented tets are renumbered (NiftySim uses |det|; the physics is the same). What
    the project cannot represent (other element or material types, Force/Pressure/Traction
    constraints, contact surfaces and cylinders, sub-models, deformable contact, volumetric visco
    terms, ...) raises :class:`NiftySimFormatError` naming it; what does not change the model
    (``Output``, hourglass kappa for tets) is ignored with a :class:`NiftySimImportWarning`.
    The element set number (from 1) is stored as cell data ``material_set``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such NiftySim model")
    with reading(path, "NiftySim XML model", "check it against NiftySim's model schema (docs/solver.md, NiftySim "
                 "interchange)"):
        return _read_model(path)


def _read_model(path: Path) -> Model:
    """:func:`read_niftysim`'s body (its errors made :class:`InputError` by the caller)."""
    r = _Reader(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as error:
        raise r.fail(f"not valid XML ({error})") from None
    if root.tag != "Model":
        raise r.fail(f"the root element is <{root.tag}>, a NiftySim model's is <Model>")
    for child in root:
        if child.tag in READ_ELEMENTS:
            continue
        if child.tag in IGNORED_ELEMENTS:
            r.warn(f"<{child.tag}> ignored: {IGNORED_ELEMENTS[child.tag]}")
            continue
        raise r.fail(f"<{child.tag}> is not supported (this project reads {', '.join(READ_ELEMENTS)}; "
                     "meshes must be inline Nodes/Elements of T4 or T4ANP, contact only rigid ContactPlates); "
                     "remove it or convert it, knowing the model changes")
    nodes, tets, formulation = _read_mesh(r, root)
    M = len(tets)
    system = _read_system(r, root)
    materials, material_set = _read_element_sets(r, root, M, system["Density"])
    constraints, gravity, gravity_shape = _read_constraints(r, root, nodes, tets)
    plates = _read_plates(r, root, nodes)
    if plates and gravity_shape not in (None, "POLY345"):
        raise r.fail(f"gravity is applied with LoadShape {gravity_shape} and the contact plates with POLY345 (NiftySim's "
                     "plates always move so); this project applies gravity and plates with one curve: use POLY345")
    try:
        loading = Loading(constraints, plates, gravity=gravity, total_time=system["TotalTime"],
                          load_shape=gravity_shape or "POLY345")
        mesh = TetMesh(nodes, tets, cell_data={"material_set": material_set})
        check_mesh(mesh, str(path))
        return Model(mesh, materials, loading, formulation=formulation, damping=system["DampingCoeff"],
                     time_step=system["TimeStep"], anp_across_materials=formulation == "T4ANP")
    except InputError:
        raise
    except ValueError as error:
        raise r.fail(str(error)) from None


def _read_mesh(r: _Reader, root: ET.Element) -> tuple[np.ndarray, np.ndarray, str]:
    nodes_el, elements_el = root.find("Nodes"), root.find("Elements")
    if nodes_el is None or elements_el is None:
        raise r.fail("a model needs inline <Nodes> and <Elements> (meshes in VTK or GMSH files are not read)")
    if nodes_el.get("DOF", "3") != "3":
        raise r.fail(f"<Nodes DOF={nodes_el.get('DOF')!r}>: only 3 degrees of freedom per node are supported")
    formulation = elements_el.get("Type", "")
    if formulation not in ("T4", "T4ANP"):
        raise r.fail(f"element type {formulation!r} is not supported; this project solves T4 and T4ANP tetrahedra")
    values = r.numbers(nodes_el, "<Nodes>")
    if len(values) % 3:
        raise r.fail(f"<Nodes> holds {len(values)} numbers, not a multiple of 3")
    nodes = values.reshape(-1, 3) / MM
    if nodes_el.get("NumNodes") is not None and r.attribute_number(nodes_el, "NumNodes", "<Nodes>", int) != len(nodes):
        raise r.fail(f"<Nodes NumNodes={nodes_el.get('NumNodes')}> but {len(nodes)} nodes are listed")
    ids = r.numbers(elements_el, "<Elements>", int)
    if len(ids) % 4:
        raise r.fail(f"<Elements> holds {len(ids)} node indices, not a multiple of 4")
    tets = ids.reshape(-1, 4)
    if elements_el.get("NumEls") is not None and r.attribute_number(elements_el, "NumEls", "<Elements>", int) != len(tets):
        raise r.fail(f"<Elements NumEls={elements_el.get('NumEls')}> but {len(tets)} elements are listed")
    if len(tets) == 0:
        raise r.fail("<Elements> lists no elements")
    if tets.min() < 0 or tets.max() >= len(nodes):
        raise r.fail(f"<Elements> refers to nodes outside 0..{len(nodes) - 1}")
    volume = TetMesh(nodes, tets).volumes
    flat = np.flatnonzero(np.abs(volume) <= 1e-12 * max(float(np.ptp(nodes)), 1.0) ** 3)
    if len(flat):
        raise r.fail(f"elements {flat[:10].tolist()} have zero volume; NiftySim cannot solve them either")
    tets = tets.copy()
    negative = volume < 0
    tets[negative, 2], tets[negative, 3] = tets[negative, 3], tets[negative, 2].copy()
    return nodes, tets, formulation


def _read_system(r: _Reader, root: ET.Element) -> dict:
    system = root.find("SystemParams")
    found = {}
    if system is not None:
        for child in system:
            if child.tag in SYSTEM_PARAMS_READ:
                values = r.numbers(child, f"<SystemParams><{child.tag}>")
                if len(values) != 1:
                    raise r.fail(f"<SystemParams><{child.tag}> must hold one number")
                found[child.tag] = float(values[0])
            elif child.tag in SYSTEM_PARAMS_FLAGS:
                values = r.numbers(child, f"<SystemParams><{child.tag}>")
                if len(values) and values[0] != 0:
                    raise r.fail(f"<SystemParams><{child.tag}> turns on {SYSTEM_PARAMS_FLAGS[child.tag]}, which this "
                                 "project does not model; set it to 0 or remove it, knowing the model changes")
            elif child.tag in SYSTEM_PARAMS_IGNORED:
                r.warn(f"<SystemParams><{child.tag}> ignored: {SYSTEM_PARAMS_IGNORED[child.tag]}")
            else:
                raise r.fail(f"<SystemParams><{child.tag}> is not a setting this project knows; remove it")
    for name in ("TimeStep", "TotalTime"):
        if name not in found:
            raise r.fail(f"<SystemParams><{name}> is missing (NiftySim requires it)")
    if found["TotalTime"] <= 0 or found["TimeStep"] <= 0:
        raise r.fail("<SystemParams> TimeStep and TotalTime must be positive (s)")
    found.setdefault("DampingCoeff", 0.0)
    found.setdefault("Density", None)
    if found["DampingCoeff"] < 0:
        raise r.fail("<SystemParams><DampingCoeff> must be >= 0 (1/s)")
    return found


def _read_element_sets(r: _Reader, root: ET.Element, M: int, default_density: float | None):
    columns = {name: np.full(M, np.nan) for name in ("mu", "kappa", "eta", "density")}
    fibre = np.tile([0.0, 0.0, 1.0], (M, 1))
    prony: list = [np.zeros((0, 2))] * M
    material_set = np.zeros(M, np.int32)
    for number, es in enumerate(root.findall("ElementSet"), start=1):
        what = f"element set {number}"
        m = es.find("Material")
        if m is None:
            raise r.fail(f"{what} has no <Material>")
        kind = m.get("Type", "")
        if kind not in MATERIAL_PARAMS:
            raise r.fail(f"{what}: material type {kind!r} is not supported (NH, TI, NHV, TIV)")
        params = r.numbers(m.find("ElasticParams"), f"{what} <ElasticParams>")
        if len(params) < MATERIAL_PARAMS[kind]:
            raise r.fail(f"{what}: a {kind} material needs {MATERIAL_PARAMS[kind]} elastic parameters, "
                         f"{len(params)} are given")
        listed = r.numbers(None, f"{what}'s element list", int, text=(es.text or "") + " " + (m.tail or ""))
        elements = r.listing(listed, es.get("Size"), M, what, "element")
        if np.any(material_set[elements]):
            twice = elements[material_set[elements] > 0][:5]
            raise r.fail(f"{what}: elements {twice.tolist()} belong to an earlier element set too")
        mu, kappa = params[0], params[1]
        if not (mu > 0 and kappa > 0):
            raise r.fail(f"{what}: mu and kappa must be positive (Pa), not {mu:g}, {kappa:g}")
        columns["mu"][elements], columns["kappa"][elements] = mu, kappa
        columns["eta"][elements] = params[2] / NIFTYSIM_ETA_PER_ETA if kind.startswith("TI") else 0.0
        if kind.startswith("TI"):
            if params[2] < 0:
                raise r.fail(f"{what}: the TI fibre parameter must be >= 0 Pa")
            direction = params[3:6]
            if np.linalg.norm(direction) == 0:
                raise r.fail(f"{what}: the TI fibre direction (a1 a2 a3) must not be zero")
            fibre[elements] = direction / np.linalg.norm(direction)
        density_el = m.find("Density")
        density = float(r.numbers(density_el, f"{what} <Density>")[0]) if density_el is not None else default_density
        if density is None or not density > 0:
            raise r.fail(f"{what} has no positive density: give <Density> in its material or in <SystemParams>")
        columns["density"][elements] = density
        if kind.endswith("V"):
            prony_terms = _read_visco(r, m, what)
            for e in elements:
                prony[e] = prony_terms
        material_set[elements] = number
    if np.any(material_set == 0):
        raise r.fail(f"elements {np.flatnonzero(material_set == 0)[:10].tolist()} belong to no ElementSet")
    K = max(len(p) for p in prony)
    g = np.zeros((M, K))
    tau = np.ones((M, K))
    for e, terms in enumerate(prony):
        if len(terms):
            g[e, :len(terms)], tau[e, :len(terms)] = terms[:, 0], terms[:, 1]
    try:
        materials = ElementMaterials(columns["mu"], columns["kappa"], columns["eta"], fibre, columns["density"], g, tau)
    except ValueError as error:
        raise r.fail(str(error)) from None
    return materials, material_set


def _read_visco(r: _Reader, m: ET.Element, what: str) -> np.ndarray:
    visco = m.find("ViscoParams")
    if visco is None:
        raise r.fail(f"{what}: a visco material needs <ViscoParams>")
    iso = r.attribute_number(visco, "NumIsoTerms", f"{what} <ViscoParams>", int)
    vol = r.attribute_number(visco, "NumVolTerms", f"{what} <ViscoParams>", int)
    terms = r.numbers(visco, f"{what} <ViscoParams>")
    if len(terms) != 2 * (iso + vol):
        raise r.fail(f"{what}: <ViscoParams> holds {len(terms)} numbers, NumIsoTerms {iso} and NumVolTerms {vol} "
                     f"need {2 * (iso + vol)}")
    if vol:
        raise r.fail(f"{what}: volumetric visco terms (NumVolTerms {vol}) are not modelled here (the volumetric "
                     "response is elastic); set NumVolTerms 0, knowing the model changes")
    return terms.reshape(-1, 2)[:iso]


def _nodes_facing(r: _Reader, c: ET.Element, nodes: np.ndarray, tets: np.ndarray, what: str) -> np.ndarray:
    """SpecType NORMAL: the nodes of the boundary facets whose outward normal lies within the
    tolerance angle (degrees) of ``Normal``."""
    if c.find("RestrictTo") is not None:
        raise r.fail(f"{what}: <RestrictTo> node rejectors are not supported; list the nodes instead")
    normal_el = c.find("Normal")
    if normal_el is None:
        raise r.fail(f"{what}: SpecType NORMAL needs a <Normal> with a ToleranceAngle")
    direction = r.numbers(normal_el, f"{what} <Normal>")
    if len(direction) != 3 or np.linalg.norm(direction) < 1e-6:
        raise r.fail(f"{what}: <Normal> must be three numbers of non-zero length")
    angle = r.attribute_number(normal_el, "ToleranceAngle", f"{what} <Normal>")
    if not 0 <= angle <= 180:
        raise r.fail(f"{what}: ToleranceAngle must lie in [0, 180] degrees, not {angle}")
    faces, _ = boundary_faces(tets)
    p = nodes[faces]
    facet = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    facet /= np.linalg.norm(facet, axis=1, keepdims=True)
    cosine = np.clip(facet @ (direction / np.linalg.norm(direction)), -1.0, 1.0)
    return np.unique(faces[np.degrees(np.arccos(cosine)) < angle])


def _read_constraints(r: _Reader, root: ET.Element, nodes: np.ndarray, tets: np.ndarray):
    N = len(nodes)
    constraints, gravity, gravity_shape = [], np.zeros(3), None
    for number, c in enumerate(root.findall("Constraint")):
        kind = c.get("Type")
        what = f"constraint {number} ({kind})"
        if kind not in CONSTRAINT_TYPES:
            raise r.fail(f"constraint {number}: type {kind!r} is not supported (Fix, Disp, Gravity); Force, Pressure "
                         "and Traction loads are not modelled here")
        shape = c.get("LoadShape")
        if shape is not None and shape not in LOAD_SHAPES:
            raise r.fail(f"{what}: LoadShape {shape!r} is not one of {', '.join(LOAD_SHAPES)} (NiftySim would fall back "
                         "to POLY345 with a warning); correct it")
        if c.get("SpecType") == "NORMAL":
            ids = _nodes_facing(r, c, nodes, tets, what)
        else:
            listed = r.numbers(c.find("Nodes"), f"{what} <Nodes>", int) if c.find("Nodes") is not None \
                else np.zeros(0, np.int64)
            if c.get("NumNodes") is None:
                raise r.fail(f"{what} needs a NumNodes attribute (a count or \"all\") or SpecType=\"NORMAL\"")
            ids = r.listing(listed, c.get("NumNodes"), N, what, "node")
        if kind == "Gravity":
            if np.any(gravity):
                raise r.fail(f"{what}: a second Gravity constraint; give one")
            if len(np.unique(ids)) != N:
                raise r.fail(f"{what} acts on {len(np.unique(ids))} of {N} nodes; this project applies gravity to "
                             "every node")
            magnitude = r.numbers(c.find("AccelerationMagnitude"), f"{what} <AccelerationMagnitude>")
            direction = r.numbers(c.find("AccelerationDirection"), f"{what} <AccelerationDirection>")
            if len(magnitude) != 1 or len(direction) != 3:
                raise r.fail(f"{what}: AccelerationMagnitude is one number and AccelerationDirection three")
            gravity = magnitude[0] * direction  # NiftySim scales the direction as given
            gravity_shape = shape or "POLY345"
            continue
        dof = c.get("DOF", "all")
        if dof not in ("0", "1", "2", "all"):
            raise r.fail(f"{what}: DOF {dof!r} must be 0, 1, 2 or \"all\"")
        mask = np.ones(3, bool) if dof == "all" else np.arange(3) == int(dof)
        values = np.zeros((len(ids), 3))
        if kind == "Disp":
            if shape is None:
                raise r.fail(f"{what} needs a LoadShape attribute (NiftySim requires it for Disp)")
            values[:, mask] = _magnitudes(r, c, len(ids), what)[:, None]
        constraints.append(Constraint(ids, np.tile(mask, (len(ids), 1)), values,
                                      load_shape=shape if kind == "Disp" else None))
    return constraints, gravity, gravity_shape


def _magnitudes(r: _Reader, c: ET.Element, count: int, what: str) -> np.ndarray:
    """The Disp magnitudes (mm) of ``count`` nodes: UNIFORM (one value for all) or DIFFORM (one per node)."""
    element = c.find("Magnitudes")
    if element is None:
        raise r.fail(f"{what} needs <Magnitudes>")
    kind = element.get("Type", "")
    values = r.numbers(element, f"{what} <Magnitudes>") / MM
    if kind == "UNIFORM":
        if len(values) != 1:
            raise r.fail(f"{what}: UNIFORM magnitudes are one value, {len(values)} are given")
        return np.full(count, values[0])
    if kind == "DIFFORM":
        if len(values) != count:
            raise r.fail(f"{what}: DIFFORM lists {len(values)} magnitudes for {count} nodes; give one per node")
        return values
    raise r.fail(f"{what}: magnitude type {kind!r} is not supported (UNIFORM, DIFFORM)")


def _read_plates(r: _Reader, root: ET.Element, nodes: np.ndarray) -> list[Plate]:
    plates = []
    for i, p in enumerate(root.findall("ContactPlate")):
        what = f"contact plate {i}"
        a, b, c = (r.numbers(p.find(name), f"{what} <{name}>") / MM for name in ("a", "b", "c"))
        displacement = r.numbers(p.find("Disp"), f"{what} <Disp>") / MM
        if any(len(v) != 3 for v in (a, b, c, displacement)):
            raise r.fail(f"{what}: the corners a, b, c and Disp are three numbers each")
        normal = np.cross(b - a, c - a)
        if np.linalg.norm(normal) == 0:
            raise r.fail(f"{what}: its corners a, b, c lie on one line")
        slaves_el = p.find("SlvNodes")
        if slaves_el is None:
            raise r.fail(f"{what} needs <SlvNodes>")
        slaves = r.listing(r.numbers(slaves_el, f"{what} <SlvNodes>", int), slaves_el.get("NumNodes"), len(nodes),
                           what, "node")
        edge = None
        if p.get("EdgeDirection") is not None:
            edge = PlateEdge(r.numbers(None, f"{what} EdgeDirection", text=p.get("EdgeDirection")),
                             r.attribute_number(p, "EdgeDistance", what) / MM,
                             r.attribute_number(p, "EdgeRadius", what) / MM)
        else:
            u, v = b - a, c - a
            rel = nodes[slaves] - a
            s, t = rel @ u / (u @ u), rel @ v / (v @ v)
            outside = int(np.sum((s < 0) | (s > 1) | (t < 0) | (t > 1)))
            if outside:
                r.warn(f"{what}: {outside} of its contact nodes start outside its rectangle; it is read as an "
                       "unbounded plane, so those nodes touch it here and would not in NiftySim")
        try:
            plates.append(Plate(a, normal, displacement, slaves, p.get("Name", f"plate{i}"), edge=edge))
        except ValueError as error:
            raise r.fail(f"{what}: {error}") from None
    return plates

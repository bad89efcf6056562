"""NiftySim XML model files: write a :class:`~BreastBiomechLib.solver.Model` so the same case runs
in NiftySim (``niftysim -x MODEL.xml``), and read such files back.

The file is in SI units, as the solver works internally: node coordinates in metres, moduli in
Pa, density kg/m^3, time s, gravity m/s^2 (the library's models are in millimetres; the reader
converts back). Mapping (see docs/solver.md and NiftySim's user guide):

- ``Elements Type`` = the formulation (T4ANP or T4); one ``ElementSet`` per distinct material,
  ``Material Type`` NH / TI (eta > 0) / NHV / TIV (Prony terms, ``ViscoParams`` with the
  isochoric (g_i, tau_i) pairs and no volumetric terms), ``ElasticParams`` mu kappa [eta a1 a2 a3];
- constraints: per component one ``Fix`` (zero values) or ``Disp`` (``Magnitudes`` per node)
  constraint with ``LoadShape``; gravity as a ``Gravity`` constraint on every node;
- plates: ``ContactPlate`` with corners ``a``, ``b``, ``c`` of a rectangle covering the slave
  nodes, (b - a) x (c - a) along the plate normal towards the tissue, ``Disp`` its translation;
- ``SystemParams``: TimeStep, TotalTime (the loading time; NiftySim has no settling phase at
  full load, so a model with ``settle_time`` is refused unless the caller accepts dropping it),
  DampingCoeff, Density.
"""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.materials import ElementMaterials
from BreastBiomechLib.solver.model import Constraint, Loading, Model, Plate
from BreastBiomechLib.solver.tled import critical_time_step, merged_constraints

MM = 1e-3
AXES = "012"


def _text(values, per_line: int) -> str:
    values = np.asarray(values).reshape(-1, per_line)
    return "\n" + "\n".join(" ".join(f"{v:.9g}" for v in row) for row in values) + "\n"


def _material_sets(mat: ElementMaterials) -> tuple[np.ndarray, np.ndarray]:
    """Rows of distinct (mu, kappa, eta, fibre, density, Prony) and each element's row."""
    table = np.column_stack([mat.mu, mat.kappa, mat.eta, mat.fibre, mat.density, mat.prony_g, mat.prony_tau])
    return np.unique(table, axis=0, return_inverse=True)


def write_niftysim(path: str | Path, model: Model, drop_settling: bool = False) -> Path:
    """Write ``model`` as a NiftySim XML file (SI units); returns the path. NiftySim moves plates
    with POLY345 and has no settling phase: other load shapes are refused, and a model with
    ``settle_time`` unless ``drop_settling``. Its ``ContactPlate`` is frictionless: plates with
    friction are refused (a plate's pose, tilted or not, is written as its corners; gravity as
    a ``Gravity`` constraint)."""
    rough = [f"{p.name} (mu {p.friction:g})" for p in model.loading.plates if p.friction > 0]
    if rough:
        raise ValueError(f"NiftySim's ContactPlate is frictionless, so plates {', '.join(rough)} cannot be written "
                         "as they are; set their friction to 0 to export the frictionless model")
    if model.loading.plates and model.loading.load_shape != "POLY345":
        raise ValueError("NiftySim moves contact plates with POLY345 only; use that load shape to export")
    if model.loading.settle_time and not drop_settling:
        raise ValueError(f"NiftySim has no settling phase: this model settles for {model.loading.settle_time} s "
                         "after loading; pass drop_settling=True to export the loading only")
    path = Path(path)
    root = ET.Element("Model")
    mesh, mat = model.mesh, model.materials
    ET.SubElement(root, "Nodes", DOF="3", NumNodes=str(len(mesh.nodes))).text = _text(mesh.nodes * MM, 3)
    ET.SubElement(root, "Elements", NumEls=str(len(mesh.tets)), Type=model.formulation).text = _text(mesh.tets, 4)
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
        params = [mu, kappa] + ([eta, a1, a2, a3] if eta > 0 else [])
        ET.SubElement(m, "ElasticParams", NumParams=str(len(params))).text = _text(params, len(params))
        if visco:
            terms = np.column_stack([g[g > 0], tau[g > 0]])
            ET.SubElement(m, "ViscoParams", NumIsoTerms=str(len(terms)), NumVolTerms="0").text = _text(terms, 2)
        ET.SubElement(m, "Density").text = f"{density:.9g}"
        es.text = None
        m.tail = _text(elements, 1)
    nodes, mask, values = merged_constraints(model)
    shape = model.loading.load_shape
    for axis in range(3):
        on = mask[:, axis]
        for kind, pick in (("Fix", on & (values[:, axis] == 0)), ("Disp", on & (values[:, axis] != 0))):
            if not np.any(pick):
                continue
            c = ET.SubElement(root, "Constraint", DOF=AXES[axis], NumNodes=str(int(pick.sum())), Type=kind,
                              LoadShape=shape)
            ET.SubElement(c, "Nodes").text = _text(nodes[pick], 1)
            if kind == "Disp":
                ET.SubElement(c, "Magnitudes", Type="DIFFORM").text = _text(values[pick, axis] * MM, 1)
    gravity = model.loading.gravity
    if np.any(gravity):
        c = ET.SubElement(root, "Constraint", NumNodes=str(len(mesh.nodes)), Type="Gravity", LoadShape=shape)
        ET.SubElement(c, "Nodes").text = _text(np.arange(len(mesh.nodes)), 1)
        ET.SubElement(c, "AccelerationMagnitude").text = f"{np.linalg.norm(gravity):.9g}"
        ET.SubElement(c, "AccelerationDirection").text = _text(gravity / np.linalg.norm(gravity), 3)
    for plate in model.loading.plates:
        a, b, c = _plate_corners(plate, mesh.nodes)
        p = ET.SubElement(root, "ContactPlate")
        for name, corner in (("a", a), ("b", b), ("c", c)):
            ET.SubElement(p, name).text = _text(corner * MM, 3)
        ET.SubElement(p, "Disp").text = _text(plate.displacement * MM, 3)
        ET.SubElement(p, "SlvNodes", NumNodes=str(len(plate.slave_nodes))).text = _text(plate.slave_nodes, 1)
    system = ET.SubElement(root, "SystemParams")
    dt = model.time_step or model.safety * critical_time_step(model, [mat])
    ET.SubElement(system, "TimeStep").text = f"{dt:.9g}"
    ET.SubElement(system, "TotalTime").text = f"{model.loading.total_time:.9g}"
    ET.SubElement(system, "DampingCoeff").text = f"{model.damping:.9g}"
    ET.SubElement(system, "Density").text = f"{float(np.median(mat.density)):.9g}"
    ET.indent(root)
    path.parent.mkdir(parents=True, exist_ok=True)
    ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)
    return path


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
                      "and NiftySim's result will differ near that edge", stacklevel=3)
    rel = (nodes_mm[plate.slave_nodes] if len(plate.slave_nodes) else nodes_mm) - plate.point
    s, t = rel @ e1, rel @ e2
    margin = 0.5 * max(np.ptp(s), np.ptp(t), 1.0)
    s0, s1, t0, t1 = s.min() - margin, s.max() + margin, t.min() - margin, t.max() + margin
    if plate.edge is not None:
        t1 = min(t1, plate.edge.distance)
    a = plate.point + s0 * e1 + t0 * e2
    return a, plate.point + s1 * e1 + t0 * e2, plate.point + s0 * e1 + t1 * e2


def _numbers(element, dtype=float) -> np.ndarray:
    return np.array((element.text or "").split(), dtype=dtype)


def read_niftysim(path: str | Path) -> Model:
    """Read a NiftySim XML model written by :func:`write_niftysim` (or by hand in the same
    subset: Nodes, T4/T4ANP Elements, NH/TI/NHV/TIV element sets, Fix/Disp/Gravity constraints,
    ContactPlate, SystemParams). Geometry comes back in mm; the element set number (from 1) is
    stored as cell data ``material_set``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such NiftySim model")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as error:
        raise ValueError(f"{path}: not valid XML ({error})") from None
    nodes_el, elements_el = root.find("Nodes"), root.find("Elements")
    if nodes_el is None or elements_el is None:
        raise ValueError(f"{path}: a NiftySim model needs <Nodes> and <Elements> (mesh files are not supported)")
    formulation = elements_el.get("Type", "T4")
    if formulation not in ("T4", "T4ANP"):
        raise ValueError(f"{path}: element type {formulation!r} is not supported; use T4 or T4ANP")
    nodes = _numbers(nodes_el).reshape(-1, 3) / MM
    tets = _numbers(elements_el, np.int64).reshape(-1, 4)
    M = len(tets)
    system = root.find("SystemParams")

    def system_value(name, default):
        found = system.find(name) if system is not None else None
        return float(found.text) if found is not None else default

    default_density = system_value("Density", 1000.0)
    columns = {name: np.full(M, np.nan) for name in ("mu", "kappa", "eta", "density")}
    fibre = np.tile([0.0, 0.0, 1.0], (M, 1))
    prony = [[] for _ in range(M)]
    material_set = np.zeros(M, np.int32)
    for number, es in enumerate(root.findall("ElementSet"), start=1):
        m = es.find("Material")
        kind = m.get("Type", "")
        if kind not in ("NH", "TI", "NHV", "TIV"):
            raise ValueError(f"{path}: material type {kind!r} is not supported (NH, TI, NHV, TIV)")
        params = _numbers(m.find("ElasticParams"))
        elements = np.array(((es.text or "") + " " + (m.tail or "")).split(), dtype=np.int64)
        if len(elements) != int(es.get("Size", len(elements))):
            raise ValueError(f"{path}: element set {number} lists {len(elements)} elements, Size says {es.get('Size')}")
        columns["mu"][elements], columns["kappa"][elements] = params[0], params[1]
        columns["eta"][elements] = params[2] if kind.startswith("TI") else 0.0
        if kind.startswith("TI"):
            fibre[elements] = params[3:6] / np.linalg.norm(params[3:6])
        density = m.find("Density")
        columns["density"][elements] = float(density.text) if density is not None else default_density
        if kind.endswith("V"):
            terms = _numbers(m.find("ViscoParams")).reshape(-1, 2)[: int(m.find("ViscoParams").get("NumIsoTerms"))]
            for e in elements:
                prony[e] = terms
        material_set[elements] = number
    if np.any(material_set == 0):
        raise ValueError(f"{path}: elements {np.flatnonzero(material_set == 0)[:10].tolist()} belong to no ElementSet")
    K = max(len(p) for p in prony)
    g = np.zeros((M, K))
    tau = np.ones((M, K))
    for e, terms in enumerate(prony):
        if len(terms):
            g[e, :len(terms)], tau[e, :len(terms)] = terms[:, 0], terms[:, 1]
    materials = ElementMaterials(columns["mu"], columns["kappa"], columns["eta"], fibre, columns["density"], g, tau)

    constraints, gravity, shape = [], np.zeros(3), "POLY345"
    for c in root.findall("Constraint"):
        kind = c.get("Type")
        shape = c.get("LoadShape", shape)
        if kind == "Gravity":
            gravity = float(c.find("AccelerationMagnitude").text) * _numbers(c.find("AccelerationDirection"))
            continue
        if kind not in ("Fix", "Disp"):
            raise ValueError(f"{path}: constraint type {kind!r} is not supported (Fix, Disp, Gravity)")
        ids = _numbers(c.find("Nodes"), np.int64)
        dof = c.get("DOF", "all")
        mask = np.array([True] * 3) if dof == "all" else np.arange(3) == int(dof)
        values = np.zeros((len(ids), 3))
        if kind == "Disp":
            magnitudes = _numbers(c.find("Magnitudes")) / MM
            values[:, mask] = np.broadcast_to(magnitudes, (len(ids),))[:, None]
        constraints.append(Constraint(ids, np.tile(mask, (len(ids), 1)), values))
    plates = []
    for i, p in enumerate(root.findall("ContactPlate")):
        a, b, c = (_numbers(p.find(name)) / MM for name in ("a", "b", "c"))
        plates.append(Plate(a, np.cross(b - a, c - a), _numbers(p.find("Disp")) / MM,
                            _numbers(p.find("SlvNodes"), np.int64), f"plate{i}"))
    total = system_value("TotalTime", 1.0)
    loading = Loading(constraints, plates, gravity=gravity, total_time=total, load_shape=shape)
    mesh = TetMesh(nodes, tets, cell_data={"material_set": material_set})
    return Model(mesh, materials, loading, formulation=formulation, damping=system_value("DampingCoeff", 0.0),
                 time_step=system_value("TimeStep", None))

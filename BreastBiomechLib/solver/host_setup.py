"""The host's set-up of a solve, shared by the TLED solver, the static reference and the NiftySim
export: stable time steps, the materials' table and ANP slots as the kernels read them, merged
constraints and their load curves, the plates' records, each batch model's plate set.

Units: SI inside (m, Pa, kg/m^3, s) where a value goes to the kernels; mm where it comes from a
:class:`~BreastBiomechLib.solver.model.Model`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import warp as wp

from BreastBiomechLib.solver import kernels as k
from BreastBiomechLib.solver.geometry import MeshGeometry
from BreastBiomechLib.solver.materials import ElementMaterials, element_groups
from BreastBiomechLib.solver.model import LOAD_SHAPES, Model, Plate
from BreastBiomechLib.solver.relaxation import MM
from BreastBiomechLib.solver.settings import DynamicRelaxation

# models an element-kernel thread computes, by the count of models listed: (up to this many models,
# this many a thread). In a batch the element kernels are bound by their instruction issue (74 % of
# the issue slots busy at 16 and 64 models, Nsight Compute, H200), and a thread that takes several
# models reads and indexes its element's connectivity, derivatives and volume once for them; with
# too few threads an element the GPU has too few to hide latencies (docs/benchmarks.md)
MODELS_PER_THREAD = ((8, 1), (32, 2), (1 << 30, 4))
UNBOUNDED_M = 1e20  # the edge distance (m) of a plate without an edge: never reached
FLOAT32_ROUNDING = 2.0 ** -24  # float32's relative rounding error (half an ulp of 1)


def wave_modulus(mat: ElementMaterials) -> np.ndarray:
    """Per element, the largest small-strain longitudinal (P-wave) modulus (Pa):
    kappa + 4 mu / 3 + 16 eta / 9. The fibre term eta/2 (I4bar - 1)^2 stiffens a uniaxial strain
    e along the fibre by 16 eta / 9 (I4bar - 1 = 4 e / 3 there); along other directions by less."""
    return mat.kappa + 4.0 * mat.mu / 3.0 + 16.0 * mat.eta / 9.0


def wave_speed_ratio(mat: ElementMaterials) -> float:
    """The largest c_dilatational / c_shear = sqrt(wave_modulus / mu) over the elements: how many
    times faster than the slowest shear wave the loads' prescribed motion must stay below."""
    return float(np.max(np.sqrt(wave_modulus(mat) / mat.mu)))


def stress_noise_floor_mm(materials: list[ElementMaterials], length_m: np.ndarray) -> np.ndarray:
    """(B,) the displacement (mm) below which float32 cannot resolve each model's equilibrium:
    float32 rounding of J - 1 times the largest bulk-to-shear modulus ratio, over the median element
    altitude. A volumetric stress kappa (J - 1) is rounded by about kappa x 6e-8, which the shear
    stiffness answers with a strain of that over mu. On a block of 2.5 mm cubes at rest the largest
    nodal change between relaxation updates stays at 0.8e-6-2e-6 mm for nu = 0.49 (kappa / mu = 50)
    and wanders at 2e-5-9e-5 mm for nu = 0.4999 (kappa / mu = 5 000): between a 25th and a third
    of this bound (5.2e-6 and 5.3e-4 mm there)."""
    ratio = np.array([float(np.max(m.kappa / np.maximum(m.mu, 1e-30))) for m in materials])
    return FLOAT32_ROUNDING * ratio * float(np.median(length_m)) / MM


def critical_time_step(model: Model, materials: list[ElementMaterials], length_m: np.ndarray | None = None) -> float:
    """min over elements and batch of L_e / c_d, c_d = sqrt(wave_modulus / rho) (s), the fibres
    counted; ``length_m`` the element altitudes if already computed."""
    if length_m is None:
        length_m = MeshGeometry.of(model.mesh.nodes, model.mesh.tets).length
    return float(min(np.min(length_m / np.sqrt(wave_modulus(m) / m.density)) for m in materials))


def merged_constraints(model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One row per constrained node (node ids, (K, 3) mask, (K, 3) final values in mm): a node in
    several constraints gets the union of their components. The kernel writes each node from one
    thread only. Two different values for one component of one node are an error."""
    cons = model.loading.constraints
    if not cons:
        return np.zeros(0, np.int64), np.zeros((0, 3), bool), np.zeros((0, 3))
    nodes = np.concatenate([c.nodes for c in cons])
    masks = np.concatenate([c.mask for c in cons])
    values = np.concatenate([c.values for c in cons])
    unique, inverse = np.unique(nodes, return_inverse=True)
    mask = np.zeros((len(unique), 3), bool)
    merged = np.zeros((len(unique), 3))
    np.logical_or.at(mask, inverse, masks)
    np.add.at(merged, inverse, np.where(masks, values, 0.0))
    count = np.zeros((len(unique), 3))
    np.add.at(count, inverse, masks.astype(float))
    merged = np.divide(merged, count, out=np.zeros_like(merged), where=count > 0)
    spread = np.zeros((len(unique), 3))
    np.maximum.at(spread, inverse, np.where(masks, np.abs(values - merged[inverse]), 0.0))
    if np.any(spread > 1e-9):
        bad = unique[np.any(spread > 1e-9, axis=1)][:5]
        raise ValueError(f"nodes {bad.tolist()} are given different prescribed values for the same component")
    return unique, mask, merged


def plate_pose(plate: Plate) -> k.PlatePose:
    """The kernels' record of ``plate`` (:class:`kernels.PlatePose`, SI units): its mm
    converted to m, an edgeless plate's face ending at :data:`UNBOUNDED_M`."""
    pose = k.PlatePose()
    pose.point = wp.vec3(*(np.asarray(plate.point, np.float64) * MM))
    pose.normal = wp.vec3(*np.asarray(plate.normal, np.float64))
    pose.motion = wp.vec3(*(np.asarray(plate.displacement, np.float64) * MM))
    pose.edge_direction = wp.vec3(*(np.asarray(plate.edge.direction, np.float64) if plate.edge else np.zeros(3)))
    pose.edge_distance = plate.edge.distance * MM if plate.edge else UNBOUNDED_M
    pose.edge_radius = plate.edge.radius * MM if plate.edge else 1.0
    pose.friction = plate.friction
    return pose


def constraint_load_shapes(model: Model, nodes: np.ndarray) -> np.ndarray:
    """The load curve of each component of the merged constraint rows (``nodes`` from
    :func:`merged_constraints`), as (K, 3) indices into ``LOAD_SHAPES``: a constraint's own shape,
    else the loading's. Two shapes for one non-zero component of one node are an error (a fixed
    component, value 0, is 0 under any curve)."""
    default = LOAD_SHAPES.index(model.loading.load_shape)
    shapes = np.full((len(nodes), 3), default, np.int32)
    chosen = np.zeros((len(nodes), 3), bool)
    for c in model.loading.constraints:
        if c.load_shape is None or not len(c.nodes):
            continue
        rows = np.searchsorted(nodes, c.nodes)
        moving = c.mask & (c.values != 0)
        code = LOAD_SHAPES.index(c.load_shape)
        clash = moving & chosen[rows] & (shapes[rows] != code)
        if np.any(clash):
            bad = c.nodes[np.any(clash, axis=1)][:5]
            raise ValueError(f"nodes {bad.tolist()} are given two load shapes for the same displaced component")
        shapes[rows] = np.where(moving, code, shapes[rows])
        chosen[rows] |= moving
    return shapes


def material_table(materials: list[ElementMaterials]) -> k.MaterialTable:
    """The B sets' materials as the kernels read them (:class:`kernels.MaterialTable`, on the
    current device): one row per group of elements whose float32 mu, kappa, eta and fibre agree in
    every set, model b's entry of row r at r * B + b."""
    f32 = np.float32
    row = element_groups(materials, lambda m: (m.mu.astype(f32), m.kappa.astype(f32), m.eta.astype(f32),
                                               *m.fibre.T.astype(f32)))
    first = np.zeros(int(row.max()) + 1, np.int64)
    first[row] = np.arange(len(row))  # one element of each row

    records = np.stack([np.column_stack([m.mu[first], m.kappa[first], m.eta[first], m.fibre[first]])
                        for m in materials], axis=1)  # (R, B, 6): mu, kappa, eta, fibre
    records = np.ascontiguousarray(records.reshape(-1, 6), dtype=f32).view(k.ElementMaterial.numpy_dtype())
    table = k.MaterialTable()
    table.row = wp.array(row.astype(np.int32), dtype=int)
    table.values = wp.array(records.reshape(-1), dtype=k.ElementMaterial)
    return table


def anp_slots(tets: np.ndarray, materials: list[ElementMaterials], vol: np.ndarray,
              across_materials: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """ANP's averaging slots: one per node and material, so that the nodal pressure is averaged
    over the elements of one material only (materials told apart by their bulk moduli, in every
    parameter set of the batch). Averaging across materials would divide a stiff neighbour's
    pressure by a soft element's bulk modulus, amplifying it by their ratio (10 from fat to
    muscle), and collapse thin soft layers. ``across_materials``: one slot per node, as
    NiftySim's T4ANP (``Model.anp_across_materials``). Returns the slot of each element node
    (M, 4) and each slot's volume (S,) (sum of its elements' volumes, the units of ``vol``)."""
    group = np.zeros(len(tets), np.int64) if across_materials else element_groups(
        materials, lambda m: [np.asarray(m.kappa, np.float64)])
    groups = int(group.max()) + 1
    pairs = tets.astype(np.int64) * groups + group[:, None]
    if int(pairs.max()) < 8 * pairs.size:  # number the (node, material) pairs present, in their order
        present = np.zeros(int(pairs.max()) + 1, bool)
        present[pairs.ravel()] = True
        slots = (np.cumsum(present) - 1)[pairs]
        n_slots = int(np.count_nonzero(present))
    else:  # very many materials: sort the pairs instead
        unique_pairs, slots = np.unique(pairs.ravel(), return_inverse=True)
        n_slots = len(unique_pairs)
    slots = slots.reshape(tets.shape).astype(np.int32)
    return slots, np.bincount(slots.ravel(), weights=np.repeat(vol, 4), minlength=n_slots)


def anp_partition_classes(materials: list[ElementMaterials], across_materials: bool = False) -> np.ndarray:
    """(B,) for each parameter set of a batch, the class of its own ANP partition (its elements
    grouped by its own bulk moduli, as :func:`anp_slots` of that set alone would): sets of one
    class average their nodal pressure over the same groups. A batch's slots are the union of its
    sets' partitions, so a set batched with another of a different class (a skin layer stiffer
    than the fat under it, a gland told from the fat) would average over a finer partition than
    its own, and its solution would depend on its batch partners (1 mm on a coarse fitting mesh).
    All 0 with ``across_materials`` (one slot per node)."""
    classes = np.zeros(len(materials), np.int64)
    if across_materials or len(materials) < 2:
        return classes
    shared = [m.rows for m in materials]
    if all(r is not None for r in shared) and all(r[1] is shared[0][1] or np.array_equal(r[1], shared[0][1])
                                                  for r in shared[1:]):
        # one tissue labelling: each set's partition of the tissues present, its groups numbered
        # in the order they first occur (a fit's batch: no pass over the elements per set)
        row = shared[0][1]
        present = np.flatnonzero(np.bincount(np.ravel(row), minlength=len(shared[0][0].kappa)))
        keys: dict[bytes, int] = {}
        for b, (table, _) in enumerate(shared):
            _, first, inverse = np.unique(np.asarray(table.kappa, np.float64)[present], return_index=True,
                                          return_inverse=True)
            key = np.argsort(np.argsort(first))[np.ravel(inverse)].tobytes()
            classes[b] = keys.setdefault(key, len(keys))
        return classes
    representatives: list[tuple[np.ndarray, int]] = []
    for b, mat in enumerate(materials):
        group = element_groups([mat], lambda m: [np.asarray(m.kappa, np.float64)])
        n = int(group.max()) + 1
        for c, (other, count) in enumerate(representatives):
            # the same partition: as many groups, each group of one set inside one group of the other
            if count == n and np.count_nonzero(np.bincount(group * n + other, minlength=n * n)) == n:
                classes[b] = c
                break
        else:
            classes[b] = len(representatives)
            representatives.append((group, n))
    return classes


def anp_mode(model: Model) -> int:
    """The element kernels' ANP mode for ``model`` (``kernels.ANP_*``)."""
    if model.formulation != "T4ANP":
        return k.ANP_OFF
    return k.ANP_ACROSS_MATERIALS if model.anp_across_materials else k.ANP_WITHIN_MATERIALS


def plate_sets_of_batch(model: Model, n_models: int, plate_displacements: list | None = None,
                        plates: list[list[Plate]] | None = None) -> list[list[Plate]]:
    """The plates of each of the ``n_models`` models of a batch: the model's own, with
    ``plate_displacements[b]`` (P, 3) mm as model b's travel, or the given ``plates[b]`` (which
    must be the model's plates in number, order and contact nodes: the contact launches share
    the node lists)."""
    own = model.loading.plates
    if plates is not None and plate_displacements is not None:
        raise ValueError("give either plate_displacements or plates per model, not both")
    if plates is None:
        if plate_displacements is None:
            return [own] * n_models
        if len(plate_displacements) != n_models:
            raise ValueError("give one plate displacement set per material set")
        plates = []
        for motion in plate_displacements:
            motion = np.asarray(motion, float).reshape(len(own), 3)
            plates.append([replace(p, displacement=d) for p, d in zip(own, motion)])
        return plates
    if len(plates) != n_models:
        raise ValueError(f"give one plate set per material set ({n_models}), not {len(plates)}")
    for b, ps in enumerate(plates):
        if len(ps) != len(own) or any(not np.array_equal(p.slave_nodes, o.slave_nodes) for p, o in zip(ps, own)):
            raise ValueError(f"plate set {b} must hold the model's {len(own)} plates with their contact nodes "
                             "(only pose, travel, edge and friction may differ between the models of a batch)")
        for p in ps:
            p.check_clear_of(model.start_positions[p.slave_nodes])
    return plates


def element_lanes(width: int) -> int:
    """Threads per element of the element kernels for ``width`` listed models: each thread
    computes up to :data:`MODELS_PER_THREAD`'s number of them, reading its element's own data
    once."""
    per_thread = next(k for most, k in MODELS_PER_THREAD if width <= most)
    return -(-width // per_thread)


def relaxation_load_iterations(model: Model, materials: list[ElementMaterials], plate_sets: list[list[Plate]],
                               relaxation: DynamicRelaxation, length_m: np.ndarray | None = None) -> np.ndarray:
    """(B,) the iterations over which dynamic ``relaxation`` applies each variant's load
    (:meth:`DynamicRelaxation.load_iterations_for` with the variant's fully relaxed
    ``materials[b]``, plates ``plate_sets[b]``, the model's constraints and extent), as
    :func:`solve_batch` does; ``length_m``: the elements' altitudes if already computed."""
    nodes = model.mesh.nodes * MM
    if length_m is None:
        length_m = MeshGeometry.of(model.mesh.nodes, model.mesh.tets).length
    constrained = max([np.abs(c.values).max(initial=0.0) for c in model.loading.constraints] + [0.0])
    extent = float(np.max(np.ptp(nodes, axis=0)))
    typical = float(np.median(length_m))
    return np.array([
        relaxation.load_iterations_for(max([np.abs(p.displacement).max() for p in ps] + [constrained]),
                                       wave_speed_ratio(m), typical, model.safety,
                                       extent if any(p.friction > 0 for p in ps) else 0.0)
        for m, ps in zip(materials, plate_sets)])

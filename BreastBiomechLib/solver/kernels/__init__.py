"""Warp kernels of the TLED solver (total Lagrangian explicit dynamics), by concern: :mod:`.common`
(load curves, model lists, force planes, the material table), :mod:`.element` (stresses and
element forces, written once), :mod:`.node` (the step's node update), :mod:`.contact` (constraints,
supports, plates) and :mod:`.reductions` (the sample's per-model sums). Their names are exported here:
``from BreastBiomechLib.solver import kernels as k; k.node_kernel(...)``.

All kernels work on a batch of B models that share one mesh, models innermost: node arrays hold
N*B entries (model b's node a at a*B + b), element arrays M*B (element e at e*B + b), ANP slot
arrays S*B, so that the threads of one element (or node) for the B models are neighbours: they
read the element's connectivity and shape-function derivatives once between them, and their
displacements and forces side by side. Materials are a table of rows shared by the elements of a
tissue (:class:`MaterialTable`). Nodal forces are three planes of floats, one per
component (``forces[c, a*B + b]``, :func:`add_force` and :func:`force_at`): the element kernel's
atomic adds of one component then fall on consecutive addresses, where a vec3 array spreads them
over three times as many memory sectors (an ANP step 18-21 % faster on the H200 at 160k-2M tets,
docs/benchmarks.md). Units inside the kernels are SI:
metres, pascal, kilograms, seconds, newtons. Vectors are in the mesh frame (LPS axes).

The step kernels work on a *list* of n models, ``models[:n]`` (the models still moving in a
relaxation, every model otherwise; n a launch parameter): thread t handles entry t mod n of the
list for element (or node) t div n, so the listed models' work is packed into consecutive threads
whatever the batch size, and a launch needs only n x (elements or nodes) threads (more are allowed;
they return at once). With every model listed (n = B) the list is not read at all. Until 2026-11-28
every kernel ran B threads per element and converged models' threads returned: fitted over a fit's
batches of 16 on a 54k-tet mesh, a step cost about 65 us however few models still moved, against 30
us for one slow model solved alone (H200, docs/benchmarks.md). For longer lists the element
kernels' ``_shared`` variants run L = ceil(n / K) threads ("lanes") an element, lane l computing
the entries l, l + L, l + 2L, ... (K from :data:`BreastBiomechLib.solver.host_setup.MODELS_PER_THREAD`):
a thread reads and indexes its element's connectivity, derivatives and volume once for its models,
and neighbouring lanes' models still lie side by side in memory (a batch of 64 steps 10-12 % faster,
of 16 5 %; H200, docs/benchmarks.md). Once half of a batch has stopped, the solver packs it down to
the models still moving (:mod:`BreastBiomechLib.solver.packing`): the kernels see a smaller batch.
The element kernels are built per formulation (:func:`element_kernels`: the ANP mode, Prony terms
or none, ANP slots that are the nodes or not, as compile-time constants), so that each holds only
its formulation's branches and registers.
"""

from BreastBiomechLib.solver.kernels.common import (
    ANP_ACROSS_MATERIALS,
    ANP_OFF,
    ANP_WITHIN_MATERIALS,
    LOAD_HILLY,
    LOAD_POLY345,
    LOAD_RAMP,
    LOAD_RAMPHOLD,
    LOAD_STEP,
    SPECIALISED,
    ElementMaterial,
    MaterialTable,
    NodeState,
    add_force,
    clipped,
    element_and_lane,
    force_at,
    listed,
    load_factor,
    material_of,
    model_at,
    set_component,
)
from BreastBiomechLib.solver.kernels.contact import (
    NodeConstraints,
    PlateContact,
    PlatePose,
    support_springs,
    touch_plate,
    zero_constrained,
)
from BreastBiomechLib.solver.kernels.element import (
    ElementKernels,
    add_element_forces,
    cofactor,
    deformation_gradient,
    element_first_piola,
    element_kernels,
    element_slots,
    isochoric_stress,
    mean_slot_change,
    model_element_stress,
    model_volume_change,
    record_inversion,
    scaled_first_piola,
    strain_energy_density,
    visco_first_piola,
)
from BreastBiomechLib.solver.kernels.node import (
    NODE_KERNEL_OPTIONS,
    NODE_KERNEL_REGISTERS,
    NodeLoads,
    node_kernel,
)
from BreastBiomechLib.solver.kernels.reductions import (
    REDUCTION_BLOCK,
    energies,
    grow_masses,
    internal_energy,
    keep_step_stable,
    largest_change,
    model_and_entry,
    normalise_iterate,
    perturbed,
    plate_forces,
    power_iteration_terms,
    reduction_launch,
    relaxation_terms,
    stable_steps,
)

__all__ = [
    "LOAD_POLY345",
    "LOAD_RAMP",
    "LOAD_STEP",
    "LOAD_RAMPHOLD",
    "LOAD_HILLY",
    "load_factor",
    "listed",
    "element_and_lane",
    "model_at",
    "add_force",
    "force_at",
    "ElementMaterial",
    "MaterialTable",
    "material_of",
    "ANP_OFF",
    "ANP_WITHIN_MATERIALS",
    "ANP_ACROSS_MATERIALS",
    "SPECIALISED",
    "set_component",
    "clipped",
    "NodeState",
    "deformation_gradient",
    "isochoric_stress",
    "visco_first_piola",
    "cofactor",
    "scaled_first_piola",
    "strain_energy_density",
    "element_slots",
    "model_volume_change",
    "record_inversion",
    "mean_slot_change",
    "element_first_piola",
    "add_element_forces",
    "model_element_stress",
    "ElementKernels",
    "element_kernels",
    "NodeConstraints",
    "PlatePose",
    "PlateContact",
    "touch_plate",
    "zero_constrained",
    "support_springs",
    "NodeLoads",
    "NODE_KERNEL_REGISTERS",
    "NODE_KERNEL_OPTIONS",
    "node_kernel",
    "REDUCTION_BLOCK",
    "reduction_launch",
    "model_and_entry",
    "energies",
    "plate_forces",
    "internal_energy",
    "relaxation_terms",
    "largest_change",
    "perturbed",
    "power_iteration_terms",
    "normalise_iterate",
    "stable_steps",
    "keep_step_stable",
    "grow_masses",
]

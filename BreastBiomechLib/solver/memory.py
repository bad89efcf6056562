"""Will a solve fit in memory? The estimate of what ``solve_batch`` allocates, checked against
what the device has free before anything is allocated, so that a mesh or batch too large is
refused with the figures and what to do instead of failing in an out-of-memory crash midway.
The image warping and TetGen's meshing are estimated and checked the same way.

Sizes in bytes. The estimate counts the solver's arrays (float32 and int32 on the device: the
state and its monitors per node and model, the materials and visco state per element and model,
the shared mesh data, the ANP slots, the contact state) and, on the CPU, where the device is the
host, also the float64 copies the set-up holds at the same time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BreastBiomechLib.mesh.tetmesh import regular_tet_volume_mm3

MEMORY_MARGIN = 0.9  # use at most this share of what is free
GB = 1024.0 ** 3
# TetGen's meshing of a breast, host bytes per element: ~450 measured at 2.5-1.8 mm edges on the
# phantom (peak resident memory over element count, above a fixed ~0.6 GB), doubled for safety
MESHING_BYTES_PER_ELEMENT = 1000
MESHING_FIXED_BYTES = int(0.6 * GB)

# bytes per entry of the device arrays of a solve (float32 / int32), see tled.solve_batch
_PER_MODEL_NODE = (5 * 12  # displacement, rounding remainder, increment, scratch state, forces
                   + 4 + 8 + 2 * 12  # fictitious mass (and in float64), body forces at the start and over the load
                   + 5 * 12  # stable-step monitor: vector, next vector, probe, base and probe forces
                   + 12 + 3 * 12  # distance to rest; relaxation: forces now and last, last state
                   + 12 + 8)  # a packed batch's results of every set: displacement, masses in float64
_PER_MODEL_ELEMENT = 3 * 4 + 12  # material table: moduli, fibre stiffness and direction (a row per element at most)
_PER_MODEL_ELEMENT_TERM = 2 * 4 + 36  # Prony weight and decay, visco state (3x3)
_PER_ELEMENT = 16 + 48 + 4 + 16 + 4  # connectivity, shape-function derivatives, volume, ANP slots, material row
_PER_NODE = 12 + 4 + 4  # reference position, constraint row, sliding-support column (one)
_PER_MODEL_SLOT = 2 * 4  # ANP pressures of the step and of the probes
_PER_MODEL_CONTACT = 12 + 4 + 12  # friction anchor, contact flag, force through the node
_HOST_PER_MODEL_NODE = 3 * 8 + 2 * 8 + 3 * 8  # set-up copies in float64: start state, masses, result
_HOST_PER_MODEL_ELEMENT = 8 * 8  # set-up copies in float64: moduli, densities, stacked materials


class TooLargeForMemory(ValueError):
    """A solve that would not fit in the memory the device has free."""


@dataclass(frozen=True)
class SolveSize:
    """The dimensions of a batched solve: models, nodes, elements, ANP slots (per model),
    Prony terms per element, contact slots (per model, all plates), plates."""

    models: int
    nodes: int
    elements: int
    slots: int
    prony_terms: int = 0
    contact_slots: int = 0
    plates: int = 0

    def device_bytes(self) -> int:
        """What the solve allocates on its device (bytes)."""
        b = self.models
        return int(b * self.nodes * _PER_MODEL_NODE
                   + b * self.elements * (_PER_MODEL_ELEMENT + self.prony_terms * _PER_MODEL_ELEMENT_TERM)
                   + self.elements * _PER_ELEMENT + self.nodes * (_PER_NODE + 4 * max(self.plates, 1))
                   + b * self.slots * _PER_MODEL_SLOT + b * self.contact_slots * _PER_MODEL_CONTACT)

    def host_bytes(self) -> int:
        """What the set-up holds on the host at the same time, in float64 (bytes)."""
        return int(self.models * (self.nodes * _HOST_PER_MODEL_NODE + self.elements * _HOST_PER_MODEL_ELEMENT))


def free_bytes(device) -> int | None:
    """Memory the warp ``device`` has free (bytes): the GPU's free memory, or for the CPU the
    host's available memory (Linux ``MemAvailable``); None where it cannot be read."""
    if getattr(device, "is_cuda", False):
        return int(device.free_memory)
    try:
        with open("/proc/meminfo") as info:
            for line in info:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def _allowed(device, limit_bytes: int | None) -> tuple[float | None, str]:
    """What a run on ``device`` (None: the host) may allocate (bytes; None: unknown) and how to say
    where that comes from."""
    free = free_bytes(device) if limit_bytes is None else int(limit_bytes)
    if free is None:
        return None, ""
    if limit_bytes is not None:
        return float(free), f"the memory limit given is {free / GB:.2f} GB"
    where = "this machine" if device is None else device
    return MEMORY_MARGIN * free, f"{where} has {free / GB:.2f} GB free, of which it uses at most {MEMORY_MARGIN:.0%}"


def check_fits(size: SolveSize, device, limit_bytes: int | None = None) -> int:
    """Refuse (:class:`TooLargeForMemory`) a solve of ``size`` on the warp ``device`` that needs
    more than :data:`MEMORY_MARGIN` of what is free there, or more than ``limit_bytes`` when given
    (a cap on a shared machine); the message gives the estimate, the limit and the largest batch
    that fits. Returns the estimate (bytes). Nothing is checked where the free memory is unknown
    and no limit is given."""
    needed = size.device_bytes() + (0 if getattr(device, "is_cuda", False) else size.host_bytes())
    allowed, limit = _allowed(device, limit_bytes)
    if allowed is None or needed <= allowed:
        return needed
    one = SolveSize(1, size.nodes, size.elements, size.slots, size.prony_terms, size.contact_slots, size.plates)
    per_model = one.device_bytes() + (0 if getattr(device, "is_cuda", False) else one.host_bytes())
    fitting = int(allowed // per_model) if per_model else 0
    remedy = (f"solve at most {fitting} model(s) at once" if fitting >= 1 else
              "use a coarser mesh (one model of this one does not fit)")
    raise TooLargeForMemory(
        f"a solve of {size.models} model(s) on {size.nodes} nodes and {size.elements} elements needs about "
        f"{needed / GB:.2f} GB, and {limit}; {remedy}, or free memory on the device")


def warp_bytes(output_voxels: int, input_voxels: int, nodes: int, elements: int, on_cuda: bool) -> int:
    """What :class:`~BreastBiomechLib.warping.predict.ImageWarper` allocates on its device (bytes):
    the undeformed image (float32), per output voxel its reference position, inside flag and value,
    the mesh's reference and deformed nodes and its connectivity; on the CPU also the float32 copy
    of the undeformed image the upload makes and the predicted image read back."""
    device = input_voxels * 4 + output_voxels * (12 + 4 + 4) + nodes * 2 * 12 + elements * 16
    host = 0 if on_cuda else input_voxels * 4 + output_voxels * 4
    return int(device + host)


def check_warp_fits(output_voxels: int, input_voxels: int, nodes: int, elements: int, device,
                    limit_bytes: int | None = None) -> int:
    """Refuse (:class:`TooLargeForMemory`) warping an image of ``input_voxels`` through a mesh onto
    an output grid of ``output_voxels`` when it needs more than the ``device`` has free (or
    ``limit_bytes``); the message names the grids and what to do. Returns the estimate (bytes)."""
    needed = warp_bytes(output_voxels, input_voxels, nodes, elements, getattr(device, "is_cuda", False))
    allowed, limit = _allowed(device, limit_bytes)
    if allowed is None or needed <= allowed:
        return needed
    raise TooLargeForMemory(
        f"warping an image of {input_voxels} voxels onto a grid of {output_voxels} voxels needs about "
        f"{needed / GB:.2f} GB, and {limit}; crop or resample the images to fewer voxels, or free memory on "
        "the device")


def meshing_elements(volume_mm3: float, edge_mm: float) -> int:
    """At most about how many elements TetGen makes of ``volume_mm3`` at ``edge_mm``: the volume
    over the largest element volume it is allowed (a regular tetrahedron of that edge); quality
    meshes of the phantom had 0.35-0.8 of that count at 8-1.8 mm edges."""
    return int(np.ceil(volume_mm3 / regular_tet_volume_mm3(edge_mm)))


def check_meshing_fits(volume_mm3: float, edge_mm: float, what: str = "the body",
                       limit_bytes: int | None = None) -> int:
    """Refuse (:class:`TooLargeForMemory`) meshing ``volume_mm3`` (mm³) at ``edge_mm`` when TetGen
    would need more host memory than is available (or ``limit_bytes``); the message gives the
    estimate and the smallest edge that fits. Returns the estimate (bytes)."""
    elements = meshing_elements(volume_mm3, edge_mm)
    needed = MESHING_FIXED_BYTES + elements * MESHING_BYTES_PER_ELEMENT
    allowed, limit = _allowed(None, limit_bytes)
    if allowed is None or needed <= allowed:
        return needed
    fitting = (allowed - MESHING_FIXED_BYTES) / MESHING_BYTES_PER_ELEMENT
    smallest = (volume_mm3 / fitting / regular_tet_volume_mm3(1.0)) ** (1 / 3) if fitting > 0 else float("inf")
    remedy = (f"use an element edge of at least {np.ceil(smallest * 10) / 10:.1f} mm" if np.isfinite(smallest)
              else "free memory on this machine")
    raise TooLargeForMemory(
        f"meshing {what} ({volume_mm3 / 1000:.0f} cm3) at {edge_mm:g} mm edges makes up to about {elements:,} "
        f"elements and needs about {needed / GB:.1f} GB, and {limit}; {remedy}")

"""``breastbiomech bench segment --sweep`` and ``bench mesh --sweep``: the robustness sweeps over
the phantom variants of :mod:`BreastBiomechLib.phantom.variants`.

Each variant is generated, segmented from its seed points (as a user would click them) and, for
the mesh sweep, both its ground-truth label map and its segmentation are meshed at every
element edge asked; with a compression fraction, each mesh is also compressed between two
plates (:func:`compression_check`), since a mesh whose elements pass every quality criterion
can still turn one inside out under a plate. A variant that raises is recorded, not fatal: a ``ValueError`` (the
project's way of refusing with a message) counts as a refusal, anything else as a raw error.
With ``--out FILE`` every finished variant is appended as one JSON line and a rerun skips the
variants already there (resumable). Variants run in ``--processes`` worker processes.
"""

from __future__ import annotations

import json
import os
import platform
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from BreastBiomechLib import __version__
from BreastBiomechLib.io.cases import case_from_dict, compression_case
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.phantom.variants import describe, sweep_variants

TISSUES = ("fat", "glandular", "muscle", "tumour")
MESH_EDGES_MM = (3.0, 4.0, 6.0, 8.0, 10.0, 12.0, 15.0)


def _outcome(error: BaseException) -> dict:
    kind = "refused" if isinstance(error, ValueError) else "error"
    return {kind: f"{type(error).__name__}: {error}"}


def _segmented(params):
    from BreastBiomechLib.phantom import generate_phantom
    from BreastBiomechLib.phantom.seeds import seed_points
    from BreastBiomechLib.segmentation import dice_per_tissue, segment_tissues

    case = generate_phantom(params)
    muscle = seed_points(case.labels, "muscle", 4).positions
    tumour = seed_points(case.labels, "tumour", 3).positions
    started = time.perf_counter()
    result = segment_tissues(case.image, muscle, tumour)
    row = {"segment_s": round(time.perf_counter() - started, 2),
           "dice": {k: round(v, 4) for k, v in dice_per_tissue(result.labels, case.labels).items() if k in TISSUES},
           "skin_layer_mm": result.summary["skin_layer_mm"]}
    return case, result, row


def segment_variant(index: int, params) -> dict:
    """One variant of the segmentation sweep: Dice per tissue, or the refusal or error."""
    row = {"variant": index, "seed": params.seed, "options": describe(params)}
    try:
        row.update(_segmented(params)[2])
    except Exception as error:  # recorded, not fatal: the sweep reports every variant
        row.update(_outcome(error))
    return row


def compression_check(mesh, compression: float, device=None) -> dict:
    """A plate compression of a breast mesh of :func:`~BreastBiomechLib.mesh.from_labels.mesh_labels`:
    plates closing by ``compression`` of the breast's left-right thickness, the chest wall and
    field-of-view cut held, the default tissue materials, dynamic relaxation
    (:func:`~BreastBiomechLib.io.cases.compression_case`); the solve's status and the elements
    it leaves inverted (volume <= 0 in the configuration it returns)."""
    from BreastBiomechLib.solver import solve_batch

    model, settings = case_from_dict(compression_case(mesh, "mesh.vtu", compression=compression), mesh)
    solution = solve_batch(model, [model.materials], device=device, relaxation=settings.relaxation)[0]
    deformed = TetMesh(mesh.nodes + solution.displacement, mesh.tets)
    return {"status": solution.status, "inverted": int((deformed.volumes <= 0).sum()), "steps": int(solution.steps)}


def mesh_variant(index: int, params, edges=MESH_EDGES_MM, compression: float | None = None, device=None) -> dict:
    """One variant of the mesh sweep: its truth labels and its segmentation meshed at each edge:
    elements, elements failing the quality criteria and seconds, or the refusal or error; with
    ``compression``, the :func:`compression_check` of each mesh on ``device``."""
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels

    row = {"variant": index, "seed": params.seed, "options": describe(params), "meshes": {}}
    try:
        case, result, figures = _segmented(params)
    except Exception as error:
        row.update(_outcome(error))
        return row
    row["dice"] = figures["dice"]
    for source, labels in (("truth", case.labels), ("segmentation", result.labels)):
        for edge in edges:
            started = time.perf_counter()
            try:
                mesh = mesh_labels(labels, MeshSettings(edge_mm=edge))
                summary = mesh.summary()
                entry = {"tets": summary["elements"], "failing": summary["quality"]["failing"]["any"]["count"]}
            except Exception as error:
                entry = _outcome(error)
            if compression is not None and "tets" in entry:
                try:
                    entry["compression"] = compression_check(mesh.mesh, compression, device)
                except Exception as error:
                    entry["compression"] = _outcome(error)
            entry["seconds"] = round(time.perf_counter() - started, 1)
            row["meshes"][f"{source}@{edge:g}"] = entry
    return row


def run_sweep(what: str, count: int, processes: int, out: str | None = None,
              edges=MESH_EDGES_MM, compression: float | None = None, device=None, family: str = "anatomy") -> dict:
    """Run the ``what`` ("segment" or "mesh") sweep over the first ``count`` variants of
    ``family`` (:func:`~BreastBiomechLib.phantom.variants.sweep_variants`); figures as one dict
    (per-variant rows under ``variants``). ``compression``, ``device``: the mesh sweep's
    :func:`compression_check` (None: none)."""
    variants = sweep_variants(count, family)
    done = {}
    path = Path(out) if out else None
    if path and path.exists():
        for line in path.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut by a kill: that variant runs again
            done[row["variant"]] = row
    foreign = sorted(i for i, row in done.items() if i >= count or row.get("seed") != variants[i].seed)
    if foreign:
        raise ValueError(f"{path} holds rows of another sweep (variants {foreign[:5]} do not match the {family} "
                         f"family's first {count}): write this sweep to another --out file")
    todo = [i for i in range(count) if i not in done]
    started = time.perf_counter()
    work = segment_variant if what == "segment" else mesh_variant
    extra = () if what == "segment" else (tuple(edges), compression, device)
    with ProcessPoolExecutor(max_workers=max(1, processes)) as pool:
        futures = {pool.submit(work, i, variants[i], *extra): i for i in todo}
        for future in futures:
            row = future.result()
            done[row["variant"]] = row
            if path:
                with path.open("a") as stream:
                    stream.write(json.dumps(row) + "\n")
    rows = [done[i] for i in range(count)]
    figures = {"benchmark": f"{what}-sweep", "family": family, "version": __version__, "machine": platform.machine(),
               "cores": os.cpu_count(), "processes": processes, "variants": count,
               "wall_s": round(time.perf_counter() - started, 1)}
    if what == "mesh":
        figures["compression"] = compression
    figures.update(_segment_summary(rows) if what == "segment" else _mesh_summary(rows, edges))
    figures["rows"] = rows
    return figures


def _segment_summary(rows) -> dict:
    dice = {t: [r["dice"][t] for r in rows if "dice" in r and t in r["dice"]] for t in TISSUES}
    return {"dice_min": {t: min(v) for t, v in dice.items() if v},
            "dice_median": {t: float(np.median(v)) for t, v in dice.items() if v},
            "refused": [r["variant"] for r in rows if "refused" in r],
            "errors": [r["variant"] for r in rows if "error" in r]}


def _mesh_summary(rows, edges) -> dict:
    summary = {}
    for source in ("truth", "segmentation"):
        for edge in edges:
            entries = [r["meshes"].get(f"{source}@{edge:g}") for r in rows if "meshes" in r]
            entries = [e for e in entries if e]
            summary[f"{source}@{edge:g}"] = {
                "meshed": sum("tets" in e for e in entries),
                "with_failing_elements": sum(e.get("failing", 0) > 0 for e in entries),
                "compressed": sum("compression" in e for e in entries),
                "compression_not_solved": sum(e["compression"].get("status") != "completed"
                                              for e in entries if "compression" in e),
                "refused": sum("refused" in e for e in entries),
                "errors": sum("error" in e for e in entries)}
    return {"by_mesh": summary, "variant_failures": [r["variant"] for r in rows if "meshes" not in r]}

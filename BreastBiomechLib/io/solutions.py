"""A solved case on disk, as ``breastbiomech simulate`` writes it: ``deformed.vtu`` (the mesh as
given, point arrays ``displacement`` mm LPS from that shape, and ``unloaded_displacement`` where
the solve started from the unloaded shape) and ``solution.json`` (the solver's verdict, the plate
forces, the sampled history). Read back as a :class:`~BreastBiomechLib.solver.Solution`, so that a
caller in another process (the Slicer panel running the command out of its process) shows the
same figures as one that solved in its own. Units: mm, N, J, s; plate forces are the plates'
forces on the tissue (LPS).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.solution import Solution

MESH_FILE, SUMMARY_FILE = "deformed.vtu", "solution.json"


def write_solution(folder, mesh: TetMesh, result) -> tuple[Path, Path]:
    """Write ``result`` (:class:`~BreastBiomechLib.solver.run_case.CaseResult`) of a case on
    ``mesh`` (the mesh as given) into ``folder``; the two files' paths."""
    from BreastBiomechLib.io.meshes import write_vtu

    folder = Path(folder)
    solution, model, reference_state = result.solution, result.model, result.reference_state
    point_data = {**mesh.point_data, "displacement": result.displacement}
    if reference_state is not None:
        point_data["unloaded_displacement"] = result.unloaded_displacement
    deformed = TetMesh(mesh.nodes, mesh.tets, point_data=point_data, cell_data=dict(mesh.cell_data))
    mesh_path = write_vtu(folder / MESH_FILE, deformed)
    plates = model.loading.plates
    summary = {
        "status": solution.status, "message": solution.message, "steps": solution.steps,
        "time_step_s": solution.time_step, "wall_s": solution.wall_time,
        "ke_ie_at_end_of_loading": solution.ke_ie_at_end_of_loading,
        "estimated_error_mm": solution.estimated_error_mm, "stable_time_step_s": solution.stable_time_step,
        "max_displacement_mm": float(np.linalg.norm(point_data["displacement"], axis=1).max()),
        "reference_state": reference_state,
        "plates": {p.name: solution.plate_forces[i].tolist() for i, p in enumerate(plates)},
        "plate_normals": {p.name: np.asarray(p.normal, float).tolist() for p in plates},
        "plate_normal_forces": {p.name: float(solution.plate_normal_forces[i]) for i, p in enumerate(plates)},
        "plate_tangential_forces": {p.name: solution.plate_tangential_forces[i].tolist()
                                    for i, p in enumerate(plates)},
        "history": {key: np.asarray(value).tolist() for key, value in solution.history.items()},
        "supports": list(model.loading.notes),
        "units": "mm, N, J, s (plate forces: force of the plate on the tissue, LPS)",
    }
    summary_path = folder / SUMMARY_FILE
    write_text_atomically(summary_path, json.dumps(summary, indent=1, allow_nan=True))
    return mesh_path, summary_path


def read_solution(folder) -> tuple[Solution, dict]:
    """The :class:`~BreastBiomechLib.solver.Solution` written in ``folder`` by
    :func:`write_solution` (displacement from the mesh as given) and the summary dict. Raises
    FileNotFoundError naming what is missing."""
    from BreastBiomechLib.io.meshes import read_vtu

    folder = Path(folder)
    for name in (MESH_FILE, SUMMARY_FILE):
        if not (folder / name).is_file():
            raise FileNotFoundError(f"{folder} holds no {name}: not a finished `breastbiomech simulate` output "
                                    "(run it again)")
    summary = json.loads((folder / SUMMARY_FILE).read_text())
    displacement = read_vtu(folder / MESH_FILE).point_data["displacement"]
    forces = np.array(list(summary["plates"].values()), float).reshape(-1, 3)
    normals = np.array([summary.get("plate_normals", {}).get(name, [np.nan] * 3) for name in summary["plates"]],
                       float).reshape(-1, 3)
    history = {key: np.asarray(value, float) for key, value in summary["history"].items()}
    solution = Solution(np.asarray(displacement, float), forces, summary["status"], summary["message"],
                        int(summary["steps"]), float(summary["time_step_s"]), float(summary["wall_s"]),
                        float(summary["ke_ie_at_end_of_loading"]), history,
                        float(summary["estimated_error_mm"]), float(summary["stable_time_step_s"]), normals)
    return solution, summary

"""The forward problem of a fit (seed section 2.4, steps 2-4): material parameters -> FE solve of
the plate compression -> FE-predicted compressed MR image -> similarity to the measured one,
for a whole batch of parameter sets in one batched solve.

Frames and units: LPS millimetres; the mesh is the fitting mesh of the undeformed breast; the
plates are the measured final planes (a compressed case's plates.json).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib.io.cases import case_from_dict, compression_case
from BreastBiomechLib.landmarks import LandmarkMapper, Landmarks
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.optimisation.space import ParameterSpace
from BreastBiomechLib.optimisation.warm_starts import FitWarmStarts
from BreastBiomechLib.solver import DynamicRelaxation, Model
from BreastBiomechLib.solver.placement import plates_to_final_planes
from BreastBiomechLib.solver.retries import RETRIES, solve_batch_with_retries

OBJECTIVES = ("nmi", "landmarks", "surface", "nmi+landmarks", "nmi+surface")
FAILED_NMI = 0.0  # -NMI of a failed solve: worse than any (NMI lies in [1, 2])
FAILED_MM = 1000.0  # a failed solve's distance (mm): worse than any in a breast


@dataclass
class Evaluation:
    """One forward evaluation: the unit position ``z``, the parameter ``values``, the
    ``objective`` (minimised), NMI and NCC of the prediction against the measured image, the
    landmark errors' mean and max (mm; NaN without landmarks), the solve's status, iterations
    and the batch's wall time (s); the mean distance (mm) of the predicted breast skin to the
    measured body surface (NaN unless the objective uses it); for a failed solve the solver's
    ``message`` (what failed and where: the step and first element of an inversion, the error
    estimate of a relaxation that ran out of iterations), empty for a completed one; in a joint
    fit of several measured states (:mod:`~BreastBiomechLib.optimisation.states`) each state's
    objective, NMI, mean landmark error and status by name in ``states``."""

    z: list[float]
    values: dict[str, float]
    objective: float
    nmi: float
    ncc: float
    landmark_mean_mm: float
    landmark_max_mm: float
    status: str
    iterations: int
    seconds: float
    surface_mm: float = float("nan")
    message: str = ""
    states: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


class FittingProblem:
    """Evaluates parameter sets of ``space`` on one compressed case.

    ``mesh``: the fitting mesh (cell array ``tissue``; node sets ``chest_wall``, ``skin``,
    ``breast_skin``, ``fov_cut`` as ``breastbiomech mesh`` makes them); ``undeformed`` and
    ``measured``: the MR volumes before and after compression; ``plates``: the measured final
    plate planes (dicts as in plates.json); ``landmarks`` (reference, measured): optional
    landmark pairs; ``objective``: "nmi" (-NMI, the seed's eq. (17)), "landmarks" (mean error,
    mm), "surface" (mean distance, mm, of the predicted breast skin nodes to the measured body
    surface, :class:`~BreastBiomechLib.similarity.surface.SurfaceDistance`; nodes outside the
    measured field of view do not count), "nmi+landmarks" (-NMI + ``landmark_weight`` x mean
    error) or "nmi+surface" (-NMI + ``surface_weight`` x mean distance); ``body``: the measured
    body mask for the surface objectives (default: found in ``measured``); ``mask``: the
    measured voxels compared (default: all); ``bins``: NMI histogram bins; ``relaxation``: the
    dynamic relaxation settings of every forward solve; ``device``: warp device. Plate offsets
    free in ``space`` move the measured ``plates`` along their normals, model by model.
    ``warm_starts``: each batch starts at the equilibrium of the best completed evaluation so
    far (:mod:`~BreastBiomechLib.optimisation.warm_starts`; not with plate friction, whose
    equilibrium depends on the path); a model that fails from there is solved again cold. Off
    by default: on ``bench optimise`` (11 free parameters, CMA-ES) the warm solves took longer
    than cold ones and converged less often (docs/benchmarks.md, "Warm starts")."""

    def __init__(self, space: ParameterSpace, mesh: TetMesh, undeformed: sitk.Image, measured: sitk.Image,
                 plates: list[dict], landmarks: tuple[Landmarks, Landmarks] | None = None,
                 objective: str = "nmi", landmark_weight: float = 0.01, surface_weight: float = 0.01,
                 body: sitk.Image | None = None, mask=None, bins: int = 64,
                 relaxation: DynamicRelaxation | None = None, device=None, warm_starts: bool = False):
        from BreastBiomechLib.similarity import Similarity
        from BreastBiomechLib.warping import ImageWarper

        if objective not in OBJECTIVES:
            raise ValueError(f"unknown objective {objective!r}; choose one of {OBJECTIVES}")
        if "landmarks" in objective and landmarks is None:
            raise ValueError(f"the {objective!r} objective needs landmarks (reference and measured)")
        if space.plates and space.plates != len(plates):
            raise ValueError(f"the parameter space offsets {space.plates} plate(s), the case has {len(plates)}")
        if landmarks is not None:
            reference, target = landmarks
            if reference.labels != target.labels:
                raise ValueError("the reference and measured landmarks must carry the same labels in the same order")
        if "tissue" not in mesh.cell_data:
            raise ValueError("the fitting mesh has no 'tissue' cell array; make it with `breastbiomech mesh`")
        self.space = space
        self.mesh = mesh
        self.tissue = np.asarray(mesh.cell_data["tissue"]).astype(int)
        self.objective = objective
        self.landmark_weight = float(landmark_weight)
        self.surface_weight = float(surface_weight)
        self.landmarks = landmarks
        # located once in their reference tets: each evaluation then only weighs its displacements
        self._landmark_mapper = LandmarkMapper(mesh, landmarks[0]) if landmarks is not None else None
        self.device = device
        self.relaxation = relaxation or DynamicRelaxation()
        self.warm_starts = FitWarmStarts() if warm_starts else None
        # the loading of `breastbiomech mesh`'s case (chest wall, field-of-view cuts), with the
        # measured plates in place of placed ones
        # (its default materials stand in until each evaluation sets its own)
        template, _ = case_from_dict(compression_case(mesh, "fitting_mesh.vtu"), mesh)
        template.loading.plates = plates_to_final_planes(mesh, plates, mesh.node_set("skin"),
                                                         mesh.node_set("breast_skin"))
        self.model: Model = Model(mesh, template.materials, template.loading, template.formulation,
                                  template.damping, template.time_step, template.safety)
        self.warper = ImageWarper(mesh, undeformed, measured, device=device)
        self.similarity = Similarity(measured, mask, bins=bins, device=device)
        self._surface = self._skin = None
        if "surface" in objective:
            from BreastBiomechLib.similarity.surface import SurfaceDistance

            self._surface = SurfaceDistance(measured, body)
            # the breast skin the image shows: not the faces where the label map's field of view cut it
            cut = mesh.node_set("fov_cut") if "fov_cut" in mesh.point_data else []
            self._skin = np.setdiff1d(mesh.node_set("breast_skin"), cut)
            if len(self._skin) == 0:
                raise ValueError("the fitting mesh has no breast skin nodes to measure to the surface")

    @property
    def failed_objective(self) -> float:
        """The objective a failed solve scores: worse than any solve's (:data:`FAILED_NMI` for
        -NMI, :data:`FAILED_MM` for the distances, their weighted sum for the sums)."""
        return {"nmi": FAILED_NMI, "landmarks": FAILED_MM, "surface": FAILED_MM,
                "nmi+landmarks": FAILED_NMI + self.landmark_weight * FAILED_MM,
                "nmi+surface": FAILED_NMI + self.surface_weight * FAILED_MM}[self.objective]

    def plate_displacements(self, z) -> np.ndarray | None:
        """The plates' displacements (P, 3) mm at unit position ``z``: the measured travel plus
        the free offsets along each normal (None when no offset is free: the measured plates)."""
        if not self.space.plates:
            return None
        return np.array([(float(p.displacement @ p.normal) + offset) * p.normal
                         for p, offset in zip(self.model.loading.plates, self.space.plate_offsets(z))])

    def surface_distance(self, displacement_mm: np.ndarray) -> float:
        """Mean distance (mm) of the displaced breast skin nodes inside the measured field of view
        to the measured body surface."""
        if self._surface is None:
            raise ValueError("this problem measures no surface distance; choose a surface objective")
        distances = self._surface.distances(self.mesh.nodes[self._skin] + displacement_mm[self._skin])
        if np.all(np.isnan(distances)):
            raise ValueError("no breast skin node lies inside the measured image after the deformation")
        return float(np.nanmean(distances))

    def solve(self, positions, relaxation: DynamicRelaxation | None = None, warm_start=None) -> list:
        """The FE solutions (:class:`~BreastBiomechLib.solver.Solution`) at unit positions (B, d),
        in one batched solve (``relaxation``: other settings than the problem's; ``warm_start``:
        a :class:`~BreastBiomechLib.solver.warm.WarmStart`, None: cold)."""
        from BreastBiomechLib.solver import solve_batch

        positions = np.atleast_2d(np.asarray(positions, float))
        materials = [self.space.element_materials(z, self.tissue) for z in positions]
        plates = [self.plate_displacements(z) for z in positions] if self.space.plates else None
        return solve_batch(self.model, materials, plates, device=self.device,
                           relaxation=relaxation or self.relaxation, warm_start=warm_start)

    def start_fit(self, folder: str | Path | None = None, recorded: list | None = None) -> None:
        """A new fit begins (or a resumed one goes on): its first batch starts cold, or at the
        best of the ``recorded`` evaluations it resumes; with a results ``folder`` the starts
        are kept there (see :mod:`~BreastBiomechLib.optimisation.warm_starts`)."""
        if self.warm_starts is None:
            return
        self.warm_starts = FitWarmStarts()
        if folder is not None:
            self.warm_starts.attach(folder, recorded or [])

    @property
    def warm_start(self):
        """The start of the next batch (None: cold): warm starts on and the plates frictionless."""
        if self.warm_starts is None or any(p.friction > 0 for p in self.model.loading.plates):
            return None
        return self.warm_starts.current

    def _solve_batch(self, positions) -> list:
        """:meth:`solve` from :attr:`warm_start`; the models that fail from there solved again
        cold in one batch (a warm start adds no failure)."""
        start = self.warm_start
        solutions = self.solve(positions, warm_start=start)
        failed = [i for i, s in enumerate(solutions) if not s.ok]
        if start is not None and failed:
            for i, solution in zip(failed, self.solve(positions[failed])):
                solutions[i] = solution
        return solutions

    def solve_alone(self, z, retries: int = RETRIES):
        """The solution at one unit position ``z``, solved by itself (the outputs of a fit's best
        parameters). Each model of a batch loads at its own pace, so alone it is solved as in
        its batch; should it still invert elements (float32 rounding can tip a marginal solve)
        it is solved again with a slower load (:mod:`BreastBiomechLib.solver.retries`,
        ``retries`` times at most)."""
        z = np.asarray(z, float)
        plates = [self.plate_displacements(z)] if self.space.plates else None
        return solve_batch_with_retries(self.model, [self.space.element_materials(z, self.tissue)], self.relaxation,
                                        plate_displacements=plates, device=self.device, retries=retries)[0]

    def predict(self, displacement_mm: np.ndarray):
        """The FE-predicted image (:class:`~BreastBiomechLib.warping.PredictedImage`, on the
        measured grid) for nodal displacements (N, 3) mm of the fitting mesh."""
        return self.warper.predict(displacement_mm)

    def evaluate(self, positions) -> list[Evaluation]:
        """Evaluate unit positions (B, d) in one batched solve; failed solves get the objective
        :attr:`failed_objective` and their status."""
        positions = np.atleast_2d(np.asarray(positions, float))
        started = time.perf_counter()
        solutions = self._solve_batch(positions)
        seconds = time.perf_counter() - started
        out = []
        for z, solution in zip(positions, solutions):
            nmi = ncc = mean = worst = surface = float("nan")
            objective = self.failed_objective
            if solution.ok:
                predicted = self.warper.warp(solution.displacement)
                nmi, ncc = self.similarity.nmi(predicted), self.similarity.ncc(predicted)
                if self._landmark_mapper is not None:
                    moved = self._landmark_mapper.map(solution.displacement)
                    errors = np.linalg.norm(moved.positions - self.landmarks[1].positions, axis=1)
                    mean, worst = float(errors.mean()), float(errors.max())
                if self._surface is not None:
                    surface = self.surface_distance(solution.displacement)
                objective = {"nmi": -nmi, "landmarks": mean, "surface": surface,
                             "nmi+landmarks": -nmi + self.landmark_weight * mean,
                             "nmi+surface": -nmi + self.surface_weight * surface}[self.objective]
            out.append(Evaluation([float(v) for v in z], self.space.values(z), float(objective), float(nmi),
                                  float(ncc), mean, worst, solution.status, int(solution.steps),
                                  round(seconds, 3), surface, "" if solution.ok else solution.message))
        if self.warm_starts is not None:
            for z, evaluation, solution in zip(positions, out, solutions):
                self.warm_starts.offer(z, evaluation.objective, solution, self.plate_displacements(z))
        return out

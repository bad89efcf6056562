"""The model-error floor measured from the case and its fit: how far the features would move with
nothing missing from the model but the fitting mesh's discretisation.

The fitted model is solved again on the uniform refinement of its fitting mesh
(:class:`~BreastBiomechLib.solver.refinement.Refinement`: every tet split into eight, the same
geometry, materials, plates and constraints). Each feature's difference between the two
solutions, times 4/3, estimates the fitting mesh's error in that feature (Richardson: linear
tetrahedra converge in displacement at second order, so the refined solution's own error is a
quarter of the coarse one's and the difference is three quarters of it). The refined model is
relaxed from the coarse solution where its equilibrium does not depend on the path (frictionless
plates, no pre-stress), else from rest. The floor of a feature
is the RMS of that estimate over the features of its region and channel (one realisation per
feature is too noisy to stand alone; the error is smooth within a region), never below the
noise model's fixed floor (``model_sd_mm``, kept as a lower bound).

What the floor holds: discretisation. Not held: the segmentation's error (the mesh's boundary
against the tissue's) and registration, which the fixed lower bound stands for.
Frames and units: LPS millimetres.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from BreastBiomechLib.discrepancy.observations import Observations
from BreastBiomechLib.discrepancy.state import ModelState
from BreastBiomechLib.discrepancy.variants import Outcome, Variant, solve_variants
from BreastBiomechLib.landmarks import Landmarks, map_landmarks
from BreastBiomechLib.landmarks.mapping import outside_tolerance_mm
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.solver.refinement import Refinement
from BreastBiomechLib.timing import staged

RICHARDSON = 4.0 / 3.0  # the coarse error over the coarse-to-refined difference at second order


@dataclass
class MeasuredFloor:
    """The measured floor of each feature (``floor`` (n,) mm, at least ``lower_bound_mm``), the
    signed discretisation error estimate it comes from (``discretisation`` (n,) mm), the
    features' groups with their count and RMS estimate (``groups``: {"region (channel)":
    {"features", "rms_mm"}}), the fitting and refined meshes' tet counts, the ``seconds`` the
    refined solve took and each feature's group (``feature_groups`` (n,))."""

    floor: np.ndarray
    discretisation: np.ndarray
    groups: dict
    lower_bound_mm: float
    tets: tuple[int, int]
    seconds: float
    feature_groups: np.ndarray | None = None

    def to_dict(self) -> dict:
        return {"discretisation": self.discretisation.tolist(), "feature_groups": list(self.feature_groups),
                "tets": list(self.tets), "seconds": self.seconds}

    @classmethod
    def from_dict(cls, record: dict, lower_bound_mm: float) -> "MeasuredFloor":
        """A floor written by :meth:`to_dict`, at the lower bound ``lower_bound_mm`` (which may
        differ from the one it was measured with: the estimate does not depend on it)."""
        error, groups = np.asarray(record["discretisation"], float), np.asarray(record["feature_groups"])
        floor, summary = floor_of(error, groups, lower_bound_mm)
        return cls(floor, error, summary, lower_bound_mm, tuple(record["tets"]), float(record["seconds"]), groups)

    def summary(self) -> dict:
        """The floor without its per-feature arrays (for a round's record and the report): its
        RMS and largest group, the tets and seconds."""
        largest = max(self.groups.items(), key=lambda item: item[1]["rms_mm"], default=(None, None))
        return {"rms_mm": float(np.sqrt(np.mean(self.floor ** 2))) if self.floor.size else 0.0,
                "discretisation_rms_mm": float(np.sqrt(np.mean(self.discretisation ** 2)))
                if self.discretisation.size else 0.0,
                "largest": {"group": largest[0], **(largest[1] or {})}, "groups": self.groups,
                "lower_bound_mm": self.lower_bound_mm, "tets": list(self.tets), "seconds": self.seconds}


def discretisation_error(state: ModelState, observations: Observations, displacement_mm: np.ndarray) -> tuple:
    """The estimated error (n,) mm of each feature of the model ``state`` whose solution on its
    fitting mesh is ``displacement_mm`` (N, 3; in a fit of several measured states (S N, 3),
    each state solved on the refined mesh), from its solution on the refined mesh; with the two
    meshes' tet counts. Raises RuntimeError when the refined model does not solve."""
    fitted = state.fitted
    variant = state.variant()
    fine_parts, predicted_landmarks = [], {}
    for fitted_state, part, coarse in zip(fitted.states, (variant, *variant.others), fitted.split(displacement_mm)):
        refinement = Refinement(part.model.mesh)
        model = refinement.model(part.model, part.materials, part.plates)
        imaged = refinement.node_values(fitted.mesh.nodes)
        outcome = warm_refined_solve(model, refinement.node_values(coarse), fitted.relaxation, fitted.device)
        if outcome is None:  # cold: from rest, the load ramped (a warm start does not hold, or failed)
            [outcome] = solve_variants([Variant(model, model.materials, model.loading.plates)], imaged,
                                       fitted.relaxation, fitted.device)
        if not outcome.ok:
            where = f" in state {fitted_state.name}" if fitted.further else ""
            raise RuntimeError(f"the fitted model on its refined mesh ({len(model.mesh.tets)} tets) did not solve"
                               f"{where} ({outcome.status}: {outcome.message}); measure the floor with a finer "
                               "fitting mesh or give a fixed one (--floor fixed --model-sd-mm)")
        fine = outcome.displacement
        fine_parts.append(fine[:len(fitted.mesh.nodes)])
        if fitted_state.reference is not None:  # the reference landmarks are in the imaged frame
            predicted_landmarks[fitted_state.name] = refined_landmarks(fitted.mesh, refinement, fine,
                                                                       fitted_state.reference).ravel()
    predicted = observations.predicted(np.concatenate(fine_parts))
    for name, values in predicted_landmarks.items():
        mine = (observations.channel == "landmarks") & observations.in_state(name)
        if mine.any():
            predicted[mine] = values
    error = RICHARDSON * (predicted - observations.predicted(displacement_mm))
    return error, (len(variant.model.mesh.tets), len(model.mesh.tets))


def refined_landmarks(fitting_mesh: TetMesh, refinement: Refinement, displacement_mm: np.ndarray,
                      landmarks: Landmarks) -> np.ndarray:
    """(K, 3) mm: the reference ``landmarks`` (imaged frame, LPS mm) moved by ``displacement_mm``
    on the nodes of ``refinement`` of ``fitting_mesh``. The refined mesh has the fitting mesh's
    surface, so a landmark lies as far outside it as outside the fitting mesh, and the fitting
    mesh's tolerance for that applies (the refined mesh's own, from its halved edges, would
    refuse a nipple the fit mapped: a 12 mm mesh with a 9 mm surface did)."""
    mesh = TetMesh(refinement.node_values(fitting_mesh.nodes), refinement.refined.tets)
    return map_landmarks(mesh, displacement_mm, landmarks, outside_tolerance_mm(fitting_mesh)).positions


def warm_refined_solve(model, start_mm: np.ndarray, relaxation, device=None) -> Outcome | None:
    """The refined ``model`` relaxed (``relaxation`` on warp ``device``) from the coarse solution carried onto its nodes
    (``start_mm``: the refinement is linear, so that is the coarse displacement field exactly),
    with the plates and constraints in full: the same equilibrium as from rest (on the small
    phantom's 170k-tet refinement 0.002 mm RMS and 0.006 mm at most from the cold solve, whose
    difference from the coarse one is 0.15 mm RMS) in two thirds of the time (2026-12-06, 2-core
    CPU). Only where the static solution does not depend on the path (frictionless plates) and
    the model starts from its mesh (no pre-stressed reference state); None otherwise, or where
    the warm solve does not complete."""
    from BreastBiomechLib.solver import solve_batch
    from BreastBiomechLib.solver.warm import WarmStart

    if model.prestate is not None or any(p.friction > 0 for p in model.loading.plates):
        return None
    [solution] = solve_batch(model, [model.materials], device=device, relaxation=relaxation,
                             warm_start=WarmStart(start_mm))
    if not solution.ok:
        return None
    return Outcome(solution.displacement, solution.status, solution.message)


def floor_of(error: np.ndarray, groups: np.ndarray, lower_bound_mm: float) -> tuple[np.ndarray, dict]:
    """Each feature's floor (n,) mm: the RMS of ``error`` over its group (``groups`` (n,) names),
    at least ``lower_bound_mm``; with {group: {"features", "rms_mm"}}."""
    floor = np.empty(len(error))
    summary = {}
    for name in sorted(set(groups.tolist())):
        members = groups == name
        rms = float(np.sqrt(np.mean(error[members] ** 2)))
        floor[members] = max(rms, lower_bound_mm)
        summary[name] = {"features": int(members.sum()), "rms_mm": rms}
    return floor, summary


@staged("model-error floor")
def measure_floor(state: ModelState, observations: Observations, displacement_mm: np.ndarray,
                  regions: np.ndarray, lower_bound_mm: float) -> MeasuredFloor:
    """The floor of ``observations`` for the model ``state`` (its solution ``displacement_mm`` on
    the fitting mesh; ``regions`` (n,) each feature's region name), grouped by region and channel."""
    started = time.perf_counter()
    error, tets = discretisation_error(state, observations, displacement_mm)
    groups = np.array([f"{r} ({c})" for r, c in zip(regions, observations.channel)])
    floor, summary = floor_of(error, groups, lower_bound_mm)
    return MeasuredFloor(floor, error, summary, lower_bound_mm, tets, round(time.perf_counter() - started, 1), groups)

"""A finished fit of a compressed case, as the diagnosis starts from it: the fit's forward
problem rebuilt (fitting mesh, measured plates, measured image), its best parameters, and the
landmarks. Reads only what a fit may use (:mod:`BreastBiomechLib.phantom.compressed_files`):
never a case's truth.json or truth mesh.

A joint fit of several measured states (:mod:`BreastBiomechLib.optimisation.states`) is read
with every state it fitted: the first state is the :class:`FittedCase` itself, each further one a
:class:`FittedCase` of its own in :attr:`FittedCase.further` (the same fitting mesh, space,
parameters and reference landmarks; its own plates, measured image, landmarks and posture). The
diagnosis stacks them: a model's solution in every state is one array of the states' nodal
displacements one after the other (:meth:`FittedCase.split`), first state first.

Frames and units: LPS millimetres; the fitting mesh as imaged (undeformed).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib.errors import InputError, reading
from BreastBiomechLib.io.case_layout import FIRST_STATE, CaseLayout
from BreastBiomechLib.io.markups import read_markups
from BreastBiomechLib.landmarks import Landmarks
from BreastBiomechLib.mesh.tetmesh import TetMesh
from BreastBiomechLib.optimisation.forward import FittingProblem
from BreastBiomechLib.optimisation.space import ParameterSpace
from BreastBiomechLib.phantom.parameters import PRONE_GRAVITY
from BreastBiomechLib.solver import DynamicRelaxation, Model
from BreastBiomechLib.solver.model import Plate
from BreastBiomechLib.timing import staged

FIT_FILES = ("settings.json", "result.json", "fitting_mesh.vtu")


@dataclass
class FittedCase:
    """The fit of one compressed case: its forward ``problem`` (with the fitting ``mesh``, the
    measured ``plates`` and images), the ``space`` searched and the best unit position ``z``,
    the ``reference`` and ``measured`` landmarks (None when the case has none), the
    ``measured_image``, the undeformed scan's posture as gravity ``imaged_gravity`` and the
    compressed scan's ``compressed_gravity`` (m/s^2, LPS; prone: anterior), the forward solves'
    ``relaxation`` and the warp ``device``; the folders it came from; the measured state's
    ``name`` and, for the first state of a joint fit, its ``further`` states (each a
    :class:`FittedCase` of the same fit)."""

    problem: FittingProblem
    z: np.ndarray
    reference: Landmarks | None
    measured: Landmarks | None
    measured_image: sitk.Image
    case_dir: Path
    fit_dir: Path
    imaged_gravity: np.ndarray = field(default_factory=lambda: np.array(PRONE_GRAVITY))
    compressed_gravity: np.ndarray = field(default_factory=lambda: np.array(PRONE_GRAVITY))
    relaxation: DynamicRelaxation = field(default_factory=DynamicRelaxation)
    device: object = None
    name: str = FIRST_STATE
    further: list["FittedCase"] = field(default_factory=list)
    _skin: dict = field(default_factory=dict, repr=False)

    @property
    def states(self) -> list["FittedCase"]:
        """Every measured state of the fit, the first (this one) first."""
        return [self, *self.further]

    @property
    def state_names(self) -> list[str]:
        return [state.name for state in self.states]

    def split(self, displacement: np.ndarray) -> list[np.ndarray]:
        """A solution in every state (S N, 3) mm, the states' nodal displacements one after the
        other: each state's (N, 3), in :attr:`states`' order."""
        displacement = np.asarray(displacement)
        n, count = len(self.mesh.nodes), len(self.states)
        if displacement.shape != (count * n, 3):
            raise ValueError(f"a solution in {count} measured state(s) of a {n}-node mesh is ({count * n}, 3), not "
                             f"{displacement.shape}")
        return [displacement[k * n:(k + 1) * n] for k in range(count)]

    def first(self, displacement: np.ndarray) -> np.ndarray:
        """The first state's part (N, 3) mm of a solution in every state (:meth:`split`)."""
        return self.split(displacement)[0]

    @property
    def mesh(self) -> TetMesh:
        return self.problem.mesh

    @property
    def space(self) -> ParameterSpace:
        return self.problem.space

    @property
    def tissue(self) -> np.ndarray:
        return self.problem.tissue

    @property
    def model(self) -> Model:
        return self.problem.model

    @property
    def plates(self) -> list[Plate]:
        return self.problem.model.loading.plates

    def skin_fraction(self, thickness_mm: float) -> np.ndarray:
        """Each element's share of volume within ``thickness_mm`` of the skin surface (cached,
        as is the nodes' depth under it that every thickness's share is counted from)."""
        from BreastBiomechLib.mesh.skin import skin_fraction, surface_distance

        if thickness_mm not in self._skin:
            nodes = self.mesh.node_set("skin" if "skin" in self.mesh.point_data else "surface")
            if "depth" not in self._skin:
                self._skin["depth"] = surface_distance(self.mesh, nodes)
            self._skin[thickness_mm] = skin_fraction(self.mesh, nodes, thickness_mm, self._skin["depth"])
        return self._skin[thickness_mm]


def recorded_solution(fitted: FittedCase) -> np.ndarray | None:
    """The fitted model's solution as its fit wrote it (N, 3) mm, in every measured state (S N, 3)
    of a joint fit (``deformed_mesh.vtu`` of the fit folder, ``states/<name>/`` for further
    states); None where a file is missing or holds another mesh's nodes."""
    from BreastBiomechLib.io.case_layout import STATES
    from BreastBiomechLib.io.meshes import read_vtu

    files = [fitted.fit_dir / "deformed_mesh.vtu"] + [fitted.fit_dir / STATES / name / "deformed_mesh.vtu"
                                                       for name in fitted.state_names[1:]]
    if not all(f.is_file() for f in files):
        return None
    solutions = [read_vtu(f).point_data["displacement"] for f in files]
    if not all(u.shape == fitted.mesh.nodes.shape for u in solutions):
        return None
    return np.concatenate(solutions)


@staged("reading the case and the fit")
def load_fitted_case(case_dir: str | Path, fit_dir: str | Path, device=None, tolerance_mm: float = 0.01,
                     imaged_gravity=PRONE_GRAVITY) -> FittedCase:
    """The fit in ``fit_dir`` (``breastbiomech optimise``'s output folder) of the compressed case
    in ``case_dir``. Refuses, naming the problem: a case without its measured image, a folder
    that holds no finished fit, a fit made on another case (its recorded fingerprint, or its
    predicted image's grid, differs) or whose mesh the landmarks do not lie in."""
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.meshes import read_vtu
    from BreastBiomechLib.phantom.compressed_files import case_fingerprint, read_compressed

    case, fit = Path(case_dir), Path(fit_dir)
    layout = CaseLayout(case)
    measured_mr = layout.state(FIRST_STATE).mr
    if not measured_mr.is_file():
        raise FileNotFoundError(f"{case}: no measured compressed image ({measured_mr.relative_to(case)}); the "
                                "diagnosis compares the fit with it")
    if not layout.mr.is_file():
        raise FileNotFoundError(f"{case}: no undeformed image ({layout.mr.name})")
    layout.check()
    missing = [name for name in FIT_FILES if not (fit / name).is_file()]
    if missing:
        raise FileNotFoundError(f"{fit}: not a finished fit (no {', '.join(missing)}); run `breastbiomech optimise` "
                                "to the end first")
    with reading(fit, "finished fit folder (case.json, settings.json, result.json)",
                 "run `breastbiomech optimise` to the end again into a new folder"):
        recorded = fit / "case.json"
        written = json.loads(recorded.read_text()) if recorded.is_file() else {}
        if written:
            if written.get("fingerprint") != case_fingerprint(case):
                raise InputError(f"{fit} is a fit of another case ({written.get('case_dir')}): its measured image or "
                                 f"plates differ from {case}'s")
        settings = json.loads((fit / "settings.json").read_text())
        result = json.loads((fit / "result.json").read_text())
        space = ParameterSpace.from_dict(settings["space"])
        z = np.asarray(result["best"]["z"], float)
        if z.shape != (space.dimension,) or not np.isfinite(z).all():
            raise InputError(f"{fit}: result.json's best position is {result['best']['z']}, not {space.dimension} finite "
                             "coordinates of the fit's space")
    measured = read_compressed(case)
    if (fit / "predicted.nrrd").is_file():
        predicted = sitk.ReadImage(str(fit / "predicted.nrrd"))
        if predicted.GetSize() != measured.image.GetSize() or not np.allclose(
                predicted.GetOrigin(), measured.image.GetOrigin(), atol=1e-3):
            raise ValueError(f"{fit}: its predicted image lies on another grid than {case}'s measured one; the fit "
                             "was made on another case")
    mesh = read_vtu(fit / "fitting_mesh.vtu")
    reference = read_markups(layout.landmarks) if layout.landmarks.is_file() else None
    if space.plates and space.plates != len(measured.plates):
        raise ValueError(f"{fit}: the fit offsets {space.plates} plates, {case} has {len(measured.plates)}; "
                         "the fit was made on another case")
    relaxation = DynamicRelaxation(tolerance_mm=tolerance_mm)
    imaged = read_image(layout.mr)

    def state(name: str, measured) -> FittedCase:
        ours = reference if measured.landmarks is not None else None  # landmarks count where both images have them
        try:
            problem = FittingProblem(space, mesh, imaged, measured.image, measured.plates,
                                     landmarks=(ours, measured.landmarks) if ours is not None else None,
                                     bins=int(settings.get("bins", 64)), relaxation=relaxation, device=device)
        except ValueError as error:
            raise ValueError(f"{fit}: the fit does not match {case}"
                             f"{'' if name == FIRST_STATE else f' (state {name})'}: {error}") from None
        return FittedCase(problem, z, ours, measured.landmarks if ours is not None else None, measured.image, case, fit,
                          np.asarray(imaged_gravity, float), np.asarray(measured.gravity, float), relaxation, device,
                          name)

    fitted = state(FIRST_STATE, measured)
    fitted.further = [state(name, read_compressed(case, name)) for name in _further_states(case, fit, written)]
    for further in fitted.further:  # one mesh: each element's skin share is computed once for every state
        further._skin = fitted._skin
    return fitted


def _further_states(case: Path, fit: Path, recorded: dict) -> list[str]:
    """The measured states beyond the first that the fit in ``fit`` fitted jointly (its case.json's
    ``states``, each fingerprint checked against the case's files), in the fit's order."""
    from BreastBiomechLib.phantom.compressed_files import case_fingerprint

    states = recorded.get("states") or {}
    layout = CaseLayout(case)
    further = []
    for name, fingerprint in states.items():
        if name == FIRST_STATE:
            continue
        if name not in layout.state_names():
            raise InputError(f"{fit} is a joint fit of the measured states {', '.join(states)}; {case} has no state "
                             f"{name!r} ({layout.state(name).folder.relative_to(case)}): restore it, or fit the case "
                             "again")
        if case_fingerprint(case, name) != fingerprint:
            raise InputError(f"{fit} is a fit of another version of state {name!r}: its measured image or plates "
                             f"differ from {case}'s; fit the case again")
        further.append(name)
    return further

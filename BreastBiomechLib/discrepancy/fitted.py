"""A finished fit of a compressed case, as the diagnosis starts from it: the fit's forward
problem rebuilt (fitting mesh, measured plates, measured image), its best parameters, and the
landmarks. Reads only what a fit may use (:mod:`BreastBiomechLib.phantom.compressed_files`):
never a case's truth.json or truth mesh.

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

FIT_FILES = ("settings.json", "result.json", "fitting_mesh.vtu")


@dataclass
class FittedCase:
    """The fit of one compressed case: its forward ``problem`` (with the fitting ``mesh``, the
    measured ``plates`` and images), the ``space`` searched and the best unit position ``z``,
    the ``reference`` and ``measured`` landmarks (None when the case has none), the
    ``measured_image``, the undeformed scan's posture as gravity ``imaged_gravity`` and the
    compressed scan's ``compressed_gravity`` (m/s^2, LPS; prone: anterior), the forward solves'
    ``relaxation`` and the warp ``device``; the folders it came from."""

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
    _skin: dict = field(default_factory=dict, repr=False)

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
        """Each element's share of volume within ``thickness_mm`` of the skin surface (cached)."""
        from BreastBiomechLib.mesh.skin import skin_fraction

        if thickness_mm not in self._skin:
            nodes = self.mesh.node_set("skin" if "skin" in self.mesh.point_data else "surface")
            self._skin[thickness_mm] = skin_fraction(self.mesh, nodes, thickness_mm)
        return self._skin[thickness_mm]


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
        if recorded.is_file():
            written = json.loads(recorded.read_text())
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
    if measured.landmarks is None:  # landmarks count where both images have them
        reference = None
    landmarks = (reference, measured.landmarks) if reference is not None else None
    if space.plates and space.plates != len(measured.plates):
        raise ValueError(f"{fit}: the fit offsets {space.plates} plates, {case} has {len(measured.plates)}; "
                         "the fit was made on another case")
    relaxation = DynamicRelaxation(tolerance_mm=tolerance_mm)
    try:
        problem = FittingProblem(space, mesh, read_image(layout.mr), measured.image, measured.plates,
                                 landmarks=landmarks, bins=int(settings.get("bins", 64)), relaxation=relaxation,
                                 device=device)
    except ValueError as error:
        raise ValueError(f"{fit}: the fit does not match {case}: {error}") from None
    return FittedCase(problem, z, reference, measured.landmarks if reference is not None else None, measured.image,
                      case, fit,
                      np.asarray(imaged_gravity, float), np.asarray(measured.gravity, float), relaxation, device)

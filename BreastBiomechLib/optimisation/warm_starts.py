"""A fit's warm starts: each batch of forward solves starts at the equilibrium of the best
completed evaluation so far (:class:`~BreastBiomechLib.solver.warm.WarmStart`), not from the
undeformed breast.

A resumed fit must solve each batch exactly as an uninterrupted one does, so the start is a
function of the results file alone: the best completed evaluation recorded so far (the first of
equal objectives), whose equilibrium is kept in the results folder (``warm_starts/``, one
``.npz`` per start, written before that evaluation's record; the two latest kept, so that the
start of a batch killed before its records were written is still there). A results folder from
before warm starts, or one whose start file is gone, resumes cold until a better evaluation comes.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from BreastBiomechLib.io.atomic import atomic_path
from BreastBiomechLib.solver.warm import WarmStart

KEPT = 2  # start files kept: the current start and the one before it


def _file_name(z) -> str:
    """The start file of unit position ``z``: a digest of its float64 coordinates."""
    return hashlib.sha1(np.asarray(z, np.float64).tobytes()).hexdigest()[:16] + ".npz"


class FitWarmStarts:
    """The start of a fit's next batch (``current``, a WarmStart or None) and its objective.
    ``offer`` each completed evaluation in order; ``attach`` a results folder to keep the
    starts there and to take up a resumed run's."""

    def __init__(self) -> None:
        self.current: WarmStart | None = None
        self.objective = np.inf
        self.folder: Path | None = None
        self._written: list[Path] = []  # the start files of this run's starts, oldest first

    def attach(self, folder: str | Path, recorded: list) -> None:
        """Keep the starts in ``folder``; ``recorded``: the evaluations of the results file
        being resumed (empty for a fresh run). The start becomes that of the best completed
        one, where its file is there."""
        self.folder = Path(folder)
        completed = [e for e in recorded if e.status == "completed"]
        if not completed:
            return
        best = min(completed, key=lambda e: e.objective)
        path = self.folder / _file_name(best.z)
        if path.exists():
            self._written = [path]
            with np.load(path) as data:
                plates = data["plate_displacements"] if data["plate_displacements"].size else None
                iterations = int(data["iterations"]) if "iterations" in data and data["iterations"] > 0 else None
                self.current = WarmStart(data["displacement"], plates, float(data["lowest_eigenvalue"]),
                                         float(data["shear_speed_squared"]), iterations)
        self.objective = float(best.objective)

    def offer(self, z, objective: float, solution, plate_displacements: np.ndarray | None) -> None:
        """A completed evaluation at unit position ``z``: its ``solution`` becomes the start if
        its ``objective`` is lower than the current start's (kept in the folder first)."""
        if not (solution.ok and objective < self.objective):
            return
        # the current start's iterations carried (the batch began there, unless it was solved cold)
        start = WarmStart.from_solution(solution, plate_displacements, self.current)
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
            path = self.folder / _file_name(z)
            with atomic_path(path) as temporary:
                with open(temporary, "wb") as stream:
                    np.savez(stream, displacement=start.displacement,
                             plate_displacements=np.zeros((0, 3)) if plate_displacements is None
                             else np.asarray(plate_displacements, float),
                             lowest_eigenvalue=start.lowest_eigenvalue, shear_speed_squared=start.shear_speed_squared,
                             iterations=start.iterations or 0)
            self._written = [p for p in self._written if p != path][-(KEPT - 1):] + [path]
            for old in set(self.folder.glob("*.npz")) - set(self._written):
                old.unlink()
        self.current, self.objective = start, float(objective)

"""A compressed "measured" phantom case on disk, in the ``compressed/`` folder of its undeformed
phantom case (:mod:`BreastBiomechLib.phantom.files`)::

    compressed/mr.nrrd              the measured compressed MR (float32; its own grid)
    compressed/landmarks.mrk.json   the 17 landmarks after compression (LPS)
    compressed/plates.json          the final plate planes as the compression records them
                                    (nominal poses): name, point, normal (LPS mm, unit), their
                                    rounded edge; the axis and compression; the scan's posture
                                    as ``gravity`` (m/s^2, LPS; absent in older cases: prone)
    compressed/truth.json           the truth model (materials, mesh size, noise) and the truth
                                    solve's figures: for validation, hidden from the fitting
    compressed/truth_mesh.vtu       the truth mesh with its ``displacement`` (mm): validation only
    compressed/overview.png         three slices of the measured image with its landmarks

Further measured states (:mod:`BreastBiomechLib.phantom.states`) hold the same files in
``states/<name>/``, with ``force.json`` (the measured plate force and its sd) where recorded.

What a fit may use: the undeformed case, ``mr.nrrd``, ``landmarks.mrk.json``, ``plates.json`` and
``force.json`` of each state (in the seed the plates are seen in the compressed image).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.io.case_layout import (FIRST_STATE, STATE_FORCE, STATE_LANDMARKS, STATE_MR, STATE_PLATES,
                                             UNDEFORMED_MR, CaseLayout)
from BreastBiomechLib.io.case_layout import REFERENCE_LANDMARKS
from BreastBiomechLib.io.images import read_image, write_image
from BreastBiomechLib.io.markups import read_markups, write_markups
from BreastBiomechLib.landmarks import Landmarks
from BreastBiomechLib.phantom.compressed import CompressedCase
from BreastBiomechLib.phantom.parameters import PRONE_GRAVITY


def write_compressed(compressed: CompressedCase, case_dir: str | Path, overview: bool = True,
                     state: str = FIRST_STATE, force: dict | None = None) -> dict[str, Path]:
    """Write ``compressed`` into the folder of measured ``state`` of ``case_dir`` (the first,
    ``compressed/``, or ``states/<name>/``; created if needed; the undeformed case is written by
    :func:`~BreastBiomechLib.phantom.files.write_phantom`), with the measured plate ``force``
    record where given (force.json); returns the paths by role."""
    from BreastBiomechLib.io.meshes import write_vtu
    from BreastBiomechLib.phantom.truth_files import TRUTH_MESH, TRUTH_RECORD

    out = CaseLayout(case_dir).state(state).folder
    out.mkdir(parents=True, exist_ok=True)
    truth = compressed.truth
    paths = {
        "measured": write_image(out / STATE_MR, compressed.image),
        "landmarks": write_markups(out / STATE_LANDMARKS, compressed.landmarks, name="Compressed landmarks"),
        "plates": out / STATE_PLATES,
        "truth": out / TRUTH_RECORD,
        "truth_mesh": write_vtu(out / TRUTH_MESH, compressed.mesh),
    }
    write_text_atomically(paths["plates"], json.dumps({"axis": truth.axis, "compression": truth.compression,
                                           "plates": compressed.plates,
                                           "gravity": [float(g) for g in compressed.gravity]}, indent=2) + "\n")
    write_text_atomically(paths["truth"], json.dumps({"truth": truth.to_dict(), "summary": compressed.summary}, indent=2) + "\n")
    if force is not None:
        paths["force"] = out / STATE_FORCE
        write_text_atomically(paths["force"], json.dumps(force, indent=2) + "\n")
    if overview:
        from BreastBiomechLib.visualisation import save_overview

        paths["overview"] = save_overview(
            out / "overview.png", compressed.image, None, compressed.landmarks,
            title=f"{'' if state == FIRST_STATE else f'State {state}: '}Compressed {truth.compression:.1%} "
                  f"{truth.axis}: measured image and landmarks")
    return paths


def write_measured_case(case_dir: str | Path, undeformed: sitk.Image, measured: sitk.Image, plates: list[dict],
                        landmarks: tuple[Landmarks, Landmarks] | None = None,
                        gravity=PRONE_GRAVITY) -> Path:
    """A case folder a fit and a diagnosis read, made from measured data rather than a phantom:
    ``case_dir``/mr.nrrd (the ``undeformed`` MR), ``compressed/mr.nrrd`` (the ``measured``
    compressed MR, its own grid), ``compressed/plates.json`` (the final ``plates``: dicts with
    name, point, normal towards the tissue, optional edge; LPS mm; the scan's posture
    ``gravity`` m/s^2 LPS; axis and compression unknown) and, with ``landmarks`` (reference,
    measured; the same labels in the same order), ``landmarks.mrk.json`` and
    ``compressed/landmarks.mrk.json``. Returns ``case_dir``."""
    folder = Path(case_dir)
    (folder / FIRST_STATE).mkdir(parents=True, exist_ok=True)
    for plate in plates:
        if np.linalg.norm(plate["normal"]) == 0:
            raise ValueError(f"plate {plate.get('name')!r} has a zero normal")
    write_image(folder / UNDEFORMED_MR, undeformed)
    write_image(folder / FIRST_STATE / STATE_MR, measured)
    if landmarks is not None:
        reference, moved = landmarks
        if reference.labels != moved.labels:
            raise ValueError("the reference and measured landmarks must carry the same labels in the same order")
        write_markups(folder / REFERENCE_LANDMARKS, reference, name="Reference landmarks")
        write_markups(folder / FIRST_STATE / STATE_LANDMARKS, moved, name="Compressed landmarks")
    write_text_atomically(folder / FIRST_STATE / STATE_PLATES, json.dumps(
        {"axis": None, "compression": None, "plates": plates, "gravity": [float(g) for g in gravity]},
        indent=2) + "\n")
    return folder


def write_measured_state(case_dir: str | Path, name: str, measured: sitk.Image, landmarks: Landmarks | None,
                         records_from: str | Path) -> Path:
    """A further measured state ``name`` of the case folder ``case_dir`` (``states/<name>/``): its
    ``measured`` MR, its ``landmarks`` (None: none; present exactly where the case's reference
    landmarks are) and, copied from the state folder ``records_from`` (the state as it was
    loaded), its plates.json and, where recorded, force.json. Returns the state's folder."""
    source = Path(records_from)
    folder = CaseLayout(case_dir).state(name).folder
    folder.mkdir(parents=True, exist_ok=True)
    write_image(folder / STATE_MR, measured)
    if landmarks is not None:
        write_markups(folder / STATE_LANDMARKS, landmarks, name=f"{name} landmarks")
    for record in (STATE_PLATES, STATE_FORCE):
        if (source / record).is_file():
            write_text_atomically(folder / record, (source / record).read_text())
    return folder


@dataclass
class MeasuredCompression:
    """What a fit may use of a compressed case: the measured ``image``, the compressed
    ``landmarks`` (None where the case has none) and the final ``plates`` (dicts: name, point,
    normal, optional edge; LPS mm), the compression ``axis`` and ``compression`` fraction (None
    and NaN where unknown: a case made from measured data), the ``folder`` and the scan's posture
    as ``gravity`` (m/s^2, LPS)."""

    image: sitk.Image
    landmarks: Landmarks | None
    plates: list[dict]
    axis: str | None
    compression: float
    folder: Path
    gravity: np.ndarray = field(default_factory=lambda: np.array(PRONE_GRAVITY))


def compressed_folder(case_dir: str | Path, state: str = FIRST_STATE) -> Path:
    """The folder of measured ``state`` of a compressed case (``compressed/``, or
    ``states/<name>/``; ``case_dir`` is the undeformed case's folder, or for the first state that
    folder itself); a FileNotFoundError that says how to make one otherwise."""
    folder = Path(case_dir)
    if state != FIRST_STATE:
        folder = CaseLayout(folder).state(state).folder
        if not (folder / STATE_PLATES).is_file():
            raise FileNotFoundError(f"{case_dir}: no measured state {state!r} ({folder} with {STATE_PLATES}); the "
                                    f"case holds {', '.join(CaseLayout(case_dir).state_names()) or 'none'}")
        return folder
    if (folder / FIRST_STATE).is_dir():
        folder = folder / FIRST_STATE
    if not (folder / STATE_PLATES).is_file():
        raise FileNotFoundError(f"{folder}: not a compressed case (no plates.json); make one with "
                                "`breastbiomech phantom --case N --compressed --out DIR`")
    return folder


def read_compressed(case_dir: str | Path, state: str = FIRST_STATE) -> MeasuredCompression:
    """Read measured ``state`` of a compressed case written by :func:`write_compressed`
    (``case_dir`` is the undeformed case's folder, or for the first state its ``compressed/``
    folder)."""
    folder = compressed_folder(case_dir, state)
    document = json.loads((folder / STATE_PLATES).read_text())
    for plate in document["plates"]:
        if np.linalg.norm(plate["normal"]) == 0:
            raise ValueError(f"{folder / STATE_PLATES}: plate {plate.get('name')!r} has a zero normal")
    gravity = np.asarray(document.get("gravity", PRONE_GRAVITY), float)
    if gravity.shape != (3,) or not np.all(np.isfinite(gravity)):
        raise ValueError(f"{folder / STATE_PLATES}: gravity is the scan's posture as three finite numbers "
                         f"(m/s^2, LPS; prone: [0, -9.81, 0]), not {document.get('gravity')!r}")
    landmarks = read_markups(folder / STATE_LANDMARKS) if (folder / STATE_LANDMARKS).is_file() else None
    compression = document.get("compression")
    return MeasuredCompression(read_image(folder / STATE_MR), landmarks, document["plates"], document.get("axis"),
                               float("nan") if compression is None else float(compression), folder, gravity)


def case_fingerprint(case_dir: str | Path, state: str = FIRST_STATE) -> str:
    """A SHA-256 of what a fit reads of measured ``state`` of the compressed case in ``case_dir``
    (its measured image and plates): a fit records it (case.json), and a diagnosis refuses a fit
    whose fingerprint differs from the case's."""
    folder = Path(case_dir)
    if state != FIRST_STATE:
        folder = compressed_folder(folder, state)
    elif (folder / FIRST_STATE).is_dir():
        folder = folder / FIRST_STATE
    digest = hashlib.sha256()
    for name in (STATE_MR, STATE_PLATES):
        digest.update((folder / name).read_bytes())
    return digest.hexdigest()

"""``breastbiomech warp|compare``: the FE-predicted image of a solved displacement, and its
similarity to the measured image with landmark errors."""

from __future__ import annotations

import json
import time

import numpy as np

from BreastBiomechLib.cli.common import device_argument, finite, positive_int
from BreastBiomechLib.io.markups import read_markups, write_markups
from BreastBiomechLib.landmarks import landmark_errors, map_landmarks


def _nodal_displacement(path: str, mesh):
    """Nodal displacements (N, 3) mm from a .vtu with a ``displacement`` point array (e.g.
    ``simulate``'s deformed.vtu) or a .npy array, checked against ``mesh``."""
    from BreastBiomechLib.io.meshes import read_vtu

    if str(path).endswith(".npy"):
        displacement = np.load(path)
    else:
        other = read_vtu(path)
        if "displacement" not in other.point_data:
            raise ValueError(f"{path}: no 'displacement' point array (simulate's deformed.vtu has one)")
        displacement = other.point_data["displacement"]
    if displacement.shape != mesh.nodes.shape:
        raise ValueError(f"{path}: {displacement.shape[0]} displacement vectors for a mesh of {len(mesh.nodes)} nodes; "
                         "the displacement must come from a solve of this mesh")
    return displacement


def cmd_warp(args) -> int:
    """The FE-predicted deformed image (and optionally the displacement field and the moved
    landmarks) of a displacement of a mesh."""
    import SimpleITK as sitk

    from BreastBiomechLib.io.images import read_image, write_image
    from BreastBiomechLib.io.meshes import read_vtu
    from BreastBiomechLib.warping import ImageWarper

    mesh = read_vtu(args.mesh)
    displacement = _nodal_displacement(args.displacement, mesh)
    volume = read_image(args.volume)
    like = read_image(args.like) if args.like else volume
    started = time.perf_counter()
    warper = ImageWarper(mesh, volume, like, device=args.device, background=args.background)
    predicted = warper.predict(displacement)
    wall = time.perf_counter() - started
    written = [write_image(args.out, predicted.image)]
    if args.inside:
        written.append(write_image(args.inside, predicted.inside))
    if args.field:
        written.append(write_image(args.field, warper.displacement_field(displacement)))
    if args.landmarks:
        if not args.landmarks_out:
            raise ValueError("--landmarks needs --landmarks-out (where to write the moved landmarks)")
        moved = map_landmarks(mesh, displacement, read_markups(args.landmarks))
        written.append(write_markups(args.landmarks_out, moved, name="Predicted landmarks"))
    inside = int(np.count_nonzero(sitk.GetArrayViewFromImage(predicted.inside)))
    print(f"predicted image on a {'x'.join(map(str, like.GetSize()))} grid: {inside} voxels inside the deformed "
          f"mesh; {wall:.2f} s on {warper.device}")
    for path in written:
        print(f"  {path}")
    return 0


def cmd_compare(args) -> int:
    """NMI and NCC of a predicted and a measured image, and landmark errors."""
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.markups import read_markups
    from BreastBiomechLib.similarity import Similarity

    predicted, measured = read_image(args.predicted), read_image(args.measured)
    if predicted.GetSize() != measured.GetSize() or not np.allclose(predicted.GetOrigin(), measured.GetOrigin(), atol=1e-3):
        raise ValueError("the predicted and measured images are on different grids; warp with --like MEASURED")
    mask = read_image(args.mask) if args.mask else None
    measure = Similarity(measured, mask, bins=args.bins, device=args.device)
    figures = {"nmi": measure.nmi(predicted), "ncc": measure.ncc(predicted), "bins": args.bins,
               "masked_voxels": int(measure.joint_histogram(predicted).sum())}
    if args.landmarks:
        reference, moved, truth = (read_markups(p) for p in args.landmarks)
        errors = landmark_errors(reference, moved, truth)
        figures["landmarks"] = {**errors.summary(), "per_landmark": {
            label: {"displacement_mm": float(d), "error_mm": float(e)}
            for label, d, e in zip(errors.labels, errors.displacement_mm, errors.error_mm)}}
    if args.json:
        print(json.dumps(figures))
        return 0
    print(f"NMI {figures['nmi']:.4f} ({args.bins} bins, {figures['masked_voxels']} voxels), NCC {figures['ncc']:.4f}")
    if args.landmarks:
        print(f"{'landmark':10s} {'displacement (mm)':>18s} {'error (mm)':>11s}")
        for label, row in figures["landmarks"]["per_landmark"].items():
            print(f"{label:10s} {row['displacement_mm']:18.2f} {row['error_mm']:11.2f}")
        s = figures["landmarks"]
        print(f"{'mean ± sd':10s} {s['displacement_mm']['mean']:11.2f} ± {s['displacement_mm']['sd']:4.2f} "
              f"{s['error_mm']['mean']:6.2f} ± {s['error_mm']['sd']:.2f}")
        print(f"{'max':10s} {s['displacement_mm']['max']:18.2f} {s['error_mm']['max']:11.2f}")
    return 0


def add_parsers(sub) -> None:
    """Register the ``warp``, ``compare`` commands on ``sub`` (argparse sub-parsers)."""
    p = sub.add_parser("warp", help="FE-predicted deformed image of a volume through a mesh displacement")
    p.add_argument("mesh", help="reference mesh (.vtu)")
    p.add_argument("displacement", help="nodal displacements: a .vtu with a 'displacement' point array "
                                        "(simulate's deformed.vtu) or a .npy (N, 3) array, mm")
    p.add_argument("volume", help="the undeformed image to warp (.nrrd/.nii.gz)")
    p.add_argument("--like", help="image whose grid the prediction takes (the measured deformed image; default VOLUME's)")
    p.add_argument("--out", required=True, help="predicted image file")
    p.add_argument("--inside", help="also write the mask of voxels inside the deformed mesh here")
    p.add_argument("--field", help="also write the dense displacement field (ITK convention) here")
    p.add_argument("--landmarks", help="reference landmarks (.mrk.json) to move with the displacement")
    p.add_argument("--landmarks-out", help="where to write the moved landmarks (.mrk.json)")
    p.add_argument("--background", type=finite, default=0.0, help="value outside the deformed body (default 0)")
    p.add_argument("--device", type=device_argument, default=None, help="cuda, cpu or a warp device name (default: warp's)")
    p.set_defaults(func=cmd_warp)

    p = sub.add_parser("compare", help="NMI and NCC of predicted vs measured image, and landmark errors")
    p.add_argument("predicted", help="predicted image (from warp)")
    p.add_argument("measured", help="measured image on the same grid")
    p.add_argument("--mask", help="compare only the non-zero voxels of this image (e.g. warp --inside)")
    p.add_argument("--bins", type=positive_int, default=64, help="histogram bins per image for NMI (default 64)")
    p.add_argument("--landmarks", nargs=3, metavar=("REFERENCE", "PREDICTED", "MEASURED"),
                   help="three .mrk.json point lists matched by label: errors as in the seed's Table 2")
    p.add_argument("--device", type=device_argument, default=None, help="cuda, cpu or a warp device name (default: warp's)")
    p.add_argument("--json", action="store_true", help="one JSON line of figures")
    p.set_defaults(func=cmd_compare)

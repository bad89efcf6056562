"""``breastbiomech mesh``: the tetrahedral FE mesh of a label map, with a compression case."""

from __future__ import annotations

import json
from pathlib import Path

from BreastBiomechLib.cli.common import end_progress, fraction, non_negative, positive, progress_line
from BreastBiomechLib.cli.niftysim import export_for_niftysim
from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.io.cases import case_from_dict, compression_case
from BreastBiomechLib.io.markups import read_markups


def cmd_mesh(args) -> int:
    """Mesh a label map; write the mesh, its surfaces, a report, a compression case and its
    NiftySim model."""
    from BreastBiomechLib.io.images import read_label_map
    from BreastBiomechLib.io.meshes import write_surface, write_vtu
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels

    labels = read_label_map(args.labels)
    nipple = None
    if args.landmarks:
        marks = read_markups(args.landmarks)
        if "nipple" not in marks.labels:
            raise ValueError(f"{args.landmarks}: no landmark labelled 'nipple'")
        nipple = marks.positions[marks.labels.index("nipple")]
    settings = MeshSettings(edge_mm=args.edge_mm, surface_edge_mm=args.surface_edge_mm,
                            interface_edge_mm=args.interface_edge_mm, refine_interfaces=not args.no_refine)

    result = mesh_labels(labels, settings, nipple_mm=nipple, progress=progress_line(args.quiet))
    end_progress()
    out = Path(args.out)
    paths = {"mesh": write_vtu(out / "mesh.vtu", result.mesh)}
    for name, surface in result.surfaces.items():
        paths[f"surface_{name}"] = write_surface(out / "surfaces" / f"{name}.vtp", surface)
    summary = result.summary()
    case = compression_case(result.mesh, "mesh.vtu", args.axis, args.compression,
                            chest_clearance_mm=args.chest_clearance_mm)
    paths["case"] = out / "case.json"
    write_text_atomically(paths["case"], case.to_json())
    model, _ = case_from_dict(case, result.mesh, paths["case"])
    paths["niftysim"], niftysim_notes = export_for_niftysim(out / "model.xml", model)
    paths["report"] = out / "mesh_report.json"
    write_text_atomically(paths["report"], json.dumps(summary, indent=1) + "\n")
    failing = summary["quality"]["failing"]["any"]
    print(f"mesh written to {out}: {summary['nodes']} nodes, {summary['elements']} tets, "
          f"{summary['volume_cm3']:.0f} cm3, {summary['seconds']['total']:.1f} s")
    print("  elements per tissue: " + ", ".join(f"{k} {v}" for k, v in summary["elements_per_tissue"].items()))
    print(f"  quality: {failing['count']} elements ({failing['percent']:.3f} %) fail the seed's criteria; "
          f"smallest dihedral angle {summary['quality']['dihedral_min_deg']:.1f} deg")
    print("  tissue Dice vs the label map: " + ", ".join(
        f"{k} {v['dice']:.3f}" for k, v in summary["tissue_representation"].items()))
    for note in summary["notes"]:
        print(f"  note: {note}")
    for note in niftysim_notes:
        print(f"  model.xml: {note}")
    for role, path in paths.items():
        print(f"  {role:20s} {path}")
    return 0


def add_parsers(sub) -> None:
    """Register the ``mesh`` command on ``sub`` (argparse sub-parsers)."""
    p = sub.add_parser("mesh", help="tetrahedral FE mesh of a tissue label map (TetGen), with a compression case")
    p.add_argument("labels", help="label map (.nrrd/.nii.gz) with the label table's values")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--edge-mm", type=positive, default=3.0, help="element edge length in mm (default 3)")
    p.add_argument("--surface-edge-mm", type=positive, default=None,
                   help="the outer surface's triangles, where finer than the interior (default: --edge-mm)")
    p.add_argument("--interface-edge-mm", type=positive, default=None,
                   help="spacing of the points inserted on tissue interfaces (default: --edge-mm)")
    p.add_argument("--no-refine", action="store_true", help="do not insert tissue-interface points")
    p.add_argument("--landmarks", help="a .mrk.json with a point labelled 'nipple' (the nipple node)")
    p.add_argument("--axis", default="LR", choices=["LR", "AP", "SI"], help="compression axis of case.json")
    p.add_argument("--compression", type=fraction, default=0.25, help="compression of case.json, fraction of thickness")
    p.add_argument("--chest-clearance-mm", type=non_negative, default=None,
                   help="band anterior to the chest wall the plates do not touch (default: the plate travel, >= 5 mm)")
    p.add_argument("--quiet", action="store_true", help="no progress on standard error")
    p.set_defaults(func=cmd_mesh)

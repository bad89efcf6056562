"""``breastbiomech segment``: tissue labels and probabilities of an MR volume."""

from __future__ import annotations

from BreastBiomechLib.cli.common import (end_progress, non_negative, non_negative_int, positive, positive_int,
                                         progress_line, weight)
from BreastBiomechLib.io.markups import read_markups


def _segmentation_settings(args):
    from BreastBiomechLib.segmentation import EMSettings, FasciaSettings, SegmentationSettings

    return SegmentationSettings(
        em=EMSettings(mrf_strength=args.mrf, bias_order=args.bias_order, max_iterations=args.iterations,
                      tolerance=args.tolerance, partial_volume=not args.no_partial_volume,
                      noise_bound=not args.no_noise_bound, fraction_smoothing=args.fraction_smoothing),
        skin_mm=args.skin_mm, measure_skin=not args.fixed_skin, keep_skin=args.keep_skin,
        fascia=None if args.no_fascia else FasciaSettings())


def cmd_segment(args) -> int:
    """Segment an MR volume from seed point lists; write the label map, probabilities, bias field
    and a JSON summary."""
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.segmentation import write_segmentation
    from BreastBiomechLib.segmentation import dice_per_tissue, segment_tissues

    image = read_image(args.volume)
    muscle = read_markups(args.seeds_muscle).positions
    tumour = read_markups(args.seeds_tumour).positions if args.seeds_tumour else None
    result = segment_tissues(image, muscle, tumour, _segmentation_settings(args), progress=progress_line(args.quiet))
    end_progress()
    extra = {"inputs": {"volume": str(args.volume), "seeds_muscle": str(args.seeds_muscle),
                        "seeds_tumour": str(args.seeds_tumour) if args.seeds_tumour else None}}
    if args.reference:
        extra["dice_vs_reference"] = dice_per_tissue(result.labels, read_image(args.reference))
    paths = write_segmentation(result, args.out, extra)
    s = result.summary
    volumes = ", ".join(f"{k} {v:.0f}" for k, v in s["tissue_volumes_cm3"].items())
    print(f"segmentation written to {args.out}: tissue volumes (cm3) {volumes}; "
          f"density {s['glandular_density']:.1%}; {sum(s['seconds'].values()):.1f} s")
    em = s["em"]
    print(f"  EM: {em['iterations']} iterations ({'converged' if em['converged'] else 'NOT converged'}), "
          f"fat {em['class_means']['fat']:.0f}, glandular {em['class_means']['glandular']:.0f}, "
          f"bias field {em['bias_range'][0]:.2f}-{em['bias_range'][1]:.2f}")
    if "dice_vs_reference" in extra:
        print("  Dice vs the reference: " + ", ".join(f"{k} {v:.3f}" for k, v in extra["dice_vs_reference"].items()))
    for role, path in paths.items():
        print(f"  {role:22s} {path}")
    return 0


def add_parsers(sub) -> None:
    """Register the ``segment`` command on ``sub`` (argparse sub-parsers)."""
    p = sub.add_parser("segment", help="tissue label map and probabilities of an MR volume (EM + MRF + bias, seeds)")
    p.add_argument("volume", help="MR volume (.nrrd/.nii.gz), T1-weighted without fat suppression")
    p.add_argument("--seeds-muscle", required=True, help="point list (.mrk.json) on the pectoral muscle, 3-5 spread over it")
    p.add_argument("--seeds-tumour", help="point list (.mrk.json) inside the tumour, if there is one")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--mrf", type=non_negative, default=0.4, help="MRF strength beta (0: no spatial prior; default 0.4)")
    p.add_argument("--bias-order", type=non_negative_int, default=3, help="bias-field polynomial order (0: none; default 3)")
    p.add_argument("--iterations", type=positive_int, default=40, help="EM iterations at most (default 40)")
    p.add_argument("--tolerance", type=positive, default=1e-5, help="EM stop: relative log-likelihood change (default 1e-5)")
    p.add_argument("--no-partial-volume", action="store_true", help="two pure classes only (no mixed-voxel class)")
    p.add_argument("--no-noise-bound", action="store_true",
                   help="let a pure class spread more than the noise the other shows (mixed voxels then broaden it)")
    p.add_argument("--fraction-smoothing", type=weight, default=0.2,
                   help="weight of the face neighbours in a final average of each voxel's glandular fraction "
                        "(0: none; default 0.2)")
    p.add_argument("--no-fascia", action="store_true",
                   help="keep in the muscle whatever its growth took in front of it (default: tissue lying on the "
                        "fascia with no fat plane between, found layer by layer or jutting out of the muscle's smooth front, is "
                        "given back to the breast)")
    p.add_argument("--skin-mm", type=non_negative, default=3.0,
                   help="outer breast layer labelled skin (default 3 mm; deeper where the image shows the skin deeper)")
    p.add_argument("--fixed-skin", action="store_true",
                   help="keep the skin layer at --skin-mm instead of deepening it to the skin seen in the image")
    p.add_argument("--keep-skin", action="store_true", help="label skin separately (default: folded into fat)")
    p.add_argument("--reference", help="ground-truth label map: report Dice per tissue")
    p.add_argument("--quiet", action="store_true", help="no progress on standard error")
    p.set_defaults(func=cmd_segment)

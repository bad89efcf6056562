"""``breastbiomech phantom``: a synthetic breast MR case with ground truth, optionally its
compressed "measured" scan made by a truth simulation with hidden effects."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from BreastBiomechLib.cli.common import (add_cluster_options, cohort_progress, device_argument, finite, fraction,
                                         non_negative, non_negative_int, positive, report_failures)
from BreastBiomechLib.cohort import place, run_tasks
from BreastBiomechLib.phantom import PhantomParameters, table1_case
from BreastBiomechLib.phantom.parameters import TABLE1_CASES
from BreastBiomechLib.phantom.table1_cases import table1_tasks


def _phantom_parameters(args):
    params = table1_case(args.case) if args.case else PhantomParameters()
    overrides = {
        "seed": args.seed, "volume_cm3": args.volume_cm3, "density": args.density,
        "tumour_diameter_mm": args.tumour_mm, "snr": args.snr, "bias_strength": args.bias,
        "spacing_mm": tuple(args.spacing) if args.spacing else None,
        "skin_separate": True if args.skin_separate else None,
    }
    values = params.to_dict()
    values.update({k: v for k, v in overrides.items() if v is not None})
    return PhantomParameters.from_dict(values)


def _add_phantom_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--case", type=int, choices=range(1, 6), metavar="1-5",
                   help="start from the preset for case 1-5 of the seed paper's Table 1")
    p.add_argument("--seed", type=non_negative_int, help="random seed (same seed, same case)")
    p.add_argument("--volume-cm3", type=positive, help="breast volume, 400-1500 cm^3")
    p.add_argument("--density", type=fraction, help="glandular volume fraction, 0.05-0.65")
    p.add_argument("--tumour-mm", type=non_negative, help="tumour diameter in mm (0: none)")
    p.add_argument("--snr", type=positive, help="fat signal / noise sigma")
    p.add_argument("--bias", type=non_negative, help="bias field amplitude (0.2 = +-20%%)")
    p.add_argument("--spacing", type=positive, nargs=3, metavar=("L", "P", "S"), help="voxel size in mm")
    p.add_argument("--skin-separate", action="store_true", help="keep skin as its own label")


def _truth_model(args):
    """The truth of ``phantom --compressed``: the Table 1 preset of ``--case`` (else the
    default truth), with ``--compression``, ``--axis``, ``--truth-edge-mm``,
    ``--chest-clearance-mm``, ``--moving-plate`` and the hidden effects applied."""
    from BreastBiomechLib.phantom.compressed import TruthModel, table1_truth

    truth = table1_truth(args.case) if args.case else TruthModel()
    compression = truth.compression if args.compression is None else args.compression
    tilt = None if args.plate_tilt is None else [list(args.plate_tilt), [0.0, 0.0]]
    if args.plate_pivot is not None and tilt is None:
        raise ValueError("--plate-pivot is the pivot of a plate's turn: give the turn with --plate-tilt")
    pivot = None if args.plate_pivot is None else [list(args.plate_pivot), [0.0, 0.0, 0.0]]
    return replace(truth, compression=compression, axis=args.axis, edge_mm=args.truth_edge_mm,  # checked again
                   chest_clearance_mm=args.chest_clearance_mm, moving_plate=args.moving_plate,
                   friction=args.friction[0] if len(args.friction) == 1 else list(args.friction),
                   gravity=args.gravity, compression_gravity=args.compression_gravity,
                   chest_wall=args.chest_wall, chest_wall_stiffness=list(args.chest_wall_stiffness),
                   plate_tilt_deg=tilt, plate_pivot_mm=pivot, skin=None if args.skin is None else list(args.skin),
                   stiff_band=None if args.stiff_band is None else list(args.stiff_band),
                   chest_wall_shift_mm=None if args.chest_wall_shift is None else list(args.chest_wall_shift))


def cmd_phantom(args) -> int:
    from BreastBiomechLib.phantom import generate_phantom, write_phantom

    truth = _truth_model(args) if args.compressed else None
    if not args.compressed and args.compression is not None:
        raise ValueError("--compression applies to a compressed case: add --compressed")
    effects = {"--chest-clearance-mm": args.chest_clearance_mm is not None or None,
               "--moving-plate": args.moving_plate != "both" or None,
               "--friction": any(args.friction) or None, "--gravity": args.gravity, "--compression-gravity": args.compression_gravity,
               "--plate-tilt": args.plate_tilt, "--chest-wall": args.chest_wall != "fixed" or None,
               "--skin": args.skin, "--stiff-band": args.stiff_band, "--chest-wall-shift": args.chest_wall_shift}
    given = [name for name, value in effects.items() if value]
    if given and not args.compressed:
        raise ValueError(f"{', '.join(given)} change the truth simulation of a compressed case: add --compressed")
    states = _states(args, truth)
    case = generate_phantom(_phantom_parameters(args))
    paths = write_phantom(case, args.out, overview=not args.no_overview)
    s = case.summary
    print(f"phantom written to {args.out}: {s['breast_volume_cm3']:.0f} cm3 breast, "
          f"density {s['glandular_density']:.1%}, grid {s['size_voxels']} at {s['spacing_mm']} mm, "
          f"{len(case.landmarks)} landmarks, {s['seconds']:.1f} s")
    for role, path in paths.items():
        print(f"  {role:20s} {path}")
    if truth is not None:
        from BreastBiomechLib.phantom.compressed import compress_phantom
        from BreastBiomechLib.phantom.compressed_files import write_compressed

        compressed = compress_phantom(case, truth, device=args.device,
                                      progress=lambda fraction, message: print(f"  [{fraction:4.0%}] {message}",
                                                                                flush=True))
        paths = write_compressed(compressed, args.out, overview=not args.no_overview)
        c = compressed.summary
        forces = ", ".join(f"{name} {force:.2f} N" for name, force in c["plate_forces_N"].items())
        print(f"compressed case written to {Path(args.out) / 'compressed'}: {truth.compression:.1%} {truth.axis}, "
              f"truth mesh {c['truth_tets']} tets ({truth.edge_mm:g} mm), {c['solve_message']}; plate forces "
              f"{forces}; largest displacement {c['max_displacement_mm']:.1f} mm; {c['seconds']:.0f} s")
        for role, path in paths.items():
            print(f"  {role:20s} {path}")
        _add_states(args.out, states, args)
    return 0


def _states(args, truth) -> list:
    """The further measured states of ``--state`` (:class:`~BreastBiomechLib.phantom.states.StateSpec`),
    checked (each one's truth made from ``truth``, the first state's) before anything is made."""
    from BreastBiomechLib.phantom.states import check_states, parse_state

    if not args.state:
        return []
    if truth is None:
        raise ValueError("--state adds a measured state to a compressed case: add --compressed")
    specs = [parse_state(words) for words in args.state]
    check_states(specs)
    for k, spec in enumerate(specs, start=1):
        spec.truth(truth, k)
    return specs


def _add_states(case_dir, specs, args) -> None:
    """Make the further states ``specs`` of the compressed phantom case ``case_dir`` and say what each is."""
    from BreastBiomechLib.phantom.states import add_states

    for made in add_states(case_dir, specs, device=args.device, overview=not args.no_overview,
                           progress=lambda message: print(f"  {message}", flush=True)):
        truth, c, force = made["truth"], made["summary"], made["force"]
        print(f"state {made['name']} written to {made['folder']}: {truth.compression:.1%} {truth.axis}, moving "
              f"{truth.moving_plate}, {c['solve_message']}; largest displacement {c['max_displacement_mm']:.1f} mm"
              + (f"; measured force {force['newtons']:.2f} +- {force['sd']:.2f} N on {force['plate']}" if force else ""))


def cmd_phantom_state(args) -> int:
    """Further measured states added to a compressed phantom case made earlier."""
    from BreastBiomechLib.phantom.states import parse_state

    _add_states(args.case_dir, [parse_state(words) for words in args.state], args)
    return 0


def _state_option(p: argparse.ArgumentParser, required: bool = False) -> None:
    p.add_argument("--state", action="append", nargs="+", metavar=("NAME", "KEY=VALUE"), required=required,
                   help="a further measured state (CASE/states/NAME) of the compressed case: the same breast and "
                        "hidden effects compressed again with these settings (compression=F, axis=LR|SI, "
                        "moving-plate=both|first|second, compression-gravity=GX,GY,GZ, force-sd=N to record the "
                        "measured plate force); repeat for several")


def cmd_table1_cases(args) -> int:
    """The compressed cases of the seed's Table 1, one cohort task per case (a rerun makes only
    the missing ones)."""
    from BreastBiomechLib.optimisation.study import log_failure

    tasks = table1_tasks(args.out, args.cases, truth_edge_mm=args.truth_edge_mm, overview=not args.no_overview)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    outcomes = run_tasks(tasks, place(args.scheduler, args.workers, args.device), progress=cohort_progress(args.quiet),
                         on_outcome=lambda o: log_failure(Path(args.out) / "failures.log", o))
    failed = [o for o in outcomes if not o.ok]
    report_failures(failed, Path(args.out) / "failures.log")
    print(f"{len(args.cases) - len(tasks)} case(s) already in {args.out}, {len(outcomes) - len(failed)} made, "
          f"{len(failed)} failed")
    return 1 if failed else 0


def add_parsers(sub) -> None:
    """Register the ``phantom`` and ``table1-cases`` commands on ``sub`` (argparse sub-parsers)."""

    p = sub.add_parser("phantom", help="generate a synthetic breast MR case with ground truth")
    p.add_argument("--out", required=True, help="output folder")
    _add_phantom_options(p)
    p.add_argument("--no-overview", action="store_true", help="skip the PNG overview")
    p.add_argument("--compressed", action="store_true",
                   help="also write a compressed 'measured' case (OUT/compressed): a truth simulation with hidden "
                        "materials, imaged like a second scan, its landmarks and plates")
    p.add_argument("--compression", type=fraction,
                   help="fraction of the breast's thickness the plates close (default: the seed's for --case, else 0.25)")
    p.add_argument("--axis", choices=("LR", "SI"), default="LR", help="compression axis (default LR, as the seed)")
    p.add_argument("--truth-edge-mm", type=positive, default=2.0,
                   help="element size of the truth mesh (default 2 mm: finer than any fitting mesh)")
    p.add_argument("--chest-clearance-mm", type=non_negative,
                   help="how far anterior to the chest the plates' flat faces end (mm; default: the plate travel, "
                        "at least 5 mm); their edges are rounded")
    p.add_argument("--moving-plate", choices=("both", "first", "second"), default="both",
                   help="which plate closes on the breast: both (half the travel each; default), or only the first "
                        "or second (lower or higher LPS coordinate) towards the other, held one, as the seed's rig "
                        "(its lateral movable plate is the second of LR for the phantom's left breast)")
    _state_option(p)
    p.add_argument("--device", type=device_argument, help="warp device of the truth simulation (cuda, cpu; default: warp's)")
    effects = p.add_argument_group("hidden effects of the truth simulation (recorded in truth.json only)")
    effects.add_argument("--friction", type=non_negative, nargs="+", default=[0.0], metavar="MU",
                         help="the plates' Coulomb friction mu: one for all plates, or one per plate (first, second)")
    effects.add_argument("--gravity", type=finite, nargs=3, metavar=("GX", "GY", "GZ"),
                         help="gravity the scan was imaged under (m/s^2, LPS; prone: 0 -9.81 0): the truth starts "
                              "pre-stressed from its unloaded state")
    effects.add_argument("--compression-gravity", type=finite, nargs=3, metavar=("GX", "GY", "GZ"),
                         help="gravity while the plates close (default: --gravity's)")
    effects.add_argument("--chest-wall", choices=("fixed", "sliding", "elastic"), default="fixed",
                         help="the chest wall's support (default fixed, as the seed)")
    effects.add_argument("--chest-wall-stiffness", type=non_negative, nargs=2, default=[0.0, 0.0],
                         metavar=("NORMAL", "TANGENTIAL"), help="elastic or sliding chest wall's springs (Pa/mm)")
    effects.add_argument("--skin", type=positive, nargs=2, metavar=("E_PA", "THICKNESS_MM"),
                         help="a skin layer of this Young's modulus and thickness (explicit elements of a truth "
                              "mesh made fine enough to hold it)")
    effects.add_argument("--plate-tilt", type=finite, nargs=2, metavar=("DEG1", "DEG2"),
                         help="the first plate's tilt about its two tilt axes (degrees, at most 10)")
    effects.add_argument("--plate-pivot", type=finite, nargs=3, metavar=("AXIS1", "AXIS2", "NORMAL"),
                         help="the pivot of --plate-tilt from the plate's final point, mm along its two tilt axes and "
                              "its normal (< 0 behind the plate; default: the point itself)")
    effects.add_argument("--stiff-band", type=positive, nargs=2, metavar=("FACTOR", "THICKNESS_MM"),
                         help="a stiff sheet the MR does not show: moduli times FACTOR in an oblique band "
                              "through the breast's centroid (not in the discrepancy library)")
    effects.add_argument("--chest-wall-shift", type=finite, nargs=3, metavar=("L", "P", "S"),
                         help="the thorax moved by this (mm, LPS) between the scans (not in the discrepancy "
                              "library)")
    p.set_defaults(func=cmd_phantom)

    p = sub.add_parser("phantom-state", help="add further measured states to a compressed phantom case: the same "
                                             "breast and hidden effects compressed again another way")
    p.add_argument("case_dir", help="a compressed phantom case (`breastbiomech phantom --compressed --out DIR`)")
    _state_option(p, required=True)
    p.add_argument("--no-overview", action="store_true", help="skip the PNG overviews")
    p.add_argument("--device", type=device_argument, help="warp device of the truth simulations (cuda, cpu; default: warp's)")
    p.set_defaults(func=cmd_phantom_state)

    p = sub.add_parser("table1-cases", help="the compressed phantom cases of the seed's Table 1, as cohort tasks "
                                            "(OUT/case<N>; a rerun makes only the missing ones)")
    p.add_argument("--out", required=True, help="output folder (one case<N> folder per case)")
    p.add_argument("--cases", nargs="+", type=int, choices=sorted(TABLE1_CASES), default=sorted(TABLE1_CASES),
                   help="which cases (default all)")
    p.add_argument("--truth-edge-mm", type=positive, default=2.0, help="element size of the truth meshes (default 2 mm)")
    p.add_argument("--no-overview", action="store_true", help="skip the PNG overviews")
    p.add_argument("--device", type=device_argument, help="warp device: cuda (every GPU), cuda:K (GPU K), cpu; default: the GPUs if any")
    add_cluster_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_table1_cases)

"""`nemsim design`, `splits` and `data check|stats`: the control design, split manifests and data files."""

from __future__ import annotations

import argparse

from nemsim.cli.common import Subparsers, UserError, output_path, seed_arg, write_json


def add_geometry_options(p: argparse.ArgumentParser) -> None:
    """--feature, --cd-nm, --mask-nm: the geometry ranges sampled with the controls (``geometry_options``)."""
    p.add_argument("--feature", choices=("hole", "trench"), default=None,
                   help="feature kind of every case (default: the scene's 40 nm hole under 80 nm of mask); "
                        "with --cd-nm/--mask-nm, each case gets its own CD and mask")
    p.add_argument("--cd-nm", default=None, metavar="LO:HI",
                   help="opening (hole diameter, trench width) in nm: a value or a range sampled as an extra "
                        "Latin-hypercube column, e.g. 24:64 (default 40)")
    p.add_argument("--mask-nm", default=None, metavar="LO:HI",
                   help="mask thickness in nm: a value or a range, e.g. 40:120 (default 80; built as whole "
                        "voxels of the scene)")


def geometry_options(args: argparse.Namespace, n: int, seed: int):
    """(kind, (n, 2) [cd_nm, mask_nm]) from --feature/--cd-nm/--mask-nm, or None when none is given."""
    if args.feature is None and args.cd_nm is None and args.mask_nm is None:
        return None
    from nemsim.geometry.feature import geometry_design, parse_range

    try:
        cd = parse_range(args.cd_nm or "40", "--cd-nm")
        mask = parse_range(args.mask_nm or "80", "--mask-nm")
    except ValueError as exc:
        raise UserError(str(exc)) from None
    return args.feature or "hole", geometry_design(n, seed, cd, mask)


def register(sub: Subparsers) -> None:
    p = sub.add_parser(
        "design",
        help="write the Latin-hypercube control design as CSV ([supp_data_generation])",
        description=(
            "Draw the Latin-hypercube design of the 14 process controls and write it as CSV: header = "
            "the 14 control names, one row per case (case id = row index), in physical units (fluxes "
            "in mol m^-2 s^-1, cosine-power exponents as integers, ion-energy means and spreads in eV). "
            "The defaults reproduce the paper's 500-case design. --kind corners draws distinct random "
            "corners of the box instead (every control at its minimum or maximum), never the physics "
            "benchmark's held-out corners: extra training cases where the Latin hypercube has none. "
            "--kind pairs writes N/2 sweep pairs: a Latin-hypercube recipe, then the same recipe with one "
            "control group (each flux, the ion energies, the ion angular exponents, the neutral angular "
            "exponent, in turn) moved to another level, and a seed_id column that gives both rows one "
            "simulator seed (common random numbers): training data for `pair_loss_weight`. --kind "
            "lhs-log-angles is the Latin hypercube with the ion angular exponents uniform in log m (the "
            "profile follows the angular spread, ~1/sqrt(m); uniform in m leaves few recipes where it "
            "changes most): extra training data for the angular responses. "
            "Examples: nemsim design --out data/design.csv; "
            "nemsim design --kind corners --n 300 --seed 44 --out data/design-corners.csv; "
            "nemsim design --kind pairs --n 600 --seed 45 --out data/design-pairs.csv; "
            "nemsim design --kind lhs-log-angles --n 1000 --seed 46 --out data/design-log-angles.csv. "
            "Geometry: --feature hole|trench with --cd-nm LO:HI and --mask-nm LO:HI adds the columns "
            "feature, cd_nm, mask_nm (two more Latin-hypercube columns; the 14 controls stay as without "
            "them), read by `nemsim generate --controls`: nemsim design --feature hole --cd-nm 24:64 "
            "--mask-nm 40:120 --out data/design-holes.csv"
        ),
    )
    add_geometry_options(p)
    p.add_argument("--n", type=int, default=500, help="number of cases (default 500)")
    p.add_argument("--seed", type=seed_arg, default=42, help="random seed (default 42, the paper's design)")
    p.add_argument("--kind", choices=("lhs", "corners", "pairs", "lhs-log-angles"), default="lhs",
                   help="lhs: Latin hypercube (default, the paper's); corners: random corners of the box; "
                        "pairs: N/2 one-group sweep pairs with shared seeds (N even); lhs-log-angles: "
                        "Latin hypercube with the ion angular exponents uniform in log m")
    p.add_argument("--out", required=True, metavar="FILE.csv",
                   help="output CSV (overwritten; missing folders are created)")
    p.set_defaults(handler=_cmd_design)

    p = sub.add_parser(
        "splits",
        help="write one split manifest JSON per setting ([supp_protocols])",
        description=(
            "Partition the cases of a design CSV, or of a trajectory file, into train/val/test for every "
            "evaluation setting (control-id, ood-ar, ood-cl, ood-joint, vis-50, vis-60) and write "
            "DIR/<setting>.json, each with its nested data-efficiency training subsets (10/20/50/100 %); "
            "print the table of set sizes. `nemsim train` and `nemsim evaluate` read these from "
            "<data dir>/splits by default and refuse manifests whose case ids are not in the data file. "
            "Example: nemsim splits --design data/design.csv --out data/splits"
        ),
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--design", metavar="FILE.csv",
                     help="design CSV (from `nemsim design`); case id = row index")
    src.add_argument("--data", metavar="FILE.h5",
                     help="trajectory file (from `nemsim generate`): its case ids and controls")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    p.add_argument("--seed", type=seed_arg, default=0, help="partition seed (default 0)")
    p.add_argument("--transitions", type=int, default=None,
                   help="transitions per trajectory (default: the data file's horizon, else 100)")
    p.set_defaults(handler=_cmd_splits)

    p = sub.add_parser(
        "data",
        help="trajectory-file tools",
        description="Tools for trajectory HDF5 files written by `nemsim generate`. "
        "Example: nemsim data check data/small.h5",
    )
    dsub = p.add_subparsers(dest="data_command", metavar="ACTION")
    dsub.required = True
    c = dsub.add_parser(
        "check",
        help="integrity checks of a trajectory HDF5 file ([supp_dataset_statistics]); exit 2 on failure",
        description=(
            "Run the integrity checks of a trajectory file: layout and format version, scene, control "
            "and channel names, state shape and dtype, timestamps, completeness and seeds of every case, "
            "unique case ids and controls, control ranges and transforms, and finite, bounded states "
            "(reads every state, so large files take a while). Prints one line per check; writes "
            "nothing. Exit code 0 if all pass, 2 otherwise. Example: nemsim data check data/small.h5"
        ),
    )
    c.add_argument("file", metavar="FILE", help="trajectory .h5 (from `nemsim generate`)")
    c.add_argument("--allow-incomplete", action="store_true",
                   help="unfinished cases are a warning, not a failure (e.g. while generation runs)")
    c.set_defaults(handler=_cmd_data_check)
    st = dsub.add_parser(
        "stats",
        help="profile metrics of the final states over the design (calibration figures), optionally paired",
        description=(
            "Compute the profile metrics (etch depth, top / bottom width, bowing, mask loss, nm) of the last "
            "state of every complete case and print their distribution over the design and the number of "
            "cases bowed by more than one voxel. With --against OTHER.h5 (the same design made with another "
            "simulator configuration) also print the paired change on the common case ids. Reads only the "
            "final states. Example: nemsim data stats data/small.h5 --against data/v1/small.h5 --json "
            "runs/stats.json"
        ),
    )
    st.add_argument("file", metavar="FILE", help="trajectory .h5 (from `nemsim generate`)")
    st.add_argument("--against", metavar="OTHER", default=None, help="a second trajectory file to pair with")
    st.add_argument("--json", dest="json_out", metavar="FILE.json", default=None,
                    help="also write the figures to this JSON file")
    st.set_defaults(handler=_cmd_data_stats)


def _cmd_data_stats(args: argparse.Namespace) -> int:
    import os

    from nemsim.data.stats import final_profiles, paired_change, stats, stats_markdown

    for path in (args.file, args.against):
        if path is not None and not os.path.isfile(path):
            raise UserError(f"no such file: {path}")
    try:
        new = final_profiles(args.file)
        report = stats(new)
        change = paired_change(new, final_profiles(args.against)) if args.against else None
    except (ValueError, KeyError) as exc:
        raise UserError(str(exc)) from None
    print(stats_markdown(report, change))  # noqa: T201
    if args.json_out:
        write_json(args.json_out, {**report, "sim_config": new.sim_config, "change": change,
                                    "against": args.against})
        print(f"wrote {args.json_out}")  # noqa: T201
    return 0


def _cmd_design(args: argparse.Namespace) -> int:
    from nemsim.controls import (
        MAX_DESIGN_N,
        corner_design,
        heldout_corners,
        lhs_design,
        pair_design,
        write_controls_csv,
    )

    if not 1 <= args.n <= MAX_DESIGN_N:
        raise UserError(f"--n must be in 1..{MAX_DESIGN_N} (the largest design drawn; the paper's has 500 "
                        f"cases), got {args.n}")
    seed_ids = None
    if args.kind == "pairs":
        if args.n % 2:
            raise UserError(f"--kind pairs needs an even --n (two cases per pair), got {args.n}")
        raw, seed_ids = pair_design(args.n // 2, args.seed)
        what = f"{args.n // 2} sweep pairs, seed {args.seed}, each pair one simulator seed (column seed_id)"
    elif args.kind == "corners":
        held_out = heldout_corners()
        try:
            raw = corner_design(args.n, args.seed, exclude=held_out)
        except ValueError as e:
            raise UserError(str(e)) from None
        what = f"random box corners, seed {args.seed}, none of the physics benchmark's {len(held_out)}"
    elif args.kind == "lhs-log-angles":
        raw = lhs_design(args.n, args.seed, log_angles=True)
        what = f"LHS seed {args.seed}, ion exponents log m"
    else:
        raw, what = lhs_design(args.n, args.seed), f"LHS seed {args.seed}"
    geometry = geometry_options(args, args.n, args.seed)
    write_controls_csv(output_path(args.out), raw, seed_ids, geometry)
    extra = "" if geometry is None else f" + {geometry[0]} geometry (cd_nm, mask_nm)"
    print(f"wrote {args.out}: {args.n} cases x 14 controls{extra} ({what})")  # noqa: T201
    return 0


def _cmd_splits(args: argparse.Namespace) -> int:
    from nemsim.data.splits import make_manifests, split_table, write_manifests

    if args.transitions is not None and args.transitions < 1:
        raise UserError(f"--transitions must be >= 1, got {args.transitions}")
    if args.data:
        from nemsim.data.hdf5 import open_trajectories

        with open_trajectories(args.data) as tf:
            raw, case_ids, horizon = tf.controls_raw, tf.case_ids, tf.scene.n_transitions
    else:
        from nemsim.controls import read_controls_csv

        raw, case_ids, horizon = read_controls_csv(args.design), None, 100
    manifests = make_manifests(raw, case_ids, seed=args.seed, n_transitions=args.transitions or horizon)
    paths = write_manifests(manifests, args.out)
    print(split_table(manifests))  # noqa: T201
    print(f"wrote {len(paths)} manifests to {args.out}")  # noqa: T201
    return 0


def _cmd_data_check(args: argparse.Namespace) -> int:
    import os

    from nemsim.data.hdf5 import check_dataset

    if not os.path.isfile(args.file):
        raise UserError(f"no such file: {args.file}")
    report = check_dataset(args.file, require_complete=not args.allow_incomplete)
    print(report.text)  # noqa: T201
    return 0 if report.ok else 2



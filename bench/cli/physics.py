"""`nemsim bench physics|responses|extrapolation|learning-curve|monotone-eps`: a surrogate judged against the
simulator."""

from __future__ import annotations

import argparse
from pathlib import Path

from bench.cli.common import add_truth_options, print_plan, sim_cost, sim_truth
from nemsim.cli.common import (
    Subparsers,
    UserError,
    add_monotone_option,
    load_checkpoint_arg,
    parse_seeds,
    setting_manifest,
    write_json,
)


def register(bench_sub: Subparsers) -> None:
    _add_physics(bench_sub)
    _add_extrapolation(bench_sub)
    _add_learning_curve(bench_sub)


def _add_learning_curve(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "learning-curve",
        help="active learning against Latin hypercubes: edge errors against simulator cases spent",
        description=(
            "Judge the starting checkpoint and every trained round of `nemsim learn run` directories "
            "(one per arm, e.g. the default acquisition and --acquisition lhs at the same budget) with the "
            "physics and extrapolation benchmarks on the same simulator runs: box-corner, interior and "
            "1.5-half-width errors and the slopes against the simulator cases each arm spent. Writes "
            "learning_curve.md, .json and .png to --out. Example: nemsim bench learning-curve --run "
            "active=runs/lc/active --run lhs=runs/lc/lhs --cache-dir runs/truth-cache "
            "--out runs/bench/learning_curve"
        ),
    )
    p.add_argument("--run", action="append", required=True, metavar="LABEL=DIR",
                   help="an arm: its label and `nemsim learn run` output directory (repeatable)")
    add_truth_options(p)
    p.add_argument("--out", default="runs/bench/learning_curve", metavar="DIR",
                   help="output directory (default runs/bench/learning_curve)")
    p.set_defaults(handler=_cmd_bench_learning_curve)


def _cmd_bench_learning_curve(args: argparse.Namespace) -> int:
    from bench import extrapolation as ex
    from bench import learning_curve as lc
    from bench import physics
    from bench.stress import initial_state

    arms = {}
    for item in args.run:
        label, sep, run_dir = item.partition("=")
        if not sep or not label.strip() or not Path(run_dir).is_dir():
            raise UserError(f"--run {item!r}: expected LABEL=DIR with an existing directory")
        arms[label.strip()] = run_dir
    try:
        start_path = lc.common_start(lc.arm_points(d) for d in arms.values())
        seeds = parse_seeds(args.seeds)
    except (FileNotFoundError, ValueError) as exc:
        raise UserError(str(exc)) from None
    start = load_checkpoint_arg(start_path, args)
    phys_cfg, ex_cfg = physics.PhysicsConfig(seeds=seeds), ex.ExtrapolationConfig(seeds=seeds)
    with sim_truth(args, start) as truth:
        x0 = initial_state(start.scene)

        def judge(checkpoint: str | Path) -> tuple[dict, dict]:
            model = load_checkpoint_arg(checkpoint, args).model
            print(f"judging {checkpoint}")  # noqa: T201
            return (physics.run_physics(model, truth, x0, phys_cfg),
                    ex.run_extrapolation(model, truth, x0, ex_cfg))  # fmt: skip

        try:
            rep = lc.run_learning_curve(arms, judge)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        rep["simulator_cost"] = sim_cost(truth)
    paths = lc.write_outputs(rep, args.out)
    print(lc.format_markdown(rep))  # noqa: T201
    print("wrote " + ", ".join(paths.values()))  # noqa: T201
    return 0


def _add_physics(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "physics",
        help="surrogate vs simulator: one-at-a-time sweeps, held-out profile errors, no-change baseline",
        description=(
            "Judge a checkpoint against the Monte Carlo simulator (two seeds per recipe): (a) one control "
            "group at a time from the median recipe (Cl+, Ar+, Cl2+, Cl fluxes; ion energies; ion angular "
            "exponents; neutral angular exponent) at --levels levels: final depth, top and bottom width, "
            "mask loss, bowing and the slope ratio surrogate/simulator; (b) held-out cases (fresh "
            "Latin-hypercube points and box corners, or a data file's split): profile-metric errors beside "
            "the seed-to-seed differences, Avg RMSE beside the seed-to-seed floor; (c) cases worse than "
            "predicting no change. Writes physics.md, physics.json and physics.png to --out. "
            "Example: nemsim bench physics --checkpoint checkpoints/nemsim-small.pt --workers 2"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt")
    p.add_argument("--levels", type=int, default=3, help="sweep levels per control group, >= 3 (default 3)")
    p.add_argument("--heldout", type=int, default=12,
                   help="fresh Latin-hypercube held-out cases (default 12; ignored with --data)")
    p.add_argument("--corners", type=int, default=16,
                   help="corners of the control box among the fresh held-out cases (default 16; never among "
                        "the corners `nemsim design --kind corners` draws for training)")
    p.add_argument("--data", default=None, metavar="FILE.h5",
                   help="take the held-out controls from this data file's split instead (re-simulated with "
                   "two seeds)")
    p.add_argument("--setting", default="control-id", help="split setting with --data (default control-id)")
    p.add_argument("--splits", default=None, metavar="DIR", help="split manifests directory with --data")
    p.add_argument("--split", default="test", help="split with --data (default test)")
    p.add_argument("--max-cases", type=int, default=None, help="first N cases of the split with --data")
    add_truth_options(p)
    p.add_argument("--out", default="runs/bench/physics", metavar="DIR",
                   help="output directory (default runs/bench/physics)")
    p.set_defaults(handler=_cmd_bench_physics)

    p = bench_sub.add_parser(
        "responses",
        help="surrogate vs a data file: slopes of each profile metric on the 14 controls, no new simulation",
        description=(
            "Roll the surrogate out on the cases of a data file (all of them, or one split with --setting) "
            "and fit each final profile metric (depth, top and bottom width, mask loss, bowing), the "
            "simulator's and the surrogate's, by least squares on the 14 normalized controls. Reports every "
            "slope the simulator's data resolve (beyond 2 standard errors), the ratio surrogate/simulator, "
            "how many are within +-25 %% and how many have the wrong sign. On a training design it asks "
            "whether a response was learned, on a test split whether it generalizes. Writes responses.md, "
            ".json and .png to --out. Example: nemsim bench responses --checkpoint "
            "checkpoints/nemsim-small.pt --data data/small.h5"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt")
    p.add_argument("--data", required=True, metavar="FILE.h5",
                   help="trajectory file (from `nemsim generate`)")
    p.add_argument("--setting", default=None,
                   help="use one split of this setting (e.g. control-id); default: every complete case")
    p.add_argument("--splits", default=None, metavar="DIR", help="split manifests directory with --setting")
    p.add_argument("--split", default="test", help="split with --setting (default test)")
    p.add_argument("--max-cases", type=int, default=None, help="the first N of those cases")
    p.add_argument("--batch-size", type=int, default=8, help="rollouts run together (default 8)")
    p.add_argument("--one-call", type=int, default=None, metavar="T0",
                   help="instead of rollouts from x_0: one network call (its k states) from each case's own "
                        "simulator state at step T0, and the slopes of the metrics' increments over it; "
                        "separates what one call learned from what a rollout compounds (e.g. 50)")
    add_monotone_option(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--out", default="runs/bench/responses", metavar="DIR",
                   help="output directory (default runs/bench/responses)")
    p.set_defaults(handler=_cmd_bench_responses)


def _add_extrapolation(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "extrapolation",
        help="surrogate vs simulator outside the training box: errors against the distance from the box",
        description=(
            "Simulate (two seeds) and predict recipes outside the training box: each control at 1.5x and 2x "
            "the box's half-width from its centre on either side (--distances; inadmissible values skipped), "
            "zero fluxes, isotropic (m = 1) and needle-like ion angles, box corners, beside in-box reference "
            "points. Reports Avg RMSE against the seed-to-seed floor and profile-metric errors, per case and "
            "per group with the ratio to the in-box error; writes extrapolation.md, .json and .png (error "
            "against normalized distance from the box) to --out. "
            "Example: nemsim bench extrapolation --checkpoint checkpoints/nemsim-small.pt --workers 2"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt")
    p.add_argument("--distances", default="1.5,2",
                   help="normalized |u| of the out-of-box points, comma-separated, each > 1 (default 1.5,2)")
    p.add_argument("--corners", type=int, default=4, help="corners of the 14-control box (default 4)")
    p.add_argument("--in-box", type=int, default=6,
                   help="in-box Latin-hypercube reference points beside the design centre (default 6)")
    p.add_argument("--needle-m", type=float, default=10_000.0,
                   help="ion angular exponent of the needle-like recipe (default 10000)")
    p.add_argument("--isotropic-m", type=float, default=1.0,
                   help="angular exponent of the isotropic recipe (default 1)")
    add_truth_options(p)
    p.add_argument("--out", default="runs/bench/extrapolation", metavar="DIR",
                   help="output directory (default runs/bench/extrapolation)")
    p.set_defaults(handler=_cmd_bench_extrapolation)
    p = bench_sub.add_parser(
        "monotone-eps",
        help="the monotone projection's eps: how far the data's SDF falls below its running maximum",
        description=(
            "Etching only removes material, so each voxel's SDF is non-decreasing in time; the simulator's "
            "stored states are so up to sub-voxel noise. For each channel (mask, Si) print quantiles of the "
            "fall of a voxel below its running maximum over the trajectories (voxels that change at some "
            "step only): the slack eps of the rollouts' monotone projection (NEMSimConfig.monotone_eps). "
            "Example: nemsim bench monotone-eps --data data/small.h5 --splits data/splits --max-cases 40"
        ),
    )
    p.add_argument("--data", required=True, metavar="FILE.h5", help="design data file (nemsim generate)")
    p.add_argument("--setting", default="control-id", help="split setting (default control-id)")
    p.add_argument("--splits", default=None, metavar="DIR", help="split manifests directory")
    p.add_argument("--split", default="train", help="split whose cases are read (default train)")
    p.add_argument("--max-cases", type=int, default=40, help="first N cases of the split (default 40)")
    p.add_argument("--json", dest="json_out", default=None, help="also write the quantiles to this JSON file")
    p.set_defaults(handler=_cmd_bench_monotone_eps)


def _cmd_bench_monotone_eps(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from nemsim.data.hdf5 import open_trajectories
    from nemsim.data.splits import resolve_manifest
    from nemsim.model.monotone import measure_eps

    if args.max_cases < 1:
        raise UserError(f"--max-cases must be >= 1, got {args.max_cases}")
    if not Path(args.data).is_file():
        raise UserError(f"{args.data} does not exist")
    with open_trajectories(args.data) as tf:
        case_ids = np.asarray(tf.case_ids)
        try:
            manifest, _ = resolve_manifest(args.setting, args.data, case_ids, tf.controls_raw,
                                           tf.scene.n_transitions, args.splits)  # fmt: skip
        except ValueError as exc:
            raise UserError(str(exc)) from None
    ids = [int(c) for c in manifest.get(args.split, [])][: args.max_cases]
    if not ids:
        raise UserError(f"split {args.split!r} of setting {args.setting!r} is empty")
    rows = [int(np.flatnonzero(case_ids == c)[0]) for c in ids]
    rep = {"setting": args.setting, "split": args.split, "case_ids": ids, **measure_eps(args.data, rows)}
    print(json.dumps({k: v for k, v in rep.items() if k != "case_ids"}, indent=2))  # noqa: T201
    if args.json_out:
        write_json(args.json_out, rep)
    return 0


def _cmd_bench_extrapolation(args: argparse.Namespace) -> int:
    from bench import extrapolation as ex
    from bench.stress import initial_state

    loaded = load_checkpoint_arg(args.checkpoint, args)
    try:
        distances = tuple(float(v) for v in args.distances.split(",") if v.strip())
    except ValueError:
        raise UserError(f"--distances {args.distances!r}: expected numbers > 1, e.g. 1.5,2") from None
    try:
        cfg = ex.ExtrapolationConfig(distances=distances, corners=args.corners, in_box=args.in_box,
                                     isotropic_m=args.isotropic_m, needle_m=args.needle_m,
                                     seeds=parse_seeds(args.seeds))
    except ValueError as exc:
        raise UserError(str(exc)) from None
    with sim_truth(args, loaded) as truth:
        print_plan(truth, ex.planned_runs(cfg))
        rep = ex.run_extrapolation(loaded.model, truth, initial_state(loaded.scene), cfg)
        rep["simulator_cost"] = sim_cost(truth)
    rep["checkpoint"] = str(args.checkpoint)
    paths = ex.write_outputs(rep, args.out)
    print(ex.format_markdown(rep))  # noqa: T201
    print("wrote " + ", ".join(paths.values()))  # noqa: T201
    return 0


def _cmd_bench_physics(args: argparse.Namespace) -> int:
    from bench import physics
    from bench.stress import initial_state

    loaded = load_checkpoint_arg(args.checkpoint, args)
    try:
        cfg = physics.PhysicsConfig(levels=args.levels, heldout=args.heldout, corners=args.corners,
                                    seeds=parse_seeds(args.seeds))
    except ValueError as exc:
        raise UserError(str(exc)) from None
    heldout = None
    if args.data:
        from nemsim.data.hdf5 import open_trajectories

        if not Path(args.data).is_file():
            raise UserError(f"{args.data} does not exist")
        with open_trajectories(args.data) as tf:
            if tf.scene != loaded.scene:
                raise UserError(f"{args.data} is on scene {tf.scene.name!r}, the checkpoint on "
                                f"{loaded.scene.name!r}")
        try:
            manifest = setting_manifest(args.data, args.setting, args.splits)
            names, raw, sim_meta = physics.heldout_from_data(args.data, manifest, args.split, args.max_cases)
        except KeyError as exc:
            raise UserError(str(exc)) from None
        heldout = (names, raw)
        if sim_meta and "sim_config" not in loaded.raw:
            loaded.raw["sim_config"] = sim_meta  # the data's simulator, for the re-simulation
    with sim_truth(args, loaded) as truth:
        held_raw = heldout[1] if heldout else physics.heldout_recipes(cfg)[1]
        print_plan(truth, physics.planned_runs(cfg, held_raw))
        rep = physics.run_physics(loaded.model, truth, initial_state(loaded.scene), cfg, heldout)
        rep["simulator_cost"] = sim_cost(truth)
    rep["checkpoint"] = str(args.checkpoint)
    paths = physics.write_outputs(rep, args.out)
    print(physics.format_markdown(rep))  # noqa: T201
    print("wrote " + ", ".join(paths.values()))  # noqa: T201
    return 0


def _cmd_bench_responses(args: argparse.Namespace) -> int:
    from bench import responses
    from nemsim.data.hdf5 import open_trajectories

    if not Path(args.data).is_file():
        raise UserError(f"{args.data} does not exist")
    if args.max_cases is not None and args.max_cases < 1:
        raise UserError(f"--max-cases must be >= 1, got {args.max_cases}")
    if args.batch_size < 1:
        raise UserError(f"--batch-size must be >= 1, got {args.batch_size}")
    loaded = load_checkpoint_arg(args.checkpoint, args)
    with open_trajectories(args.data) as tf:
        if tf.scene != loaded.scene:
            raise UserError(f"{args.data} is on scene {tf.scene.name!r}, the checkpoint on "
                            f"{loaded.scene.name!r}")
        if args.setting is None:
            rows = [r for r in range(tf.n_cases) if tf.complete[r]]
            cases = "every complete case"
        else:
            try:
                manifest = setting_manifest(args.data, args.setting, args.splits)
                rows = [tf.row_of(c) for c in manifest[args.split]]
            except KeyError as exc:
                raise UserError(f"split {args.split!r} of {args.setting!r}: {exc}") from None
            cases = f"the {args.split} split of {args.setting}"
        rows = rows[: args.max_cases]
        try:
            rep = responses.run_responses(loaded.model, tf.states, tf.controls_raw, rows, tf.scene,
                                          batch_size=args.batch_size, progress=not args.no_progress,
                                          one_call=args.one_call)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    rep.update(checkpoint=str(args.checkpoint), data=str(args.data), cases=cases)
    paths = responses.write_outputs(rep, args.out)
    print(responses.format_markdown(rep))  # noqa: T201
    print("wrote " + ", ".join(paths.values()))  # noqa: T201
    return 0

"""`nemsim bench noise|pair-noise`: the simulator's Monte Carlo noise floor, and what a shared seed takes out
of a sweep pair's difference."""

from __future__ import annotations

import argparse

from nemsim.cli.common import (
    Subparsers,
    UserError,
    add_scene_option,
    add_sim_overrides,
    sim_config,
    write_json,
)


def register(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "noise",
        help="Monte Carlo noise floor: Avg RMSE between two seeds",
        description=(
            "Simulate the first design cases twice with two different seeds and print the Avg RMSE "
            "(overall and per channel: mask, Si), the Final RMSE and the per-case Avg RMSE between the "
            "two runs, in normalized SDF units: the error floor no surrogate can be expected to beat. "
            "Writes nothing unless --json is given. Example: nemsim bench noise --scene small --cases 3"
        ),
    )
    add_scene_option(p)
    p.add_argument("--cases", type=int, default=5, help="first design cases (default 5)")
    p.add_argument("--seeds", default="1,2", help="the two seeds, comma-separated (default 1,2)")
    add_sim_overrides(p)
    p.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")
    p.set_defaults(handler=_cmd_bench_noise)
    _add_pair_noise(bench_sub)


def _add_pair_noise(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "pair-noise",
        help="Monte Carlo noise of sweep-pair differences: common random numbers vs independent seeds",
        description=(
            "Read one sweep-pair design (`nemsim design --kind pairs`) simulated with two base seeds and "
            "print, per control group and over all pairs, the RMS of the pairs' simulated difference "
            "(the response) beside its Monte Carlo noise when both members share a seed (common random "
            "numbers) and when they do not: the whole field over time (normalized SDF) and the final etch "
            "depth, top and bottom width and mask loss (nm). Writes nothing unless --json is given. "
            "Example: nemsim generate --scene small --controls data/design-pairs.csv --n 28 --seed 4 "
            "--out data/small-pairs-seed4.h5; nemsim bench pair-noise --data data/small-pairs.h5 "
            "--other data/small-pairs-seed4.h5"
        ),
    )
    p.add_argument("--data", required=True, metavar="FILE.h5", help="the pair design under one base seed")
    p.add_argument("--other", required=True, metavar="FILE.h5",
                   help="the same design (or its first cases) under another base seed")
    p.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")
    p.set_defaults(handler=_cmd_bench_pair_noise)


def _cmd_bench_noise(args: argparse.Namespace) -> int:
    from bench.noise import bench_noise
    from nemsim.controls import lhs_design
    from nemsim.rules import compile_rules, load_rules
    from nemsim.scenes import get_scene

    try:
        seeds = tuple(int(s) for s in args.seeds.split(","))
    except ValueError:
        raise UserError(f"--seeds {args.seeds!r}: expected two integers, e.g. 1,2") from None
    if len(seeds) != 2 or seeds[0] == seeds[1]:
        raise UserError(f"--seeds {args.seeds!r}: expected two different integers")
    if args.cases < 1:
        raise UserError(f"--cases must be >= 1, got {args.cases}")
    scene = get_scene(args.scene)
    rules = compile_rules(load_rules())
    rep = bench_noise(scene, rules, lhs_design()[: args.cases], sim_config(args.overrides), seeds)
    title = f"noise floor ({scene.name}, {rep['n_cases']} design cases, seeds {seeds[0]} vs {seeds[1]}):"
    print(title)  # noqa: T201
    print(f"  Avg RMSE   {rep['avg_rmse']:.5f}   (mask {rep['per_channel_avg_rmse'][0]:.5f}, "  # noqa: T201
          f"Si {rep['per_channel_avg_rmse'][1]:.5f})")
    print(f"  Final RMSE {rep['final_rmse']:.5f}")  # noqa: T201
    print("  per case   " + "  ".join(f"{v:.5f}" for v in rep["per_case_avg_rmse"]))  # noqa: T201
    if "symmetrized" in rep:
        sym = rep["symmetrized"]
        print(f"  symmetrized states: Avg RMSE {sym['avg_rmse']:.5f} "  # noqa: T201
              f"({rep['avg_rmse'] / sym['avg_rmse']:.2f}x quieter); one symmetrized run against the other "
              f"raw run {sym['vs_raw_avg_rmse']:.5f}")
    if args.json_out:
        write_json(args.json_out, rep)
    return 0


def _cmd_bench_pair_noise(args: argparse.Namespace) -> int:
    import os

    from bench.noise import PAIR_METRICS, bench_pair_noise

    for path in (args.data, args.other):
        if not os.path.isfile(path):
            raise UserError(f"no such file: {path}")
    try:
        rep = bench_pair_noise(args.data, args.other)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    print(f"sweep-pair noise ({rep['scene']}, {rep['all']['n_pairs']} pairs under two base seeds): "  # noqa: T201
          "response / noise with common random numbers / noise with independent seeds")
    print(f"{'group':<14} {'pairs':>5}  {'field [SDF]':>26}"  # noqa: T201
          + "".join(f"  {m + ' [nm]':>20}" for m in PAIR_METRICS))
    for name, g in [*rep["by_group"].items(), ("all", rep["all"])]:
        cells = [f"{g['field']['response']:.4f} / {g['field']['crn_noise']:.4f} / "
                 f"{g['field']['independent_noise']:.4f}"]
        cells += [f"{g[m]['response']:.1f} / {g[m]['crn_noise']:.1f} / {g[m]['independent_noise']:.1f}"
                  for m in PAIR_METRICS]
        print(f"{name:<14} {g['n_pairs']:>5}  {cells[0]:>26}" + "".join(f"  {c:>20}" for c in cells[1:]))  # noqa: T201
    if args.json_out:
        write_json(args.json_out, rep)
    return 0

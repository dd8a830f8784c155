"""`nemsim bench inverse`: inverse design judged by the simulator on held-out and unreachable targets."""

from __future__ import annotations

import argparse

from nemsim.cli.common import Subparsers


def register(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "inverse",
        help="inverse design judged by the simulator: held-out reachable targets and unreachable ones",
        description=(
            "Targets from simulator runs of held-out random recipes (fresh Latin-hypercube points, seed "
            "--seed) plus deliberately unreachable targets; for each, `nemsim inverse` finds recipes and "
            "the simulator runs the top-1. Success: the simulator's run meets every tolerance (depth +-5 "
            "nm, widths +-3 nm, mask loss +-2 nm); an unreachable target must be reported as such. Writes "
            "inverse.md and inverse.json to --out. Example: nemsim bench inverse --checkpoint "
            "checkpoints/nemsim-small.pt --out benchmarks/small/inverse"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt")
    p.add_argument("--targets", type=int, default=8, help="reachable targets (default 8)")
    p.add_argument("--seed", type=int, default=7, help="seed of the held-out recipes (default 7)")
    p.add_argument("--unreachable", type=int, default=3,
                   help="deliberately unreachable targets to include, 0..3 (default 3)")
    p.add_argument("--methods", default="auto",
                   help="search methods to compare, comma-separated subset of auto, adam, cma (default auto: "
                   "cma when installed, else adam)")
    p.add_argument("--refine", default="both", choices=("off", "on", "both"),
                   help="simulator-corrected design (`nemsim inverse --refine`, its in-loop simulator runs "
                   "with seed 3): off, on (only the refined variant of each method, '<method>+refine') or "
                   "both (an A/B on the same targets; the default)")
    p.add_argument("--rounds", type=int, default=None, metavar="N",
                   help="with --refine: corrected rounds at most (default 2)")
    p.add_argument("--verify-top", type=int, default=None, metavar="R",
                   help="with --refine: round-0 recipes simulated (default 2)")
    p.add_argument("--budget", type=float, default=None, metavar="S",
                   help="with --refine: wall seconds per design (default 60)")
    p.add_argument("--out", default="runs/bench/inverse", metavar="DIR",
                   help="output directory (default runs/bench/inverse)")
    p.set_defaults(handler=_cmd_bench_inverse)


def _cmd_bench_inverse(args: argparse.Namespace) -> int:
    from bench.inverse import format_bench, run_bench, write_bench
    from nemsim.analysis.inverse import refine_config_from_dict

    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    given = {"rounds": args.rounds, "verify_top": args.verify_top, "budget_s": args.budget}
    rcfg = refine_config_from_dict({k: v for k, v in given.items() if v is not None})
    report = run_bench(args.checkpoint, n_targets=args.targets, seed=args.seed, methods=methods,
                       n_unreachable=args.unreachable, refine=args.refine, refine_config=rcfg)
    paths = write_bench(report, args.out)
    print(format_bench(report))  # noqa: T201
    print(f"wrote {paths['md']}, {paths['json']}")  # noqa: T201
    return 0

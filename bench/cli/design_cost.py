"""`nemsim bench design-cost`: simulator calls to reach a target, surrogate-guided design against Bayesian
optimisation and random search on the simulator alone (``bench.design_cost``)."""

from __future__ import annotations

import argparse

from nemsim.cli.common import Subparsers, UserError

DESCRIPTION = """\
How many simulator runs does it take to find a recipe that meets a profile specification? Targets are
the final-step depth, top and bottom width and mask loss of simulator runs of held-out recipes (inside the
control box, near its faces, near its corners) plus deliberately unreachable ones; tolerances depth +-5 nm,
widths +-3 nm, mask loss +-2 nm. Three strategies per target, with the same box and budget:

  design  the surrogate-guided design with simulator refinement (what POST /design runs with verify);
  bo      Bayesian optimisation on the simulator alone (BoTorch, qLogNEI on a SingleTaskGP; needs the
          optional package: pip install 'nemsim[design-bench]');
  random  uniform random recipes.

A recipe that meets every tolerance in a strategy's own run (seed 3) is run again with seed 2; the target is
hit when that independent confirmation meets them too (the design's first recipe, predicted to meet before
any run, goes straight to that run: its round-0 claim). Every simulator call counts, confirmations
included. Each hit's recipe is run once more (seed 4, outside the budget) to measure how often answers
hold. Reported: hit rate, median calls to target, calls per hit, hits met again, unreachable targets
reported, CPU and wall time per target, and a figure of hits against calls.

The run folder (--out) keeps every simulator run (sims.jsonl) and one JSON per target (targets/): stop the
command at any time and run it again to continue; --report-only rewrites results.json, design_cost.md and
design_cost.png from it. Variants of the design can share a folder under different --design-label names
(e.g. --confirm after --design-label design-before).

Cost: the strategies' simulator runs dominate. The default simulator is the full domain: the one that made
the model's data and that POST /design runs (about 6-7 CPU s per `small` run on an Intel Xeon); the
quarter domain (--domain quarter) costs 2-3x less per run and has the same mean profile, but its seed
noise is larger where it matters here: the target's own recipe, rerun with another seed, meets 19 of the
22 targets on the full domain and 13 on the quarter domain (mask loss differs 0.12 against 0.88 nm between
seeds on average). BO costs about as much again per call for its model; a full run of 25 targets and three
strategies takes about two hours of one core.

Examples:
  nemsim bench design-cost --checkpoint checkpoints/nemsim-small.pt --out runs/design_cost
  nemsim bench design-cost --checkpoint checkpoints/nemsim-small.pt --out runs/design_cost --report-only
  nemsim bench design-cost --checkpoint checkpoints/nemsim-small.pt --out runs/dc-quick --interior 3 \\
      --faces 0 --corners 0 --unreachable 1 --strategies design,random --budget 10
"""


def register(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "design-cost",
        help="simulator calls to reach a target: surrogate-guided design vs BO and random search",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt (its simulator configuration is used)")
    p.add_argument(
        "--out",
        default="runs/bench/design_cost",
        metavar="DIR",
        help="run folder: simulator runs, one JSON per target, the reports (default runs/bench/design_cost)",
    )
    g = p.add_argument_group("targets")
    g.add_argument("--interior", type=int, default=12, help="held-out targets inside the box (default 12)")
    g.add_argument("--faces", type=int, default=6, help="held-out targets near a face of the box (default 6)")
    g.add_argument("--corners", type=int, default=4, help="held-out targets near a corner (default 4)")
    g.add_argument("--unreachable", type=int, default=3, help="unreachable targets, 0..3 (default 3)")
    g.add_argument(
        "--seed",
        type=int,
        default=7,
        help="seed of the held-out recipes (interior; faces +1, corners +2; default 7)",
    )
    g.add_argument(
        "--step", type=int, default=None, help="the targets' state index (default: the model's horizon)"
    )
    g = p.add_argument_group("strategies")
    g.add_argument(
        "--strategies",
        default="design,bo,random",
        help="comma-separated subset of design, bo, random (default all three)",
    )
    g.add_argument(
        "--budget",
        type=int,
        default=30,
        help="simulator calls per strategy and target, confirmations included (default 30)",
    )
    g.add_argument(
        "--domain",
        default="full",
        choices=("quarter", "full"),
        help="simulated domain (default full: the model's data and POST /design; quarter: 2-3x less CPU "
        "per run, the same mean profile, noisier between seeds)",
    )
    g.add_argument(
        "--confirm",
        default="inside",
        choices=("inside", "after"),
        help="design: the confirmation simulator inside the design loop (a recipe met in the "
        "loop is confirmed before it is the answer; default), or after it (its verified "
        "answer is confirmed once)",
    )
    g.add_argument(
        "--design-label",
        default="design",
        metavar="NAME",
        help="the design's name in the results (default design)",
    )
    g.add_argument(
        "--refine",
        default="",
        metavar="K=V,...",
        help="design: RefineConfig fields (nemsim.analysis.inverse), e.g. rounds=3,verify_top=1",
    )
    g.add_argument(
        "--search",
        default="",
        metavar="K=V,...",
        help="design: numeric SearchConfig fields of its searches (nemsim.analysis.inverse), e.g. "
        "edge_weight=0,cma_evals=300 (edge_weight 0: no pull toward the inner box)",
    )
    g.add_argument(
        "--bo-init", type=int, default=8, help="BO: Sobol recipes before the first fit (default 8)"
    )
    p.add_argument(
        "--report-only", action="store_true", help="write the reports from the run folder, simulate nothing"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd)


def _fields(text: str, option: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            try:
                out[key.strip()] = int(value)
            except ValueError:
                out[key.strip()] = float(value)
        except ValueError:
            raise UserError(f"{option}: expected KEY=NUMBER items, got {item!r}") from None
    return out


def _cmd(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from bench.design_cost import (
        BOConfig,
        DesignCostConfig,
        format_markdown,
        report,
        run_design_cost,
        write_outputs,
    )

    try:
        if args.report_only:
            rep = report(args.out)
        else:
            cfg = DesignCostConfig(
                interior=args.interior,
                faces=args.faces,
                corners=args.corners,
                unreachable=args.unreachable,
                seed=args.seed,
                budget=args.budget,
                domain=args.domain,
                step=args.step,
                strategies=tuple(s.strip() for s in args.strategies.split(",") if s.strip()),
                confirm=args.confirm,
                design_label=args.design_label,
                refine=_fields(args.refine, "--refine"),
                search=_fields(args.search, "--search"),
                bo=replace(BOConfig(), init=args.bo_init),
            )
            rep = run_design_cost(args.checkpoint, args.out, cfg, progress=not args.no_progress)
    except (ValueError, FileNotFoundError) as exc:
        raise UserError(str(exc)) from None
    paths = write_outputs(rep, args.out)
    print(format_markdown(rep))  # noqa: T201
    print(f"wrote {paths['md']}, {paths['json']}, {paths['png']}")  # noqa: T201
    return 0

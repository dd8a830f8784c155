"""`nemsim bench speed-error|collect|compare`: speed against error, the results table, the comparison."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nemsim.cli.common import EXIT_BUG, Subparsers, UserError, setting_manifest


def register(bench_sub: Subparsers) -> None:
    from bench.speed_error import RUNTIMES as SPEED_ERROR_RUNTIMES
    from bench.speed_error import SIM_DOMAINS

    p = bench_sub.add_parser(
        "speed-error",
        help="speed against error: simulator budgets 1..1/16 (full and quarter domain) and surrogate "
        "variants, incl. equal accuracy",
        description=(
            "On the setting's first N test cases, time one trajectory of the simulator at particle budgets "
            "1, 1/2, 1/4, 1/8, 1/16, on the full domain (the data's) and on the quarter domain (where the "
            "scene allows it; else skipped, noted), and of every checkpoint under every runtime "
            "(backend-precision), score each against an independent full-budget full-domain simulator run "
            "(the file's own trajectory vs that run is the noise floor), and report, against each simulator "
            "domain side by side, the speed-up over its budget-1 time and at equal accuracy (its time "
            "interpolated log-log at the variant's Avg RMSE between its budgets), at batch 1 and per "
            "trajectory at the throughput batch; wall and CPU seconds. Prints the Markdown tables and "
            "writes speed_error.{json,md,png} to --out (default runs/speed_error: committed results under "
            "benchmarks/ are only written when named with --out). "
            "Example: nemsim bench speed-error --data data/small.h5 "
            "--checkpoints checkpoints/nemsim-small.pt --out benchmarks/small"
        ),
    )
    p.add_argument("--data", required=True, metavar="FILE.h5", help="trajectory file (nemsim generate)")
    p.add_argument("--setting", default="control-id", help="split setting (default control-id)")
    p.add_argument("--checkpoints", nargs="+", default=[], metavar="CKPT",
                   help="checkpoint .pt files to time and score (default: none, simulator only)")
    p.add_argument("--splits", default=None, metavar="DIR",
                   help="directory of <setting>.json manifests (default: <data dir>/splits, else computed)")
    p.add_argument("--cases", type=int, default=5, help="first N test cases (default 5)")
    p.add_argument("--budgets", default="1,0.5,0.25,0.125,0.0625",
                   help="simulator particle budgets, fractions in (0, 1] of the full budget "
                   "(default 1,0.5,0.25,0.125,0.0625)")  # fmt: skip
    p.add_argument("--sim-domains", default=",".join(SIM_DOMAINS),
                   help="simulated domains (SimConfig.domain) timed and scored at every budget, from "
                   f"{', '.join(SIM_DOMAINS)} (default: both; full, the data's simulator, always runs; "
                   "quarter is skipped, noted in the report, on a scene it refuses, e.g. tiny)")  # fmt: skip
    p.add_argument("--runtimes", default=",".join(SPEED_ERROR_RUNTIMES),
                   help="surrogate runtimes <backend>-<precision>, from "
                   f"{', '.join(SPEED_ERROR_RUNTIMES)} (default: all; torch-f32, the reference, always runs; "
                   "openvino falls back to torch, noted, when not installed)")  # fmt: skip
    p.add_argument("--batch", type=int, default=16,
                   help="batch of the throughput run, reported per trajectory (default 16; 0: skip)")
    p.add_argument("--seed", type=int, default=1, help="entropy of the reference reruns (default 1)")
    p.add_argument("--steps", type=int, default=None, help="transitions (default: the scene's horizon)")
    p.add_argument("--threads", type=int, default=1,
                   help="torch and OpenVINO threads (default 1: the simulator is single-threaded too)")
    p.add_argument("--out", default="runs/speed-error", metavar="DIR",
                   help="output directory (default runs/speed-error; the committed results: "
                   "--out benchmarks/small)")
    p.set_defaults(handler=_cmd_bench_speed_error)

    p = bench_sub.add_parser(
        "collect",
        help="assemble results.json and the README table from training runs and a speed-error report",
        description=(
            "Read test_metrics.json, summary.json and metrics.csv (and the model name from best.pt) of "
            "each training run directory and, if given, the noise floor and speed figures of `nemsim bench "
            "speed-error`; write results.json (one table per setting, a budget run under its own table "
            "such as 'control-id, 45 min'; per model: test Avg/Final RMSE, CD, params, rollout s, budget, "
            "steps reached, final training loss, training wall and CPU seconds), budget_curve.png next to "
            "it (validation Avg RMSE against the run's wall minutes, one line per run, one panel per "
            "table) and put the Markdown table between its markers in the README (other text is kept). "
            "Two runs of the same table and model are refused. "
            "Example: nemsim bench collect --runs runs/* --speed-error benchmarks/small/speed_error.json"
        ),
    )
    p.add_argument("--runs", nargs="+", required=True, metavar="DIR",
                   help="run dirs with test_metrics.json (from `nemsim train`)")
    p.add_argument("--speed-error", default=None, metavar="FILE.json",
                   help="speed_error.json of `nemsim bench speed-error` (noise floor and speed)")
    p.add_argument("--out", default="runs/results/results.json", metavar="FILE.json",
                   help="output JSON (default runs/results/results.json; the committed table: "
                   "--out benchmarks/small/results.json)")
    p.add_argument("--readme", default=None, metavar="FILE.md",
                   help="Markdown file for the table (default: README.md next to --out)")
    p.set_defaults(handler=_cmd_bench_collect)
    _add_bench_compare(bench_sub)


def _add_bench_compare(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "compare",
        help="run (or show the state of) the committed plan of the equal-wall-clock model comparison",
        description=(
            "Read a comparison plan (every run: model, size, learning rate, setting, minutes; probes that "
            "choose each baseline's size and learning rate by validation score) and run what is left as "
            "`nemsim train ... --resume` subprocesses: partial runs first, then pending ones in plan order, "
            "at most --jobs at a time, one thread each, pinned to one of --cores with taskset; output in "
            "RUN/console.log. Ctrl-C or SIGTERM stops the runs, which keep their last.pt: the same command "
            "resumes them. Every finished run's summary, metrics and config are copied into the plan's "
            "record (committed, so a session on a fresh machine skips what is done). Refuses when the data "
            "file or splits are missing, naming the commands that make them. Example: nemsim bench compare "
            "--plan benchmarks/small/compare-45min.plan.yaml --jobs 2; then nemsim bench collect --runs "
            "benchmarks/small/compare-45min/full/*/* --out benchmarks/small/results.json"
        ),
    )
    p.add_argument("--plan", required=True, metavar="FILE.yaml", help="the comparison plan")
    p.add_argument("--runs-dir", default="runs/compare-45min", metavar="DIR",
                   help="run directories: DIR/probes/NAME, DIR/full/SETTING/MODEL "
                   "(default runs/compare-45min)")
    p.add_argument("--status", action="store_true",
                   help="print every run's state (done, partial, pending, blocked), minutes spent and best "
                   "validation Avg RMSE, then exit")  # fmt: skip
    p.add_argument("--jobs", type=int, default=1, help="runs at once, one core each (default 1)")
    p.add_argument("--cores", default="0,1", metavar="I,J",
                   help="cores the runs are pinned to with taskset, least used first (default 0,1)")
    p.add_argument("--only", default=None, metavar="NAME,...", help="run only these plan entries")
    p.add_argument("--hours", type=float, default=None,
                   help="start only runs that finish (budget left + a margin for the test) within this many "
                   "hours: nothing is left half-done when the session's machine goes away")  # fmt: skip
    p.add_argument("--dry-run", action="store_true", help="print the commands that would run, start nothing")
    p.set_defaults(handler=_cmd_bench_compare)


def _cmd_bench_compare(args: argparse.Namespace) -> int:
    from bench.comparison.plan import format_status, plan_status, read_plan
    from bench.comparison.runner import RunnerConfig, run_plan

    plan = read_plan(args.plan)
    try:
        cores = tuple(int(c) for c in args.cores.split(",") if c.strip())
    except ValueError:
        raise UserError(f"--cores {args.cores!r}: expected core numbers, e.g. 0,1") from None
    only = tuple(n.strip() for n in (args.only or "").split(",") if n.strip())
    if args.status:
        statuses = plan_status(plan, args.runs_dir)
        for name in only:
            plan.entry(name)
        print(format_status([s for s in statuses if not only or s.entry.name in only]))  # noqa: T201
        return 0
    cfg = RunnerConfig(runs_dir=Path(args.runs_dir), jobs=args.jobs, cores=cores, only=only, hours=args.hours,
                       dry_run=args.dry_run)  # fmt: skip
    failed = run_plan(plan, cfg, echo=lambda line: print(line, flush=True))  # noqa: T201
    if failed:
        print(f"{failed} run(s) failed: see their console.log; the same command retries them",  # noqa: T201
              file=sys.stderr)
        return EXIT_BUG
    if not args.dry_run:
        print(f"record: {plan.record} (commit it); results: nemsim bench collect --runs "  # noqa: T201
              f"{plan.record}/full/*/* --out {plan.record.parent}/results.json")
    return 0


def _cmd_bench_speed_error(args: argparse.Namespace) -> int:
    import os

    import torch

    from bench.speed_error import (
        SIM_DOMAINS,
        SpeedErrorConfig,
        format_markdown,
        parse_runtime,
        run_speed_error,
        write_speed_error,
    )

    if not os.path.isfile(args.data):
        raise UserError(f"no such file: {args.data}")
    missing = [c for c in args.checkpoints if not os.path.isfile(c)]
    if missing:
        raise UserError(f"no such checkpoint: {missing[0]}")
    if args.cases < 1 or args.threads < 1 or args.batch < 0:
        raise UserError("--cases and --threads must be >= 1, --batch >= 0")
    try:
        budgets = tuple(float(b) for b in args.budgets.split(",") if b.strip())
    except ValueError:
        raise UserError(f"--budgets {args.budgets!r}: expected numbers, e.g. 1,0.25") from None
    if any(not 0 < b <= 1 for b in budgets):
        raise UserError(f"--budgets {args.budgets!r}: each budget must be in (0, 1]")
    runtimes = tuple(r.strip() for r in args.runtimes.split(",") if r.strip())
    try:
        for r in runtimes:
            parse_runtime(r)
    except ValueError as exc:
        raise UserError(f"--runtimes: {exc}") from None
    domains = tuple(d.strip() for d in args.sim_domains.split(",") if d.strip())
    unknown = [d for d in domains if d not in SIM_DOMAINS]
    if unknown:
        raise UserError(f"--sim-domains: unknown domain {unknown[0]!r}; expected some of "
                        f"{', '.join(SIM_DOMAINS)}")  # fmt: skip
    torch.set_num_threads(args.threads)
    manifest = setting_manifest(args.data, args.setting, args.splits)
    cfg = SpeedErrorConfig(cases=args.cases, budgets=budgets, runtimes=runtimes, threads=args.threads,
                           throughput_batch=args.batch, seed=args.seed, steps=args.steps,
                           sim_domains=domains)  # fmt: skip
    try:
        report = run_speed_error(args.data, args.checkpoints, manifest, cfg)
    except (KeyError, ValueError) as exc:
        raise UserError(str(exc).strip("'\"").splitlines()[0]) from exc
    paths = write_speed_error(report, args.out)
    print(format_markdown(report))  # noqa: T201
    print(f"wrote {paths['json']}, {paths['md']}, {paths['png']}")  # noqa: T201
    return 0


def _cmd_bench_collect(args: argparse.Namespace) -> int:
    from bench.results import collect_results, results_markdown, write_results

    try:
        results = collect_results(args.runs, args.speed_error)
    except (OSError, ValueError) as exc:
        raise UserError(str(exc)) from exc
    paths = write_results(results, args.out, args.readme)
    print(results_markdown(results))  # noqa: T201
    print(f"wrote {', '.join(str(p) for p in paths.values())}")  # noqa: T201
    if "figure" not in paths:
        print("no validation curve with wall times (metrics.csv of runs trained before the loop recorded "  # noqa: T201
              f"them): no {paths['json'].parent / 'budget_curve.png'}")
    return 0

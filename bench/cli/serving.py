"""`nemsim bench service`: latency of the HTTP service in-process, under load against `nemsim serve`, or
the probes of `bench.service_probes` (--probes) against `nemsim serve`."""

from __future__ import annotations

import argparse
import logging

from nemsim.cli.common import Subparsers, UserError, write_json
from service.cli import resolve_checkpoint


def register(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "service",
        help="p50/p95 latency of POST /rollout, uncached and cached",
        description=(
            "Time POST /rollout (metrics only) through the whole app stack with an in-process ASGI "
            "client (no network): uncached requests with distinct random controls, then one request "
            "repeated from the cache; print p50/p95 latency in ms. Writes nothing unless --json is "
            "given. Example: nemsim bench service --checkpoint runs/nemsim/best.pt -n 10"
        ),
    )
    p.add_argument("--checkpoint", default=None,
                   help="checkpoint .pt (default: $NEMSIM_CHECKPOINT or checkpoints/*.pt)")
    p.add_argument("--steps", type=int, default=100, help="transitions per rollout (default 100)")
    p.add_argument("-n", "--requests", type=int, default=20,
                   help="uncached requests, each with distinct controls (default 20)")
    p.add_argument("--cached-requests", type=int, default=200,
                   help="repeats of one cached request (default 200)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random controls (default 0)")
    p.add_argument("--sim-cases", type=int, default=0,
                   help="then time the full-domain simulator on the first N of the uncached recipes, one "
                        "core, and report the service's speed-up over it (its median wall / the uncached "
                        "p50; default 0: no simulator)")
    p.add_argument("--clients", type=int, default=None,
                   help="load mode: start `nemsim serve` on a loopback port and drive it with this many "
                        "concurrent HTTP clients (mixed routes); reports p50/p95/p99 per route, errors, RSS")
    p.add_argument("--seconds", type=float, default=60.0, help="load mode: duration (default 60)")
    p.add_argument("--probes", action="store_true",
                   help="probe mode: start `nemsim serve` (default settings) on a loopback port and run "
                        "quiet, load, burst, slowloris, silent-socket, fuzz, simulator-job, SIGTERM / "
                        "kill -9 and memory probes (a few minutes); prints the targets, writes "
                        "--json / --md")
    p.add_argument("--fuzz-calls", type=int, default=10_000,
                   help="probe mode: fuzzed requests (default 10000)")
    p.add_argument("--md", dest="md_out", default=None, help="probe mode: also write the report as Markdown")
    p.add_argument("--note", default="",
                   help="probe mode: a sentence for the report (e.g. how the machine was shared)")
    p.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")
    p.set_defaults(handler=_cmd_bench_service)


def _bench_service_probes(args: argparse.Namespace) -> int:
    import sys
    from pathlib import Path

    from bench.service_probes import ProbeConfig, run_probes
    from bench.service_report import probes_markdown

    if args.fuzz_calls < 0:
        raise UserError(f"--fuzz-calls must be >= 0, got {args.fuzz_calls}")
    cfg = ProbeConfig(steps=args.steps, fuzz_calls=args.fuzz_calls, seed=args.seed)
    report = run_probes(resolve_checkpoint(args.checkpoint), cfg, note=args.note,
                        progress=lambda msg: print(msg, file=sys.stderr, flush=True))  # noqa: T201
    page = probes_markdown(report)
    print(page)  # noqa: T201
    if args.json_out:
        write_json(args.json_out, report)
    if args.md_out:
        Path(args.md_out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.md_out).write_text(page)
    return 0


def _bench_service_load(args: argparse.Namespace) -> int:
    from bench.serving import bench_load

    if args.clients < 1 or not args.seconds > 0:
        raise UserError(f"--clients must be >= 1 and --seconds > 0, got {args.clients} and {args.seconds}")
    report = bench_load(
        resolve_checkpoint(args.checkpoint), clients=args.clients, seconds=args.seconds, steps=args.steps,
        seed=args.seed,
    )
    lines = [
        f"{report['clients']} clients x {report['wall_s']:.0f} s against nemsim serve "
        f"({report['checkpoint']}, "
        f"{report['steps']} steps):",
        f"  {'route':<26}{'n':>6}{'p50 ms':>10}{'p95 ms':>10}{'p99 ms':>10}  status counts",
    ]
    for name, r in report["routes"].items():
        if r["n"]:
            lines.append(
                f"  {name:<26}{r['n']:>6}{r['p50_ms']:>10.1f}{r['p95_ms']:>10.1f}{r['p99_ms']:>10.1f}"
                f"  {r['status']}"
            )
        else:
            lines.append(f"  {name:<26}{0:>6}{'-':>10}{'-':>10}{'-':>10}  {r['status']}")
    srv = report["server"]
    lines.append(
        f"  errors {report['errors']}; uncached rollouts {report['uncached_rollouts_per_s']:.2f}/s; "
        "server RSS "
        f"{srv['rss_mb_at_start']:.0f} MB at the start, {srv['rss_mb']:.0f} MB at the end (peak "
        f"{srv['peak_rss_mb']:.0f} MB), CPU {srv['cpu_s_during_run']:.1f} s"
    )
    print("\n".join(lines))  # noqa: T201
    if args.json_out:
        write_json(args.json_out, report)
    return 0


def _cmd_bench_service(args: argparse.Namespace) -> int:
    from bench.serving import bench_service

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request would drown the report
    if args.steps < 1 or args.requests < 1 or args.cached_requests < 1:
        raise UserError("--steps, --requests and --cached-requests must be >= 1")
    if not 0 <= args.sim_cases <= args.requests:
        raise UserError(f"--sim-cases must be between 0 and --requests ({args.requests}), "
                        f"got {args.sim_cases}")
    if args.probes:
        return _bench_service_probes(args)
    if args.clients is not None:
        return _bench_service_load(args)
    report = bench_service(
        resolve_checkpoint(args.checkpoint),
        n=args.requests,
        n_cached=args.cached_requests,
        steps=args.steps,
        seed=args.seed,
        sim_cases=args.sim_cases,
    )
    u, c = report["uncached"], report["cached"]
    print(  # noqa: T201
        f"POST /rollout, {report['steps']} steps, metrics only, model {report['model_id']} "
        "(in-process ASGI):\n"
        f"  uncached: p50 {u['p50_ms']:.1f} ms  p95 {u['p95_ms']:.1f} ms  (n={u['n']}); model rollout p50 "
        f"{u['rollout_p50_ms']:.1f} ms; outside it p50 {u['outside_rollout_p50_ms']:.1f} ms, share "
        f"{u['outside_rollout_share_p50']:.2f}; "
        f"CPU {u['cpu_ms_per_request']:.1f} ms per request\n"
        f"  cached:   p50 {c['p50_ms']:.2f} ms  p95 {c['p95_ms']:.2f} ms  (n={c['n']}); "
        f"CPU {c['cpu_ms_per_request']:.2f} ms per request"
    )
    if "simulator" in report:
        sim = report["simulator"]["median"]
        print(f"  full-domain simulator (n={report['simulator']['n_cases']}): median {sim['wall_s']:.2f} s "  # noqa: T201
              f"wall, {sim['cpu_s']:.2f} s CPU; the service {report['simulator_speedup']:.1f}x faster (p50)")
    if args.json_out:
        write_json(args.json_out, report)
    return 0

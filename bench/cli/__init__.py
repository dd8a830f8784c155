"""The bench's commands in the `nemsim` CLI: `nemsim bench ...` and `nemsim stress`.

``register`` is the entry point ``bench`` of the group ``nemsim.cli`` (pyproject.toml): `nemsim` calls it
with its subparsers, and it adds the `bench` group (one module per family of benchmarks) and the top-level
`stress` command. The library never imports this package.
"""

from __future__ import annotations

from bench.cli import design_cost, inverse, noise, physics, results, serving, sim, stress
from nemsim.cli.common import Subparsers


def register(sub: Subparsers) -> None:
    bench = sub.add_parser(
        "bench",
        help="benchmarks",
        description=(
            "Benchmarks of the simulator (sim, noise), the surrogate (rollout, speed-error), the HTTP "
            "service (service), the model comparison (compare) and the results table (collect). Each "
            "prints its figures; most also write them as JSON with --json. "
            "Example: nemsim bench sim --scenes small"
        ),
    )
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH")
    bench_sub.required = True
    sim.register(bench_sub)
    noise.register(bench_sub)
    serving.register(bench_sub)
    stress.register_rollout(bench_sub)
    physics.register(bench_sub)
    results.register(bench_sub)
    inverse.register(bench_sub)
    design_cost.register(bench_sub)
    stress.register(sub)

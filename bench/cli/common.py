"""What the bench commands that judge a surrogate against simulator runs share: options and the SimTruth."""

from __future__ import annotations

import argparse
import dataclasses
import typing

from nemsim.cli.common import UserError, add_monotone_option, add_sim_overrides, sim_config


def add_truth_options(p: argparse.ArgumentParser) -> None:
    """Flags of the commands that judge a surrogate against simulator runs."""
    p.add_argument("--sim-steps", type=int, default=None,
                   help="transitions simulated and compared (default: the scene's horizon, 100)")
    p.add_argument("--seeds", default="1,2", help="the simulator seed pair, comma-separated (default 1,2)")
    p.add_argument("--sim-rng", choices=("counter", "stream"), default="counter",
                   help="the simulator's random numbers: counter (default), common random numbers keyed by "
                   "(seed, macro step, source, particle), so the runs of one seed share their noise and "
                   "the differences between recipes (the sweeps' slopes) carry less of it; stream, one "
                   "stream per kernel call, as the training data were made; both draw the same "
                   "distributions")
    p.add_argument("--workers", type=int, default=1, help="parallel simulations, one core each (default 1)")
    p.add_argument("--cache-dir", default=None, metavar="DIR",
                   help="keep the simulator runs here and reuse them on a rerun (default: a temporary "
                   "directory)")
    add_sim_overrides(p)
    add_monotone_option(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def sim_truth(args: argparse.Namespace, loaded: typing.Any) -> typing.Any:
    """The SimTruth of a checkpoint's scene and rules (the simulator configuration the checkpoint
    records, else the defaults, with --sim-rng, then the --set overrides)."""
    from nemsim.evaluation.truth import SimTruth
    from nemsim.sim import SimConfig

    config = dataclasses.replace(SimConfig.from_record(loaded.raw.get("sim_config")) or SimConfig(),
                                 rng_mode=args.sim_rng)
    if args.overrides:
        over = sim_config(args.overrides)  # validates every KEY=VALUE
        keys = {item.partition("=")[0].strip() for item in args.overrides}
        config = dataclasses.replace(config, **{k: getattr(over, k) for k in keys})
    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    try:
        return SimTruth(loaded.scene, loaded.rules, config, steps=args.sim_steps, workers=args.workers,
                        cache_dir=args.cache_dir, progress=not args.no_progress)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def sim_cost(truth: typing.Any) -> dict:
    """What the simulator runs of a command cost (printed and stored in its report)."""
    cost = {"runs": truth.n_simulated, "wall_s": round(truth.sim_wall_s, 1), "workers": truth.workers,
            "steps": truth.steps, "rng_mode": truth.config.rng_mode}
    per = truth.sim_wall_s / max(truth.n_simulated, 1) * truth.workers
    print(f"simulator: {cost['runs']} runs in {cost['wall_s']:.1f} s wall ({per:.2f} s per run per "  # noqa: T201
          f"worker)", flush=True)
    return cost


def print_plan(truth: typing.Any, runs: list) -> None:
    """The simulator runs a command is about to make (those not shared or cached)."""
    from nemsim.evaluation.truth import particle_work

    todo = truth.missing(runs)
    print(f"planned: {len(todo)} simulator runs of {truth.steps} transitions on {truth.scene.name} "  # noqa: T201
          f"({len(runs) - len(todo)} shared or cached), {truth.workers} worker(s); particle work = "
          f"{particle_work(todo):.0f} design-centre runs", flush=True)

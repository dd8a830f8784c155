"""`nemsim stress` and `nemsim bench rollout`: a surrogate's stability on hard cases and its rollout speed."""

from __future__ import annotations

import argparse
import re
from typing import Any

from bench.cli.common import add_truth_options, print_plan, sim_cost, sim_truth
from nemsim.cli.common import Subparsers, UserError, load_checkpoint_arg, parse_seeds, write_json


def register(sub: Subparsers) -> None:
    """`nemsim stress` (a top-level command)."""
    p = sub.add_parser(
        "stress",
        help="hard-case stability: sub-box corners, angles, long and noisy rollouts",
        description=(
            "Roll a checkpoint out from the scene's initial state past its trained horizon on hard "
            "controls: the design-range centre, the corners of the flux/ion-energy sub-box, extreme "
            "angle exponents, and noisy states and controls. Per case report whether values stay finite and "
            "within --abs-bound (the pass criterion), etch-depth decreases and the growth of the state "
            "norm; print the table. Then check physical invariants against the Monte Carlo simulator, each "
            "with a tolerance from the simulator's seed-to-seed noise: zero flux leaves the state unchanged, "
            "ions off matches the simulator's neutral-only run, depth never decreases, mask loss >= -tol, "
            "depth non-decreasing in each ion flux and in ion energy, and responding where the simulator "
            "responds. Exit code 0 if every case is finite and bounded and no invariant is violated, 1 "
            "otherwise. Writes nothing unless --json / --noise-out is given. "
            "Example: nemsim stress --checkpoint runs/nemsim/best.pt --max-corners 16 --workers 2"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt")
    p.add_argument("--steps", type=int, default=300, help="rollout length (default 300; trained horizon 100)")
    p.add_argument("--max-corners", type=int, default=None,
                   help="evenly spaced subset (>= 2) of the 128 flux/energy corners (default: all)")
    p.add_argument("--noise-cases", type=int, default=4,
                   help="cases with noisy state and controls (default 4)")
    p.add_argument("--batch-size", type=int, default=16, help="cases rolled out together (default 16)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--abs-bound", type=float, default=1.5,
                   help="|value| above this, in normalized SDF units (data lie in [-1, 1]), is a blow-up "
                   "(default 1.5)")
    p.add_argument("--no-invariants", action="store_true",
                   help="only the finite/bounded stability cases (no simulator runs)")
    add_truth_options(p)
    p.add_argument("--pair-bases", type=int, default=2,
                   help="Latin-hypercube base recipes of the monotonicity grid beside the design centre "
                   "(default 2)")
    p.add_argument("--levels", type=int, default=3,
                   help="levels of each monotone axis from design min to max (default 3)")
    p.add_argument("--tol-factor", type=float, default=1.0,
                   help="multiply every seed-to-seed tolerance by this (default 1)")
    p.add_argument("--noise", default=None, metavar="FILE.json",
                   help="read the tolerances from this noise file instead of simulating the seed pairs")
    p.add_argument("--noise-out", default=None, metavar="FILE.json",
                   help="write the measured tolerances to this noise file (for --noise)")
    p.add_argument("--json", dest="json_out", default=None, help="write the full report to this JSON file")
    p.set_defaults(handler=_cmd_stress)


def register_rollout(bench_sub: Subparsers) -> None:
    """`nemsim bench rollout`."""
    p = bench_sub.add_parser(
        "rollout",
        help="100-step rollout wall time: fp32, bf16, channels_last, depth window, OpenVINO; max |Δ| vs fp32",
        description=(
            "Time the same autoregressive rollouts of a model under each precision/memory-format "
            "variant (one warm-up, then --repeats timed runs, interleaved) and print median and min wall "
            "seconds per rollout and the max |Δ| of the trajectory against fp32 (normalized SDF units). "
            "Writes nothing unless --json is given. "
            "Example: nemsim bench rollout --scene small --variants fp32,bf16 --threads 1"
        ),
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="checkpoint .pt (one of --checkpoint and --scene is required)")
    src.add_argument("--scene", help="untrained NEMSim on this scene (seed 0): paper, small or tiny")
    p.add_argument("--steps", type=int, default=100, help="transitions per rollout (default 100)")
    p.add_argument("--batch", type=int, default=1, help="trajectories per rollout (default 1)")
    p.add_argument("--repeats", type=int, default=5, help="timed rollouts per variant (default 5)")
    p.add_argument("--variants", default="fp32,fp32-percall,bf16,channels_last",
                   help="comma-separated subset of fp32, fp32-percall, bf16, channels_last, fp32-window (the "
                   "depth-windowed rollout; NEMSim only), openvino-f32, openvino-bf16, openvino-int8 (NNCF "
                   "post-training quantization; needs pip install nncf) (default: the first four)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--arm", dest="arms", action="append", default=[], metavar="NAME:KEY=VALUE[,KEY=VALUE]",
                   help="also time an untrained model of the same configuration with these overrides through "
                   "OpenVINO f32 (speed only, before training it), e.g. --arm k20:steps_per_call=20 "
                   "--arm lean:decoder_refine=0,decoder_widths=[24,8]; repeatable; NEMSim only")
    p.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")
    p.set_defaults(handler=_cmd_bench_rollout)


def _cmd_stress(args: argparse.Namespace) -> int:
    from bench.stress import StressConfig, format_table, initial_state, run_stress

    if args.steps < 1 or args.batch_size < 1 or args.noise_cases < 0:
        raise UserError("--steps and --batch-size must be >= 1, --noise-cases >= 0")
    if args.max_corners is not None and args.max_corners < 2:
        raise UserError(f"--max-corners must be >= 2, got {args.max_corners}")
    loaded = load_checkpoint_arg(args.checkpoint, args)
    cfg = StressConfig(steps=args.steps, max_corners=args.max_corners, noise_cases=args.noise_cases,
                       batch_size=args.batch_size, seed=args.seed, abs_bound=args.abs_bound)
    x0 = initial_state(loaded.scene)
    report = run_stress(loaded.model, loaded.scene, x0, cfg, progress=not args.no_progress)
    report["checkpoint"] = str(args.checkpoint)
    print(format_table(report))  # noqa: T201
    passed = report["summary"]["passed"]
    if not args.no_invariants:
        from bench.invariants import (
            InvariantConfig,
            format_invariants,
            planned_runs,
            read_noise,
            run_invariants,
            write_noise,
        )

        try:
            inv_cfg = InvariantConfig(seeds=parse_seeds(args.seeds), pair_bases=args.pair_bases,
                                      levels=args.levels, tol_factor=args.tol_factor)
            noise = read_noise(args.noise, loaded.scene.name) if args.noise else None
        except ValueError as exc:
            raise UserError(str(exc)) from None
        with sim_truth(args, loaded) as truth:
            print_plan(truth, planned_runs(inv_cfg, noise))
            inv = run_invariants(loaded.model, truth, x0, inv_cfg, long_steps=cfg.steps,
                                 stress_cases=report["cases"], abs_bound=cfg.abs_bound, noise=noise)
            inv["simulator_cost"] = sim_cost(truth)
        print(format_invariants(inv))  # noqa: T201
        report["invariants"] = inv
        passed = passed and inv["passed"]
        if args.noise_out:
            write_noise(args.noise_out, inv["noise"])
    report["passed"] = passed
    if args.json_out:
        write_json(args.json_out, report)
    return 0 if passed else 1


def _cmd_bench_rollout(args: argparse.Namespace) -> int:
    import torch

    from bench.rollout_speed import VARIANTS, bench_rollout, format_bench
    from bench.stress import initial_state

    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        raise UserError(f"unknown variant(s) {bad}; choose from {list(VARIANTS)}")
    if args.steps < 1 or args.batch < 1 or args.repeats < 1:
        raise UserError("--steps, --batch and --repeats must be >= 1")
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.checkpoint:
        loaded = load_checkpoint_arg(args.checkpoint)
        model, scene = loaded.model, loaded.scene
    else:
        from nemsim.registry import build_model
        from nemsim.rules.compile import compile_rules
        from nemsim.rules.schema import load_rules
        from nemsim.scenes import get_scene

        try:
            scene = get_scene(args.scene)
        except (KeyError, ValueError) as exc:
            raise UserError(str(exc)) from exc
        torch.manual_seed(0)
        model = build_model("nemsim", scene, compile_rules(load_rules()))
    arms = {name: _arm_model(model, overrides) for name, overrides in map(_parse_arm, args.arms)}
    report = bench_rollout(model, initial_state(scene), steps=args.steps, batch=args.batch,
                           repeats=args.repeats, variants=variants, arms=arms)
    report["source"] = args.checkpoint or f"untrained nemsim on {scene.name}"
    print(format_bench(report))  # noqa: T201
    if args.json_out:
        write_json(args.json_out, report)
    return 0


def _parse_arm(text: str) -> tuple[str, dict[str, Any]]:
    """"NAME:KEY=VALUE,KEY=VALUE" -> (NAME, {KEY: VALUE}); values read as YAML (numbers, [lists])."""
    import yaml

    name, sep, body = text.partition(":")
    pairs = [p for p in re.split(r",(?![^\[]*\])", body) if p.strip()] if sep else []
    if not name or not pairs or any("=" not in p for p in pairs):
        raise UserError(f"--arm {text!r}: expected NAME:KEY=VALUE[,KEY=VALUE], e.g. k20:steps_per_call=20")
    out: dict[str, Any] = {}
    for p in pairs:
        key, _, value = p.partition("=")
        v = yaml.safe_load(value)
        out[key.strip()] = tuple(v) if isinstance(v, list) else v
    return name.strip(), out


def _arm_model(model: Any, overrides: dict[str, Any]) -> Any:
    """An untrained NEMSim of ``model``'s configuration with ``overrides`` (seed 0)."""
    import dataclasses

    import torch

    from nemsim.model.surrogate import NEMSim

    if not isinstance(model, NEMSim):
        raise UserError("--arm needs a NEMSim checkpoint or scene")
    try:
        cfg = dataclasses.replace(model.config, **overrides)
    except TypeError as exc:
        raise UserError(f"--arm: {exc}") from exc
    torch.manual_seed(0)
    return NEMSim(model.rules, cfg)

"""`nemsim bench sim|sim-quarter|yields|allocator|bowing`: the simulator's speed and physics (its noise:
``bench.cli.noise``)."""

from __future__ import annotations

import argparse
import typing
from pathlib import Path

from nemsim.cli.common import (
    Subparsers,
    UserError,
    add_scene_option,
    add_sim_overrides,
    config_values,
    floats,
    sim_config,
    write_json,
)


def register(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "sim",
        help="simulator speed: median s/trajectory and primaries/s",
        description=(
            "Time the Monte Carlo simulator on the first design cases of each scene, one core, after a "
            "JIT warm-up, and print per scene the median wall and CPU seconds per full trajectory and "
            "the primary particles traced per second. Writes nothing unless --json is given. "
            "Example: nemsim bench sim --scenes small --cases 3"
        ),
    )
    p.add_argument("--scenes", default="small,paper",
                   help="comma-separated scenes from tiny, small, paper (default small,paper)")
    p.add_argument("--cases", type=int, default=5, help="first design cases to time (default 5)")
    add_sim_overrides(p)
    p.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")
    p.set_defaults(handler=_cmd_bench_sim)
    _add_sim_quarter(bench_sub)
    p = bench_sub.add_parser(
        "yields",
        help="flat-surface etch/sputter yields of the simulator vs published values",
        description=(
            "Fire monoenergetic Cl+, Ar+ and thermal Cl at a fresh flat surface through the simulator's "
            "own surface-event code and print the yield per projectile against ion energy and incidence "
            "angle (Cl+ on Cl-saturated Si, Ar+ on Si, Cl+ on resist, neutral-only Cl), next to the "
            "cited published values (sources in the output). Writes OUT.md and OUT.json; refuses to "
            "overwrite. Example: nemsim bench yields --out runs/yields/yields"
        ),
    )
    p.add_argument("--out", default="runs/yields/yields",
                   help="output path w/o extension: writes OUT.md and OUT.json (default: runs/yields/yields)")
    p.add_argument("--n", type=int, default=2000, help="projectiles per point (neutrals: 50 n; default 2000)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    add_sim_overrides(p)
    p.set_defaults(handler=_cmd_bench_yields)
    _add_bench_allocator(bench_sub)
    p = bench_sub.add_parser(
        "bowing",
        help="bowing map over ion angular exponent x ion energy x flux ratio (final time)",
        description=(
            "Simulate the median recipe with the three ions' angular exponent, mean energy and flux "
            "set on a grid, and write the final-time bowing (profile metric, and the same metric without "
            "Psi's smoothing, and on the rows' equivalent diameters), depth, widths and mask loss per point "
            "to OUT.md and OUT.json (refuses to overwrite). --before also runs each point without the "
            "excess-probability yield; --variant NAME:KEY=VALUE,... also runs it with optional simulator "
            "mechanisms switched on (SimConfig fields: resist_sputter_scale, ion_reflect_spread_deg, "
            "ion_reflect_diffuse, ion_reflect_energy, ion_wing_fraction, ion_wing_m, sputter_calibration). "
            "Example: nemsim bench bowing --m 50 --energies 500 --ion-q 0.8 --seed 0,1 "
            "--variant facet3:resist_sputter_scale=3 --out runs/bowing/facet"
        ),
    )
    add_scene_option(p)
    p.add_argument("--m", default="50,300,3000", help="ion angular exponents, comma-separated")
    p.add_argument("--energies", default="160,330,500", help="ion mean energies [eV], comma-separated")
    p.add_argument("--ion-q", default="0.5,0.8",
                   help="ion-flux unit coordinates in the design range (0 low .. 1 high), comma-separated")
    p.add_argument("--seed", default="0", help="simulator seeds, comma-separated: one run each (default 0)")
    p.add_argument("--before", action="store_true",
                   help="also run every point without the excess-probability yield (variants after/before)")
    p.add_argument("--variant", dest="variants", action="append", default=[], metavar="NAME:KEY=VALUE,...",
                   help="also run every point with these SimConfig fields changed (repeatable), e.g. "
                        "facet3:resist_sputter_scale=3 or wing:ion_wing_fraction=0.1,ion_wing_m=5")
    p.add_argument("--design-rows", default=None, metavar="I,J,...",
                   help="instead of the grid, run these rows of the 500-case design (e.g. 0,100,200)")
    p.add_argument("--out", default="runs/bowing/map", help="output path without extension")
    add_sim_overrides(p)
    p.set_defaults(handler=_cmd_bench_bowing)


def _add_sim_quarter(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "sim-quarter",
        help="simulator: quarter domain between mirror walls against the full domain (profiles, speed)",
        description=(
            "Simulate a fresh Latin hypercube of recipes on the full box and on its quarter between mirror "
            "walls (SimConfig.domain), two seeds each, and report per recipe and profile metric (final etch "
            "depth, top and bottom width, mask loss) the quarter-minus-full difference of the seed means "
            "against the seed-to-seed spread, the field Avg RMSE between the runs, and wall and CPU seconds "
            "per trajectory of each domain (bench/sim_quarter.py). Writes JSON and Markdown where asked. "
            "Example: nemsim bench sim-quarter --recipes 12 --json benchmarks/small/sim_quarter.json "
            "--md benchmarks/small/sim_quarter.md"
        ),
    )
    p.add_argument("--scene", default="small", choices=("small", "paper"),
                   help="grid (even sizes only: the quarter cannot run on tiny; default small)")
    p.add_argument("--recipes", type=int, default=12, help="Latin-hypercube recipes (default 12)")
    p.add_argument("--design-seed", type=int, default=None,
                   help="seed of the recipes' Latin hypercube (default: `bench physics`'s held-out seed)")
    p.add_argument("--seeds", default="1,2", help="the two simulator seeds, comma-separated (default 1,2)")
    add_sim_overrides(p)
    p.add_argument("--json", dest="json_out", default=None, help="write the report to this JSON file")
    p.add_argument("--md", dest="md_out", default=None, help="write the report to this Markdown file")
    p.set_defaults(handler=_cmd_bench_sim_quarter)


def _cmd_bench_sim_quarter(args: argparse.Namespace) -> int:
    import os

    from bench.machine import cpu_name
    from bench.sim_quarter import bench_quarter, to_markdown
    from nemsim.controls import HELDOUT_SEED, lhs_design
    from nemsim.rules import compile_rules, load_rules
    from nemsim.scenes import get_scene

    seeds = tuple(int(v) for v in floats(args.seeds, "--seeds"))
    if len(seeds) != 2 or seeds[0] == seeds[1]:
        raise UserError(f"--seeds {args.seeds!r}: expected two different integers")
    if args.recipes < 2:
        raise UserError(f"--recipes must be >= 2, got {args.recipes}")
    config = sim_config(args.overrides)
    if config.domain != "full":
        raise UserError("--set domain=...: this command runs both domains itself")
    design_seed = HELDOUT_SEED if args.design_seed is None else args.design_seed
    scene = get_scene(args.scene)
    rules = compile_rules(load_rules())
    design = lhs_design(args.recipes, seed=design_seed)
    rep = bench_quarter(scene, rules, design, config, seeds, log=lambda line: print(line, flush=True))  # type: ignore[arg-type]  # noqa: T201
    cmd = (f"nemsim bench sim-quarter --scene {args.scene} --recipes {args.recipes} "
           f"--design-seed {design_seed} --seeds {seeds[0]},{seeds[1]}"
           + "".join(f" --set {o}" for o in args.overrides))
    rep = {"command": cmd, "cpu": cpu_name(), "design_seed": design_seed, **rep}
    text = to_markdown(rep, cmd, rep["cpu"])
    print(text, end="")  # noqa: T201
    if args.md_out:
        os.makedirs(os.path.dirname(args.md_out) or ".", exist_ok=True)
        with open(args.md_out, "w") as fh:
            fh.write(text)
    if args.json_out:
        write_json(args.json_out, rep)
    return 0


def _add_bench_allocator(bench_sub: Subparsers) -> None:
    p = bench_sub.add_parser(
        "allocator",
        help="CPU seconds per training step with glibc's default allocator vs the tuned one",
        description=(
            "Time optimizer steps of a checkpoint's model (random states, bf16 autocast, one thread) in "
            "fresh processes, alternating glibc's default allocator and the settings `nemsim` runs with "
            "(nemsim/cli/allocator.py), and print wall, user and system seconds per step. System time is the "
            "page-fault cost the settings remove; compare CPU seconds when the machine is busy. "
            "Example: nemsim bench allocator --checkpoint checkpoints/nemsim-small.pt"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt whose model is stepped")
    p.add_argument("--batch", type=int, default=24, help="batch size (default 24, the training recipe's)")
    p.add_argument("--steps", type=int, default=4, help="timed steps per process (default 4)")
    p.add_argument("--rounds", type=int, default=2, help="processes per allocator, alternated (default 2)")
    p.add_argument("--json", dest="json_out", default=None, help="also write the rows to this JSON file")
    p.set_defaults(handler=_cmd_bench_allocator)


def _cmd_bench_bowing(args: argparse.Namespace) -> int:
    import os

    from bench.bowing import before_variants, bowing_map, design_points, to_markdown
    from nemsim.rules import compile_rules, load_rules
    from nemsim.scenes import get_scene

    try:
        scene = get_scene(args.scene)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    ms, energies = floats(args.m, "--m"), floats(args.energies, "--energies")
    qs = floats(args.ion_q, "--ion-q")
    if any(not 0.0 <= q <= 1.0 for q in qs):
        raise UserError(f"--ion-q values must be in [0, 1], got {args.ion_q}")
    md_path, json_path = args.out + ".md", args.out + ".json"
    for path in (md_path, json_path):
        if os.path.exists(path):
            raise UserError(f"{path} exists; choose another --out (this command never overwrites)")
    rules, config = compile_rules(load_rules()), sim_config(args.overrides)
    seeds = tuple(int(v) for v in floats(args.seed, "--seed"))
    variants = before_variants(config) if args.before else [("base", config)]
    variants += [_variant(text, config) for text in args.variants]
    if len({name for name, _ in variants}) != len(variants):
        raise UserError(f"--variant names must be unique and not after/before/base, got {args.variants}")
    show = lambda r: print({k: v for k, v in r.items() if k != "diameter_profile"}, flush=True)  # noqa: E731, T201
    if args.design_rows is not None:
        idx = tuple(int(v) for v in floats(args.design_rows, "--design-rows"))
        if any(not 0 <= i < 500 for i in idx):
            raise UserError(f"--design-rows must be in [0, 499], got {args.design_rows}")
        rows = design_points(scene, rules, variants, idx, seeds, log=show)
        what = f"--design-rows {args.design_rows}"
    else:
        rows = bowing_map(scene, rules, variants, ms, energies, qs, seeds, log=show)
        what = f"--m {args.m} --energies {args.energies} --ion-q {args.ion_q}"
    os.makedirs(os.path.dirname(md_path) or ".", exist_ok=True)
    cmd = f"nemsim bench bowing --scene {args.scene} {what} --seed {args.seed}"
    cmd += " --before" if args.before else ""
    cmd += "".join(f" --set {o}" for o in args.overrides) + "".join(f" --variant {v}" for v in args.variants)
    with open(md_path, "w") as fh:
        fh.write(f"Command: {cmd}\n\n" + to_markdown(rows))
    write_json(json_path, {"command": cmd, "rows": rows})
    return 0


def _cmd_bench_allocator(args: argparse.Namespace) -> int:
    from bench.allocator import compare_allocators
    from bench.machine import cpu_name

    for name in ("batch", "steps", "rounds"):
        if getattr(args, name) < 1:
            raise UserError(f"--{name} must be >= 1, got {getattr(args, name)}")
    if not Path(args.checkpoint).is_file():
        raise UserError(f"checkpoint {args.checkpoint} does not exist")
    rows = compare_allocators(args.checkpoint, batch=args.batch, steps=args.steps, rounds=args.rounds)
    print(f"{Path(args.checkpoint).name}, batch {args.batch}, {args.steps} steps per process, "  # noqa: T201
          f"one thread, {cpu_name()}")
    print("| allocator | round | wall s/step | user s/step | sys s/step | CPU s/step |")  # noqa: T201
    print("|---|---:|---:|---:|---:|---:|")  # noqa: T201
    for r in rows:
        cpu = float(r["user_s"]) + float(r["sys_s"])  # type: ignore[arg-type]
        print(f"| {r['allocator']} | {r['round']} | {r['wall_s']:.2f} | {r['user_s']:.2f} | "  # noqa: T201
              f"{r['sys_s']:.2f} | {cpu:.2f} |")
    if args.json_out:
        write_json(args.json_out, {"checkpoint": Path(args.checkpoint).name, "batch": args.batch,
                                    "steps": args.steps, "cpu": cpu_name(), "rows": rows})
    return 0


def _cmd_bench_yields(args: argparse.Namespace) -> int:
    import dataclasses
    import os

    from bench.yields import compare, measure_yields, to_markdown
    from nemsim.rules import compile_rules, load_rules

    if args.n < 2:
        raise UserError(f"--n must be >= 2 projectiles per point, got {args.n}")
    md_path, json_path = args.out + ".md", args.out + ".json"
    for path in (md_path, json_path):
        if os.path.exists(path):
            raise UserError(f"{path} exists; choose another --out (this command never overwrites)")
    config = sim_config(args.overrides)
    points = measure_yields(compile_rules(load_rules()), config, n=args.n, seed=args.seed)
    rows = compare(points)
    text = to_markdown(points, rows)
    print(text, end="")  # noqa: T201
    os.makedirs(os.path.dirname(md_path) or ".", exist_ok=True)
    with open(md_path, "w") as fh:
        sets = "".join(f" --set {o}" for o in args.overrides)
        fh.write(f"Command: nemsim bench yields --n {args.n} --seed {args.seed}{sets}\n\n" + text)
    write_json(json_path, {"points": [dataclasses.asdict(p) for p in points], "comparison": rows})
    return 0


def _variant(text: str, base: typing.Any) -> tuple[str, typing.Any]:
    """``NAME:KEY=VALUE,KEY=VALUE`` -> (NAME, ``base`` with those SimConfig fields replaced)."""
    import dataclasses

    name, sep, body = text.partition(":")
    if not sep or not name.strip() or not body.strip():
        raise UserError(f"--variant {text!r}: expected NAME:KEY=VALUE[,KEY=VALUE...]")
    values = config_values([v for v in body.split(",") if v.strip()], "--variant")
    try:
        return name.strip(), dataclasses.replace(base, **values)
    except (TypeError, ValueError) as exc:
        raise UserError(f"--variant {text!r}: {exc}") from exc


def _cmd_bench_sim(args: argparse.Namespace) -> int:
    from bench.sim_speed import bench_speed
    from nemsim.controls import lhs_design
    from nemsim.rules import compile_rules, load_rules
    from nemsim.scenes import get_scene

    try:
        scenes = [get_scene(name.strip()) for name in args.scenes.split(",") if name.strip()]
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    if args.cases < 1:
        raise UserError(f"--cases must be >= 1, got {args.cases}")
    config = sim_config(args.overrides)
    rules = compile_rules(load_rules())
    design = lhs_design()[: args.cases]
    out = {}
    header = f"{'scene':<7} {'cases':>5} {'median s/traj':>14} {'median cpu s':>13} {'primaries/s':>12}"
    print(header)  # noqa: T201
    for scene in scenes:
        rep = bench_speed(scene, rules, design, config)
        med = rep["median"]
        out[scene.name] = rep
        print(  # noqa: T201
            f"{scene.name:<7} {rep['n_cases']:>5} {med['wall_s']:>14.2f} {med['cpu_s']:>13.2f} "
            f"{med['primaries_per_s']:>12.3g}"
        )
    if args.json_out:
        write_json(args.json_out, out)
    return 0

"""The `nemsim` command line: one argparse parser, one subcommand per job.

Each subcommand parses its flags and calls one library function; heavy imports (torch, numba, h5py)
happen inside the handlers so `nemsim --help` stays instant. Handlers return a process exit code:
0 success, 2 bad input or failed check (with one readable line on stderr).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence

Handler = Callable[[argparse.Namespace], int]


class UserError(Exception):
    """Bad input from the command line: printed as one line, exit code 2."""


def _write_json(path: str, obj: object) -> None:
    """Write a report as indented JSON (the --json option of several commands)."""
    import json

    with open(path, "w") as fh:
        json.dump(obj, fh, indent=2)


def _add_scene_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default="small", choices=("tiny", "small", "paper"),
                   help="grid: paper 2 nm, small 4 nm, tiny 8 nm voxels (tests only); default: small")


def _add_sim_overrides(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a SimConfig constant, e.g. --set capacity=8 (repeatable)")


# ------------------------------------------------------------------------------------------------
# Each _add_* function registers one group of subcommands. Keep handlers thin: parse, call the
# library, print a short report.
# ------------------------------------------------------------------------------------------------

# ==== section: rules (owner: rules) =============================================================


def _add_rules(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "rules",
        help="validate and compile an Event Rules Library (rules/*.yaml)",
        description=(
            "Tools for the Event Rules Library, the YAML file of surface events (projectile, target, "
            "probability and yield models, products) that the simulator and the models read. "
            "`check` validates a file and prints its events; `compile` writes the fixed tensors. "
            "Example: nemsim rules check rules/cl_si.yaml"
        ),
    )
    rsub = p.add_subparsers(dest="rules_command", metavar="ACTION")
    rsub.required = True
    c = rsub.add_parser(
        "check",
        help="validate a rules file and print a summary table",
        description=(
            "Validate a rules YAML file against the schema and the species/controls vocabulary, then "
            "print one row per event (family, projectile, target, probability and yield model, products "
            "or deposition pool) and the library's sha256. Writes nothing. Exit code 0 if the file is "
            "valid, 2 (with the first error on stderr) if not. Example: nemsim rules check"
        ),
    )
    c.add_argument("path", nargs="?", default=None, help="rules YAML (default: the repo's rules/cl_si.yaml)")
    c.set_defaults(handler=_cmd_rules_check)
    k = rsub.add_parser(
        "compile",
        help="compile a rules file to fixed tensors (.npz)",
        description=(
            "Validate a rules YAML file and compile it to the fixed tensors the simulator and the models "
            "use; write them as one NumPy .npz file (arrays R, phi, psi, alpha0, r_mech, w_src, w_sink, "
            "s_dep, plus the event names and the library sha256) and print their shapes. "
            "Example: nemsim rules compile --out rules.npz"
        ),
    )
    k.add_argument("path", nargs="?", default=None, help="rules YAML (default: the repo's rules/cl_si.yaml)")
    k.add_argument("--out", required=True, metavar="FILE.npz", help="output .npz (arrays R, phi, psi, alpha0,"
                   " r_mech, w_src, w_sink, s_dep, plus names and sha256)")  # fmt: skip
    k.set_defaults(handler=_cmd_rules_compile)


def _load_compiled_rules(path: str | None):
    from nemsim.rules import RulesError, compile_rules, load_rules

    try:
        spec = load_rules(path)
    except (RulesError, FileNotFoundError) as exc:
        raise UserError(str(exc).splitlines()[0]) from None
    return spec, compile_rules(spec)


def _cmd_rules_check(args: argparse.Namespace) -> int:
    from nemsim.rules.vocab import FAMILIES

    spec, rt = _load_compiled_rules(args.path)
    head = f"{'#':>3}  {'name':<28} {'family':<9} {'proj':<6} {'target':<7} {'prob':<9} {'yield':<9} relation"
    lines = [head, "-" * len(head)]
    for e, ev in enumerate(spec.events):
        if ev.is_primary:
            rel = ", ".join(f"+{p.species}({p.coeff})" for p in ev.products) or "-"
        else:
            rel = f"<-pool {ev.dep_params['species']} p_stick={ev.dep_params['p_stick']}"  # type: ignore[index]
        lines.append(
            f"{e + 1:>3}  {ev.name:<28} {FAMILIES[rt.group[e]]:<9} {ev.projectile:<6} {ev.target:<7} "
            f"{ev.prob_model or '-':<9} {ev.yield_model or '-':<9} {rel}"
        )
    n_primary = int(rt.is_primary.sum())
    lines.append(
        f"{rt.n_events} events ({n_primary} primary, {rt.n_events - n_primary} product-mediated); "
        f"sha256 {rt.sha256}"
    )
    print("\n".join(lines))  # noqa: T201
    return 0


def _cmd_rules_compile(args: argparse.Namespace) -> int:
    import numpy as np

    _, rt = _load_compiled_rules(args.path)
    arrays = rt.to_npz_dict()
    try:
        np.savez(args.out, **arrays, names=rt.names, sha256=np.array(rt.sha256))
    except OSError as exc:
        raise UserError(f"cannot write {args.out}: {exc.strerror}") from None
    shapes = ", ".join(f"{k} {tuple(v.shape)}" for k, v in arrays.items())
    print(f"wrote {args.out}: {shapes}; sha256 {rt.sha256}")  # noqa: T201
    return 0


# ==== section: controls, design, splits, data (owner: data) ====================================


def _add_data(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "design",
        help="write the Latin-hypercube control design as CSV ([supp_data_generation])",
        description=(
            "Draw the Latin-hypercube design of the 14 process controls and write it as CSV: header = "
            "the 14 control names, one row per case (case id = row index), in physical units (fluxes "
            "in mol m^-2 s^-1, cosine-power exponents as integers, ion-energy means and spreads in eV). "
            "The defaults reproduce the paper's 500-case design. "
            "Example: nemsim design --out data/design.csv"
        ),
    )
    p.add_argument("--n", type=int, default=500, help="number of cases (default 500)")
    p.add_argument("--seed", type=int, default=42, help="LHS seed (default 42, the paper's design)")
    p.add_argument("--out", required=True, metavar="FILE.csv", help="output CSV (overwritten)")
    p.set_defaults(handler=_cmd_design)

    p = sub.add_parser(
        "splits",
        help="write one split manifest JSON per setting ([supp_protocols])",
        description=(
            "Partition the cases of a design CSV into train/val/test for every evaluation setting "
            "(control-id, ood-ar, ood-cl, ood-joint, vis-50, vis-60) and write DIR/<setting>.json, each "
            "with its nested data-efficiency training subsets (10/20/50/100 %); print the table of set "
            "sizes. `nemsim train` and `nemsim evaluate` read these from <data dir>/splits by default. "
            "Example: nemsim splits --design data/design.csv --out data/splits"
        ),
    )
    p.add_argument("--design", required=True, metavar="FILE.csv",
                   help="design CSV (from `nemsim design`); case id = row index")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    p.add_argument("--seed", type=int, default=0, help="partition seed (default 0)")
    p.add_argument("--transitions", type=int, default=100, help="transitions per trajectory (default 100)")
    p.set_defaults(handler=_cmd_splits)

    p = sub.add_parser(
        "data",
        help="trajectory-file tools",
        description="Tools for trajectory HDF5 files written by `nemsim generate`. "
        "Example: nemsim data check data/small.h5",
    )
    dsub = p.add_subparsers(dest="data_command", metavar="ACTION")
    dsub.required = True
    c = dsub.add_parser(
        "check",
        help="integrity checks of a trajectory HDF5 file ([supp_dataset_statistics]); exit 2 on failure",
        description=(
            "Run the integrity checks of a trajectory file: layout and format version, scene, control "
            "and channel names, state shape and dtype, timestamps, completeness and seeds of every case, "
            "unique case ids and controls, control ranges and transforms, and finite, bounded states "
            "(reads every state, so large files take a while). Prints one line per check; writes "
            "nothing. Exit code 0 if all pass, 2 otherwise. Example: nemsim data check data/small.h5"
        ),
    )
    c.add_argument("file", metavar="FILE", help="trajectory .h5 (from `nemsim generate`)")
    c.add_argument("--allow-incomplete", action="store_true",
                   help="unfinished cases are a warning, not a failure (e.g. while generation runs)")
    c.set_defaults(handler=_cmd_data_check)


def _cmd_design(args: argparse.Namespace) -> int:
    from nemsim.controls import lhs_design, write_controls_csv

    if args.n < 1:
        raise UserError(f"--n must be >= 1, got {args.n}")
    raw = lhs_design(args.n, args.seed)
    try:
        write_controls_csv(args.out, raw)
    except OSError as exc:
        raise UserError(f"cannot write {args.out}: {exc.strerror}") from None
    print(f"wrote {args.out}: {args.n} cases x 14 controls (LHS seed {args.seed})")  # noqa: T201
    return 0


def _cmd_splits(args: argparse.Namespace) -> int:
    from nemsim.controls import read_controls_csv
    from nemsim.data.splits import make_manifests, split_table, write_manifests

    try:
        raw = read_controls_csv(args.design)
    except FileNotFoundError:
        raise UserError(f"no such file: {args.design}") from None
    except ValueError as exc:
        raise UserError(str(exc)) from None
    manifests = make_manifests(raw, seed=args.seed, n_transitions=args.transitions)
    try:
        paths = write_manifests(manifests, args.out)
    except OSError as exc:
        raise UserError(f"cannot write to {args.out}: {exc.strerror}") from None
    print(split_table(manifests))  # noqa: T201
    print(f"wrote {len(paths)} manifests to {args.out}")  # noqa: T201
    return 0


def _cmd_data_check(args: argparse.Namespace) -> int:
    import os

    from nemsim.data.hdf5 import check_dataset

    if not os.path.isfile(args.file):
        raise UserError(f"no such file: {args.file}")
    report = check_dataset(args.file, require_complete=not args.allow_incomplete)
    print(report.text)  # noqa: T201
    return 0 if report.ok else 2


# ==== section: simulator: generate, sensitivity, bench sim/noise (owner: sim) ===================


def _add_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "generate",
        help="simulate trajectories of the control design into an HDF5 file (resumable)",
        description=(
            "Run the Monte Carlo simulator on cases 0..N-1 of the 500-case design (or on the rows of "
            "--controls) and write one HDF5 trajectory file. Rerunning the same command resumes: finished "
            "cases are kept, a half-written case is redone. The file is validated on close. "
            "Example: nemsim generate --scene small --n 20 --workers 2 --out data/small.h5"
        ),
    )
    _add_scene_option(p)
    p.add_argument("--n", type=int, default=None,
                   help="first N cases of the design or of --controls (default: all; the design has 500)")
    p.add_argument("--seed", type=int, default=0,
                   help="base simulator seed; per-case seeds derive from it and the case id (default 0)")
    p.add_argument("--out", required=True, metavar="FILE.h5", help="output trajectory file")
    p.add_argument("--controls", metavar="FILE.csv", default=None,
                   help="simulate these control rows instead of the design (header as `nemsim design`)")
    p.add_argument("--cases", metavar="A-B", default=None,
                   help="only rows A..B (0-based, inclusive) of the selected cases, e.g. 0-9 (default: all)")
    p.add_argument("--workers", type=int, default=1, help="parallel simulations, one core each (default 1)")
    p.add_argument("--executor", default="process", choices=("process", "ray"),
                   help="local process pool (default) or a Ray cluster ($RAY_ADDRESS, else a local Ray)")
    _add_sim_overrides(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_generate)

    bench_sub = _bench_subparsers(sub)
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
    _add_sim_overrides(p)
    p.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")
    p.set_defaults(handler=_cmd_bench_sim)
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
    _add_scene_option(p)
    p.add_argument("--cases", type=int, default=5, help="first design cases (default 5)")
    p.add_argument("--seeds", default="1,2", help="the two seeds, comma-separated (default 1,2)")
    _add_sim_overrides(p)
    p.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")
    p.set_defaults(handler=_cmd_bench_noise)


def _sim_config(overrides: list[str]):
    """SimConfig with ``KEY=VALUE`` overrides (values parsed as int, float, or left as text)."""
    import dataclasses

    from nemsim.sim import SimConfig

    fields = {f.name: f for f in dataclasses.fields(SimConfig)}
    kwargs = {}
    for item in overrides:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or key not in fields:
            raise UserError(f"--set {item!r}: expected KEY=VALUE with KEY one of {sorted(fields)}")
        try:
            value = int(text) if text.strip().lstrip("-").isdigit() else float(text)
        except ValueError:
            raise UserError(f"--set {item!r}: value must be a number") from None
        kwargs[key] = value
    try:
        return SimConfig(**kwargs)
    except (TypeError, ValueError) as exc:
        raise UserError(f"--set: {exc}") from exc


def _parse_range(text: str, n: int) -> tuple[int, int]:
    a, sep, b = text.partition("-")
    try:
        lo, hi = int(a), int(b) if sep else int(a)
    except ValueError:
        raise UserError(f"--cases {text!r}: expected A-B (two integers, inclusive)") from None
    if not 0 <= lo <= hi < n:
        raise UserError(f"--cases {text!r}: need 0 <= A <= B < {n} (number of available cases)")
    return lo, hi


def _cmd_generate(args: argparse.Namespace) -> int:
    import os

    import numpy as np

    from nemsim.controls import DESIGN_N, check_admissible, lhs_design, read_controls_csv
    from nemsim.rules import compile_rules, load_rules
    from nemsim.scenes import get_scene
    from nemsim.sim.generate import generate_dataset

    scene = get_scene(args.scene)
    config = _sim_config(args.overrides)
    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    if args.controls:
        if not os.path.isfile(args.controls):
            raise UserError(f"no such file: {args.controls}")
        try:
            controls = read_controls_csv(args.controls)
        except ValueError as exc:
            raise UserError(str(exc)) from exc
        if args.n is not None:
            controls = controls[: args.n]
    else:
        n = DESIGN_N if args.n is None else args.n
        if not 1 <= n <= DESIGN_N:
            raise UserError(f"--n must be in [1, {DESIGN_N}], got {n}")
        controls = lhs_design()[:n]
    case_ids = np.arange(len(controls))
    if args.cases:
        lo, hi = _parse_range(args.cases, len(controls))
        controls, case_ids = controls[lo : hi + 1], case_ids[lo : hi + 1]
    for cid, row in zip(case_ids, controls, strict=True):
        bad = check_admissible(row)
        if bad:
            raise UserError(f"case {cid}: {bad[0]}")
    rules = compile_rules(load_rules())
    try:
        report = generate_dataset(
            args.out, scene, rules, controls, case_ids, seed=args.seed, config=config,
            workers=args.workers, executor=args.executor, progress=not args.no_progress,
        )  # fmt: skip
    except RuntimeError as exc:  # e.g. Ray missing
        raise UserError(str(exc)) from exc
    except ValueError as exc:  # e.g. an incompatible existing file
        raise UserError(str(exc)) from exc
    print(  # noqa: T201
        f"{report['path']}: {report['written']} cases simulated, {report['skipped']} already complete, "
        f"{report['wall_s']:.1f} s"
    )
    return 0


def _cmd_bench_sim(args: argparse.Namespace) -> int:
    from nemsim.controls import lhs_design
    from nemsim.rules import compile_rules, load_rules
    from nemsim.scenes import get_scene
    from nemsim.sim.bench import bench_speed

    try:
        scenes = [get_scene(name.strip()) for name in args.scenes.split(",") if name.strip()]
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    if args.cases < 1:
        raise UserError(f"--cases must be >= 1, got {args.cases}")
    config = _sim_config(args.overrides)
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
        _write_json(args.json_out, out)
    return 0


def _cmd_bench_noise(args: argparse.Namespace) -> int:
    from nemsim.controls import lhs_design
    from nemsim.rules import compile_rules, load_rules
    from nemsim.scenes import get_scene
    from nemsim.sim.bench import bench_noise

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
    rep = bench_noise(scene, rules, lhs_design()[: args.cases], _sim_config(args.overrides), seeds)
    title = f"noise floor ({scene.name}, {rep['n_cases']} design cases, seeds {seeds[0]} vs {seeds[1]}):"
    print(title)  # noqa: T201
    print(f"  Avg RMSE   {rep['avg_rmse']:.5f}   (mask {rep['per_channel_avg_rmse'][0]:.5f}, "  # noqa: T201
          f"Si {rep['per_channel_avg_rmse'][1]:.5f})")
    print(f"  Final RMSE {rep['final_rmse']:.5f}")  # noqa: T201
    print("  per case   " + "  ".join(f"{v:.5f}" for v in rep["per_case_avg_rmse"]))  # noqa: T201
    if args.json_out:
        _write_json(args.json_out, rep)
    return 0


# ==== section: models, train, evaluate, counterfactual (owner: model) ==========================


def _add_model(sub: argparse._SubParsersAction) -> None:
    from pathlib import Path

    from nemsim.train import SETTINGS, add_train_arguments

    p = sub.add_parser(
        "train",
        help="train a model on one-step transitions ([supp_training])",
        description=(
            "Train a registered model with the one-step MSE on the train split of a setting; every "
            "val_every epochs roll out the validation trajectories and keep the best as OUT/best.pt "
            "(early stop after `patience` rounds without improvement). Writes OUT/best.pt, OUT/last.pt "
            "(resume with --resume), OUT/metrics.csv, OUT/train.log and, unless --no-test, "
            "OUT/test_metrics.json. For DDP: torchrun --nproc-per-node N -m nemsim.train ARGS. "
            "Example: nemsim train --model nemsim --data data/small.h5 --setting control-id --out runs/nemsim"
        ),
    )
    add_train_arguments(p)
    p.set_defaults(handler=_cmd_train)

    p = sub.add_parser(
        "evaluate",
        help="100-step autoregressive evaluation of a checkpoint ([supp_protocols])",
        description=(
            "Roll a checkpoint out autoregressively from x_0 over the full horizon on one split of a "
            "setting and print Avg RMSE, Final RMSE (normalized SDF units), the final-step Chamfer "
            "distance (voxels), the parameter count and the rollout time per trajectory. Writes a PNG "
            "figure (see --plot) and optionally the metrics as JSON and the predictions as HDF5. "
            "Example: nemsim evaluate --checkpoint runs/nemsim/best.pt --data data/small.h5 "
            "--setting control-id --json runs/nemsim/eval.json"
        ),
    )
    p.add_argument("--checkpoint", required=True, type=Path,
                   help="checkpoint .pt (e.g. OUT/best.pt of `nemsim train`); its scene must match --data")
    p.add_argument("--data", required=True, type=Path, help="HDF5 dataset file")
    p.add_argument("--setting", required=True, choices=SETTINGS, help="split setting whose cases are scored")
    p.add_argument("--split", default="test", choices=("train", "val", "test"),
                   help="which part of the setting (default test)")
    p.add_argument("--splits", type=Path,
                   help="directory of split manifests <setting>.json (default: <data dir>/splits if present, "
                   "else computed from the data file)")
    p.add_argument("--json", type=Path, help="write the metrics as JSON here")
    p.add_argument("--save-rollouts", type=Path, help="write predictions (N, T+1, 2, D, H, W) to this HDF5")
    p.add_argument("--plot", type=Path,
                   help="PNG path (default: --json with .png, else eval_<setting>.png next to the "
                   "checkpoint)")
    p.add_argument("--steps", type=int, help="rollout length in transitions (default: full horizon, 100)")
    p.add_argument("--batch-size", type=int, default=1,
                   help="trajectories rolled out together (default 1, the paper's per-trajectory timing)")
    p.add_argument("--no-cd", action="store_true", help="skip the Chamfer distance (the slowest metric)")
    p.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:N")
    p.set_defaults(handler=_cmd_evaluate)

    p = sub.add_parser(
        "models",
        help="list registered models with their trainable-parameter counts",
        description=(
            "Build every registered model (NEMSim and the baselines) for a scene with the default rules "
            "library and print its name and trainable-parameter count; the names are what "
            "`nemsim train --model` accepts. Writes nothing unless --json is given. "
            "Example: nemsim models --scene small"
        ),
    )
    p.add_argument("--scene", default="small", help="scene name: paper, small or tiny (default small)")
    p.add_argument("--json", type=Path, help='write {name: {"params": int}} here')
    p.set_defaults(handler=_cmd_models)

    p = sub.add_parser(
        "counterfactual",
        help="Cl+/Cl flux interventions vs mechanism response ([supp_mechanism_alignment])",
        description=(
            "For each case of the split, scale the Cl+ and neutral-Cl fluxes by {0.5, 1, 1.5} (eight "
            "interventions), predict one step from the case's initial state, and relate the change of "
            "each mechanism family's response (ΔM, %) to the change of Si removal (ΔR, %) with "
            "per-group Pearson correlations. Prints the table and writes counterfactual.json, "
            "counterfactual_table.csv and counterfactual.png to --out. Runs on the CPU. "
            "Example: nemsim counterfactual --checkpoint runs/nemsim/best.pt --data data/small.h5"
        ),
    )
    p.add_argument("--checkpoint", required=True, type=Path,
                   help="checkpoint .pt of a NEMSim model (needs its mechanism outputs); scene must match "
                   "--data")
    p.add_argument("--data", required=True, type=Path, help="HDF5 dataset file")
    p.add_argument("--setting", default="control-id", choices=SETTINGS,
                   help="split setting whose cases are used (default control-id)")
    p.add_argument("--split", default="test", choices=("train", "val", "test"),
                   help="which part of the setting (default test)")
    p.add_argument("--splits", type=Path,
                   help="directory of split manifests <setting>.json (default: <data dir>/splits if present, "
                   "else computed from the data file)")
    p.add_argument("--out", type=Path, help="output directory (default: <checkpoint dir>/counterfactual)")
    p.add_argument("--max-cases", type=int, help="analyse only the first N cases of the split (default: all)")
    p.set_defaults(handler=_cmd_counterfactual)


def _cmd_train(args: argparse.Namespace) -> int:
    from nemsim.train import TrainInputError, run

    try:
        return run(args)
    except (TrainInputError, FileNotFoundError) as exc:
        raise UserError(str(exc)) from None


def _load_for_eval(args: argparse.Namespace):
    """(loaded model, trajectory file, manifest) with the data file's scene checked against the checkpoint."""
    from pathlib import Path

    from nemsim.data.hdf5 import open_trajectories
    from nemsim.train import TrainInputError, _load_manifest
    from nemsim.training.checkpoint import CheckpointMismatch, load_checkpoint

    for path in (args.checkpoint, args.data):
        if not Path(path).is_file():
            raise UserError(f"{path} does not exist")
    tf = open_trajectories(args.data)
    try:
        loaded = load_checkpoint(args.checkpoint, scene=tf.scene, device=getattr(args, "device", "cpu"))
        manifest = _load_manifest(Path(args.data), args.setting, args.splits, tf)
    except (CheckpointMismatch, TrainInputError) as exc:
        raise UserError(str(exc)) from None
    if tf.rules_sha256 and tf.rules_sha256 != loaded.raw["rules_sha256"]:
        logging.getLogger("nemsim.cli").warning(
            "data was generated with rules %s..., the checkpoint's library is %s...",
            str(tf.rules_sha256)[:12], loaded.raw["rules_sha256"][:12])
    return loaded, tf, manifest


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from pathlib import Path

    from nemsim.data.dataset import TrajectoryDataset
    from nemsim.evaluation.evaluate import evaluate, plot_evaluation, write_json

    loaded, tf, manifest = _load_for_eval(args)
    cases = TrajectoryDataset(args.data, manifest, args.split)
    if len(cases) == 0:
        raise UserError(f"split {args.split!r} of setting {args.setting!r} is empty")
    result = evaluate(loaded.model, cases, loaded.scene, steps=args.steps, batch_size=args.batch_size,
                      device=args.device, chamfer=not args.no_cd, rollout_path=args.save_rollouts,
                      rollout_attrs={"checkpoint": str(args.checkpoint), "setting": args.setting,
                                     "model": loaded.name})
    cd = "n/a" if result.cd is None else f"{result.cd:.4f}"
    print(f"{loaded.name} on {args.setting}/{args.split} ({result.n_cases} cases, {result.steps} steps)")  # noqa: T201
    print(f"  Avg RMSE   {result.avg_rmse:.5f}")  # noqa: T201
    print(f"  Final RMSE {result.final_rmse:.5f}")  # noqa: T201
    print(f"  CD         {cd} voxels")  # noqa: T201
    print(f"  Params     {result.params} ({result.params / 1e6:.3f} M)")  # noqa: T201
    print(f"  Rollout    {result.rollout_seconds:.2f} s total, "  # noqa: T201
          f"{result.rollout_seconds_per_case:.3f} s per trajectory")
    extra = {"setting": args.setting, "split": args.split, "model": loaded.name,
             "checkpoint": str(args.checkpoint)}
    if args.json:
        write_json(result, args.json, extra)
    plot = args.plot or (args.json.with_suffix(".png") if args.json
                         else Path(args.checkpoint).with_name(f"eval_{args.setting}.png"))
    plot_evaluation(result, loaded.scene, plot, title=f"{loaded.name} {args.setting}")
    print(f"  figure     {plot}")  # noqa: T201
    return 0


def _cmd_models(args: argparse.Namespace) -> int:
    import json

    from nemsim.evaluation.metrics import count_params
    from nemsim.model.registry import available_models, build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.scenes import get_scene

    try:
        scene = get_scene(args.scene)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    rules = compile_rules(load_rules())
    table = {}
    for name in available_models():
        table[name] = {"params": int(count_params(build_model(name, scene, rules)))}
        print(f"{name:<18} {table[name]['params']:>10,d}")  # noqa: T201
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(table, indent=2))
    return 0


def _cmd_counterfactual(args: argparse.Namespace) -> int:
    from pathlib import Path

    import numpy as np

    from nemsim.analysis.counterfactual import analyze, format_table, write_outputs

    args.device = "cpu"
    loaded, tf, manifest = _load_for_eval(args)
    ids = list(manifest[args.split])[: args.max_cases]
    if not ids:
        raise UserError(f"split {args.split!r} of setting {args.setting!r} is empty")
    row_of = {int(c): r for r, c in enumerate(np.asarray(tf.case_ids))}
    raw = np.asarray(tf.controls_raw)
    cases = [(int(c), np.asarray(tf.states[row_of[int(c)], 0]), raw[row_of[int(c)]]) for c in ids]
    result = analyze(loaded.model, cases)
    out = args.out or Path(args.checkpoint).parent / "counterfactual"
    paths = write_outputs(result, out)
    print(format_table(result))  # noqa: T201
    print(f"wrote {paths['json']}, {paths['csv']}, {paths['png']}")  # noqa: T201
    return 0


# ==== section: metrics, sensitivity (owner: metrics) ============================================


def _add_metrics(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sensitivity",
        help="rank the 14 controls by their importance for the final etch profile",
        description=(
            "Importance score I = 0.7|beta| + 0.3|rho| ([supp_protocols], eq:supp_control_importance) of "
            "each control for etch depth, top-opening width, neck width, bottom width and bowing at the "
            "final state, averaged over the quantities; printed as a ranked table with percentages. "
            "Writes nothing unless --json is given. Example: nemsim sensitivity data/small.h5"
        ),
    )
    p.add_argument("file", metavar="FILE", help="trajectory file (.h5) written by `nemsim generate`")
    p.add_argument("--json", metavar="OUT", default=None, help="also write the full result as JSON")
    p.set_defaults(handler=_cmd_sensitivity)


def _cmd_sensitivity(args: argparse.Namespace) -> int:
    import os

    from nemsim.analysis.sensitivity import sensitivity_from_file

    if not os.path.isfile(args.file):
        raise UserError(f"no such file: {args.file}")
    try:
        result = sensitivity_from_file(args.file)
    except (OSError, KeyError, ValueError) as exc:
        raise UserError(f"{args.file}: {exc}") from exc
    print(result.table())  # noqa: T201
    if args.json:
        _write_json(args.json, result.to_dict())
    return 0


# ==== section: serve (owner: service) ==========================================================


def _add_service(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="serve a checkpoint over HTTP (FastAPI; OpenAPI docs at /docs)",
        description=(
            "Serve a trained checkpoint with uvicorn: POST /rollout (controls -> trajectory metrics and "
            "surface meshes), GET /mechanisms, /health, /ready and /model; interactive OpenAPI docs at "
            "/docs. Runs until interrupted; writes nothing. Other settings come from NEMSIM_* "
            "environment variables. Example: nemsim serve --checkpoint runs/nemsim/best.pt --port 8000"
        ),
    )
    p.add_argument(
        "--checkpoint", default=None, help="checkpoint .pt (default: $NEMSIM_CHECKPOINT or checkpoints/*.pt)"
    )
    p.add_argument("--host", default="127.0.0.1",
                   help="bind address (default 127.0.0.1; containers: 0.0.0.0)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")
    p.add_argument("--workers", type=int, default=1,
                   help="worker processes, each with its own model copy (default 1)")
    p.set_defaults(handler=_cmd_serve)
    _add_bench_service(_bench_subparsers(sub))


def _bench_subparsers(sub: argparse._SubParsersAction) -> argparse._SubParsersAction:
    """The `bench` group's sub-subparsers: the one `_add_sim` made, or a new group if it made none."""
    bench = sub.choices.get("bench")
    if bench is None:
        bench = sub.add_parser(
            "bench",
            help="benchmarks",
            description=(
                "Benchmarks of the simulator (sim, noise), the surrogate (rollout, speed-error), the HTTP "
                "service (service) and the results table (collect). Each prints its figures; most also "
                "write them as JSON with --json. Example: nemsim bench sim --scenes small"
            ),
        )
        group = bench.add_subparsers(dest="bench", metavar="BENCH")
        group.required = True
        return group
    for action in bench._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action
    raise RuntimeError("the `bench` parser has no subcommands group")  # a programming error in cli.py


def _add_bench_service(bench_sub: argparse._SubParsersAction) -> None:
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
    p.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")
    p.set_defaults(handler=_cmd_bench_service)


def _resolve_checkpoint(arg: str | None) -> str:
    from pathlib import Path

    from service.config import Settings

    path = Path(arg).expanduser() if arg else Settings().resolved_checkpoint()
    if path is None:
        raise UserError("no checkpoint: pass --checkpoint, set NEMSIM_CHECKPOINT or add checkpoints/*.pt")
    if not path.is_file():
        raise UserError(f"checkpoint {path} does not exist")
    return str(path.resolve())


def _cmd_serve(args: argparse.Namespace) -> int:
    import os

    import uvicorn

    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    # every worker process builds its app from the environment, so the choice travels there
    os.environ["NEMSIM_CHECKPOINT"] = _resolve_checkpoint(args.checkpoint)
    from service.config import get_settings

    get_settings.cache_clear()
    uvicorn.run(
        "service.main:create_app", factory=True, host=args.host, port=args.port, workers=args.workers,
        log_level="info",
    )
    return 0


def _cmd_bench_service(args: argparse.Namespace) -> int:
    from service.bench import bench_service

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request would drown the report
    if args.steps < 1 or args.requests < 1 or args.cached_requests < 1:
        raise UserError("--steps, --requests and --cached-requests must be >= 1")
    report = bench_service(
        _resolve_checkpoint(args.checkpoint),
        n=args.requests,
        n_cached=args.cached_requests,
        steps=args.steps,
        seed=args.seed,
    )
    u, c = report["uncached"], report["cached"]
    print(  # noqa: T201
        f"POST /rollout, {report['steps']} steps, metrics only, model {report['model_id']} "
        "(in-process ASGI):\n"
        f"  uncached: p50 {u['p50_ms']:.1f} ms  p95 {u['p95_ms']:.1f} ms  (n={u['n']})\n"
        f"  cached:   p50 {c['p50_ms']:.2f} ms  p95 {c['p95_ms']:.2f} ms  (n={c['n']})"
    )
    if args.json_out:
        _write_json(args.json_out, report)
    return 0


# ==== section: stress, bench rollout (owner: stress/speed) ======================================


def _add_stress(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "stress",
        help="hard-case stability: sub-box corners, angles, long and noisy rollouts",
        description=(
            "Roll a checkpoint out from the scene's initial state past its trained horizon on hard "
            "controls: the design-range centre, the corners of the flux/ion-energy sub-box, extreme "
            "angle exponents, and noisy states and controls. Per case report whether values stay finite and "
            "within --abs-bound (the pass criterion), etch-depth decreases and the growth of the state "
            "norm; print the table. Exit code 0 if every case is finite and bounded, 1 otherwise. Writes nothing unless --json is given. "
            "Example: nemsim stress --checkpoint runs/nemsim/best.pt --max-corners 16"
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
    p.add_argument("--json", dest="json_out", default=None, help="write the full report to this JSON file")
    p.set_defaults(handler=_cmd_stress)
    p = _bench_subparsers(sub).add_parser(
        "rollout",
        help="100-step rollout wall time: fp32 vs bf16 vs channels_last, with max |Δ| vs fp32",
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
                   help="comma-separated subset of fp32, fp32-percall, bf16, channels_last "
                   "(default: all four)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")
    p.set_defaults(handler=_cmd_bench_rollout)


def _cmd_stress(args: argparse.Namespace) -> int:
    from nemsim.evaluation.stress import StressConfig, format_table, initial_state, run_stress
    from nemsim.training.checkpoint import load_checkpoint

    if args.steps < 1 or args.batch_size < 1 or args.noise_cases < 0:
        raise UserError("--steps and --batch-size must be >= 1, --noise-cases >= 0")
    if args.max_corners is not None and args.max_corners < 2:
        raise UserError(f"--max-corners must be >= 2, got {args.max_corners}")
    try:
        loaded = load_checkpoint(args.checkpoint)
    except (FileNotFoundError, ValueError) as exc:
        raise UserError(str(exc)) from exc
    cfg = StressConfig(steps=args.steps, max_corners=args.max_corners, noise_cases=args.noise_cases,
                       batch_size=args.batch_size, seed=args.seed, abs_bound=args.abs_bound)
    report = run_stress(loaded.model, loaded.scene, initial_state(loaded.scene), cfg)
    report["checkpoint"] = str(args.checkpoint)
    print(format_table(report))  # noqa: T201
    if args.json_out:
        _write_json(args.json_out, report)
    return 0 if report["summary"]["passed"] else 1


def _cmd_bench_rollout(args: argparse.Namespace) -> int:
    import torch

    from nemsim.evaluation.bench import VARIANTS, bench_rollout, format_bench
    from nemsim.evaluation.stress import initial_state

    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        raise UserError(f"unknown variant(s) {bad}; choose from {list(VARIANTS)}")
    if args.steps < 1 or args.batch < 1 or args.repeats < 1:
        raise UserError("--steps, --batch and --repeats must be >= 1")
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.checkpoint:
        from nemsim.training.checkpoint import load_checkpoint

        try:
            loaded = load_checkpoint(args.checkpoint)
        except (FileNotFoundError, ValueError) as exc:
            raise UserError(str(exc)) from exc
        model, scene = loaded.model, loaded.scene
    else:
        from nemsim.model.registry import build_model
        from nemsim.rules.compile import compile_rules
        from nemsim.rules.schema import load_rules
        from nemsim.scenes import get_scene

        try:
            scene = get_scene(args.scene)
        except (KeyError, ValueError) as exc:
            raise UserError(str(exc)) from exc
        torch.manual_seed(0)
        model = build_model("nemsim", scene, compile_rules(load_rules()))
    report = bench_rollout(model, initial_state(scene), steps=args.steps, batch=args.batch,
                           repeats=args.repeats, variants=variants)
    report["source"] = args.checkpoint or f"untrained nemsim on {scene.name}"
    print(format_bench(report))  # noqa: T201
    if args.json_out:
        _write_json(args.json_out, report)
    return 0


# ==== section: bench speed-error, bench collect (owner: speed-error / results) ==================


def _add_speed_error(sub: argparse._SubParsersAction) -> None:
    from nemsim.evaluation.speed_error import RUNTIMES as SPEED_ERROR_RUNTIMES

    bench_sub = _bench_subparsers(sub)
    p = bench_sub.add_parser(
        "speed-error",
        help="speed against error: simulator budgets 1..1/16 and surrogate variants, incl. equal accuracy",
        description=(
            "On the setting's first N test cases, time one trajectory of the simulator at particle budgets "
            "1, 1/2, 1/4, 1/8, 1/16 and of every checkpoint under every runtime (backend-precision), score "
            "each against an independent full-budget simulator run (the file's own trajectory vs that run "
            "is the noise floor), and report the speed-up against the full-budget simulator and at equal "
            "accuracy (the simulator's time interpolated log-log at the variant's Avg RMSE), at batch 1 and "
            "per trajectory at the throughput batch; wall and CPU seconds. Prints the Markdown table and "
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
    p.add_argument("--out", default="runs/speed_error", metavar="DIR",
                   help="output directory (default runs/speed_error)")
    p.set_defaults(handler=_cmd_bench_speed_error)

    p = bench_sub.add_parser(
        "collect",
        help="assemble results.json and the README table from training runs and a speed-error report",
        description=(
            "Read test_metrics.json (and the model name from best.pt) of each training run directory "
            "and, if given, the noise floor and speed figures of `nemsim bench speed-error`; write "
            "results.json (per setting and model: Avg/Final RMSE, CD, params, rollout s) and put the "
            "Markdown table between its markers in the README (other text is kept). Two runs of the "
            "same setting and model are refused. "
            "Example: nemsim bench collect --runs runs/* --speed-error benchmarks/small/speed_error.json"
        ),
    )
    p.add_argument("--runs", nargs="+", required=True, metavar="DIR",
                   help="run dirs with test_metrics.json (from `nemsim train`)")
    p.add_argument("--speed-error", default=None, metavar="FILE.json",
                   help="speed_error.json of `nemsim bench speed-error` (noise floor and speed)")
    p.add_argument("--out", default="benchmarks/small/results.json", metavar="FILE.json",
                   help="output JSON (default benchmarks/small/results.json)")
    p.add_argument("--readme", default=None, metavar="FILE.md",
                   help="Markdown file for the table (default: README.md next to --out)")
    p.set_defaults(handler=_cmd_bench_collect)


def _load_setting_manifest(data: str, setting: str, splits: str | None) -> dict:
    from pathlib import Path

    from nemsim.data import splits as splits_mod

    directory = Path(splits) if splits else Path(data).parent / "splits"
    if splits or (directory / f"{setting}.json").is_file():
        try:
            return splits_mod.load_manifest(directory, setting)
        except (OSError, ValueError) as exc:
            raise UserError(str(exc)) from None
    from nemsim.data.hdf5 import open_trajectories

    with open_trajectories(data) as tf:
        manifests = splits_mod.make_manifests(tf.controls_raw, tf.case_ids,
                                              n_transitions=tf.scene.n_transitions)  # fmt: skip
    if setting not in manifests:
        raise UserError(f"unknown setting {setting!r}; expected one of {sorted(manifests)}")
    return manifests[setting]


def _cmd_bench_speed_error(args: argparse.Namespace) -> int:
    import os

    import torch

    from nemsim.evaluation.speed_error import (
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
    torch.set_num_threads(args.threads)
    manifest = _load_setting_manifest(args.data, args.setting, args.splits)
    cfg = SpeedErrorConfig(cases=args.cases, budgets=budgets, runtimes=runtimes, threads=args.threads,
                           throughput_batch=args.batch, seed=args.seed, steps=args.steps)  # fmt: skip
    try:
        report = run_speed_error(args.data, args.checkpoints, manifest, cfg)
    except (KeyError, ValueError) as exc:
        raise UserError(str(exc).strip("'\"").splitlines()[0]) from exc
    paths = write_speed_error(report, args.out)
    print(format_markdown(report))  # noqa: T201
    print(f"wrote {paths['json']}, {paths['md']}, {paths['png']}")  # noqa: T201
    return 0


def _cmd_bench_collect(args: argparse.Namespace) -> int:
    from nemsim.evaluation.results import collect_results, results_markdown, write_results

    try:
        results = collect_results(args.runs, args.speed_error)
    except (OSError, ValueError) as exc:
        raise UserError(str(exc)) from exc
    out, readme = write_results(results, args.out, args.readme)
    print(results_markdown(results))  # noqa: T201
    print(f"wrote {out} and {readme}")  # noqa: T201
    return 0


# ------------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nemsim",
        description=(
            "NEMSim: Event Rules Library, Monte Carlo etch simulator, neural surrogate and service. "
            "Typical workflow: design -> splits -> generate -> data check -> train -> evaluate -> serve. "
            "Run `nemsim COMMAND --help` for each command. Exit codes: 0 success, 1 `stress` found a failing "
            "case, 2 bad input or failed check (one line on stderr), 130 interrupted."
        ),
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in (_add_rules, _add_data, _add_sim, _add_model, _add_metrics, _add_service, _add_stress,
                _add_speed_error):
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    handler: Handler = args.handler
    try:
        return int(handler(args) or 0)
    except UserError as exc:
        print(f"nemsim {args.command}: {exc}", file=sys.stderr)  # noqa: T201
        return 2
    except KeyboardInterrupt:
        print("interrupted; rerun the same command to resume where supported", file=sys.stderr)  # noqa: T201
        return 130


if __name__ == "__main__":
    sys.exit(main())

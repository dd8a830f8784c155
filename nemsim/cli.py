"""The `nemsim` command line: one argparse parser, one subcommand per job.

Each subcommand parses its flags and calls one library function; heavy imports (torch, numba, h5py)
happen inside the handlers so `nemsim --help` stays instant. Handlers return a process exit code:
0 success, 1 `stress` found a failing case, 2 bad input or failed check.

Errors have one boundary, ``main()``: handlers raise, they do not print. ``_error_report`` sorts what
reaches it into
  * bad input or a damaged file (exit 2, one line on stderr): ``UserError``; ``ValueError``, the library's
    kind for bad input (``TrainInputError``, ``CheckpointMismatch``, ``RulesError`` derive from it);
    ``OSError`` (missing, unwritable, locked or truncated files, h5py's errors); a YAML syntax error (with
    its line); and anything raised while h5py or ``torch.load`` read a file (a damaged ``.h5`` or ``.pt``);
  * a bug (exit 1): one line naming the exception and the hint to rerun with ``--debug``, which re-raises
    so the traceback shows.
Handlers still turn a library error into a ``UserError`` where they can say more (which option, what to do).
Output paths the user names get their missing parent directories created (``_output_path``).
"""

from __future__ import annotations

import argparse
import logging
import sys
import typing
from collections.abc import Callable, Sequence
from pathlib import Path

Handler = Callable[[argparse.Namespace], int]

EXIT_BAD_INPUT = 2  # bad input, a damaged file or a failed check
EXIT_BUG = 1  # an unexpected exception (also `stress`'s failing case)
EXIT_INTERRUPTED = 130
EXIT_BROKEN_PIPE = 141  # as if killed by SIGPIPE, the shell convention


class UserError(Exception):
    """Bad input from the command line: printed as one line, exit code 2."""


def _output_path(path: str | Path) -> Path:
    """A file path the user named for output, with its missing parent directories created."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


def _run_output(command: str, checkpoint: str | Path, suffix: str = "") -> Path:
    """Default output of a command about a checkpoint: runs/<command>/<ckpt dir>-<ckpt name><suffix>.

    Under runs/ (ignored by git), so a default never writes into a committed folder such as checkpoints/;
    committed results are written only through an explicit --out.
    """
    ckpt = Path(checkpoint).resolve()
    return Path("runs") / command / f"{ckpt.parent.name}-{ckpt.stem}{suffix}"


def _write_json(path: str, obj: object) -> None:
    """Write a report as indented JSON (the --json option of several commands)."""
    import json

    with open(_output_path(path), "w") as fh:
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

# ==== section: rules =============================================================


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
            "or deposition pool) and the library's sha256. The family is physical, chemical or coupled; "
            "the YAML spells the coupled family's group label `both`, as the paper's schema does "
            "([eq:supp_group_mapping]). Writes nothing. Exit code 0 if the file is valid, 2 (with the "
            "first error, and for a YAML syntax error its line, on stderr) if not. "
            "Example: nemsim rules check"
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
    from nemsim.rules import compile_rules, load_rules

    spec = load_rules(path)  # RulesError (a ValueError) names the event and field; main() prints it
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
    np.savez(_output_path(args.out), **arrays, names=rt.names, sha256=np.array(rt.sha256))
    shapes = ", ".join(f"{k} {tuple(v.shape)}" for k, v in arrays.items())
    print(f"wrote {args.out}: {shapes}; sha256 {rt.sha256}")  # noqa: T201
    return 0


# ==== section: controls, design, splits, data ====================================


def _add_data(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "design",
        help="write the Latin-hypercube control design as CSV ([supp_data_generation])",
        description=(
            "Draw the Latin-hypercube design of the 14 process controls and write it as CSV: header = "
            "the 14 control names, one row per case (case id = row index), in physical units (fluxes "
            "in mol m^-2 s^-1, cosine-power exponents as integers, ion-energy means and spreads in eV). "
            "The defaults reproduce the paper's 500-case design. --kind corners draws distinct random "
            "corners of the box instead (every control at its minimum or maximum), never the physics "
            "benchmark's held-out corners: extra training cases where the Latin hypercube has none. "
            "--kind pairs writes N/2 sweep pairs: a Latin-hypercube recipe, then the same recipe with one "
            "control group (each flux, the ion energies, the ion angular exponents, the neutral angular "
            "exponent, in turn) moved to another level, and a seed_id column that gives both rows one "
            "simulator seed (common random numbers): training data for `pair_loss_weight`. --kind "
            "lhs-log-angles is the Latin hypercube with the ion angular exponents uniform in log m (the "
            "profile follows the angular spread, ~1/sqrt(m); uniform in m leaves few recipes where it "
            "changes most): extra training data for the angular responses. "
            "Examples: nemsim design --out data/design.csv; "
            "nemsim design --kind corners --n 300 --seed 44 --out data/design-corners.csv; "
            "nemsim design --kind pairs --n 600 --seed 45 --out data/design-pairs.csv; "
            "nemsim design --kind lhs-log-angles --n 1000 --seed 46 --out data/design-log-angles.csv"
        ),
    )
    p.add_argument("--n", type=int, default=500, help="number of cases (default 500)")
    p.add_argument("--seed", type=int, default=42, help="random seed (default 42, the paper's design)")
    p.add_argument("--kind", choices=("lhs", "corners", "pairs", "lhs-log-angles"), default="lhs",
                   help="lhs: Latin hypercube (default, the paper's); corners: random corners of the box; "
                        "pairs: N/2 one-group sweep pairs with shared seeds (N even); lhs-log-angles: "
                        "Latin hypercube with the ion angular exponents uniform in log m")
    p.add_argument("--out", required=True, metavar="FILE.csv",
                   help="output CSV (overwritten; missing folders are created)")
    p.set_defaults(handler=_cmd_design)

    p = sub.add_parser(
        "splits",
        help="write one split manifest JSON per setting ([supp_protocols])",
        description=(
            "Partition the cases of a design CSV, or of a trajectory file, into train/val/test for every "
            "evaluation setting (control-id, ood-ar, ood-cl, ood-joint, vis-50, vis-60) and write "
            "DIR/<setting>.json, each with its nested data-efficiency training subsets (10/20/50/100 %); "
            "print the table of set sizes. `nemsim train` and `nemsim evaluate` read these from "
            "<data dir>/splits by default and refuse manifests whose case ids are not in the data file. "
            "Example: nemsim splits --design data/design.csv --out data/splits"
        ),
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--design", metavar="FILE.csv",
                     help="design CSV (from `nemsim design`); case id = row index")
    src.add_argument("--data", metavar="FILE.h5",
                     help="trajectory file (from `nemsim generate`): its case ids and controls")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    p.add_argument("--seed", type=int, default=0, help="partition seed (default 0)")
    p.add_argument("--transitions", type=int, default=None,
                   help="transitions per trajectory (default: the data file's horizon, else 100)")
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
    st = dsub.add_parser(
        "stats",
        help="profile metrics of the final states over the design (calibration figures), optionally paired",
        description=(
            "Compute the profile metrics (etch depth, top / bottom width, bowing, mask loss, nm) of the last "
            "state of every complete case and print their distribution over the design and the number of "
            "cases bowed by more than one voxel. With --against OTHER.h5 (the same design made with another "
            "simulator configuration) also print the paired change on the common case ids. Reads only the "
            "final states. Example: nemsim data stats data/small.h5 --against data/v1/small.h5 --json "
            "runs/stats.json"
        ),
    )
    st.add_argument("file", metavar="FILE", help="trajectory .h5 (from `nemsim generate`)")
    st.add_argument("--against", metavar="OTHER", default=None, help="a second trajectory file to pair with")
    st.add_argument("--json", dest="json_out", metavar="FILE.json", default=None,
                    help="also write the figures to this JSON file")
    st.set_defaults(handler=_cmd_data_stats)


def _cmd_data_stats(args: argparse.Namespace) -> int:
    import os

    from nemsim.data.stats import final_profiles, paired_change, stats, stats_markdown

    for path in (args.file, args.against):
        if path is not None and not os.path.isfile(path):
            raise UserError(f"no such file: {path}")
    try:
        new = final_profiles(args.file)
        report = stats(new)
        change = paired_change(new, final_profiles(args.against)) if args.against else None
    except (ValueError, KeyError) as exc:
        raise UserError(str(exc)) from None
    print(stats_markdown(report, change))  # noqa: T201
    if args.json_out:
        _write_json(args.json_out, {**report, "sim_config": new.sim_config, "change": change,
                                    "against": args.against})
        print(f"wrote {args.json_out}")  # noqa: T201
    return 0


def _cmd_design(args: argparse.Namespace) -> int:
    from nemsim.controls import corner_design, lhs_design, pair_design, write_controls_csv

    if args.n < 1:
        raise UserError(f"--n must be >= 1, got {args.n}")
    seed_ids = None
    if args.kind == "pairs":
        if args.n % 2:
            raise UserError(f"--kind pairs needs an even --n (two cases per pair), got {args.n}")
        raw, seed_ids = pair_design(args.n // 2, args.seed)
        what = f"{args.n // 2} sweep pairs, seed {args.seed}, each pair one simulator seed (column seed_id)"
    elif args.kind == "corners":
        from bench.physics import PhysicsConfig, box_corners

        held_out = box_corners(PhysicsConfig.corners, PhysicsConfig.heldout_seed)
        try:
            raw = corner_design(args.n, args.seed, exclude=held_out)
        except ValueError as e:
            raise UserError(str(e)) from None
        what = f"random box corners, seed {args.seed}, none of the physics benchmark's {len(held_out)}"
    elif args.kind == "lhs-log-angles":
        raw = lhs_design(args.n, args.seed, log_angles=True)
        what = f"LHS seed {args.seed}, ion exponents log m"
    else:
        raw, what = lhs_design(args.n, args.seed), f"LHS seed {args.seed}"
    write_controls_csv(_output_path(args.out), raw, seed_ids)
    print(f"wrote {args.out}: {args.n} cases x 14 controls ({what})")  # noqa: T201
    return 0


def _cmd_splits(args: argparse.Namespace) -> int:
    from nemsim.data.splits import make_manifests, split_table, write_manifests

    if args.transitions is not None and args.transitions < 1:
        raise UserError(f"--transitions must be >= 1, got {args.transitions}")
    if args.data:
        from nemsim.data.hdf5 import open_trajectories

        with open_trajectories(args.data) as tf:
            raw, case_ids, horizon = tf.controls_raw, tf.case_ids, tf.scene.n_transitions
    else:
        from nemsim.controls import read_controls_csv

        raw, case_ids, horizon = read_controls_csv(args.design), None, 100
    manifests = make_manifests(raw, case_ids, seed=args.seed, n_transitions=args.transitions or horizon)
    paths = write_manifests(manifests, args.out)
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


# ==== section: simulator: generate, sensitivity, bench sim/noise ===================


def _add_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "generate",
        help="simulate trajectories of the control design into an HDF5 file (resumable)",
        description=(
            "Run the Monte Carlo simulator on cases 0..N-1 of the 500-case design (or on the rows of "
            "--controls) and write one HDF5 trajectory file. Rerunning the same command resumes: finished "
            "cases are kept, a half-written case is redone; a larger --n appends the new cases. Ctrl-C or "
            "kill -TERM stops the workers and keeps every finished case. The file is validated on close. "
            "Example: nemsim generate --scene small --n 20 --workers 2 --out data/small.h5. The paper "
            "scene (~20 s per case on one core, hours for 500 cases): nemsim generate --scene paper "
            "--workers 2 --state-dtype float16 --out data/paper.h5 (rerun to resume), then nemsim data "
            "check data/paper.h5"
        ),
    )
    _add_scene_option(p)
    p.add_argument("--n", type=int, default=None,
                   help="first N cases of the design or of --controls (default: all; the design has 500)")
    p.add_argument("--seed", type=int, default=0,
                   help="base simulator seed; per-case seeds derive from it and the case id (default 0)")
    p.add_argument("--out", required=True, metavar="FILE.h5", help="output trajectory file")
    p.add_argument("--controls", metavar="FILE.csv", default=None,
                   help="simulate these control rows instead of the design (header as `nemsim design`; "
                        "a seed_id column gives a row the seed of that case id)")
    p.add_argument("--cases", metavar="A-B", default=None,
                   help="only rows A..B (0-based, inclusive) of the selected cases, e.g. 0-9 (default: all)")
    p.add_argument("--workers", type=int, default=1, help="parallel simulations, one core each (default 1)")
    p.add_argument("--executor", default="process", choices=("process", "ray"),
                   help="local process pool (default) or a Ray cluster ($RAY_ADDRESS, else a local Ray)")
    p.add_argument("--state-dtype", default="float32", choices=("float32", "float16"),
                   help="storage of the states: float16 takes ~0.4x the space and adds at most 2.4e-4 "
                        "of rounding to the normalized SDF (read back as float32; default float32)")
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
    _add_pair_noise(bench_sub)
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
    _add_sim_overrides(p)
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
    _add_scene_option(p)
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
    _add_sim_overrides(p)
    p.set_defaults(handler=_cmd_bench_bowing)


def _add_bench_allocator(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser(
        "allocator",
        help="CPU seconds per training step with glibc's default allocator vs the tuned one",
        description=(
            "Time optimizer steps of a checkpoint's model (random states, bf16 autocast, one thread) in "
            "fresh processes, alternating glibc's default allocator and the settings `nemsim` runs with "
            "(nemsim/allocator.py), and print wall, user and system seconds per step. System time is the "
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


def _floats(text: str, option: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise UserError(f"{option} {text!r}: expected comma-separated numbers") from None
    if not values:
        raise UserError(f"{option}: no values given")
    return values


def _cmd_bench_bowing(args: argparse.Namespace) -> int:
    import os

    from nemsim.rules import compile_rules, load_rules
    from nemsim.scenes import get_scene
    from bench.bowing import before_variants, bowing_map, design_points, to_markdown

    try:
        scene = get_scene(args.scene)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    ms, energies = _floats(args.m, "--m"), _floats(args.energies, "--energies")
    qs = _floats(args.ion_q, "--ion-q")
    if any(not 0.0 <= q <= 1.0 for q in qs):
        raise UserError(f"--ion-q values must be in [0, 1], got {args.ion_q}")
    md_path, json_path = args.out + ".md", args.out + ".json"
    for path in (md_path, json_path):
        if os.path.exists(path):
            raise UserError(f"{path} exists; choose another --out (this command never overwrites)")
    rules, config = compile_rules(load_rules()), _sim_config(args.overrides)
    seeds = tuple(int(v) for v in _floats(args.seed, "--seed"))
    variants = before_variants(config) if args.before else [("base", config)]
    variants += [_variant(text, config) for text in args.variants]
    if len({name for name, _ in variants}) != len(variants):
        raise UserError(f"--variant names must be unique and not after/before/base, got {args.variants}")
    show = lambda r: print({k: v for k, v in r.items() if k != "diameter_profile"}, flush=True)  # noqa: E731, T201
    if args.design_rows is not None:
        idx = tuple(int(v) for v in _floats(args.design_rows, "--design-rows"))
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
    _write_json(json_path, {"command": cmd, "rows": rows})
    return 0


def _cmd_bench_allocator(args: argparse.Namespace) -> int:
    from nemsim.allocator import bench
    from bench.machine import cpu_name

    for name in ("batch", "steps", "rounds"):
        if getattr(args, name) < 1:
            raise UserError(f"--{name} must be >= 1, got {getattr(args, name)}")
    if not Path(args.checkpoint).is_file():
        raise UserError(f"checkpoint {args.checkpoint} does not exist")
    rows = bench(args.checkpoint, batch=args.batch, steps=args.steps, rounds=args.rounds)
    print(f"{Path(args.checkpoint).name}, batch {args.batch}, {args.steps} steps per process, "  # noqa: T201
          f"one thread, {cpu_name()}")
    print("| allocator | round | wall s/step | user s/step | sys s/step | CPU s/step |")  # noqa: T201
    print("|---|---:|---:|---:|---:|---:|")  # noqa: T201
    for r in rows:
        cpu = float(r["user_s"]) + float(r["sys_s"])  # type: ignore[arg-type]
        print(f"| {r['allocator']} | {r['round']} | {r['wall_s']:.2f} | {r['user_s']:.2f} | "  # noqa: T201
              f"{r['sys_s']:.2f} | {cpu:.2f} |")
    if args.json_out:
        _write_json(args.json_out, {"checkpoint": Path(args.checkpoint).name, "batch": args.batch,
                                    "steps": args.steps, "cpu": cpu_name(), "rows": rows})
    return 0


def _cmd_bench_yields(args: argparse.Namespace) -> int:
    import dataclasses
    import os

    from nemsim.rules import compile_rules, load_rules
    from bench.yields import compare, measure_yields, to_markdown

    if args.n < 2:
        raise UserError(f"--n must be >= 2 projectiles per point, got {args.n}")
    md_path, json_path = args.out + ".md", args.out + ".json"
    for path in (md_path, json_path):
        if os.path.exists(path):
            raise UserError(f"{path} exists; choose another --out (this command never overwrites)")
    config = _sim_config(args.overrides)
    points = measure_yields(compile_rules(load_rules()), config, n=args.n, seed=args.seed)
    rows = compare(points)
    text = to_markdown(points, rows)
    print(text, end="")  # noqa: T201
    os.makedirs(os.path.dirname(md_path) or ".", exist_ok=True)
    with open(md_path, "w") as fh:
        sets = "".join(f" --set {o}" for o in args.overrides)
        fh.write(f"Command: nemsim bench yields --n {args.n} --seed {args.seed}{sets}\n\n" + text)
    _write_json(json_path, {"points": [dataclasses.asdict(p) for p in points], "comparison": rows})
    return 0


def _sim_config(overrides: list[str]):
    """SimConfig with ``KEY=VALUE`` overrides (values parsed as int or float; text for text fields such as
    ``sputter_calibration``)."""
    from nemsim.sim import SimConfig

    try:
        return SimConfig(**_config_values(overrides, "--set"))  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise UserError(f"--set: {exc}") from exc


def _config_values(items: list[str], option: str) -> dict[str, object]:
    """{field: value} of ``KEY=VALUE`` items naming SimConfig fields (numbers; text for text fields)."""
    import dataclasses

    from nemsim.sim import SimConfig

    fields = {f.name: f for f in dataclasses.fields(SimConfig)}
    kwargs: dict[str, object] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or key not in fields:
            raise UserError(f"{option} {item!r}: expected KEY=VALUE with KEY one of {sorted(fields)}")
        if fields[key].type in ("str", str):
            kwargs[key] = text.strip()
            continue
        try:
            kwargs[key] = int(text) if text.strip().lstrip("-").isdigit() else float(text)
        except ValueError:
            raise UserError(f"{option} {item!r}: value must be a number") from None
    return kwargs


def _variant(text: str, base):
    """``NAME:KEY=VALUE,KEY=VALUE`` -> (NAME, ``base`` with those SimConfig fields replaced)."""
    import dataclasses

    name, sep, body = text.partition(":")
    if not sep or not name.strip() or not body.strip():
        raise UserError(f"--variant {text!r}: expected NAME:KEY=VALUE[,KEY=VALUE...]")
    values = _config_values([v for v in body.split(",") if v.strip()], "--variant")
    try:
        return name.strip(), dataclasses.replace(base, **values)
    except (TypeError, ValueError) as exc:
        raise UserError(f"--variant {text!r}: {exc}") from exc


def _parse_range(text: str, n: int) -> tuple[int, int]:
    a, sep, b = text.partition("-")
    try:
        lo, hi = int(a), int(b) if sep else int(a)
    except ValueError:
        raise UserError(f"--cases {text!r}: expected A-B (two integers, inclusive)") from None
    if not 0 <= lo <= hi < n:
        raise UserError(f"--cases {text!r}: need 0 <= A <= B < {n} (number of available cases)")
    return lo, hi


def _add_pair_noise(bench_sub: argparse._SubParsersAction) -> None:
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


def _cmd_generate(args: argparse.Namespace) -> int:
    import os

    import numpy as np

    from nemsim.controls import DESIGN_N, check_admissible, lhs_design, read_controls_csv, read_seed_ids
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
            controls, seed_ids = read_controls_csv(args.controls), read_seed_ids(args.controls)
        except ValueError as exc:
            raise UserError(str(exc)) from exc
        if args.n is not None:
            controls = controls[: args.n]
    else:
        n = DESIGN_N if args.n is None else args.n
        if not 1 <= n <= DESIGN_N:
            raise UserError(f"--n must be in [1, {DESIGN_N}], got {n}")
        controls, seed_ids = lhs_design()[:n], None
    case_ids = np.arange(len(controls))
    seeds_from = case_ids if seed_ids is None else seed_ids[: len(controls)]
    if args.cases:
        lo, hi = _parse_range(args.cases, len(controls))
        controls, case_ids, seeds_from = controls[lo : hi + 1], case_ids[lo : hi + 1], seeds_from[lo : hi + 1]
    for cid, row in zip(case_ids, controls, strict=True):
        bad = check_admissible(row)
        if bad:
            raise UserError(f"case {cid}: {bad[0]}")
    rules = compile_rules(load_rules())
    try:
        report = generate_dataset(
            args.out, scene, rules, controls, case_ids, seed=args.seed, config=config,  # type: ignore[arg-type]
            workers=args.workers, executor=args.executor, progress=not args.no_progress,
            state_dtype=args.state_dtype, seed_ids=[int(s) for s in seeds_from],
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
    from bench.sim_speed import bench_speed

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
    from bench.noise import bench_noise
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
        _write_json(args.json_out, rep)
    return 0


# ==== section: models, train, evaluate, counterfactual ==========================


def _add_model(sub: argparse._SubParsersAction) -> None:
    from pathlib import Path

    from bench.speed_error import RUNTIMES as SPEED_ERROR_RUNTIMES
    from nemsim.train import SETTINGS, add_train_arguments

    p = sub.add_parser(
        "train",
        help="train a model on one-step transitions ([supp_training])",
        description=(
            "Train a registered model with the one-step MSE on the train split of a setting; every "
            "val_every epochs roll out the validation trajectories and keep the best as OUT/best.pt "
            "(early stop after `patience` rounds without improvement). Writes OUT/best.pt, OUT/last.pt "
            "(resume with --resume), OUT/metrics.csv (per epoch, with the run's cumulative wall and CPU "
            "seconds), OUT/summary.json, OUT/train.log and, unless --no-test, OUT/test_metrics.json. "
            "Budgets: --epochs, --max-steps, --max-minutes (wall clock, kept across --resume). "
            "For DDP: torchrun --nproc-per-node N -m nemsim.train ARGS. "
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
                   help="PNG path (default: --json with .png, else "
                   "runs/evaluate/<checkpoint dir>-<checkpoint name>_<setting>.png)")
    p.add_argument("--steps", type=int, help="rollout length in transitions (default: full horizon, 100)")
    p.add_argument("--batch-size", type=int, default=1,
                   help="trajectories rolled out together (default 1, the paper's per-trajectory timing)")
    p.add_argument("--no-cd", action="store_true", help="skip the Chamfer distance (the slowest metric)")
    p.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:N")
    p.add_argument("--runtime", default="torch-f32", choices=SPEED_ERROR_RUNTIMES,
                   help="what runs the rollouts: torch-f32 (PyTorch, the reference; default), torch-bf16 "
                   "(CPU autocast), openvino-f32 or openvino-bf16 (the exported step graph the service runs; "
                   "falls back to torch, named in the output, when OpenVINO is missing); CPU only")
    p.add_argument("--threads", type=int, default=1,
                   help="torch and OpenVINO threads (default 1, as the benchmarks and the service)")
    _add_monotone_option(p)
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
            "counterfactual_table.csv and counterfactual.png to --out (default under runs/). "
            "Runs on the CPU. "
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
    p.add_argument("--out", type=Path,
                   help="output directory (default: runs/counterfactual/<checkpoint dir>-<checkpoint name>)")
    p.add_argument("--max-cases", type=int, help="analyse only the first N cases of the split (default: all)")
    p.set_defaults(handler=_cmd_counterfactual)


def _cmd_train(args: argparse.Namespace) -> int:
    from nemsim.train import run

    return run(args)


def _load_for_eval(args: argparse.Namespace):
    """(loaded model, trajectory file, manifest) with the data file's scene checked against the checkpoint."""
    from pathlib import Path

    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.data.hdf5 import open_trajectories
    from nemsim.data.splits import resolve_manifest

    for path in (args.checkpoint, args.data):
        if not Path(path).is_file():
            raise UserError(f"{path} does not exist")
    tf = open_trajectories(args.data)
    loaded = load_checkpoint(args.checkpoint, scene=tf.scene, device=getattr(args, "device", "cpu"))
    manifest, _ = resolve_manifest(args.setting, args.data, tf.case_ids, tf.controls_raw,
                                   tf.scene.n_transitions, args.splits)  # fmt: skip
    tf.warn_if_other_rules(loaded.raw["rules_sha256"], "the checkpoint's library")
    return loaded, tf, manifest


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import torch

    from nemsim.data.dataset import TrajectoryDataset
    from nemsim.evaluation.evaluate import evaluate, plot_evaluation, write_json
    from nemsim.inference.runtime import compile_model
    from bench.speed_error import parse_runtime

    if args.batch_size < 1:
        raise UserError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    if args.runtime != "torch-f32" and args.device != "cpu":
        raise UserError(f"--runtime {args.runtime} runs on the CPU only; drop --device {args.device}")
    loaded, tf, manifest = _load_for_eval(args)
    _apply_monotone(args, loaded.model)
    horizon = loaded.scene.n_transitions
    if args.steps is not None and not 1 <= args.steps <= horizon:
        raise UserError(f"--steps must be in [1, {horizon}] (the scene's horizon), got {args.steps}")
    cases = TrajectoryDataset(args.data, manifest, args.split)
    if len(cases) == 0:
        raise UserError(f"split {args.split!r} of setting {args.setting!r} is empty")
    torch.set_num_threads(args.threads)
    predictor = None
    if args.runtime != "torch-f32":
        predictor = compile_model(loaded.model, *parse_runtime(args.runtime), threads=args.threads)  # type: ignore[arg-type]
    result = evaluate(loaded.model, cases, loaded.scene, steps=args.steps, batch_size=args.batch_size,  # type: ignore[arg-type]
                      device=args.device, chamfer=not args.no_cd, rollout_path=args.save_rollouts,
                      rollout_attrs={"checkpoint": str(args.checkpoint), "setting": args.setting,
                                     "model": loaded.name, "runtime": args.runtime},
                      predictor=predictor)
    cd = "n/a" if result.cd is None else f"{result.cd:.4f}"
    print(f"{loaded.name} on {args.setting}/{args.split} ({result.n_cases} cases, {result.steps} steps, "  # noqa: T201
          f"{result.runtime})")
    if predictor is not None and predictor.fallback_reason:
        print(f"  note: {args.runtime} was asked for; {predictor.fallback_reason}")  # noqa: T201
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
                         else _run_output("evaluate", args.checkpoint, f"_{args.setting}.png"))
    plot_evaluation(result, loaded.scene, plot, title=f"{loaded.name} {args.setting}")
    print(f"  figure     {plot}")  # noqa: T201
    return 0


def _cmd_models(args: argparse.Namespace) -> int:
    import json

    from nemsim.evaluation.metrics import count_params
    from nemsim.registry import available_models, build_model
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
    import numpy as np

    from nemsim.analysis.counterfactual import analyze, format_table, write_outputs

    if args.max_cases is not None and args.max_cases < 1:
        raise UserError(f"--max-cases must be >= 1, got {args.max_cases}")
    args.device = "cpu"
    loaded, tf, manifest = _load_for_eval(args)
    ids = list(manifest[args.split])[: args.max_cases]
    if not ids:
        raise UserError(f"split {args.split!r} of setting {args.setting!r} is empty")
    row_of = {int(c): r for r, c in enumerate(np.asarray(tf.case_ids))}
    raw = np.asarray(tf.controls_raw)
    cases = [(int(c), np.asarray(tf.states[row_of[int(c)], 0]), raw[row_of[int(c)]]) for c in ids]
    result = analyze(loaded.model, cases)
    out = args.out or _run_output("counterfactual", args.checkpoint)
    paths = write_outputs(result, out)
    print(format_table(result))  # noqa: T201
    print(f"wrote {paths['json']}, {paths['csv']}, {paths['png']}")  # noqa: T201
    return 0


# ==== section: metrics, sensitivity ============================================


def _add_metrics(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sensitivity",
        help="rank the 14 controls by their importance for the final etch profile",
        description=(
            "Importance score I = 0.7|beta| + 0.3|rho| ([supp_protocols], eq:supp_control_importance) of "
            "each control for etch depth, top-opening width, neck width, bottom width and bowing at the "
            "final state, averaged over the quantities; printed as a ranked table with percentages. "
            "It reads only the controls and the final states, so damage elsewhere in the file goes "
            "unnoticed here: `nemsim data check` reads every state. "
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


# ==== section: serve ==========================================================


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
    p.add_argument("--host", default=None,
                   help="bind address (default $NEMSIM_HOST or 127.0.0.1; containers: 0.0.0.0)")
    p.add_argument("--port", type=int, default=None,
                   help="TCP port (default $NEMSIM_PORT or 8000; e.g. NEMSIM_PORT=8080 make serve)")
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
                "service (service), the model comparison (compare) and the results table (collect). Each "
                "prints its figures; most also write them as JSON with --json. "
                "Example: nemsim bench sim --scenes small"
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
    p.add_argument("--clients", type=int, default=None,
                   help="load mode: start `nemsim serve` on a loopback port and drive it with this many "
                        "concurrent HTTP clients (mixed routes); reports p50/p95/p99 per route, errors, RSS")
    p.add_argument("--seconds", type=float, default=60.0, help="load mode: duration (default 60)")
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
    args.host = args.host or os.environ.get("NEMSIM_HOST") or "127.0.0.1"
    port = args.port if args.port is not None else os.environ.get("NEMSIM_PORT", "8000")
    try:
        args.port = int(port)
        if not 0 < args.port < 65536:
            raise ValueError
    except ValueError:
        raise UserError(
            f"the port must be an integer in 1..65535 (--port or NEMSIM_PORT), got {port!r}"
        ) from None
    # every worker process builds its app from the environment, so the choice travels there
    os.environ["NEMSIM_CHECKPOINT"] = _resolve_checkpoint(args.checkpoint)
    os.environ.setdefault("NEMSIM_EXIT_ON_LOAD_FAILURE", "1")  # a checkpoint that can never load: exit 3
    from service.config import get_settings
    from service.main import LOAD_FAILURE_EXIT
    from service.protocol import uvicorn_options

    get_settings.cache_clear()
    try:
        settings = get_settings()
        keys = settings.api_key_set()
    except ValueError as exc:  # a bad NEMSIM_* value
        raise UserError(f"invalid NEMSIM_* setting: {' '.join(str(exc).split())}") from None
    from service.loading import CheckpointError, read_checkpoint_safely

    try:  # fail before binding (every worker would fail the same way): exit 3 like a failed load
        read_checkpoint_safely(os.environ["NEMSIM_CHECKPOINT"])
    except CheckpointError as exc:
        print(f"nemsim serve: {exc}", file=sys.stderr)  # noqa: T201
        return 3
    from service.access import bind_warning

    warning = bind_warning(args.host, keys, settings.allow_remote_without_key)
    if warning:
        logging.getLogger("nemsim.serve").warning(warning)
    uvicorn.run(
        "service.main:create_app", factory=True, host=args.host, port=args.port, workers=args.workers,
        log_level="info", **uvicorn_options(settings, bind_settings=args.workers == 1),
    )
    if LOAD_FAILURE_EXIT["failed"]:
        print("nemsim serve: the checkpoint can never load (reason above); stopped", file=sys.stderr)  # noqa: T201
        return 3
    return 0


def _bench_service_load(args: argparse.Namespace) -> int:
    from bench.serving import bench_load

    if args.clients < 1 or not args.seconds > 0:
        raise UserError(f"--clients must be >= 1 and --seconds > 0, got {args.clients} and {args.seconds}")
    report = bench_load(
        _resolve_checkpoint(args.checkpoint), clients=args.clients, seconds=args.seconds, steps=args.steps,
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
        _write_json(args.json_out, report)
    return 0


def _cmd_bench_service(args: argparse.Namespace) -> int:
    from bench.serving import bench_service

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request would drown the report
    if args.steps < 1 or args.requests < 1 or args.cached_requests < 1:
        raise UserError("--steps, --requests and --cached-requests must be >= 1")
    if args.clients is not None:
        return _bench_service_load(args)
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
        f"  uncached: p50 {u['p50_ms']:.1f} ms  p95 {u['p95_ms']:.1f} ms  (n={u['n']}); model rollout p50 "
        f"{u['rollout_p50_ms']:.1f} ms, share of the latency outside it p50 "
        f"{u['outside_rollout_share_p50']:.2f}; "
        f"CPU {u['cpu_ms_per_request']:.1f} ms per request\n"
        f"  cached:   p50 {c['p50_ms']:.2f} ms  p95 {c['p95_ms']:.2f} ms  (n={c['n']}); "
        f"CPU {c['cpu_ms_per_request']:.2f} ms per request"
    )
    if args.json_out:
        _write_json(args.json_out, report)
    return 0


# ==== section: stress, bench rollout ======================================


def _add_stress(sub: argparse._SubParsersAction) -> None:
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
    _add_truth_options(p)
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
    p = _bench_subparsers(sub).add_parser(
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
                   "depth-windowed rollout; NEMSim only), openvino-f32, openvino-bf16 (default: the first "
                   "four)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")
    p.set_defaults(handler=_cmd_bench_rollout)


def _add_truth_benches(sub: argparse._SubParsersAction) -> None:
    bench_sub = _bench_subparsers(sub)
    p = bench_sub.add_parser(
        "physics",
        help="surrogate vs simulator: one-at-a-time sweeps, held-out profile errors, no-change baseline",
        description=(
            "Judge a checkpoint against the Monte Carlo simulator (two seeds per recipe): (a) one control "
            "group at a time from the median recipe (Cl+, Ar+, Cl2+, Cl fluxes; ion energies; ion angular "
            "exponents; neutral angular exponent) at --levels levels: final depth, top and bottom width, "
            "mask loss, bowing and the slope ratio surrogate/simulator; (b) held-out cases (fresh "
            "Latin-hypercube points and box corners, or a data file's split): profile-metric errors beside "
            "the seed-to-seed differences, Avg RMSE beside the seed-to-seed floor; (c) cases worse than "
            "predicting no change. Writes physics.md, physics.json and physics.png to --out. "
            "Example: nemsim bench physics --checkpoint checkpoints/nemsim-small.pt --workers 2"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt")
    p.add_argument("--levels", type=int, default=3, help="sweep levels per control group, >= 3 (default 3)")
    p.add_argument("--heldout", type=int, default=12,
                   help="fresh Latin-hypercube held-out cases (default 12; ignored with --data)")
    p.add_argument("--corners", type=int, default=16,
                   help="corners of the control box among the fresh held-out cases (default 16; never among "
                        "the corners `nemsim design --kind corners` draws for training)")
    p.add_argument("--data", default=None, metavar="FILE.h5",
                   help="take the held-out controls from this data file's split instead (re-simulated with "
                   "two seeds)")
    p.add_argument("--setting", default="control-id", help="split setting with --data (default control-id)")
    p.add_argument("--splits", default=None, metavar="DIR", help="split manifests directory with --data")
    p.add_argument("--split", default="test", help="split with --data (default test)")
    p.add_argument("--max-cases", type=int, default=None, help="first N cases of the split with --data")
    _add_truth_options(p)
    p.add_argument("--out", default="runs/bench/physics", metavar="DIR",
                   help="output directory (default runs/bench/physics)")
    p.set_defaults(handler=_cmd_bench_physics)

    p = bench_sub.add_parser(
        "responses",
        help="surrogate vs a data file: slopes of each profile metric on the 14 controls, no new simulation",
        description=(
            "Roll the surrogate out on the cases of a data file (all of them, or one split with --setting) "
            "and fit each final profile metric (depth, top and bottom width, mask loss, bowing), the "
            "simulator's and the surrogate's, by least squares on the 14 normalized controls. Reports every "
            "slope the simulator's data resolve (beyond 2 standard errors), the ratio surrogate/simulator, "
            "how many are within +-25 %% and how many have the wrong sign. On a training design it asks "
            "whether a response was learned, on a test split whether it generalizes. Writes responses.md, "
            ".json and .png to --out. Example: nemsim bench responses --checkpoint "
            "checkpoints/nemsim-small.pt --data data/small.h5"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt")
    p.add_argument("--data", required=True, metavar="FILE.h5",
                   help="trajectory file (from `nemsim generate`)")
    p.add_argument("--setting", default=None,
                   help="use one split of this setting (e.g. control-id); default: every complete case")
    p.add_argument("--splits", default=None, metavar="DIR", help="split manifests directory with --setting")
    p.add_argument("--split", default="test", help="split with --setting (default test)")
    p.add_argument("--max-cases", type=int, default=None, help="the first N of those cases")
    p.add_argument("--batch-size", type=int, default=8, help="rollouts run together (default 8)")
    p.add_argument("--one-call", type=int, default=None, metavar="T0",
                   help="instead of rollouts from x_0: one network call (its k states) from each case's own "
                        "simulator state at step T0, and the slopes of the metrics' increments over it; "
                        "separates what one call learned from what a rollout compounds (e.g. 50)")
    _add_monotone_option(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--out", default="runs/bench/responses", metavar="DIR",
                   help="output directory (default runs/bench/responses)")
    p.set_defaults(handler=_cmd_bench_responses)


    p = bench_sub.add_parser(
        "extrapolation",
        help="surrogate vs simulator outside the training box: errors against the distance from the box",
        description=(
            "Simulate (two seeds) and predict recipes outside the training box: each control at 1.5x and 2x "
            "the box's half-width from its centre on either side (--distances; inadmissible values skipped), "
            "zero fluxes, isotropic (m = 1) and needle-like ion angles, box corners, beside in-box reference "
            "points. Reports Avg RMSE against the seed-to-seed floor and profile-metric errors, per case and "
            "per group with the ratio to the in-box error; writes extrapolation.md, .json and .png (error "
            "against normalized distance from the box) to --out. "
            "Example: nemsim bench extrapolation --checkpoint checkpoints/nemsim-small.pt --workers 2"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt")
    p.add_argument("--distances", default="1.5,2",
                   help="normalized |u| of the out-of-box points, comma-separated, each > 1 (default 1.5,2)")
    p.add_argument("--corners", type=int, default=4, help="corners of the 14-control box (default 4)")
    p.add_argument("--in-box", type=int, default=6,
                   help="in-box Latin-hypercube reference points beside the design centre (default 6)")
    p.add_argument("--needle-m", type=float, default=10_000.0,
                   help="ion angular exponent of the needle-like recipe (default 10000)")
    p.add_argument("--isotropic-m", type=float, default=1.0,
                   help="angular exponent of the isotropic recipe (default 1)")
    _add_truth_options(p)
    p.add_argument("--out", default="runs/bench/extrapolation", metavar="DIR",
                   help="output directory (default runs/bench/extrapolation)")
    p.set_defaults(handler=_cmd_bench_extrapolation)
    p = bench_sub.add_parser(
        "monotone-eps",
        help="the monotone projection's eps: how far the data's SDF falls below its running maximum",
        description=(
            "Etching only removes material, so each voxel's SDF is non-decreasing in time; the simulator's "
            "stored states are so up to sub-voxel noise. For each channel (mask, Si) print quantiles of the "
            "fall of a voxel below its running maximum over the trajectories (voxels that change at some "
            "step only): the slack eps of the rollouts' monotone projection (NEMSimConfig.monotone_eps). "
            "Example: nemsim bench monotone-eps --data data/small.h5 --splits data/splits --max-cases 40"
        ),
    )
    p.add_argument("--data", required=True, metavar="FILE.h5", help="design data file (nemsim generate)")
    p.add_argument("--setting", default="control-id", help="split setting (default control-id)")
    p.add_argument("--splits", default=None, metavar="DIR", help="split manifests directory")
    p.add_argument("--split", default="train", help="split whose cases are read (default train)")
    p.add_argument("--max-cases", type=int, default=40, help="first N cases of the split (default 40)")
    p.add_argument("--json", dest="json_out", default=None, help="also write the quantiles to this JSON file")
    p.set_defaults(handler=_cmd_bench_monotone_eps)


def _cmd_bench_monotone_eps(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from nemsim.data.hdf5 import open_trajectories
    from nemsim.data.splits import resolve_manifest
    from nemsim.model.monotone import measure_eps

    if args.max_cases < 1:
        raise UserError(f"--max-cases must be >= 1, got {args.max_cases}")
    if not Path(args.data).is_file():
        raise UserError(f"{args.data} does not exist")
    with open_trajectories(args.data) as tf:
        case_ids = np.asarray(tf.case_ids)
        try:
            manifest, _ = resolve_manifest(args.setting, args.data, case_ids, tf.controls_raw,
                                           tf.scene.n_transitions, args.splits)  # fmt: skip
        except ValueError as exc:
            raise UserError(str(exc)) from None
    ids = [int(c) for c in manifest.get(args.split, [])][: args.max_cases]
    if not ids:
        raise UserError(f"split {args.split!r} of setting {args.setting!r} is empty")
    rows = [int(np.flatnonzero(case_ids == c)[0]) for c in ids]
    rep = {"setting": args.setting, "split": args.split, "case_ids": ids, **measure_eps(args.data, rows)}
    print(json.dumps({k: v for k, v in rep.items() if k != "case_ids"}, indent=2))  # noqa: T201
    if args.json_out:
        _write_json(args.json_out, rep)
    return 0


def _cmd_bench_extrapolation(args: argparse.Namespace) -> int:
    from bench import extrapolation as ex
    from bench.stress import initial_state

    loaded = _load_truth_checkpoint(args.checkpoint, args)
    try:
        distances = tuple(float(v) for v in args.distances.split(",") if v.strip())
    except ValueError:
        raise UserError(f"--distances {args.distances!r}: expected numbers > 1, e.g. 1.5,2") from None
    try:
        cfg = ex.ExtrapolationConfig(distances=distances, corners=args.corners, in_box=args.in_box,
                                     isotropic_m=args.isotropic_m, needle_m=args.needle_m,
                                     seeds=_parse_seeds(args.seeds))
    except ValueError as exc:
        raise UserError(str(exc)) from None
    with _sim_truth(args, loaded) as truth:
        _print_plan(truth, ex.planned_runs(cfg))
        rep = ex.run_extrapolation(loaded.model, truth, initial_state(loaded.scene), cfg)
        rep["simulator_cost"] = _sim_cost(truth)
    rep["checkpoint"] = str(args.checkpoint)
    paths = ex.write_outputs(rep, args.out)
    print(ex.format_markdown(rep))  # noqa: T201
    print("wrote " + ", ".join(paths.values()))  # noqa: T201
    return 0


def _load_truth_checkpoint(path: str, args: argparse.Namespace | None = None):
    from nemsim.inference.checkpoint import load_checkpoint

    try:
        loaded = load_checkpoint(path)
    except (FileNotFoundError, ValueError) as exc:
        raise UserError(str(exc)) from exc
    if args is not None:
        _apply_monotone(args, loaded.model)
    return loaded


def _cmd_bench_physics(args: argparse.Namespace) -> int:
    from bench import physics
    from bench.stress import initial_state

    loaded = _load_truth_checkpoint(args.checkpoint, args)
    try:
        cfg = physics.PhysicsConfig(levels=args.levels, heldout=args.heldout, corners=args.corners,
                                    seeds=_parse_seeds(args.seeds))
    except ValueError as exc:
        raise UserError(str(exc)) from None
    heldout = None
    if args.data:
        from pathlib import Path

        from nemsim.data.hdf5 import open_trajectories

        if not Path(args.data).is_file():
            raise UserError(f"{args.data} does not exist")
        with open_trajectories(args.data) as tf:
            if tf.scene != loaded.scene:
                raise UserError(f"{args.data} is on scene {tf.scene.name!r}, the checkpoint on "
                                f"{loaded.scene.name!r}")
        try:
            manifest = _load_setting_manifest(args.data, args.setting, args.splits)
            names, raw, sim_meta = physics.heldout_from_data(args.data, manifest, args.split, args.max_cases)
        except KeyError as exc:
            raise UserError(str(exc)) from None
        heldout = (names, raw)
        if sim_meta and "sim_config" not in loaded.raw:
            loaded.raw["sim_config"] = sim_meta  # the data's simulator, for the re-simulation
    with _sim_truth(args, loaded) as truth:
        held_raw = heldout[1] if heldout else physics.heldout_recipes(cfg)[1]
        _print_plan(truth, physics.planned_runs(cfg, held_raw))
        rep = physics.run_physics(loaded.model, truth, initial_state(loaded.scene), cfg, heldout)
        rep["simulator_cost"] = _sim_cost(truth)
    rep["checkpoint"] = str(args.checkpoint)
    paths = physics.write_outputs(rep, args.out)
    print(physics.format_markdown(rep))  # noqa: T201
    print("wrote " + ", ".join(paths.values()))  # noqa: T201
    return 0


def _cmd_stress(args: argparse.Namespace) -> int:
    from nemsim.inference.checkpoint import load_checkpoint
    from bench.stress import StressConfig, format_table, initial_state, run_stress

    if args.steps < 1 or args.batch_size < 1 or args.noise_cases < 0:
        raise UserError("--steps and --batch-size must be >= 1, --noise-cases >= 0")
    if args.max_corners is not None and args.max_corners < 2:
        raise UserError(f"--max-corners must be >= 2, got {args.max_corners}")
    try:
        loaded = load_checkpoint(args.checkpoint)
    except (FileNotFoundError, ValueError) as exc:
        raise UserError(str(exc)) from exc
    _apply_monotone(args, loaded.model)
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
            inv_cfg = InvariantConfig(seeds=_parse_seeds(args.seeds), pair_bases=args.pair_bases,
                                      levels=args.levels, tol_factor=args.tol_factor)
            noise = read_noise(args.noise, loaded.scene.name) if args.noise else None
        except ValueError as exc:
            raise UserError(str(exc)) from None
        with _sim_truth(args, loaded) as truth:
            _print_plan(truth, planned_runs(inv_cfg, noise))
            inv = run_invariants(loaded.model, truth, x0, inv_cfg, long_steps=cfg.steps,
                                 stress_cases=report["cases"], abs_bound=cfg.abs_bound, noise=noise)
            inv["simulator_cost"] = _sim_cost(truth)
        print(format_invariants(inv))  # noqa: T201
        report["invariants"] = inv
        passed = passed and inv["passed"]
        if args.noise_out:
            write_noise(args.noise_out, inv["noise"])
    report["passed"] = passed
    if args.json_out:
        _write_json(args.json_out, report)
    return 0 if passed else 1


def _cmd_bench_responses(args: argparse.Namespace) -> int:
    from pathlib import Path

    from nemsim.data.hdf5 import open_trajectories
    from bench import responses

    if not Path(args.data).is_file():
        raise UserError(f"{args.data} does not exist")
    if args.max_cases is not None and args.max_cases < 1:
        raise UserError(f"--max-cases must be >= 1, got {args.max_cases}")
    if args.batch_size < 1:
        raise UserError(f"--batch-size must be >= 1, got {args.batch_size}")
    loaded = _load_truth_checkpoint(args.checkpoint, args)
    with open_trajectories(args.data) as tf:
        if tf.scene != loaded.scene:
            raise UserError(f"{args.data} is on scene {tf.scene.name!r}, the checkpoint on "
                            f"{loaded.scene.name!r}")
        if args.setting is None:
            rows = [r for r in range(tf.n_cases) if tf.complete[r]]
            cases = "every complete case"
        else:
            try:
                manifest = _load_setting_manifest(args.data, args.setting, args.splits)
                rows = [tf.row_of(c) for c in manifest[args.split]]
            except KeyError as exc:
                raise UserError(f"split {args.split!r} of {args.setting!r}: {exc}") from None
            cases = f"the {args.split} split of {args.setting}"
        rows = rows[: args.max_cases]
        try:
            rep = responses.run_responses(loaded.model, tf.states, tf.controls_raw, rows, tf.scene,
                                          batch_size=args.batch_size, progress=not args.no_progress,
                                          one_call=args.one_call)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    rep.update(checkpoint=str(args.checkpoint), data=str(args.data), cases=cases)
    paths = responses.write_outputs(rep, args.out)
    print(responses.format_markdown(rep))  # noqa: T201
    print("wrote " + ", ".join(paths.values()))  # noqa: T201
    return 0


def _add_truth_options(p: argparse.ArgumentParser) -> None:
    """Flags of the commands that judge a surrogate against simulator runs."""
    p.add_argument("--sim-steps", type=int, default=None,
                   help="transitions simulated and compared (default: the scene's horizon, 100)")
    p.add_argument("--seeds", default="1,2", help="the simulator seed pair, comma-separated (default 1,2)")
    p.add_argument("--workers", type=int, default=1, help="parallel simulations, one core each (default 1)")
    p.add_argument("--cache-dir", default=None, metavar="DIR",
                   help="keep the simulator runs here and reuse them on a rerun (default: a temporary "
                   "directory)")
    _add_sim_overrides(p)
    _add_monotone_option(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_monotone_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-monotone", action="store_true",
                   help="roll out without the monotone projection (each state lifted to at least its running "
                   "maximum minus the model's monotone_eps; on for NEMSim checkpoints), e.g. to compare")


def _apply_monotone(args: argparse.Namespace, model: typing.Any) -> None:
    """--no-monotone: the model's rollouts skip the projection (its config's ``monotone_eps`` set to None)."""
    import dataclasses

    cfg: typing.Any = getattr(model, "config", None)
    if args.no_monotone and getattr(cfg, "monotone_eps", None) is not None:
        model.config = dataclasses.replace(cfg, monotone_eps=None)


def _parse_seeds(text: str) -> tuple[int, int]:
    try:
        seeds = tuple(int(s) for s in text.split(","))
    except ValueError:
        raise UserError(f"--seeds {text!r}: expected two integers, e.g. 1,2") from None
    if len(seeds) != 2 or seeds[0] == seeds[1]:
        raise UserError(f"--seeds {text!r}: expected two different integers")
    return seeds  # type: ignore[return-value]


def _sim_truth(args: argparse.Namespace, loaded):
    """The SimTruth of a checkpoint's scene and rules (the simulator configuration the checkpoint
    records, else the defaults, with --set overrides)."""
    from nemsim.evaluation.truth import SimTruth
    from nemsim.sim import SimConfig

    config = SimConfig.from_record(loaded.raw.get("sim_config"))
    if args.overrides:
        import dataclasses

        over = _sim_config(args.overrides)  # validates every KEY=VALUE
        keys = {item.partition("=")[0].strip() for item in args.overrides}
        config = dataclasses.replace(config or SimConfig(), **{k: getattr(over, k) for k in keys})
    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    try:
        return SimTruth(loaded.scene, loaded.rules, config, steps=args.sim_steps, workers=args.workers,
                        cache_dir=args.cache_dir, progress=not args.no_progress)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def _sim_cost(truth) -> dict:
    """What the simulator runs of a command cost (printed and stored in its report)."""
    cost = {"runs": truth.n_simulated, "wall_s": round(truth.sim_wall_s, 1), "workers": truth.workers,
            "steps": truth.steps}
    per = truth.sim_wall_s / max(truth.n_simulated, 1) * truth.workers
    print(f"simulator: {cost['runs']} runs in {cost['wall_s']:.1f} s wall ({per:.2f} s per run per "  # noqa: T201
          f"worker)", flush=True)
    return cost


def _print_plan(truth, runs) -> None:
    from nemsim.evaluation.truth import particle_work

    todo = truth.missing(runs)
    print(f"planned: {len(todo)} simulator runs of {truth.steps} transitions on {truth.scene.name} "  # noqa: T201
          f"({len(runs) - len(todo)} shared or cached), {truth.workers} worker(s); particle work = "
          f"{particle_work(todo):.0f} design-centre runs", flush=True)


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
        from nemsim.inference.checkpoint import load_checkpoint

        try:
            loaded = load_checkpoint(args.checkpoint)
        except (FileNotFoundError, ValueError) as exc:
            raise UserError(str(exc)) from exc
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
    report = bench_rollout(model, initial_state(scene), steps=args.steps, batch=args.batch,
                           repeats=args.repeats, variants=variants)
    report["source"] = args.checkpoint or f"untrained nemsim on {scene.name}"
    print(format_bench(report))  # noqa: T201
    if args.json_out:
        _write_json(args.json_out, report)
    return 0


# ==== section: bench speed-error, bench collect ==================


def _add_speed_error(sub: argparse._SubParsersAction) -> None:
    from bench.speed_error import RUNTIMES as SPEED_ERROR_RUNTIMES

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


def _add_bench_compare(bench_sub: argparse._SubParsersAction) -> None:
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


def _load_setting_manifest(data: str, setting: str, splits: str | None) -> dict:
    """The split manifest of ``setting`` for the trajectory file ``data`` (see resolve_manifest)."""
    from nemsim.data.hdf5 import open_trajectories
    from nemsim.data.splits import resolve_manifest

    with open_trajectories(data) as tf:
        manifest, _ = resolve_manifest(setting, data, tf.case_ids, tf.controls_raw, tf.scene.n_transitions,
                                       splits)
    return manifest


def _cmd_bench_speed_error(args: argparse.Namespace) -> int:
    import os

    import torch

    from bench.speed_error import (
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


# ==== section: inverse design, calibration, bench inverse (owner: inverse) =======================


def _add_inverse(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "inverse",
        help="recipes (controls) whose predicted profile meets target metrics, with intervals",
        description=(
            "Search the control box for recipes whose predicted profile metrics (etch depth, top width, "
            "bottom width, mask loss, bowing; any subset, each with a tolerance, in nm) meet the targets "
            "at a time step: screening of quasi-random recipes, then multi-start Adam on normalized "
            "controls through the differentiable rollout; integer controls are rounded at the end and "
            "re-evaluated. Prints K ranked recipes with predicted metrics, conformal intervals (from "
            "<checkpoint stem>.calibration.json, see `nemsim calibrate`), a distance-to-training-data "
            "flag and the search's cost; a target no recipe meets is reported as unreachable with the "
            "closest recipe and its miss. Spec (JSON): {\"targets\": {\"etch_depth\": {\"value\": 100, "
            "\"tol\": 5}, \"bottom_width\": {\"value\": 30, \"tol\": 3}}, \"step\": 100, \"fixed\": "
            "{\"angle_cl\": 5}, \"bounds\": {\"flux_cl\": [0.002, 0.01]}, \"secondary\": {\"metric\": "
            "\"mask_loss\", \"goal\": \"min\"}, \"k\": 3}. With --refine the simulator works inside the "
            "design loop: it runs the top --verify-top recipes; if none meets every tolerance, the "
            "simulator-minus-surrogate offset at the best one shifts the targets and a local search "
            "around it (a trust region) proposes a new recipe for the simulator, for up to --rounds rounds "
            "or until --budget seconds; the top recipe is then the best simulated one (labelled as such). "
            "--verify does this by default (--no-refine: only simulate the top recipes). Example: nemsim "
            "inverse --checkpoint checkpoints/nemsim-small.pt --spec target.json --verify"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="NEMSim checkpoint .pt")
    p.add_argument("--spec", required=True, metavar="FILE.json",
                   help="the design spec (JSON file, or - for stdin); see the description")
    p.add_argument("--verify", action="store_true",
                   help="also run the simulator on the top recipes (about 2.5 s each on small) and report "
                   "achieved against target; by default inside the design loop (--refine), so the top "
                   "recipe is the best simulated one")
    p.add_argument("--refine", action=argparse.BooleanOptionalAction, default=None,
                   help="simulator-corrected design (implies --verify; see the description); default: on "
                   "with --verify (--no-refine: only simulate the top recipes)")
    p.add_argument("--verify-top", type=int, default=None, metavar="R",
                   help="recipes simulated (default 1; with --refine 2, the round-0 recipes)")
    p.add_argument("--rounds", type=int, default=None, metavar="N",
                   help="simulator-corrected rounds at most (default 2)")
    p.add_argument("--budget", type=float, default=None, metavar="S",
                   help="wall seconds of the whole design: a corrected round starts only if its estimated "
                   "cost fits (default 60)")
    p.add_argument("--sim-seed", type=int, default=1,
                   help="simulator seed of the verification runs (default 1)")
    p.add_argument("--seed", type=int, default=0, help="search seed (default 0)")
    p.add_argument("--json", dest="json_out", default=None, metavar="FILE",
                   help="write the full result as JSON to FILE (- for stdout, then no table)")
    p.set_defaults(handler=_cmd_inverse)

    p = sub.add_parser(
        "calibrate",
        help="conformal intervals of profile metrics for a checkpoint (writes <stem>.calibration.json)",
        description=(
            "Split-conformal calibration of a checkpoint's per-step profile-metric errors: roll the model "
            "out on the validation cases of a setting, take the residuals predicted - simulated per metric "
            "and step, and store the interval offsets for the nominal levels next to the checkpoint "
            "(<stem>.calibration.json; the service and `nemsim inverse` read it), with the coverage "
            "measured on the test cases and the training cases' controls (distance flag). Example: "
            "nemsim calibrate --checkpoint checkpoints/nemsim-small.pt --data data/small.h5 --splits "
            "data/splits"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt")
    p.add_argument("--data", required=True, metavar="FILE.h5", help="trajectory file the checkpoint was "
                   "trained on")
    p.add_argument("--splits", default=None, metavar="DIR", help="split manifests directory (default: "
                   "<data dir>/splits, else computed)")
    p.add_argument("--setting", default="control-id", help="split setting (default control-id)")
    p.add_argument("--levels", default="0.8,0.9", help="nominal coverages, comma-separated (default 0.8,0.9)")
    p.add_argument("--max-cases", type=int, default=None, help="first N cases of each split (quick runs)")
    p.add_argument("--out", default=None, metavar="FILE.json",
                   help="output file (default: <checkpoint dir>/<stem>.calibration.json)")
    p.set_defaults(handler=_cmd_calibrate)

    p = _bench_subparsers(sub).add_parser(
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


def _cmd_inverse(args: argparse.Namespace) -> int:
    import json

    from nemsim.analysis.inverse import format_result, load_design_context, run_design, spec_from_dict
    from nemsim.analysis.inverse_refine import REFINE_WITH_VERIFY, refine_config_from_dict

    text = sys.stdin.read() if args.spec == "-" else Path(args.spec).read_text()
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise UserError(f"{args.spec}: not JSON: {exc}") from None
    spec = spec_from_dict(data)
    refine = None
    if args.refine or (args.refine is None and args.verify and REFINE_WITH_VERIFY):
        given = {"rounds": args.rounds, "budget_s": args.budget, "verify_top": args.verify_top}
        refine = refine_config_from_dict({k: v for k, v in given.items() if v is not None})
    top = 1 if args.verify_top is None else args.verify_top
    if not 1 <= top <= 10:
        raise UserError(f"--verify-top must be in 1..10, got {top}")
    ctx = load_design_context(args.checkpoint)
    result = run_design(ctx, spec, seed=args.seed, verify=args.verify, verify_top=top, sim_seed=args.sim_seed,
                        progress=args.json_out != "-", refine=refine)
    if args.json_out == "-":
        print(json.dumps(result, indent=2))  # noqa: T201
        return 0
    print(format_result(result))  # noqa: T201
    if args.json_out:
        _write_json(args.json_out, result)
        print(f"wrote {args.json_out}")  # noqa: T201
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from nemsim.analysis.intervals import calibrate, calibration_path, format_coverage

    try:
        levels = tuple(float(v) for v in args.levels.split(","))
    except ValueError:
        raise UserError(f"--levels must be numbers in (0, 1) separated by commas, got {args.levels!r}"
                        ) from None
    if args.max_cases is not None and args.max_cases < 2:
        raise UserError(f"--max-cases must be >= 2, got {args.max_cases}")
    args.device = "cpu"
    loaded, tf, manifest = _load_for_eval(args)
    cal = calibrate(loaded, tf, manifest, args.checkpoint, levels=levels, max_cases=args.max_cases,
                    progress=True)
    out = cal.write(_output_path(args.out) if args.out else calibration_path(args.checkpoint))
    print(format_coverage(cal))  # noqa: T201
    print(f"wrote {out}")  # noqa: T201
    return 0


def _cmd_bench_inverse(args: argparse.Namespace) -> int:
    from bench.inverse import format_bench, run_bench, write_bench
    from nemsim.analysis.inverse_refine import refine_config_from_dict

    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    given = {"rounds": args.rounds, "verify_top": args.verify_top, "budget_s": args.budget}
    rcfg = refine_config_from_dict({k: v for k, v in given.items() if v is not None})
    report = run_bench(args.checkpoint, n_targets=args.targets, seed=args.seed, methods=methods,
                       n_unreachable=args.unreachable, refine=args.refine, refine_config=rcfg)
    paths = write_bench(report, args.out)
    print(format_bench(report))  # noqa: T201
    print(f"wrote {paths['md']}, {paths['json']}")  # noqa: T201
    return 0


# ------------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="nemsim",
        description=(
            "NEMSim: Event Rules Library, Monte Carlo etch simulator, neural surrogate and service. "
            "Typical workflow: design -> splits -> generate -> data check -> train -> evaluate -> serve. "
            "Run `nemsim COMMAND --help` for each command. Exit codes: 0 success, 1 `stress` found a failing "
            "case, 2 bad input, a damaged file or a failed check (one line on stderr), 1 an unexpected "
            "error (a bug: one line; --debug shows the traceback), 130 interrupted."
        ),
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in (_add_rules, _add_data, _add_sim, _add_model, _add_metrics, _add_service, _add_stress,
                _add_truth_benches, _add_speed_error, _add_inverse):
        add(sub)
    _add_debug_option(parser)
    return parser


def _raised_in(exc: BaseException, package: str, module: str | None = None) -> bool:
    """Whether the innermost Python frame of exc's traceback lies in ``package`` (and file ``module``)."""
    tb = exc.__traceback__
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    parts = Path(tb.tb_frame.f_code.co_filename).parts
    return package in parts and (module is None or parts[-1] == module)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    if isinstance(exc, KeyError) and len(exc.args) == 1:
        text = str(exc.args[0])
    return text.splitlines()[0] if text else type(exc).__name__


def _named_file(args: argparse.Namespace, suffixes: tuple[str, ...]) -> str | None:
    """The one file argument of the command with one of these suffixes (None if none or several)."""
    names = {str(v) for k, v in vars(args).items()
             if k in ("data", "file", "out", "checkpoint", "path", "config") and v is not None
             and str(v).lower().endswith(suffixes)}  # fmt: skip
    return names.pop() if len(names) == 1 else None


def _yaml_error_in(exc: BaseException) -> BaseException | None:
    """A yaml.YAMLError that is exc or caused it (``raise ... from None`` keeps it as __context__)."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if type(cur).__module__.startswith("yaml"):
            return cur
        cur = cur.__cause__ or cur.__context__
    return None


def _error_report(exc: Exception, args: argparse.Namespace) -> tuple[int, str]:
    """(exit code, one-line message) for an exception that reached main(); see the module docstring."""
    import pickle
    import zipfile

    if isinstance(exc, UserError):
        return EXIT_BAD_INPUT, _first_line(exc)
    if _raised_in(exc, "h5py"):
        name = _named_file(args, (".h5", ".hdf5"))
        where = f"{name}: " if name else ""
        if isinstance(exc, BlockingIOError):
            return EXIT_BAD_INPUT, f"{where}file in use (by another nemsim process?): {_first_line(exc)}"
        if getattr(args, "data_command", None) == "check":  # the check's own verdict
            return EXIT_BAD_INPUT, f"{where}FAILED: the file is damaged: {_first_line(exc)}"
        return EXIT_BAD_INPUT, (f"{where}cannot read HDF5 data: {_first_line(exc)} (damaged or truncated? "
                                f"`nemsim data check {name or 'FILE'}` tells)")
    if isinstance(exc, (EOFError, pickle.UnpicklingError, zipfile.BadZipFile)) or (
        isinstance(exc, RuntimeError) and _raised_in(exc, "torch", "serialization.py")
    ):
        name = _named_file(args, (".pt", ".pth"))
        what = f"{type(exc).__name__}: {_first_line(exc).split('. ')[0]}"
        where = f"{name}: " if name else ""
        return EXIT_BAD_INPUT, f"{where}not a readable checkpoint, damaged or truncated ({what})"
    if isinstance(exc, OSError):
        if exc.filename is not None and exc.strerror:
            return EXIT_BAD_INPUT, f"{exc.filename}: {exc.strerror}"
        return EXIT_BAD_INPUT, _first_line(exc)
    yaml_error = _yaml_error_in(exc)
    if yaml_error is not None:  # say which file, line and column (the library's messages drop them)
        mark = getattr(yaml_error, "problem_mark", None)
        name = mark.name if mark is not None and not str(mark.name).startswith("<") else (
            _named_file(args, (".yaml", ".yml", ".json")))
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(yaml_error, "problem", None) or _first_line(yaml_error)
        return EXIT_BAD_INPUT, f"{name + ': ' if name else ''}YAML syntax error{where}: {problem}"
    if isinstance(exc, ValueError):
        return EXIT_BAD_INPUT, _first_line(exc)
    return EXIT_BUG, (f"unexpected error {type(exc).__name__}: {_first_line(exc)} (a bug; rerun with --debug "
                      "for the traceback)")


def _command_name(args: argparse.Namespace) -> str:
    """``nemsim COMMAND [ACTION]`` of a parsed command line, e.g. ``nemsim data check``."""
    words = [args.command] + [getattr(args, k) for k in ("rules_command", "data_command", "bench")
                              if getattr(args, k, None)]  # fmt: skip
    return " ".join(["nemsim", *words])


class _Parser(argparse.ArgumentParser):
    """An argparse parser whose usage errors are one line on stderr (exit 2), like every other error."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: {message} (see `{self.prog} --help`)\n")


def _add_debug_option(parser: argparse.ArgumentParser, top: bool = True) -> None:
    """--debug on the top parser and every subcommand (SUPPRESS: a subcommand does not reset it)."""
    parser.add_argument("--debug", action="store_true", default=False if top else argparse.SUPPRESS,
                        help="on an error, show the full traceback instead of one line")
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                _add_debug_option(child, top=False)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    handler: Handler = args.handler
    try:
        return int(handler(args) or 0)
    except KeyboardInterrupt:
        print("interrupted; rerun the same command to resume where supported", file=sys.stderr)  # noqa: T201
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # output piped into e.g. `head`, which stopped reading: end quietly
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        return EXIT_BROKEN_PIPE
    except Exception as exc:  # the CLI's one error boundary, see the module docstring
        if args.debug:
            raise
        code, line = _error_report(exc, args)
        print(f"{_command_name(args)}: {line}", file=sys.stderr)  # noqa: T201
        return code


def entry() -> int:
    """The `nemsim` console script: ``main()`` in a process with the tuned allocator (``nemsim.allocator``:
    re-executes once with its environment when it is not set yet)."""
    from nemsim.allocator import reexec_tuned

    reexec_tuned()
    return main()


if __name__ == "__main__":
    sys.exit(main())

"""`nemsim learn`: active learning (``nemsim.training.active``): propose, measure, run."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from nemsim.cli.common import Subparsers, UserError, output_path, seed_arg, write_json
from nemsim.data.splits import SETTINGS

ACQUISITIONS = ("distance", "ensemble", "jitter", "checkpoint", "change")  # nemsim.training.active
ACQUISITION_HELP = (
    "distance: unit-space distance to the nearest recipe the model trained on (no model call); ensemble: "
    "spread of the rollouts of --members copies of the model with weights perturbed by --weight-noise of "
    "each tensor's RMS; jitter: spread of the rollouts under --members control perturbations of "
    "--control-noise (normalized units); checkpoint: difference from the rollout of the model this "
    "one was trained from (--second-checkpoint; in round r > 1 of `run`, round r - 1's model); change: "
    "how much the model predicts will change"
)
DESCRIPTION = (
    "Active learning: spend simulator runs where the current model is most likely wrong. Each round "
    "proposes candidate recipes over the whole admissible region (a Latin hypercube inside the box, points "
    "on its faces, its corners, and the band past its edges that the explorer's sliders reach: a quarter of "
    "each range beyond either edge), scores each by an acquisition -- a number computed from the current "
    "model that should be large where its error is large -- picks a batch among the best that is spread out "
    "in control space (greedy k-center, so it is not eight copies of one corner), simulates it, fine-tunes "
    "the model on everything so far, and repeats. Why an acquisition must be measured, not assumed: a "
    "conformal interval has the same width for every recipe, and model disagreement can be small exactly "
    "where the model is confidently wrong. `nemsim learn measure` rolls the model out on held-out simulated "
    "cases and prints each acquisition's Spearman rank correlation with the model's actual error there; "
    "`nemsim learn run` uses the one you choose (default: the best over the whole region for the served "
    "model). Acquisitions: " + ACQUISITION_HELP + ". "
    "Examples: nemsim learn propose --out runs/learn/candidates.csv; nemsim learn measure "
    "--checkpoint checkpoints/nemsim-small.pt --data data/small.h5 --splits data/splits "
    "--extra-data data/small-quarter.h5 --truth-cache runs/truth-cache "
    "--probe-report benchmarks/small/physics/physics.json --out runs/learn/measure; nemsim learn run "
    "--checkpoint checkpoints/nemsim-small.pt --data data/small.h5 --splits data/splits "
    "--extra-data data/small-quarter.h5 --config configs/small/rollout-quarter.train.yaml --train-steps 300 "
    "--rounds 4 --batch 16 --workers 2 --out runs/learn (rerun the same command to resume)"
)


def _add_proposal_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("candidates (unit coordinates: 0..1 across each control's design range)")
    g.add_argument("--interior", type=int, default=256, help="Latin-hypercube points inside the box (256)")
    g.add_argument(
        "--faces", type=int, default=128, help="points with one control on a face of the box (128)"
    )
    g.add_argument("--corners", type=int, default=64, help="distinct corners of the box (64)")
    g.add_argument("--band", type=int, default=128, help="points with 1-3 controls past the box (128)")
    g.add_argument(
        "--band-width",
        type=float,
        default=0.25,
        help="how far past an edge band points go, as a fraction of the control's range (0.25: "
        "where the explorer's sliders end)",
    )
    g.add_argument("--seed", type=seed_arg, default=0, help="seed of the candidates (default 0)")


def _add_score_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("model-based acquisitions")
    g.add_argument("--members", type=int, default=4, help="perturbed models or control perturbations (4)")
    g.add_argument(
        "--weight-noise",
        type=float,
        default=0.05,
        help="ensemble: perturbation std per weight / RMS of its tensor (0.05)",
    )
    g.add_argument(
        "--control-noise",
        type=float,
        default=0.1,
        help="jitter: control perturbation std in normalized units, box half-width 1 (0.1)",
    )
    g.add_argument("--every", type=int, default=10, help="compare rollouts every this many steps (10)")
    g.add_argument(
        "--second-checkpoint",
        type=Path,
        help="the model --checkpoint was trained from, for the acquisition 'checkpoint' (for "
        "checkpoints/nemsim-small.pt, built by configs/nemsim-small.yaml: its first stage, "
        "runs/nemsim-small/k10/best.pt)",
    )


def _add_data_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", required=True, type=Path, help="the current model (.pt)")
    p.add_argument(
        "--data",
        required=True,
        type=Path,
        help="the trajectory file whose split the model trained and validated on (data/small.h5)",
    )
    p.add_argument("--setting", default="control-id", choices=SETTINGS, help="its split setting (control-id)")
    p.add_argument("--splits", type=Path, help="directory of split manifests (default: next to --data)")
    p.add_argument(
        "--extra-data",
        type=Path,
        action="append",
        default=[],
        metavar="FILE.h5",
        help="a further file the model trained on, every complete case (repeatable)",
    )


def register(sub: Subparsers) -> None:
    p = sub.add_parser(
        "learn",
        help="active learning: propose recipes, measure acquisitions, run rounds",
        description=DESCRIPTION,
    )
    lsub = p.add_subparsers(dest="learn_command", metavar="ACTION")
    lsub.required = True

    c = lsub.add_parser(
        "propose",
        help="write the candidate recipes of one round as CSV",
        description="Write the candidates over the admissible region (interior, faces, "
        "corners, band) as CSV: the 14 controls in physical units, then `kind`. "
        "Deterministic given --seed. " + DESCRIPTION.split(" Examples:")[0],
    )
    _add_proposal_options(c)
    c.add_argument("--out", required=True, type=Path, metavar="FILE.csv", help="output CSV")
    c.set_defaults(handler=_cmd_propose)

    m = lsub.add_parser(
        "measure",
        help="Spearman correlation of each acquisition with the model's actual error",
        description=(
            "Roll the checkpoint out on held-out simulated cases -- the --split cases of --data, and the "
            "recipes of benchmark reports (--probe-report, e.g. the physics benchmark's held-out corners or "
            "the extrapolation benchmark's points past the box) whose simulator runs --truth-cache holds -- "
            "compute every acquisition there and print its Spearman rank correlation with the model's Avg "
            "RMSE and final depth error, per set and over all. Simulates nothing. Writes OUT/acquisitions.md "
            "and OUT/acquisitions.json (every case, its errors and scores)."
        ),
    )
    _add_data_options(m)
    m.add_argument("--split", default="test", choices=("train", "val", "test"), help="held-out split (test)")
    m.add_argument("--cases", type=int, help="use the first N cases of the split (default: all)")
    m.add_argument("--truth-cache", type=Path, help="cached simulator runs (`nemsim bench ... --cache-dir`)")
    m.add_argument(
        "--probe-report",
        type=Path,
        action="append",
        default=[],
        metavar="FILE.json",
        help="a benchmark report whose cases' `controls` are probes (repeatable; with --truth-cache)",
    )
    m.add_argument("--seeds", default="1,2", help="simulator seeds of the cached runs (1,2)")
    m.add_argument(
        "--acquisitions",
        default=None,
        help=f"comma-separated, some of {', '.join(ACQUISITIONS)} (default: all; checkpoint only with "
        "--second-checkpoint)",
    )
    _add_score_options(m)
    m.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory")
    m.add_argument("--no-progress", action="store_true", help="no progress bars")
    m.set_defaults(handler=_cmd_measure)

    r = lsub.add_parser(
        "run",
        help="R rounds: score, simulate the best batch, fine-tune (resumable)",
        description=(
            "Run R rounds of active learning into OUT (round-NN/: candidates.csv, batch.csv, data.h5, "
            "train/, round.json). Round r simulates batch.csv with base seed --sim-seed + r - 1 (round.json "
            "records the equivalent `nemsim generate` command) and fine-tunes from the previous round's "
            "best.pt on --data's training split, --extra-data and every round's data so far. Rerunning the "
            "same command resumes: finished phases are skipped, a partial data.h5 or training run continues; "
            "other options on the same OUT are refused. " + DESCRIPTION.split(" Examples:")[0]
        ),
    )
    _add_data_options(r)
    r.add_argument(
        "--config",
        required=True,
        type=Path,
        help="TrainConfig YAML of each round's fine-tuning, e.g. configs/small/rollout-quarter.train.yaml "
        "(its `model:` part is ignored: the checkpoint's architecture is kept)",
    )
    r.add_argument(
        "--train-steps", type=int, required=True, help="optimizer steps of each round's fine-tuning"
    )
    r.add_argument("--rounds", type=int, default=4, help="rounds (4)")
    r.add_argument("--batch", type=int, default=16, help="recipes simulated per round (16)")
    r.add_argument(
        "--acquisition",
        default=None,
        choices=(*ACQUISITIONS, "lhs"),
        help="what ranks the candidates (default checkpoint: the best measured by `nemsim learn measure`); "
        "lhs: no acquisition, each round a fresh Latin hypercube (`nemsim design --n B`), the control arm of "
        "a learning curve",
    )
    r.add_argument("--pool-factor", type=int, default=4, help="batch chosen among the N x batch best (4)")
    r.add_argument("--sim-seed", type=seed_arg, default=100, help="base simulator seed of round 1 (100)")
    r.add_argument(
        "--sim-domain",
        default="auto",
        choices=("auto", "full", "quarter"),
        help="simulated domain (auto: quarter where the grid allows, 2.3x cheaper)",
    )
    r.add_argument("--workers", type=int, default=1, help="parallel simulations (1)")
    r.add_argument("--executor", default="process", choices=("process", "ray"), help="process pool or Ray")
    r.add_argument("--device", help="training device (default: the config's, auto)")
    _add_proposal_options(r)
    _add_score_options(r)
    r.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory")
    r.add_argument("--no-progress", action="store_true", help="no progress bars")
    r.set_defaults(handler=_cmd_run)


def _proposal_config(args: argparse.Namespace) -> Any:
    from nemsim.training.active import ProposalConfig

    return ProposalConfig(
        interior=args.interior,
        faces=args.faces,
        corners=args.corners,
        band=args.band,
        band_width=args.band_width,
        seed=args.seed,
    )


def _score_config(args: argparse.Namespace) -> Any:
    from nemsim.training.active import ScoreConfig

    return ScoreConfig(
        members=args.members,
        weight_noise=args.weight_noise,
        control_noise=args.control_noise,
        every=args.every,
    )


def _cmd_propose(args: argparse.Namespace) -> int:
    import csv

    from nemsim.controls import CONTROL_NAMES
    from nemsim.training.active import propose

    try:
        cands = propose(_proposal_config(args))
    except ValueError as exc:
        raise UserError(str(exc)) from None
    with open(output_path(args.out), "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([*CONTROL_NAMES, "kind"])
        for row, kind in zip(cands.raw, cands.kind, strict=True):
            w.writerow([repr(float(v)) for v in row] + [kind])
    counts = ", ".join(f"{n} {k}" for k, n in cands.counts().items())
    print(f"{args.out}: {len(cands)} candidates ({counts})")  # noqa: T201
    return 0


def _check_files(*paths: Path | None) -> None:
    for path in paths:
        if path is not None and not Path(path).is_file():
            raise UserError(f"{path} does not exist")


def _report_recipes(path: Path) -> Any:
    from nemsim.training.active import report_recipes

    try:
        return report_recipes(json.loads(Path(path).read_text(encoding="utf-8")))
    except (OSError, ValueError) as exc:
        raise UserError(f"--probe-report {path}: {exc}") from None


def _probes(args: argparse.Namespace, loaded: Any, tf: Any) -> list[Any]:
    from nemsim.cli.common import setting_manifest
    from nemsim.evaluation.truth import SimTruth
    from nemsim.sim import SimConfig
    from nemsim.training.active import file_probe, truth_probe

    ids = list(setting_manifest(args.data, args.setting, args.splits)[args.split])[: args.cases]
    probes = [file_probe(tf, ids, f"{args.setting}-{args.split}")]
    if args.probe_report and args.truth_cache is None:
        raise UserError("--probe-report needs --truth-cache DIR (the cached simulator runs of its recipes)")
    if not args.probe_report:
        return probes
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    config = SimConfig.from_record(loaded.raw.get("sim_config")) or SimConfig()
    truth = SimTruth(loaded.scene, loaded.rules, config, cache_dir=args.truth_cache)
    for path in args.probe_report:
        probe, skipped = truth_probe(truth, _report_recipes(path), seeds, Path(path).stem)
        if skipped:
            print(f"{path}: {skipped} recipes without cached runs for seeds {seeds} skipped")  # noqa: T201
        if len(probe.raw):
            probes.append(probe)
    return probes


def _cmd_measure(args: argparse.Namespace) -> int:
    import time

    from nemsim.cli.common import load_checkpoint_arg
    from nemsim.data.hdf5 import open_trajectories
    from nemsim.sim import SimConfig
    from nemsim.sim.process import initial_state
    from nemsim.training.active import format_measurement, measure_acquisitions, to_unit, training_recipes

    _check_files(args.checkpoint, args.data, args.second_checkpoint, *args.extra_data)
    every = [n for n in ACQUISITIONS if n != "checkpoint" or args.second_checkpoint is not None]
    names = (
        every if args.acquisitions is None else [n.strip() for n in args.acquisitions.split(",") if n.strip()]
    )
    loaded = load_checkpoint_arg(args.checkpoint)
    second = None if args.second_checkpoint is None else load_checkpoint_arg(args.second_checkpoint).model
    train_unit = to_unit(training_recipes(args.data, args.setting, args.splits, args.extra_data))
    x0 = initial_state(loaded.scene, SimConfig.from_record(loaded.raw.get("sim_config")))
    t0 = time.perf_counter()
    with open_trajectories(args.data) as tf:
        try:
            report = measure_acquisitions(
                loaded.model,
                loaded.scene,
                x0,
                _probes(args, loaded, tf),
                names,
                _score_config(args),
                train_unit=train_unit,
                second=second,
                progress=not args.no_progress,
            )
        except ValueError as exc:
            raise UserError(str(exc)) from None
    report["checkpoint"] = str(args.checkpoint)
    report["wall_s"] = round(time.perf_counter() - t0, 1)
    table = format_measurement(report)
    out = Path(args.out)
    write_json(out / "acquisitions.json", report)
    (out / "acquisitions.md").write_text(
        f"Spearman rank correlation of each acquisition with the actual error "
        f"of {args.checkpoint} on held-out simulated cases\n\n{table}\n"
    )
    print(table)  # noqa: T201
    print(f"{report['wall_s']:.0f} s; {out / 'acquisitions.md'}, {out / 'acquisitions.json'}")  # noqa: T201
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from nemsim.training.active import DEFAULT_ACQUISITION, LearnConfig, LearnJob, run_learning
    from nemsim.training.config import read_config_file

    _check_files(args.checkpoint, args.data, args.config, args.second_checkpoint, *args.extra_data)
    if args.train_steps < 1 or args.workers < 1:
        raise UserError(f"--train-steps and --workers must be >= 1, got {args.train_steps}, {args.workers}")
    try:
        train, _ = read_config_file(args.config)
        changes: dict[str, Any] = {"max_steps": args.train_steps, "progress": not args.no_progress}
        if args.device:
            changes["device"] = args.device
        config = LearnConfig(
            rounds=args.rounds,
            batch=args.batch,
            acquisition=args.acquisition or DEFAULT_ACQUISITION,
            pool_factor=args.pool_factor,
            proposals=_proposal_config(args),
            scoring=_score_config(args),
            sim_seed=args.sim_seed,
            sim_domain=args.sim_domain,
        )
        job = LearnJob(
            checkpoint=args.checkpoint,
            data=args.data,
            out=args.out,
            train=train.replace(**changes),
            config=config,
            setting=args.setting,
            splits=args.splits,
            extra_data=tuple(args.extra_data),
            second_checkpoint=args.second_checkpoint,
            workers=args.workers,
            executor=args.executor,
            progress=not args.no_progress,
        )
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if config.acquisition == "checkpoint" and args.second_checkpoint is None:
        raise UserError(
            "the acquisition 'checkpoint' (the default) compares the model with the one it was "
            "trained from: give --second-checkpoint (for checkpoints/nemsim-small.pt: its recipe's first "
            "stage, runs/nemsim-small/k10/best.pt), or choose another --acquisition"
        )
    states = run_learning(job, echo=lambda line: print(f"nemsim learn: {line}", flush=True))  # noqa: T201
    print(f"nemsim learn: {len(states)} rounds; the model: {states[-1]['checkpoint']}")  # noqa: T201
    return 0

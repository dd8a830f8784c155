"""`nemsim train`: one training run, or a multi-stage recipe (``--recipe``) of runs warm-started in turn.

The command line becomes a ``nemsim.training.run.TrainJob``: a TrainConfig read from --config, with the
flags of ``CONFIG_FLAGS`` overriding one field each, plus what to train on and where to write.
``nemsim.training.run.run_training`` does the rest; ``nemsim.training.recipe`` runs the stages of a recipe.
For DDP: ``torchrun --nproc-per-node N -m nemsim.train ARGS``.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from pathlib import Path

from nemsim.cli.common import Subparsers, UserError, seed_arg
from nemsim.data.splits import SETTINGS

# flags that override one TrainConfig field each (over --config); the type comes from the field
CONFIG_FLAGS: dict[str, tuple[str, str]] = {
    "--epochs": ("max_epochs", "epoch budget (overrides max_epochs; default 350)"),
    "--max-steps": ("max_steps", "optimizer-step budget (overrides max_steps; default none): ends training "
                    "there, validates, and the learning-rate cosine spans it"),
    "--max-samples": ("max_samples", "training-items budget (overrides max_samples; default none): the "
                      "same training on every device, ceil(N / batch) optimizer steps at the device's batch"),
    "--max-minutes": ("max_train_minutes",
                      "wall-clock budget in minutes (overrides max_train_minutes; default none): training "
                      "stops at the first optimizer step at which the run's wall time (training steps, "
                      "validation and checkpoints, summed over --resume) reaches M, validates and tests as "
                      "usual; the learning-rate cosine spans the budget (set warmup_steps in --config). "
                      "Example: --max-minutes 45 --resume continues a killed 45-minute run"),
    "--seed": ("seed", "override the seed (default 0)"),
    "--bf16": ("bf16", "bfloat16 autocast for the training forward pass (default: on a CUDA GPU or a CPU "
                       "with AVX-512 BF16 or AMX, where it is faster, off elsewhere; rollouts stay fp32)"),
    "--channels-last": ("channels_last", "channels_last_3d memory format (default off)"),
    "--device": ("device", "auto (default: cuda if available, else cpu), cpu, cuda, cuda:N"),
    "--rollout-steps": ("rollout_steps", "validation rollout length in transitions (default: full horizon, "
                        "100)"),
}
JOB_FLAGS = ("--model", "--data", "--setting", "--out")  # required without --recipe
# what --recipe may be given beside it
RECIPE_FLAGS = ("--out", "--recipe", "--device", "--no-progress", "--data-workers")


def _add_config_flags(p: argparse.ArgumentParser, flags: tuple[str, ...]) -> None:
    from nemsim.training.config import TrainConfig

    types = {f.name: str(f.type) for f in dataclasses.fields(TrainConfig)}
    for flag in flags:
        name, help_text = CONFIG_FLAGS[flag]
        kind = types[name].split(" | ")[0]
        if kind == "bool":
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=help_text)
        else:
            typ = seed_arg if flag == "--seed" else {"int": int, "float": float}.get(kind, str)
            p.add_argument(flag, type=typ, help=help_text,
                           metavar="M" if flag == "--max-minutes" else None)


def add_train_arguments(p: argparse.ArgumentParser, *, recipe: bool = False) -> None:
    """The arguments of one training run; with ``recipe`` also --recipe (then --model etc. are optional)."""
    need = not recipe
    p.add_argument("--model", required=need, help="registered model name (see `nemsim models`)")
    p.add_argument("--data", required=need, type=Path, help="HDF5 dataset file (from `nemsim generate`)")
    p.add_argument("--setting", required=need, choices=SETTINGS, help="split setting")
    p.add_argument("--out", required=need, type=Path,
                   help="output directory (best.pt, last.pt, metrics.csv, train.log, test_metrics.json; with "
                        "--recipe one subdirectory per stage)")
    if recipe:
        p.add_argument("--recipe", type=Path, metavar="FILE.yaml",
                       help="run the stages of this recipe in order into OUT/<stage name>, each warm-started "
                            "from the previous stage's best.pt and resumable (see the description); beside "
                            "it only --out, --device, --no-progress and --data-workers")
        p.add_argument("--data-workers", type=int, metavar="N",
                       help="with --recipe: simulate the recipe's data on N cores (generate --workers N; "
                            "default 1)")
    p.add_argument("--config", type=Path,
                   help="YAML/JSON: TrainConfig fields (lr, batch_size, ...); model overrides under `model:` "
                        "(default: the paper's values)")
    _add_config_flags(p, ("--epochs", "--max-steps", "--max-minutes"))
    p.add_argument("--fraction", type=float,
                   help="train on this data-efficiency fraction of the train split: 0.1, 0.2, 0.5 or 1 "
                        "(default 1)")
    p.add_argument("--extra-data", type=Path, action="append", default=[], metavar="FILE.h5",
                   help="also train on every complete case of this trajectory file (repeatable): a larger "
                        "design of the same scene, simulator configuration and rules, e.g. `nemsim "
                        "design --n 1500 --seed 43` simulated with `nemsim generate --controls`; validation "
                        "and test stay those of --data's split, so the paper protocol's cases are unchanged")
    p.add_argument("--pair-data", type=Path, metavar="FILE.h5",
                   help="sweep pairs to add to every batch (`pairs_per_step`, default 4) with losses on "
                        "their predicted difference (in --config: `pair_loss_weight` on the fields, "
                        "`response_loss_weight` on the profile metrics): the cases of this file that share "
                        "a simulator seed, e.g. `nemsim design --kind pairs --n 600 --seed 45` simulated "
                        "with `nemsim generate --controls ... --sim-rng counter` (common random numbers); "
                        "same scene, simulator configuration and rules as --data")
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    p.add_argument("--init-from", type=Path,
                   help="start from this checkpoint's weights (same model and rules); parameters it "
                        "lacks keep their initialization, e.g. the extra-step head of a steps_per_call > 1 "
                        "model started from a one-step checkpoint. A checkpoint of another scene is a warm "
                        "start too, e.g. a `small` model onto `paper` data (NEMSim's weights fit any grid: "
                        "convolutions, pooling and per-channel maps); the log names both scenes. Ignored "
                        "when --resume finds OUT/last.pt")
    p.add_argument("--complete-only", action="store_true",
                   help="train, validate and test on the split's cases that the data file holds complete, "
                        "e.g. a prefix of a design still being generated (default: refuse unfinished "
                        "cases); the log counts the dropped cases of each split")
    p.add_argument("--splits", type=Path,
                   help="directory of split manifests <setting>.json (default: <data dir>/splits if present, "
                        "else computed from the data file)")
    _add_config_flags(p, ("--seed", "--bf16", "--channels-last", "--device", "--rollout-steps"))
    p.add_argument("--perturb", default="none",
                   help="rule-library perturbation (ablation): none (default), structure-only, "
                        "mechanism-shuffle, event-drop, rate-noise")
    p.add_argument("--perturb-seed", type=seed_arg, default=0,
                   help="seed of the rule perturbation (default 0)")
    p.add_argument("--no-test", action="store_true", help="skip the final test evaluation of best.pt")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def register(sub: Subparsers) -> None:
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
            "A recipe (--recipe FILE.yaml: `scene`, then `stages`, each a `name` and the `args` of one "
            "`nemsim train`) runs its stages in order into OUT/<name>, each warm-started (--init-from) from "
            "the previous stage's best.pt and run with --resume: rerunning the command skips finished "
            "stages and resumes an interrupted one; one progress line per stage. "
            "For DDP: torchrun --nproc-per-node N -m nemsim.train ARGS. "
            "Example: nemsim train --model nemsim --data data/small.h5 --setting control-id --out "
            "runs/nemsim; nemsim train --recipe configs/nemsim-small.yaml --out runs/nemsim-small"
        ),
    )
    add_train_arguments(p, recipe=True)
    p.set_defaults(handler=_cmd_train)


def _train_config(args: argparse.Namespace) -> tuple[typing.Any, dict[str, typing.Any]]:
    """(TrainConfig, model overrides) from --config and the flags that override its fields."""
    from nemsim.training.config import TrainConfig, read_config_file

    try:
        cfg, model_overrides = read_config_file(args.config) if args.config else (TrainConfig(), {})
    except (OSError, ValueError) as exc:
        raise UserError(f"--config {args.config}: {exc}") from None
    changes: dict[str, typing.Any] = {}
    for flag, (name, _) in CONFIG_FLAGS.items():
        value = getattr(args, flag[2:].replace("-", "_"), None)
        if value is not None:
            changes[name] = value
    if args.no_progress:
        changes["progress"] = False
    try:
        return (cfg.replace(**changes) if changes else cfg), model_overrides
    except ValueError as exc:
        raise UserError(str(exc)) from None


def _job(args: argparse.Namespace) -> typing.Any:
    """The TrainJob of a parsed `nemsim train` command line (without --recipe)."""
    from nemsim.training.run import TrainJob

    missing = [flag for flag in JOB_FLAGS if getattr(args, flag[2:]) is None]
    if missing:
        raise UserError(f"the following arguments are required: {', '.join(missing)} (or --recipe)")
    cfg, model_overrides = _train_config(args)
    return TrainJob(model=args.model, data=args.data, setting=args.setting, out=args.out, config=cfg,
                    model_overrides=model_overrides, splits=args.splits, fraction=args.fraction,
                    extra_data=tuple(args.extra_data), pair_data=args.pair_data,
                    complete_only=args.complete_only, resume=args.resume, init_from=args.init_from,
                    perturb=args.perturb, perturb_seed=args.perturb_seed, test=not args.no_test)


def _cmd_train(args: argparse.Namespace) -> int:
    from nemsim.training.run import run_training

    if args.recipe is not None:
        return _cmd_recipe(args)
    run_training(_job(args))
    return 0


class _StageParser(argparse.ArgumentParser):
    """The arguments of one recipe stage: a usage error names the stage (one line, exit 2)."""

    def error(self, message: str) -> typing.NoReturn:
        raise UserError(f"{self.prog}: {message}")


def _stage_jobs(args: argparse.Namespace, recipe: typing.Any) -> dict[str, typing.Any]:
    """{stage name: TrainJob} of every stage (output OUT/<name>, --resume, warm start from the previous
    stage's best.pt), with every data file checked against the recipe's scene before anything runs."""
    from nemsim.data.hdf5 import open_trajectories

    probe = argparse.ArgumentParser(add_help=False)
    add_train_arguments(probe, recipe=True)
    allowed = {flag[2:].replace("-", "_") for flag in RECIPE_FLAGS}
    given = [a.option_strings[0] for a in probe._actions
             if a.dest not in allowed and getattr(args, a.dest, a.default) != a.default]
    if given:
        raise UserError(f"--recipe takes the training arguments from its stages; beside it give only "
                        f"{', '.join(RECIPE_FLAGS[:1] + RECIPE_FLAGS[2:])} (got {given[0]})")
    if args.out is None:
        raise UserError("--recipe needs --out DIR (stage NAME writes to DIR/NAME)")
    forwarded = ["--device", args.device] if args.device else []
    forwarded += ["--no-progress"] if args.no_progress else []
    jobs: dict[str, typing.Any] = {}
    prev: Path | None = None
    for stage in recipe.stages:
        parser = _StageParser(prog=f"{args.recipe}: stage {stage.name}")
        add_train_arguments(parser)
        warm: list[str] = ["--init-from", str(prev)] if prev is not None else []
        stage_args = parser.parse_args([*stage.args, "--out", str(args.out / stage.name), "--resume", *warm,
                                        *forwarded])
        job = jobs[stage.name] = dataclasses.replace(_job(stage_args), recipe=str(args.recipe))
        if not Path(job.data).is_file():
            raise UserError(f"{args.recipe}: stage {stage.name}: data file {job.data} does not exist")
        with open_trajectories(job.data) as tf:
            if tf.scene.name != recipe.scene:
                raise UserError(f"{args.recipe}: stage {stage.name}: {job.data} is on scene "
                                f"{tf.scene.name!r}, the recipe on {recipe.scene!r}")
        prev = job.out / "best.pt"
    return jobs


def _run_nemsim(words: list[str]) -> int:
    """Run one `nemsim` command line in its own process (a recipe's data command); its exit code. A SIGTERM
    of this process is passed on to the command, which stops as it would itself (``generate`` keeps its
    finished cases), and then ends the recipe like Ctrl-C: no data command outlives the recipe."""
    import signal
    import subprocess
    import sys
    import threading

    proc = subprocess.Popen([sys.executable, "-m", "nemsim.cli", *words])
    terminated: list[int] = []

    def forward(signum: int, frame: object) -> None:
        terminated.append(signum)
        proc.send_signal(signal.SIGTERM)

    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, forward) if main_thread else None
    try:
        code = proc.wait()
    except KeyboardInterrupt:  # Ctrl-C reached the command too (one process group): let it finish stopping
        proc.send_signal(signal.SIGTERM)
        proc.wait()
        raise
    finally:
        if main_thread and previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if terminated:
        raise KeyboardInterrupt(f"terminated by signal {terminated[0]}")
    return code


def _cmd_recipe(args: argparse.Namespace) -> int:
    import yaml

    from nemsim.training.recipe import recipe_from_dict, run_recipe, run_recipe_data
    from nemsim.training.run import run_training

    try:
        recipe = recipe_from_dict(yaml.safe_load(Path(args.recipe).read_text()))
    except ValueError as exc:
        raise UserError(f"{args.recipe}: {exc}") from None
    echo = lambda line: print(f"nemsim train: {line}", flush=True)  # noqa: E731, T201
    workers = ["--workers", str(args.data_workers)] if args.data_workers else []
    if args.data_workers is not None and args.data_workers < 1:
        raise UserError(f"--data-workers must be >= 1, got {args.data_workers}")
    try:
        run_recipe_data(recipe, lambda w: _run_nemsim(w + workers if w[0] == "generate" else w), echo)
    except RuntimeError as exc:
        raise UserError(f"{args.recipe}: {exc}") from None
    jobs = _stage_jobs(args, recipe)
    bests = run_recipe(recipe, args.out, lambda stage, out, prev: run_training(jobs[stage.name]), echo=echo)
    print(f"nemsim train: recipe {args.recipe} done: {bests[-1]}")  # noqa: T201
    return 0

"""What the command groups share: the exit codes, ``UserError``, output paths and the common options.

Command groups outside the library (``service.cli``, ``bench.cli``) use these too, so every command speaks
the same way: handlers raise ``UserError`` for bad input (one line, exit 2) and return an exit code.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from collections.abc import Callable
from pathlib import Path

Handler = Callable[[argparse.Namespace], int]
Subparsers = argparse._SubParsersAction  # what `nemsim` hands each command group to add its parsers to

EXIT_BAD_INPUT = 2  # bad input, a damaged file or a failed check
EXIT_BUG = 1  # an unexpected exception (also `stress`'s failing case)
EXIT_INTERRUPTED = 130
EXIT_BROKEN_PIPE = 141  # as if killed by SIGPIPE, the shell convention


class UserError(Exception):
    """Bad input from the command line: printed as one line, exit code 2."""


def output_path(path: str | Path) -> Path:
    """A file path the user named for output, with its missing parent directories created."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


def run_output(command: str, checkpoint: str | Path, suffix: str = "") -> Path:
    """Default output of a command about a checkpoint: runs/<command>/<ckpt dir>-<ckpt name><suffix>.

    Under runs/ (ignored by git), so a default never writes into a committed folder such as checkpoints/;
    committed results are written only through an explicit --out.
    """
    ckpt = Path(checkpoint).resolve()
    return Path("runs") / command / f"{ckpt.parent.name}-{ckpt.stem}{suffix}"


def write_json(path: str | Path, obj: object) -> None:
    """Write a report as indented JSON (the --json option of several commands)."""
    import json

    with open(output_path(path), "w") as fh:
        json.dump(obj, fh, indent=2)


def add_scene_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default="small", choices=("tiny", "small", "paper"),
                   help="grid: paper 2 nm, small 4 nm, tiny 8 nm voxels (tests only); default: small")


def add_sim_overrides(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a SimConfig constant, e.g. --set capacity=8 (repeatable)")


def sim_config(overrides: list[str]) -> typing.Any:
    """SimConfig with ``KEY=VALUE`` overrides (values parsed as int or float; text for text fields such as
    ``sputter_calibration``)."""
    from nemsim.sim import SimConfig

    try:
        return SimConfig(**config_values(overrides, "--set"))  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise UserError(f"--set: {exc}") from exc


def config_values(items: list[str], option: str) -> dict[str, object]:
    """{field: value} of ``KEY=VALUE`` items naming SimConfig fields (numbers; text for text fields)."""
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


MAX_SEED = 2**63 - 1  # numpy's and torch's generators take seeds 0..2**63 - 1


def seed_arg(text: str) -> int:
    """argparse type of a random seed: an integer in 0..MAX_SEED (argparse names the option in its error)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be an integer in 0..{MAX_SEED} (a random seed), got {text!r}")
    return value


def read_text_arg(path: str | Path, option: str) -> str:
    """The text of the file an option names (``-`` for stdin); UserError naming the option and the file if it
    cannot be read or is not UTF-8 text."""
    import sys

    if str(path) == "-":
        return sys.stdin.read()
    try:
        return Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{option} {path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise UserError(f"{option} {path}: {exc.strerror or exc}") from None


def floats(text: str, option: str) -> tuple[float, ...]:
    """Comma-separated numbers of an option, e.g. ``--m 50,300``."""
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise UserError(f"{option} {text!r}: expected comma-separated numbers") from None
    if not values:
        raise UserError(f"{option}: no values given")
    return values


def parse_seeds(text: str) -> tuple[int, int]:
    """``--seeds A,B``: two different integers."""
    try:
        seeds = tuple(int(s) for s in text.split(","))
    except ValueError:
        raise UserError(f"--seeds {text!r}: expected two integers, e.g. 1,2") from None
    if len(seeds) != 2 or seeds[0] == seeds[1]:
        raise UserError(f"--seeds {text!r}: expected two different integers")
    return seeds  # type: ignore[return-value]


def add_monotone_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-monotone", action="store_true",
                   help="roll out without the monotone projection (each state lifted to at least its running "
                   "maximum minus the model's monotone_eps; on for NEMSim checkpoints), e.g. to compare")


def apply_monotone(args: argparse.Namespace, model: typing.Any) -> None:
    """--no-monotone: the model's rollouts skip the projection (its config's ``monotone_eps`` set to None)."""
    cfg: typing.Any = getattr(model, "config", None)
    if args.no_monotone and getattr(cfg, "monotone_eps", None) is not None:
        model.config = dataclasses.replace(cfg, monotone_eps=None)


def load_checkpoint_arg(path: str | Path, args: argparse.Namespace | None = None) -> typing.Any:
    """The checkpoint an option names (a missing, damaged or mismatched one is bad input, exit 2, through the
    error boundary); with ``args``, --no-monotone applied."""
    from nemsim.inference.checkpoint import load_checkpoint

    loaded = load_checkpoint(path)
    if args is not None:
        apply_monotone(args, loaded.model)
    return loaded


def setting_manifest(data: str | Path, setting: str, splits: str | Path | None) -> dict:
    """The split manifest of ``setting`` for the trajectory file ``data`` (see resolve_manifest)."""
    from nemsim.data.hdf5 import open_trajectories
    from nemsim.data.splits import resolve_manifest

    with open_trajectories(data) as tf:
        manifest, _ = resolve_manifest(setting, data, tf.case_ids, tf.controls_raw, tf.scene.n_transitions,
                                       splits)
    return manifest


def load_for_eval(args: argparse.Namespace) -> tuple[typing.Any, typing.Any, dict]:
    """(loaded model, trajectory file, manifest) of --checkpoint, --data, --setting and --splits, with the
    data file's scene checked against the checkpoint."""
    from nemsim.data.hdf5 import open_trajectories
    from nemsim.data.splits import resolve_manifest
    from nemsim.inference.checkpoint import load_checkpoint

    for path in (args.checkpoint, args.data):
        if not Path(path).is_file():
            raise UserError(f"{path} does not exist")
    tf = open_trajectories(args.data)
    loaded = load_checkpoint(args.checkpoint, scene=tf.scene, device=getattr(args, "device", "cpu"))
    manifest, _ = resolve_manifest(args.setting, args.data, tf.case_ids, tf.controls_raw,
                                   tf.scene.n_transitions, args.splits)  # fmt: skip
    tf.warn_if_other_rules(loaded.raw["rules_sha256"], "the checkpoint's library")
    return loaded, tf, manifest

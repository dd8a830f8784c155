"""Stamp benchmark results with the checkpoint that made them: ``python -m bench.stamp CHECKPOINT FILE...``.

The id is the first 12 hex digits of the checkpoint file's SHA-256 (what ``GET /model`` reports). A JSON
object gets top-level ``"checkpoint"`` and ``"checkpoint_id"`` keys; a Markdown file gets one line under its
title. Stamping again replaces the stamp, so ``make benchmarks`` can run any number of times.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from nemsim.inference.checkpoint import checkpoint_id

MARK = "_Made with checkpoint "


def stamp_json(path: Path, name: str, cid: str) -> None:
    obj = json.loads(path.read_text())
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: a JSON object is needed to stamp, found {type(obj).__name__}")
    stamped = {"checkpoint": name, "checkpoint_id": cid, **obj}  # the stamp first; a restamp overwrites
    stamped["checkpoint"], stamped["checkpoint_id"] = name, cid
    path.write_text(json.dumps(stamped, indent=2) + "\n")


def stamp_markdown(path: Path, name: str, cid: str) -> None:
    lines = [line for line in path.read_text().splitlines() if not line.startswith(MARK)]
    at = 1 if lines and lines[0].startswith("#") else 0
    lines[at:at] = [f"{MARK}`{name}` (id `{cid}`)._"]
    path.write_text("\n".join(lines) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.stamp", description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", help="the checkpoint .pt that made the results")
    p.add_argument("files", nargs="+", help="result files (.json objects, .md)")
    args = p.parse_args(argv)
    ckpt = Path(args.checkpoint)
    if not ckpt.is_file():
        p.error(f"checkpoint {ckpt} not found")
    cid = checkpoint_id(ckpt)
    for f in map(Path, args.files):
        if f.suffix == ".json":
            stamp_json(f, ckpt.name, cid)
        elif f.suffix == ".md":
            stamp_markdown(f, ckpt.name, cid)
        else:
            p.error(f"{f}: only .json and .md results are stamped")
    print(f"stamped {len(args.files)} files with {ckpt.name} (id {cid})")  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())

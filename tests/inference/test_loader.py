"""``nemsim.inference.checkpoint``'s one loader: weights-only reads (no code from the file runs), every
shipped checkpoint and resume state readable that way, damaged or non-finite weights refused, and failures
that name the file by its base name only."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from nemsim.inference import CheckpointError, CheckpointNotFound, load_checkpoint, read_checkpoint
from nemsim.inference.checkpoint import weights_digest

REPO = Path(__file__).resolve().parents[2]


class _Touch:
    """Pickles to `Path(marker).touch()`: running it leaves a file behind."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def _copy_with(tiny_checkpoint: Path, path: Path, edit) -> Path:
    ckpt = torch.load(tiny_checkpoint, map_location="cpu", weights_only=True)
    edit(ckpt)
    torch.save(ckpt, path)
    return path


def test_malicious_checkpoint_runs_no_code(tiny_checkpoint, tmp_path):
    marker = tmp_path / "pwned"
    evil = _copy_with(tiny_checkpoint, tmp_path / "evil.pt", lambda c: c.update(summary=[_Touch(marker)]))
    with pytest.raises(CheckpointError, match="refused"):
        load_checkpoint(evil)
    assert not marker.exists()


@pytest.mark.parametrize(
    "path", sorted(p.relative_to(REPO).as_posix() for p in (REPO / "checkpoints").rglob("*.pt")) or ["none"]
)
def test_committed_checkpoints_read_weights_only(path):
    """Every committed checkpoint, resume states (optimizer and numpy RNG state) included."""
    if path == "none":
        pytest.skip("no committed checkpoints")
    ckpt = read_checkpoint(REPO / path)
    assert ckpt["model_name"] and "model_state" in ckpt


def test_shipped_checkpoint_loads():
    loaded = load_checkpoint(REPO / "checkpoints" / "nemsim-small.pt")
    assert loaded.name == "nemsim" and loaded.scene.name == "small"


def test_truncated_checkpoint_names_only_the_file(tmp_path, tiny_checkpoint):
    data = tiny_checkpoint.read_bytes()
    path = tmp_path / "cut.pt"
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="cut.pt") as info:
        read_checkpoint(path)
    assert str(tmp_path) not in str(info.value)
    with pytest.raises(CheckpointNotFound, match="absent.pt"):
        read_checkpoint(tmp_path / "absent.pt")
    with pytest.raises(FileNotFoundError):  # also an OSError for callers that catch those
        load_checkpoint(tmp_path / "absent.pt")


def _first_float(ckpt: dict) -> str:
    return next(k for k, t in ckpt["model_state"].items() if t.is_floating_point() and t.numel() > 4)


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_weights_are_refused(tiny_checkpoint, tmp_path, value):
    """A copy of a tiny checkpoint with NaN / Inf written into one weight never loads."""

    def poison(ckpt: dict) -> None:
        ckpt["model_state"][_first_float(ckpt)].view(-1)[:3] = value
        ckpt.pop("weights_sha256")  # as an older checkpoint without a digest: the finite check alone

    bad = _copy_with(tiny_checkpoint, tmp_path / "poisoned.pt", poison)
    with pytest.raises(CheckpointError, match=r"poisoned\.pt.*NaN or Inf"):
        load_checkpoint(bad)
    with pytest.raises(ValueError):  # the library's kind for bad input (the CLI exits 2)
        read_checkpoint(bad)


def test_weights_that_differ_from_their_digest_are_refused(tiny_checkpoint, tmp_path):
    """Finite but altered weights (a damaged file): the digest recorded at save time no longer matches."""
    assert read_checkpoint(tiny_checkpoint)["weights_sha256"] == weights_digest(
        torch.load(tiny_checkpoint, map_location="cpu", weights_only=True)["model_state"]
    )

    def alter(ckpt: dict) -> None:
        ckpt["model_state"][_first_float(ckpt)].view(-1)[0] += 0.5

    bad = _copy_with(tiny_checkpoint, tmp_path / "altered.pt", alter)
    with pytest.raises(CheckpointError, match=r"altered\.pt.*digest"):
        read_checkpoint(bad)


def test_a_missing_weight_is_named(tiny_checkpoint, tmp_path):
    """One weight removed (digest dropped too): refused naming that weight, not as a version mismatch."""
    gone: list[str] = []

    def drop(ckpt: dict) -> None:
        gone.append(_first_float(ckpt))
        ckpt["model_state"].pop(gone[0])
        ckpt.pop("weights_sha256")

    bad = _copy_with(tiny_checkpoint, tmp_path / "partial.pt", drop)
    with pytest.raises(CheckpointError, match=rf"partial\.pt.*damaged: weight '{gone[0]}' is missing"):
        load_checkpoint(bad)


def test_unbuildable_checkpoint_is_a_checkpoint_error(tiny_checkpoint, tmp_path):
    def unknown_option(ckpt: dict) -> None:
        ckpt["model_config"]["no_such_option"] = 1

    bad = _copy_with(tiny_checkpoint, tmp_path / "odd.pt", unknown_option)
    with pytest.raises(CheckpointError, match=r"odd\.pt.*could not be rebuilt"):
        load_checkpoint(bad)


def test_scene_by_name(tiny_checkpoint):
    from nemsim.inference import CheckpointMismatch

    assert load_checkpoint(tiny_checkpoint, scene="tiny").scene.name == "tiny"
    with pytest.raises(CheckpointMismatch, match="scene"):
        load_checkpoint(tiny_checkpoint, scene="small")


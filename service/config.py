"""Service settings: one `Settings(BaseSettings)` read from `NEMSIM_*` environment variables.

Read through the cached `get_settings()` dependency (never at import); tests replace it with
`app.dependency_overrides[get_settings]` or pass `create_app(settings=...)`.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

REPO_ROOT = Path(__file__).resolve().parents[1]


def checkpoint_dirs() -> list[Path]:
    """Where the default checkpoint is looked for: `checkpoints/` at the repo root, then in the cwd.

    The second entry covers a non-editable install (e.g. the Docker image), where `service/` lives in
    site-packages and the shipped checkpoint sits next to the working directory.
    """
    dirs = [REPO_ROOT / "checkpoints", Path.cwd() / "checkpoints"]
    return list(dict.fromkeys(d.resolve() for d in dirs))


def default_checkpoint() -> Path | None:
    """The single (or, sorted by name, the first) `*.pt` under the checkpoint directories, or None."""
    for directory in checkpoint_dirs():
        found = sorted(directory.glob("*.pt")) if directory.is_dir() else []
        if found:
            return found[0]
    return None


class Settings(BaseSettings):
    """Everything the service can be told; each field is the env var `NEMSIM_<FIELD>`."""

    model_config = SettingsConfigDict(env_prefix="NEMSIM_", extra="ignore")

    checkpoint: Path | None = Field(
        default=None, description="checkpoint (.pt) to serve; default: the first *.pt under checkpoints/"
    )
    max_steps: int = Field(default=100, ge=1, le=10_000, description="ceiling on `steps` per rollout")
    max_body_bytes: int = Field(default=1_000_000, ge=1_024, description="request bodies above this get 413")
    max_concurrency: int = Field(default=1, ge=1, description="rollouts computed at the same time")
    max_queue: int = Field(default=16, ge=0, description="requests allowed to wait for a slot; more get 503")
    queue_timeout_s: float = Field(default=60.0, gt=0, description="longest wait for a slot before 503")
    cache_size: int = Field(default=32, ge=0, description="rollouts kept (LRU) for repeats and mesh requests")
    max_meshes: int = Field(default=8, ge=0, description="meshes one POST /rollout may ask for inline")
    warmup_steps: int = Field(
        default=2, ge=0, description="steps of the warm-up rollout before /ready (0: none)"
    )
    torch_threads: int | None = Field(
        default=None, ge=1, description="torch intra-op threads (None: torch default)"
    )
    runtime_backend: Literal["openvino", "torch"] = Field(
        default="openvino", description="rollout runtime; openvino falls back to torch (logged) if missing"
    )
    runtime_precision: Literal["f32", "bf16"] = Field(
        default="bf16", description="rollout precision (bf16: same Avg RMSE within 1 %, measured)"
    )
    runtime_threads: int = Field(
        default=1, ge=1, description="OpenVINO threads per rollout; keep threads x max_concurrency <= cores"
    )

    @field_validator("checkpoint")
    @classmethod
    def _expand(cls, value: Path | None) -> Path | None:
        return value.expanduser() if value is not None else None

    def resolved_checkpoint(self) -> Path | None:
        """The checkpoint to load: the explicit one, else the default one (None if there is none)."""
        return self.checkpoint if self.checkpoint is not None else default_checkpoint()


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings (read from the environment once)."""
    return Settings()

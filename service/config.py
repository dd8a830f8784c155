"""Service settings: one `Settings(BaseSettings)` read from `NEMSIM_*` environment variables.

Read through the cached `get_settings()` (never at import); the routes read the app's own settings
(`service.deps.app_settings`: `create_app(settings=...)`, else `get_settings()`).
"""

from __future__ import annotations

import ipaddress
import types
import typing
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, ValidationError, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

REPO_ROOT = Path(__file__).resolve().parents[1]


def checkpoint_dirs() -> list[Path]:
    """Where the default checkpoint is looked for: `checkpoints/` at the repo root, then in the cwd.

    The second entry covers a non-editable install (e.g. the Docker image), where `service/` lives in
    site-packages and the shipped checkpoint sits next to the working directory.
    """
    dirs = [REPO_ROOT / "checkpoints", Path.cwd() / "checkpoints"]
    return list(dict.fromkeys(d.resolve() for d in dirs))


DEFAULT_SCENE = "small"  # the scene of the served model (checkpoints/README.md)


def default_checkpoint(scene: str = DEFAULT_SCENE) -> Path:
    """`nemsim-<scene>.pt` in the first checkpoint directory that has it, else in the first one (it is then
    missing, and loading says so): never another file, so the server never serves another scene's model."""
    name = f"nemsim-{scene}.pt"
    dirs = checkpoint_dirs()
    return next((d / name for d in dirs if (d / name).is_file()), dirs[0] / name)


MIN_KEY_CHARS = 16  # shorter API keys are guessable
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


def parse_networks(text: str) -> tuple[IPNetwork, ...]:
    """Comma-separated addresses or networks (`10.0.0.0/8`, `::1`); ValueError naming a bad entry."""
    out = []
    for entry in (e.strip() for e in text.split(",")):
        if not entry:
            continue
        try:
            out.append(ipaddress.ip_network(entry, strict=False))
        except ValueError:
            raise ValueError(
                f"{entry!r} is not an IP address or network; expected comma-separated addresses or networks "
                "such as 10.0.0.0/8 or ::1"
            ) from None
    return tuple(out)


def host_name(host: str) -> str:
    """The name of a Host header value: lower case, without the port and a trailing dot (`[::1]:80` ->
    `[::1]`)."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[: host.find("]") + 1] if "]" in host else host
    return host.rsplit(":", 1)[0].rstrip(".") if host.count(":") == 1 else host.rstrip(".")


class Settings(BaseSettings):
    """Everything the service can be told; each field is the env var `NEMSIM_<FIELD>`."""

    model_config = SettingsConfigDict(env_prefix="NEMSIM_", extra="ignore")

    checkpoint: Path | None = Field(
        default=None, description="checkpoint (.pt) to serve; default: checkpoints/nemsim-<scene>.pt"
    )
    scene: str | None = Field(
        default=None,
        pattern=r"^[A-Za-z0-9_-]{1,64}$",
        description=f"scene the served model must be of (refused otherwise); default: the checkpoint's, or "
        f"{DEFAULT_SCENE!r} when no checkpoint is given",
    )
    max_steps: int = Field(default=100, ge=1, le=10_000, description="ceiling on `steps` per rollout")
    max_body_bytes: int = Field(default=1_000_000, ge=1_024, description="request bodies above this get 413")
    max_concurrency: int = Field(default=1, ge=1, description="uncached rollouts computed at the same time")
    max_queue: int = Field(
        default=16, ge=0, description="requests allowed to wait for a slot (per kind of work); more get 503"
    )
    max_queue_per_client: int = Field(
        default=8, ge=1, description="of those, how many one client (API key, else address) may have waiting"
    )
    mesh_concurrency: int = Field(
        default=1, ge=1, description="meshes extracted at the same time (never behind rollouts)"
    )
    mechanisms_concurrency: int = Field(
        default=1, ge=1, description="uncached /mechanisms analyses at the same time (never behind rollouts)"
    )
    queue_timeout_s: float = Field(default=60.0, gt=0, description="longest wait for a slot before 503")
    cache_size: int = Field(
        default=32,
        ge=0,
        description="rollouts kept for repeats, mesh links and slices: a rollout's id (and its mesh links) "
        "resolves until this many other rollouts have been answered by POST /rollout after it (computed or "
        "repeated; follow-up requests of other ids do not count): under a flood of new rollouts, this many "
        "rollout computations; rollouts whose follow-ups or repeats were requested stay longer, up to half "
        "this many more, as the memory budget allows. Later: 404, and POST /rollout again gives the same id",
    )
    response_max_mb: int = Field(
        default=96,
        ge=1,
        description="large response bodies (every field, meshes) being sent at once, in MB; a body beyond "
        "it gets 503 + Retry-After (one body is always sent), so concurrent clients cannot push the server "
        "past its memory budget (`service.memory.ResponseBudget`)",
    )
    cache_max_mb: int = Field(
        default=128,
        ge=1,
        description="memory budget of the rollout cache in MB (meshes: a quarter more); the states are "
        "stored losslessly in a fraction of their float16 size, so `cache_size` 100-step `small` rollouts of "
        "the design box fit in the default (the id guarantee above holds while they fit; far larger "
        "rollouts leave room for fewer), and the loaded `small` server stays under 1 GB resident (simulator "
        "and inverse-design jobs compute in child processes)",
    )
    max_meshes: int = Field(default=8, ge=0, description="meshes one POST /rollout may ask for inline")
    warmup_steps: int = Field(
        default=2, ge=0, description="steps of the warm-up rollout before /ready (0: none)"
    )
    torch_threads: int | None = Field(
        default=None,
        ge=1,
        description="torch intra-op threads (None: torch's default, e.g. OMP_NUM_THREADS, capped at the CPU "
        "count divided by max_concurrency, so concurrent rollouts do not oversubscribe the cores)",
    )
    runtime_backend: Literal["openvino", "torch", "cuda"] = Field(
        default="openvino",
        description="rollout runtime; openvino falls back to torch (logged) if missing; cuda: CUDA graphs on "
        "the GPU (`nemsim serve --device cuda`), eager torch on the CPU without CUDA (logged)",
    )
    runtime_precision: Literal["auto", "f32", "bf16"] = Field(
        default="auto", description="rollout precision; auto: bf16 where the device computes in it (a GPU, "
        "a CPU with AVX-512 BF16 or AMX), else f32 (`nemsim.inference.precision`; bf16: same Avg RMSE within "
        "1 %, measured); GET /model says what runs",
    )
    rollout_nice: int = Field(
        default=0,
        ge=0,
        le=19,
        description="rollouts compute on threads this much nicer than the server (Linux; 0: the same "
        "priority). Jobs run at the server's priority, one at a time on one core",
    )
    runtime_threads: int = Field(
        default=1, ge=1, description="OpenVINO threads per rollout; keep threads x max_concurrency <= cores"
    )

    # --- connection limits (service.protocol; `nemsim serve` hands the uvicorn ones to uvicorn) ---
    max_request_line_bytes: int = Field(
        default=8_192, ge=256, description="longer request lines (URLs) get 414"
    )
    max_header_bytes: int = Field(default=32_768, ge=1_024, description="larger request heads get 431")
    head_timeout_s: float = Field(
        default=10.0, gt=0, description="a request head must arrive within this (else 408 / close)"
    )
    body_timeout_s: float = Field(
        default=30.0, gt=0, description="a request body must arrive within this of its head (else 408)"
    )
    handler_timeout_s: float = Field(
        default=300.0, gt=0, description="a request not answered within this gets 504"
    )
    max_connections: int = Field(
        default=512, ge=1, description="open connections; a new one beyond them closes one being refused, "
        "else one waiting beyond its address's cap, else the one that waited longest without a request (not "
        "one just opened), or is dropped at once when none qualifies",
    )
    limit_concurrency: int = Field(
        default=256, ge=1, description="requests in flight; more get 503 at once (probes exempt)"
    )
    keep_alive_s: int = Field(
        default=5, ge=1, description="uvicorn: idle keep-alive connections close after this"
    )
    max_connections_per_client: int = Field(
        default=32, ge=1, description="connections one client address is served on (trusted proxies "
        "exempt); one beyond them waits for its request, which then closes that address's connection that "
        "waited longest without one (not one just opened) or, with none such, is answered 503 + "
        "Retry-After: one address cannot shut out others, nor another client on it (every local client on "
        "loopback), and a burst from it gets answers, not resets",
    )

    # --- access control and operations (service.access, service.metrics) ---
    api_keys: SecretStr = Field(
        default=SecretStr(""), description="comma-separated API keys (header X-API-Key); none: loopback only"
    )
    api_keys_file: Path | None = Field(
        default=None, description="file with one API key per line (# comments)"
    )
    allow_remote_without_key: bool = Field(
        default=False, description="without API keys, also answer clients on other machines (not advised)"
    )
    allowed_hosts: str = Field(
        default="", description="without API keys, Host names answered besides localhost and loopback "
        "addresses (comma-separated; * for any, not advised): others get 400 (DNS rebinding)",
    )
    trusted_proxies: str = Field(
        default="", description="addresses or networks (comma-separated, e.g. 10.0.0.0/8) of reverse proxies "
        "whose proxy_header names the client; none by default (loopback is not trusted by itself)",
    )
    proxy_header: Literal["x-forwarded-for", "forwarded"] = Field(
        default="x-forwarded-for", description="the header the trusted proxies append the client to (the "
        "other one is ignored)",
    )
    rate_limit_per_minute: int = Field(
        default=1200, ge=0, description="requests per minute per client (API key, else address); 0: no limit"
    )
    rate_limit_burst: int = Field(default=100, ge=1, description="requests a client may send at once")
    key_failure_burst: int = Field(
        default=20, ge=1, description="wrong API keys one client address may send before it gets 429 + "
        "Retry-After; while it is over, its requests that need a key get 429 whatever key they carry",
    )
    key_failures_per_minute: int = Field(
        default=6, ge=1, description="... and, beyond that burst, how many more wrong keys per minute",
    )
    docs: bool = Field(default=True, description="serve /docs and /openapi.json")
    access_log: bool = Field(
        default=True, description="one JSON line per request on the service.access logger"
    )

    extrapolation: Literal["allow", "clip", "refuse"] = Field(
        default="allow",
        description="controls outside the training box: allow (answer with a quantitative warning), clip "
        "(to the box, saying which) or refuse (422)",
    )

    exit_on_load_failure: bool = Field(
        default=False,
        description="stop the process (non-zero exit) when the checkpoint can never load; `nemsim serve` "
        "turns this on",
    )
    sim_workers: int = Field(default=1, ge=1, le=64, description="simulator jobs run at the same time")
    sim_queue: int = Field(
        default=4, ge=0, le=1_000,
        description="simulator jobs waiting for a worker; more get 503 + Retry-After",
    )
    sim_max_work: float = Field(
        default=20.0, gt=0, description="largest simulator job accepted, in runs of the design centre "
        "(simulated particles scale with the total flux and the steps; 422 beyond it)",
    )
    jobs_keep_s: float = Field(default=3_600.0, gt=0, description="finished jobs are forgotten after this")
    jobs_keep_max: int = Field(
        default=16, ge=1, le=10_000, description="finished jobs kept (oldest forgotten first)"
    )
    jobs_per_client: int = Field(
        default=1, ge=1, le=1_000,
        description="jobs one client (API key, else address) may have running or waiting; more get 429 + "
        "Retry-After",
    )
    jobs_dir: Path | None = Field(
        default=None,
        description="where simulator and design jobs keep their files (a nemsim-job-* folder per child "
        "process, removed when it ends; the folders of a server that died are removed at start-up); default: "
        "the system temp dir",
    )

    @field_validator("trusted_proxies")
    @classmethod
    def _networks(cls, value: str) -> str:
        parse_networks(value)
        return value

    @field_validator("checkpoint", "scene", "jobs_dir", mode="before")
    @classmethod
    def _empty_is_unset(cls, value: object) -> object:
        return None if isinstance(value, str) and not value.strip() else value

    @field_validator("checkpoint")
    @classmethod
    def _expand(cls, value: Path | None) -> Path | None:
        return value.expanduser() if value is not None else None

    def trusted_proxy_networks(self) -> tuple[IPNetwork, ...]:
        return parse_networks(self.trusted_proxies)

    def allowed_host_names(self) -> frozenset[str]:
        """`allowed_hosts` lower-cased, without ports and trailing dots."""
        names = (host_name(h) for h in self.allowed_hosts.split(","))
        return frozenset(n for n in names if n)

    def api_key_set(self) -> frozenset[str]:
        """The configured API keys (env and file); ValueError naming the source of a key too short."""
        keys = [(k.strip(), "NEMSIM_API_KEYS") for k in self.api_keys.get_secret_value().split(",")]
        if self.api_keys_file is not None:
            try:
                lines = self.api_keys_file.read_text().splitlines()
            except OSError as exc:
                raise ValueError(f"NEMSIM_API_KEYS_FILE cannot be read ({exc.strerror})") from None
            keys += [(line.split("#", 1)[0].strip(), "NEMSIM_API_KEYS_FILE") for line in lines]
        out = set()
        for key, source in keys:
            if not key:
                continue
            if len(key) < MIN_KEY_CHARS:
                raise ValueError(
                    f"{source} holds a key of {len(key)} characters; use at least {MIN_KEY_CHARS}"
                )
            out.add(key)
        return frozenset(out)

    def resolved_checkpoint(self) -> Path:
        """The checkpoint to load: the explicit one, else `nemsim-<scene>.pt` (`default_checkpoint`)."""
        if self.checkpoint is not None:
            return self.checkpoint
        return default_checkpoint(self.scene or DEFAULT_SCENE)

    def expected_scene(self) -> str | None:
        """The scene the loaded model must be of: the configured one, else the default scene when the
        checkpoint is the default file (also when named explicitly, as `nemsim serve` passes it on), else
        None (any: the operator named another file)."""
        if self.scene is not None:
            return self.scene
        if self.checkpoint is None or self.checkpoint.resolve() == default_checkpoint().resolve():
            return DEFAULT_SCENE
        return None


def accepted_form(name: str) -> str:
    """What the setting `name` (a `Settings` field) accepts, in words: "an integer in 1..10000", "true or
    false", "one of 'allow', 'clip', 'refuse'"."""
    field = Settings.model_fields[name]
    kind = field.annotation
    if isinstance(kind, types.UnionType):  # `X | None`: what X accepts
        kind = next(a for a in typing.get_args(kind) if a is not type(None))
    if typing.get_origin(kind) is Literal:
        return "one of " + ", ".join(repr(v) for v in typing.get_args(kind))
    if kind is bool:
        return "true or false (also 1/0, yes/no, on/off)"
    bounds = {k: getattr(m, k) for m in field.metadata for k in ("ge", "gt", "le") if hasattr(m, k)}
    if kind in (int, float):
        what = "an integer" if kind is int else "a number"
        if "ge" in bounds and "le" in bounds:
            return f"{what} in {bounds['ge']}..{bounds['le']}"
        signs = {"ge": ">=", "gt": ">", "le": "<="}
        return " ".join([what, *(f"{signs[k]} {v}" for k, v in bounds.items())])
    pattern = next((m.pattern for m in field.metadata if getattr(m, "pattern", None)), None)
    return f"text matching {pattern}" if pattern else "text"


def invalid_settings(exc: ValidationError) -> str:
    """One line naming every bad `NEMSIM_*` value of a failed `Settings()`, its value and what is accepted:
    ``NEMSIM_MAX_STEPS='abc': expected an integer in 1..10000; NEMSIM_DOCS='maybe': expected true or
    false (also 1/0, yes/no, on/off)``. A secret (the API keys) is never echoed."""
    order = list(Settings.model_fields)
    parts = []
    for err in sorted(exc.errors(), key=lambda e: order.index(str(e["loc"][0])) if e["loc"] else -1):
        name = str(err["loc"][0]) if err["loc"] else ""
        if name not in Settings.model_fields:  # not a field's value: the model's own rule
            parts.append(str(err["msg"]))
            continue
        value = "<hidden>" if Settings.model_fields[name].annotation is SecretStr else repr(err["input"])
        why = str(err["ctx"]["error"]) if err["type"] == "value_error" else f"expected {accepted_form(name)}"
        parts.append(f"NEMSIM_{name.upper()}={value}: {why}")
    return "; ".join(parts)


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings (read from the environment once)."""
    return Settings()

"""`nemsim serve`: the HTTP service as a command of the `nemsim` CLI (entry point ``nemsim.cli``: serve).

``register`` adds the parser; the service's modules (FastAPI, uvicorn) are imported only when the command
runs, so `nemsim --help` and every other command work without them.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from nemsim.cli.common import Subparsers, UserError

SERVICE_EXTRA = "pip install 'nemsim[service]'"  # what `nemsim serve` needs beyond the library


def register(sub: Subparsers) -> None:
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
    p.add_argument("--device", choices=("cpu", "cuda"), default=None,
                   help="where rollouts compute: cpu (the OpenVINO runtime; default) or cuda (CUDA graphs: "
                        "a whole constant-control rollout is one replay; without CUDA it falls back to the "
                        "CPU, logged); the same as NEMSIM_RUNTIME_BACKEND=openvino|cuda")
    p.set_defaults(handler=_cmd_serve)


def resolve_checkpoint(arg: str | None) -> str:
    """The checkpoint to serve: --checkpoint, else $NEMSIM_CHECKPOINT, else the settings' default."""
    from service.config import Settings

    path = Path(arg).expanduser() if arg else Settings().resolved_checkpoint()
    if path is None:
        raise UserError("no checkpoint: pass --checkpoint, set NEMSIM_CHECKPOINT or add checkpoints/*.pt")
    if not path.is_file():
        raise UserError(f"checkpoint {path} does not exist")
    return str(path.resolve())


def _cmd_serve(args: argparse.Namespace) -> int:
    try:  # the service's own dependencies, beyond the library's
        import fastapi  # noqa: F401
        import pydantic_settings  # noqa: F401
        import uvicorn
    except ImportError as exc:
        raise UserError(f"`nemsim serve` needs the service's packages ({exc}): {SERVICE_EXTRA}") from None
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
    os.environ["NEMSIM_CHECKPOINT"] = resolve_checkpoint(args.checkpoint)
    if args.device is not None:
        os.environ["NEMSIM_RUNTIME_BACKEND"] = "cuda" if args.device == "cuda" else "openvino"
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
    from service.main import checkpoint_problem

    problem = checkpoint_problem(settings)  # fail before binding: exit 3 like a failed load
    if problem is not None:
        print(f"nemsim serve: {problem}", file=sys.stderr)  # noqa: T201
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

"""`nemsim serve`: the HTTP service as a command of the `nemsim` CLI (entry point ``nemsim.cli``: serve).

``register`` adds the parser; the service's modules (FastAPI, uvicorn) are imported only when the command
runs, so `nemsim --help` and every other command work without them.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from nemsim.cli.common import EXIT_BUG, Subparsers, UserError

if TYPE_CHECKING:
    import uvicorn

    from service.config import Settings

SERVICE_EXTRA = "pip install 'nemsim[service]'"  # what `nemsim serve` needs beyond the library
EXIT_MODEL = 3  # the checkpoint cannot be served (unreadable, damaged, incompatible, of another scene)
EXIT_BIND = 4  # the address cannot be bound (in use, not this machine's, not permitted)
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)  # a clean stop: in-flight requests drained, exit 0


def register(sub: Subparsers) -> None:
    p = sub.add_parser(
        "serve",
        help="serve a checkpoint over HTTP (FastAPI; OpenAPI docs at /docs)",
        description=(
            "Serve a trained checkpoint with uvicorn: POST /rollout (controls -> trajectory metrics and "
            "surface meshes), GET /mechanisms, /health, /ready and /model; interactive OpenAPI docs at "
            "/docs. Runs until SIGTERM or SIGINT; writes nothing. Other settings come from NEMSIM_* "
            "environment variables. Exit codes: 0 stopped cleanly (requests in flight answered), 2 a bad "
            "option or setting (one line naming each, its value and what is accepted) or no checkpoint "
            f"file, {EXIT_MODEL} the checkpoint cannot be served, {EXIT_BIND} the address cannot be bound. "
            "Example: nemsim serve --checkpoint runs/nemsim/best.pt --port 8000"
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


def resolve_checkpoint(arg: str | None, settings: Settings | None = None) -> str:
    """The checkpoint to serve: --checkpoint, else $NEMSIM_CHECKPOINT, else the default of `settings` (of
    the environment when not given); a UserError when that path names no file (missing, or a directory:
    then naming the .pt files in it)."""
    path = Path(arg).expanduser() if arg else (settings or read_settings()).resolved_checkpoint()
    if path.is_dir():
        found = sorted(p.name for p in path.glob("*.pt"))[:3]
        hint = f" (it holds {', '.join(found)})" if found else " (it holds no .pt file)"
        raise UserError(f"checkpoint {path} is a directory: name a .pt file{hint}")
    if not path.is_file():
        raise UserError(f"checkpoint {path} does not exist")
    return str(path.resolve())


def read_settings() -> Settings:
    """The settings from the NEMSIM_* environment; a UserError naming every bad value in one line."""
    from pydantic import ValidationError

    from service.config import get_settings, invalid_settings

    get_settings.cache_clear()
    try:
        settings = get_settings()
        settings.api_key_set()
    except ValidationError as exc:
        raise UserError(f"invalid settings: {invalid_settings(exc)}") from None
    except ValueError as exc:  # an API key too short, or a key file that cannot be read
        raise UserError(f"invalid settings: {exc}") from None
    return settings


def bind(host: str, port: int) -> socket.socket:
    """A TCP socket bound to host:port (IPv6 for an address with a colon), before anything loads, so an
    address that cannot be served ends the command at once; OSError naming what to change otherwise."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise OSError(
            f"cannot bind {host}:{port} ({exc.strerror or exc}): --host / NEMSIM_HOST takes an address of "
            "this machine (127.0.0.1, 0.0.0.0, ::) and --port / NEMSIM_PORT a port no other process uses"
        ) from None
    return sock


def run_server(config: uvicorn.Config, sock: socket.socket) -> bool:
    """Serve on `sock` until SIGTERM or SIGINT (in-flight requests drained); whether the server started.

    uvicorn hands a signal that stopped it back to the handler it found, which would end the process by
    that signal (exit 143 for SIGTERM): the handler it finds does nothing instead, so a clean stop exits 0."""
    import uvicorn

    previous = {sig: signal.signal(sig, lambda *_: None) for sig in STOP_SIGNALS}
    try:
        if config.workers > 1:
            from uvicorn.supervisors import Multiprocess

            Multiprocess(config, sockets=[sock]).run()
            return True
        server = uvicorn.Server(config)
        try:
            server.run(sockets=[sock])
        except SystemExit:  # uvicorn's own exit when the app's start-up failed (reason logged)
            return False
        return server.started
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _stop(code: int, message: str) -> int:
    print(f"nemsim serve: {message}", file=sys.stderr)  # noqa: T201 -- the command's one line, as UserError's
    return code


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
    # bad settings are named before the checkpoint is looked for; every worker process builds its app from
    # the environment, so the choice travels there
    os.environ["NEMSIM_CHECKPOINT"] = resolve_checkpoint(args.checkpoint, read_settings())
    if args.device is not None:
        os.environ["NEMSIM_RUNTIME_BACKEND"] = "cuda" if args.device == "cuda" else "openvino"
    os.environ.setdefault("NEMSIM_EXIT_ON_LOAD_FAILURE", "1")  # a checkpoint that can never load: exit 3
    settings = read_settings()
    from service.main import LOAD_FAILURE_EXIT, checkpoint_problem, loading
    from service.protocol import uvicorn_options

    problem = checkpoint_problem(settings)  # fail before binding, since every worker would fail the same way
    if problem is not None:
        return _stop(EXIT_MODEL, problem)
    try:
        sock = bind(args.host, args.port)
    except OSError as exc:
        return _stop(EXIT_BIND, str(exc))
    from service.access import bind_warning

    log = logging.getLogger("nemsim.serve")
    warning = bind_warning(args.host, settings.api_key_set(), settings.allow_remote_without_key)
    if warning:
        log.warning(warning)
    config = uvicorn.Config(
        "service.main:create_app", factory=True, host=args.host, port=args.port, workers=args.workers,
        log_level="info", **uvicorn_options(settings, bind_settings=args.workers == 1),
    )
    log.info("serving on http://%s:%d (docs at /docs)", f"[{args.host}]" if ":" in args.host else args.host,
             args.port)
    started = run_server(config, sock)
    if LOAD_FAILURE_EXIT["failed"]:
        code = _stop(EXIT_MODEL, "the checkpoint can never load (reason above); stopped")
    elif not started:
        code = _stop(EXIT_BUG, "the server could not start (reason above)")
    else:
        code = 0
    if loading():  # the runtime's native threads abort an interpreter that shuts down under them
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code

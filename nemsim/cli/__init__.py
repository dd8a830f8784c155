"""The `nemsim` command line: one argparse parser, one module per command group.

Command groups: ``rules``; ``data`` (design, splits, data check|stats); ``sim`` (generate); ``train``;
``evaluate`` (evaluate, models, counterfactual); ``analysis`` (sensitivity, inverse, calibrate); ``learn``
(active learning: propose, measure, run). Commands
implemented outside the library are plugins: each entry point of the group ``nemsim.cli`` (pyproject.toml:
`serve` from ``service.cli``, `bench ...` and `stress` from ``bench.cli``) is a ``register(subparsers)``
that adds its parsers, so the library never imports those packages. Each module's handlers parse their
flags and call one library function; heavy imports (torch, numba, h5py) happen inside the handlers so
`nemsim --help` stays instant. Handlers return a process exit code: 0 success, 1 `stress` found a failing
case, 2 bad input or failed check.

Errors have one boundary, ``main()``: handlers raise, they do not print. ``_error_report`` sorts what
reaches it into
  * bad input or a damaged file (exit 2, one line on stderr): ``UserError``; ``ValueError``, the library's
    kind for bad input (``TrainInputError``, ``CheckpointMismatch``, ``RulesError`` derive from it);
    ``OSError`` (missing, unwritable, locked or truncated files, h5py's errors); a YAML syntax error (with
    its line); and anything raised while h5py or ``torch.load`` read a file (a damaged ``.h5`` or ``.pt``);
  * a bug (exit 1): one line naming the exception and the hint to rerun with ``--debug``, which re-raises
    so the traceback shows.
Handlers still turn a library error into a ``UserError`` where they can say more (which option, what to do).
Output paths the user names get their missing parent directories created (``common.output_path``).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import typing
from collections.abc import Sequence
from pathlib import Path

from nemsim.cli import analysis, data, evaluate, learn, rules, sim, train
from nemsim.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_BROKEN_PIPE,
    EXIT_BUG,
    EXIT_INTERRUPTED,
    Handler,
    Subparsers,
    UserError,
)

__all__ = ["EXIT_BAD_INPUT", "EXIT_BUG", "UserError", "build_parser", "entry", "main"]

PLUGIN_GROUP = "nemsim.cli"  # entry points: NAME = "module:register"
COMMAND_GROUPS = (rules, data, sim, train, evaluate, analysis, learn)
INSTALL_HINTS = {"serve": "pip install 'nemsim[service]'"}  # what a plugin that fails to import needs


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("nemsim")
    except PackageNotFoundError:  # run from a source tree that is not installed
        from nemsim import __version__

        return __version__


def _version_text() -> str:
    """The version, and the runtime a served model rolls out on here by default: OpenVINO when installed,
    at the precision this CPU computes fastest in (``nemsim.inference.precision``)."""
    from importlib.util import find_spec

    from nemsim.inference.precision import machine

    m = machine()
    backend = "openvino" if find_spec("openvino") is not None else "torch"
    flags = ", ".join(m["bf16_flags"]) or "no bf16 arithmetic"
    return (f"nemsim {_version()}\nserved runtime {backend}-{m['default_precision']} on {m['cpu']} ({flags}; "
            "NEMSIM_RUNTIME_PRECISION=f32|bf16 overrides)")


class _VersionAction(argparse.Action):
    """``--version``: composed only when asked (it reads /proc/cpuinfo), printed to stdout, exit 0."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS,
                 default: str = argparse.SUPPRESS, help: str | None = None) -> None:
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object,
                 option_string: str | None = None) -> None:
        print(_version_text())  # noqa: T201
        parser.exit()


def _unavailable(name: str, exc: BaseException) -> Handler:
    """The handler of a plugin command whose module failed to import: says what to install."""

    def handler(args: argparse.Namespace) -> int:
        hint = INSTALL_HINTS.get(name, "pip install -e '.[service,test]' in the source tree")
        raise UserError(f"`nemsim {name}` is not available ({type(exc).__name__}: {_first_line(exc)}); "
                        f"install it: {hint}")

    return handler


def _add_plugins(sub: Subparsers) -> None:
    """Every ``nemsim.cli`` entry point's commands, by entry-point name; a plugin that fails to import
    becomes a command that says what to install, and the rest of the CLI works."""
    from importlib.metadata import entry_points

    for ep in sorted(entry_points(group=PLUGIN_GROUP), key=lambda e: e.name):
        try:
            register = ep.load()
        except Exception as exc:  # noqa: BLE001 -- a broken plugin must not take the other commands down
            if ep.name not in sub.choices:
                p = sub.add_parser(ep.name, help=f"(not available: {type(exc).__name__}; `nemsim {ep.name}` "
                                                 "says what to install)", add_help=False)
                p.set_defaults(handler=_unavailable(ep.name, exc), any_arguments=True)
            continue
        register(sub)


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
    parser.add_argument("--version", action=_VersionAction,
                        help="print the version and the default rollout runtime on this CPU, and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for group in COMMAND_GROUPS:
        group.register(sub)
    _add_plugins(sub)
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
             if k in ("data", "file", "out", "checkpoint", "path", "config", "recipe", "design", "controls",
                      "spec") and v is not None
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
    unpickling = (EOFError, pickle.UnpicklingError, zipfile.BadZipFile)
    if isinstance(exc, unpickling) or (
        isinstance(exc, RuntimeError) and _raised_in(exc, "torch", "serialization.py")
    ):
        name = _named_file(args, (".pt", ".pth"))
        what = f"{type(exc).__name__}: {_first_line(exc).split('. ')[0]}"
        where = f"{name}: " if name else ""
        return EXIT_BAD_INPUT, f"{where}not a readable checkpoint, damaged or truncated ({what})"
    cause = exc.__cause__
    if isinstance(exc, ValueError) and cause is not None and (
        isinstance(cause, unpickling) or _raised_in(cause, "torch")
    ):  # the checkpoint loader's message about a file torch could not read, which names it by its base name
        name = _named_file(args, (".pt", ".pth"))
        return EXIT_BAD_INPUT, f"{name + ': ' if name else ''}not a readable checkpoint: {_first_line(exc)}"
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
    if isinstance(exc, UnicodeDecodeError):  # a text file (CSV, JSON, YAML) that is not UTF-8 text
        name = _named_file(args, (".csv", ".json", ".yaml", ".yml", ".txt"))
        where = f"{name}: " if name else ""
        return EXIT_BAD_INPUT, f"{where}not UTF-8 text ({exc.reason} at byte {exc.start})"
    if isinstance(exc, ValueError):
        return EXIT_BAD_INPUT, _first_line(exc)
    return EXIT_BUG, (f"unexpected error {type(exc).__name__}: {_first_line(exc)} (a bug; rerun with --debug "
                      "for the traceback)")


def _command_name(args: argparse.Namespace) -> str:
    """``nemsim COMMAND [ACTION]`` of a parsed command line, e.g. ``nemsim data check``."""
    actions = ("rules_command", "data_command", "learn_command", "bench")
    words = [args.command] + [getattr(args, k) for k in actions if getattr(args, k, None)]
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
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and not getattr(args, "any_arguments", False):  # only an unavailable plugin takes any
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
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
    """The `nemsim` console script: ``main()`` in a process with the tuned allocator
    (``nemsim.cli.allocator``: re-executes once with its environment when it is not set yet)."""
    from nemsim.cli.allocator import reexec_tuned

    reexec_tuned()
    return exit_process(main())


def exit_process(code: int) -> int:
    """End a command's process with ``code``. An interrupted one (Ctrl-C, SIGTERM) has closed its files on
    the way out already, so it exits without the interpreter's shutdown, which joins every worker pool's
    manager thread and can wait forever on one whose workers were just terminated (``concurrent.futures``
    feeding a queue that no process reads any more)."""
    if code == EXIT_INTERRUPTED:
        import os

        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        logging.shutdown()
        os._exit(code)
    return code

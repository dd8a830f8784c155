"""The `nemsim` command line: one argparse parser, one subcommand per job.

Each subcommand parses its flags and calls one library function; heavy imports (torch, numba, h5py)
happen inside the handlers so `nemsim --help` stays instant. Handlers return a process exit code:
0 success, 2 bad input or failed check (with one readable line on stderr).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence

Handler = Callable[[argparse.Namespace], int]


class UserError(Exception):
    """Bad input from the command line: printed as one line, exit code 2."""


# ------------------------------------------------------------------------------------------------
# Each _add_* function registers one group of subcommands. Keep handlers thin: parse, call the
# library, print a short report.
# ------------------------------------------------------------------------------------------------

# ==== section: rules (owner: rules) =============================================================


def _add_rules(sub: argparse._SubParsersAction) -> None:
    pass


# ==== section: controls, design, splits, data (owner: data) ====================================


def _add_data(sub: argparse._SubParsersAction) -> None:
    pass


# ==== section: simulator: generate, sensitivity, bench sim/noise (owner: sim) ===================


def _add_sim(sub: argparse._SubParsersAction) -> None:
    pass


# ==== section: models, train, evaluate, counterfactual (owner: model) ==========================


def _add_model(sub: argparse._SubParsersAction) -> None:
    pass


# ==== section: serve (owner: service) ==========================================================


def _add_service(sub: argparse._SubParsersAction) -> None:
    pass


# ------------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nemsim",
        description=(
            "NEMSim: Event Rules Library, Monte Carlo etch simulator, neural surrogate and service. "
            "Run `nemsim COMMAND --help` for each command."
        ),
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in (_add_rules, _add_data, _add_sim, _add_model, _add_service):
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    handler: Handler = args.handler
    try:
        return int(handler(args) or 0)
    except UserError as exc:
        print(f"nemsim {args.command}: {exc}", file=sys.stderr)  # noqa: T201
        return 2
    except KeyboardInterrupt:
        print("interrupted; rerun the same command to resume where supported", file=sys.stderr)  # noqa: T201
        return 130


if __name__ == "__main__":
    sys.exit(main())

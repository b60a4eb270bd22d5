"""Entry point of the ``wara`` command.

Each verb lives in its own module under :mod:`wara.commands` (one module per verb, as
cantools does) exposing ``register(subparsers)``; adding a verb is one line in
:data:`COMMANDS`. A run imports only its verb's module (``wara ctl`` does not load the
simulator); ``wara``, ``wara --help`` or an unknown verb import them all. Exit codes: 0
success, 1 the job ran but did not meet its goal, 2 bad arguments or configuration, 3
unreachable target, 141 the reader of the output went away (as a shell reports SIGPIPE).
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
from collections.abc import Sequence
from typing import Any

from config import ConfigError
from config.numbers import NEGATIVE_NUMBER

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INFEASIBLE = 3
EXIT_BROKEN_PIPE = 128 + 13  # SIGPIPE

#: Modules under wara.commands, in the order ``wara --help`` lists them; each registers
#: the verb of its name (without a ``_cmd`` suffix, which keeps ``config_cmd`` apart from
#: the ``config`` package).
COMMANDS: tuple[str, ...] = (
    "plan",
    "config_cmd",
    "can",
    "sim",
    "bench",
    "acceptance",
    "ctl",
    "serve",
    "demo",
    "soak",
    "hil",
    "walk",
    "place",
    "cycle",
    "survey",
    "opcua",
    "campaign",
    "commission",
)


class UsageError(Exception):
    """Arguments that parse but make no sense (e.g. four start extensions expected).
    One problem per line of the message (each line printed as its own error line)."""


class _Parser(argparse.ArgumentParser):
    """The parser of ``wara`` and of every verb under it (subparsers take its class).

    ``-1e9`` is a value, not an option: argparse's own test of a negative number knows
    no exponent (``--distance-mm -1e9`` was "expected one argument"); this one is the
    full decimal spelling of :mod:`config.numbers`."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NEGATIVE_NUMBER

    def error(self, message: str) -> None:  # type: ignore[override]
        # One line, exit 2: what argparse does, minus the usage block.
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def check_walk_steps(steps: int) -> None:
    """``--steps`` of a walk: 1..MAX_WALK_STEPS, the control channel's limit."""
    from ipc_app.service.requests import MAX_WALK_STEPS

    if not 1 <= steps <= MAX_WALK_STEPS:
        raise UsageError(f"--steps must be within 1..{MAX_WALK_STEPS}, got {steps}")


def stop_on_sigterm() -> None:
    """SIGTERM as Ctrl-C, for a command with processes of its own (a campaign's cluster,
    the child runs of ``wara commission``): they are shut down on the way out."""

    def _raise(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _raise)


def verb_of(module: str) -> str:
    return module.removesuffix("_cmd")


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The parser for ``argv``: with only its verb's module imported when ``argv`` starts
    with a known verb, else with every verb (for ``--help`` and the list of choices)."""
    wanted = tuple(m for m in COMMANDS if argv and verb_of(m) == argv[0]) or COMMANDS
    parser = _Parser(
        prog="wara",
        description="W-ARa attitude adjustment: planning, control, CAN bridge and HIL simulator.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in wanted:
        module = importlib.import_module(f"wara.commands.{name}")
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    try:
        code = args.func(args)
        sys.stdout.flush()  # here, so a reader that went away is seen below
    except BrokenPipeError:  # the reader of our output went away (`wara ... | head`)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # the interpreter's last flush goes nowhere
        return EXIT_BROKEN_PIPE
    except ConfigError as exc:
        for line in str(exc).splitlines():  # one line per problem, each self-contained
            print(f"wara: configuration error: {line}", file=sys.stderr)
        return EXIT_USAGE
    except UsageError as exc:
        for line in str(exc).splitlines() or [""]:
            print(f"wara {args.command}: error: {line}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("wara: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

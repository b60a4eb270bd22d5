"""The ``wara`` verbs: one line each in ``wara.cli.COMMANDS``; a run imports only its own."""

from __future__ import annotations

import argparse
import importlib
import re
import subprocess
import sys

import pytest

from wara import cli


def _verbs(parser: argparse.ArgumentParser) -> list[str]:
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return list(sub.choices)


def test_each_module_registers_the_verb_of_its_name() -> None:
    for module in cli.COMMANDS:
        parser = argparse.ArgumentParser()
        sub = parser.add_subparsers()
        importlib.import_module(f"wara.commands.{module}").register(sub)
        assert list(sub.choices) == [cli.verb_of(module)], module


@pytest.mark.parametrize("argv", [[], ["--help"], ["no-such-verb"]])
def test_without_a_known_verb_every_verb_is_there(argv: list[str]) -> None:
    assert _verbs(cli.build_parser(argv)) == [cli.verb_of(m) for m in cli.COMMANDS]


def test_a_known_verb_gets_only_its_own_parser() -> None:
    assert _verbs(cli.build_parser(["config", "validate"])) == ["config"]
    assert _verbs(cli.build_parser(["walk", "plan"])) == ["walk"]


def _imported_by(*argv: str) -> set[str]:
    probe = (
        "import sys; from wara.cli import build_parser; "
        f"build_parser({list(argv)!r}); print(' '.join(sys.modules))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True
    )
    return set(proc.stdout.split())


def test_a_verb_imports_only_its_own_module() -> None:
    ctl = _imported_by("ctl", "status")
    assert "wara.commands.ctl" in ctl
    assert not {m for m in ctl if m.startswith("wara.commands.") and m != "wara.commands.ctl"}
    assert not {"hil_sim", "matplotlib", "numba", "scipy"} & ctl
    everything = _imported_by("--help")
    assert {f"wara.commands.{m}" for m in cli.COMMANDS} <= everything


def test_help_lists_every_verb() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "wara", "--help"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    for module in cli.COMMANDS:
        assert re.search(rf"^\s+{cli.verb_of(module)}\s", proc.stdout, re.M), proc.stdout


def test_a_reader_that_goes_away_ends_the_command_quietly() -> None:
    """`wara plan ... --json | head -c 1`: the pipe closed before the output is written
    ends the command with 141 (SIGPIPE's code), no traceback on stderr."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "wara", "plan", "--roll-deg", "2", "--pitch-deg", "1", "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # before the interpreter has started: the write finds no reader
    err = proc.stderr.read()
    assert proc.wait(timeout=120) == 141, err
    assert "Traceback" not in err and "BrokenPipeError" not in err, err

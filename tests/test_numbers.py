"""Numbers and names as people type them (config.numbers, docs/hostile-input.md): ASCII
digits in one spelling on every command line, names without control or bidi characters
in the audit trail."""

from __future__ import annotations

import argparse
import contextlib
import io
import json

import pytest

from config.numbers import (
    check_name,
    is_wara_type,
    parse_decimal,
    parse_decimals,
    parse_integer,
)
from ipc_app.service import ctl
from wara.cli import build_parser, main


def run_main(args: list[str]) -> tuple[int, str, str]:
    """``(exit code, stdout, stderr)`` of ``wara ARGS`` in this process, argparse's exit
    (SystemExit) included."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(args)
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


NOT_INTEGERS = ["4_0", "\u0664", "\u0661", "1_000", "4.0", "0x10", " ", "", "+", "4 0", "1e3"]
NOT_DECIMALS = ["1_0", "\u0664", "inf", "-Infinity", "nan", "1e999", "1,5", "0x1p3", "", "."]
HOSTILE_NAMES = [
    "",
    "   ",
    "x" * 10_000,
    "op\x1b[31mred",
    "op\r\nforged: entry",
    "op\x00",
    "op\u202eevil",
    "op\u200bzero",
    " padded",
]


@pytest.mark.parametrize("text", NOT_INTEGERS)
def test_an_integer_is_ascii_digits_in_one_spelling(text: str) -> None:
    with pytest.raises(ValueError, match="not an integer"):
        parse_integer(text)


@pytest.mark.parametrize("text", NOT_DECIMALS)
def test_a_decimal_is_ascii_finite_and_in_one_spelling(text: str) -> None:
    with pytest.raises(ValueError, match=r"not a (finite )?number"):
        parse_decimal(text)


def test_the_spellings_people_use_are_read() -> None:
    assert parse_integer("40") == 40 and parse_integer("-3") == -3 and parse_integer("+7") == 7
    assert parse_decimal("-1e9") == -1e9 and parse_decimal(".5") == 0.5
    assert parse_decimal("8.") == 8.0 and parse_decimal("2.5E-3") == 0.0025
    assert parse_decimals("6, -6,0,0,0.03", 5) == (6.0, -6.0, 0.0, 0.0, 0.03)
    with pytest.raises(ValueError, match=r"value 1 .* not a number"):
        parse_decimals("1_0,0,0,0,0", 5)
    with pytest.raises(ValueError, match="expected 5"):
        parse_decimals("1,2", 5)


@pytest.mark.parametrize("bad", HOSTILE_NAMES)
def test_a_name_for_the_audit_trail_refuses_control_bidi_and_size(bad: str) -> None:
    with pytest.raises(ValueError):
        check_name(bad, "user")


def test_plain_names_pass() -> None:
    for good in ("Zhang Wei", "op-3", "müller", "张伟"):
        assert check_name(good) == good


def _actions(parser: argparse.ArgumentParser, path: str) -> list[tuple[str, argparse.Action]]:
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for verb, sub in action.choices.items():
                out.extend(_actions(sub, f"{path} {verb}"))
        else:
            out.append((path, action))
    return out


def test_every_numeric_option_of_every_command_uses_the_one_number_syntax() -> None:
    """A new option with ``type=int`` or ``type=float`` (which take ``4_0`` and ``٤``), or
    a numeric default without a checked type, fails here."""
    actions = _actions(build_parser(), "wara")
    assert len(actions) > 100  # the walk went into the verbs
    wrong = []
    for path, a in actions:
        numeric_default = isinstance(a.default, int | float) and not isinstance(a.default, bool)
        if a.type in (int, float) or (numeric_default and not is_wara_type(a.type)):
            wrong.append(f"{path} {'/'.join(a.option_strings) or a.dest}")
    assert not wrong, f"options parsed with int()/float(): {wrong}"


@pytest.mark.parametrize(
    "args",
    [
        ["place", "plan", "--ring", "4_0"],
        ["place", "plan", "--ring", "\u0664"],
        ["place", "plan", "--previous-deviation", "1_0,0,0,0,0"],
        ["plan", "--roll-deg", "\u0661", "--pitch-deg", "0"],
        ["plan", "--roll-deg", "0", "--pitch-deg", "0", "--start-upper-mm", "1_0,0,0,0"],
        ["ctl", "walk", "--steps", "\u0661"],
        ["ctl", "place", "--ring", "4_0"],
        ["ctl", "cycle", "--ring", "5", "--previous-deviation", "0,0,0,0,\u0664"],
        ["can", "busload", "--active", "0,1_0"],
        ["cycle", "--rings", "1_0"],
        ["ctl", "confirm-fixed", "--user", "op\x1b[2Jx"],
        ["ctl", "confirm-fixed", "--user", ""],
        ["ctl", "confirm-fixed", "--user", "u" * 10_000],
        ["ctl", "confirm-fixed", "--user", "op\u202eevil"],
        ["ctl", "jog", "--cylinder", "leg\r\n1", "--distance-mm", "1"],
    ],
)
def test_hostile_numbers_and_names_on_the_command_line_exit_2_in_one_line(
    args: list[str],
) -> None:
    code, out, err = run_main(args)
    assert code == 2, (args, code, err)
    assert out == "" and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and "\x1b" not in err and "\u202e" not in err


def test_a_negative_exponent_value_needs_no_equals_sign(tmp_path) -> None:
    """``--distance-mm -1e9`` is a value: the parse passes and the request reaches the
    (absent) service, which answers with its own reason, not argparse's "expected one
    argument"."""
    sock = tmp_path / "no.sock"
    code, _, err = run_main(
        ["ctl", "jog", "--socket", str(sock), "--cylinder", "main_leg_1", "--distance-mm", "-1e9"]
    )
    assert "expected one argument" not in err
    assert code == 2 and "no W-ARa service listening" in err, err


@pytest.mark.parametrize("user", HOSTILE_NAMES)
def test_the_service_refuses_such_a_user_in_a_request(user: str) -> None:
    for req in (
        {"cmd": "confirm_fixed", "user": user},
        {"cmd": "audit", "user": user, "action": "x", "result": "ok"},
    ):
        reply = ctl.parse(json.dumps(req).encode())
        assert isinstance(reply, dict) and reply["code"] == "bad_request", reply
    reply = ctl.parse(
        json.dumps({"cmd": "audit", "user": "op", "action": "x", "result": "a\x1b[2Jb"}).encode()
    )
    assert isinstance(reply, dict) and reply["code"] == "bad_request"

"""Numbers and names as people type them: on a command line, in a survey sheet, in a
control request. One spelling each, ASCII only.

Python's ``int()`` and ``float()`` take more than a person means: ``int("4_0")`` is 40,
``int("٤")`` (an Arabic-Indic digit) is 4, ``float("1_0")`` is 10.0, ``float("inf")`` is
infinite. Here:

* an integer is :data:`INTEGER_SYNTAX`, ``[+-]?[0-9]+`` (at most
  :data:`MAX_INTEGER_DIGITS` digits);
* a decimal is :data:`DECIMAL_SYNTAX`,
  ``[+-]?([0-9]+(.[0-9]*)?|.[0-9]+)([eE][+-]?[0-9]{1,3})?``, and finite (``1e999`` is
  refused, not infinity);
* a name (a user, a cylinder id, a survey point) is 1..:data:`MAX_NAME_CHARS`
  characters, none of them a control, format, surrogate, private-use, unassigned or
  line/paragraph separator character (Unicode categories Cc, Cf, Cs, Co, Cn, Zl, Zp:
  ESC, CR, LF, NUL, the right-to-left override), not blank and without spaces at either
  end: it goes into the audit trail and the records as it is.

:func:`parse_integer`, :func:`parse_decimal`, :func:`check_name` and :func:`check_text`
raise ValueError with
a one-line reason; :func:`integer`, :func:`decimal`, :func:`decimals`, :func:`integers`
and :func:`name` are the argparse types of the ``wara`` command built on them (every
numeric option uses one; a test walks the whole parser). :data:`NEGATIVE_NUMBER` is what
the parser takes for a negative number rather than an option (``-1e9`` included).
"""

from __future__ import annotations

import argparse
import math
import re
import unicodedata
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")
F = TypeVar("F", bound=Callable[..., Any])

#: An integer as a person writes it: ASCII digits, an optional sign.
INTEGER_SYNTAX = re.compile(r"[+-]?[0-9]+")
#: A decimal as a person writes it: ASCII digits, optional sign, point and exponent.
DECIMAL_SYNTAX = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]{1,3})?")
#: A negative decimal: a value, not an option, on a command line (``-3``, ``-.5``, ``-1e9``).
NEGATIVE_NUMBER = re.compile(r"^-(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]{1,3})?$")
#: The most digits an integer may have (no count, ring or seed of ours comes close).
MAX_INTEGER_DIGITS = 18
#: The longest name (user, operator, cylinder id, survey point).
MAX_NAME_CHARS = 64
#: Unicode categories no name may contain: control, format (bidi overrides, zero-width
#: characters), surrogate, private use, unassigned, line and paragraph separator.
REFUSED_CATEGORIES = frozenset({"Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"})


def shown(text: str) -> str:
    """``text`` for a one-line message: its repr (control characters escaped), cut."""
    return repr(text) if len(text) <= 40 else repr(text[:37]) + f"... ({len(text)} characters)"


def parse_integer(text: str) -> int:
    """``text`` in :data:`INTEGER_SYNTAX` as an int; ValueError otherwise."""
    if INTEGER_SYNTAX.fullmatch(text) is None:
        raise ValueError(
            f"{shown(text)} is not an integer (ASCII digits 0-9 with an optional sign; "
            "no '_', no digits of other scripts)"
        )
    if len(text.lstrip("+-")) > MAX_INTEGER_DIGITS:
        raise ValueError(f"{shown(text)}: more than {MAX_INTEGER_DIGITS} digits")
    return int(text)


def parse_decimal(text: str) -> float:
    """``text`` in :data:`DECIMAL_SYNTAX` as a finite float; ValueError otherwise."""
    if DECIMAL_SYNTAX.fullmatch(text) is None:
        hint = " (use a decimal point, e.g. 8.5)" if "," in text else ""
        raise ValueError(
            f"{shown(text)} is not a number (ASCII digits, optional sign, decimal point and "
            f"exponent, e.g. -2.5 or 1e-3; no '_', no digits of other scripts){hint}"
        )
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{shown(text)} is not a finite number")
    return value


def check_text(value: object, what: str, max_chars: int) -> str:
    """``value`` if it is one line of text (possibly empty) of at most ``max_chars``
    characters and no control, format or line-break character, else ValueError."""
    if not isinstance(value, str):
        raise ValueError(f"{what} must be a string, got a {type(value).__name__}")
    if len(value) > max_chars:
        raise ValueError(f"{what} is {len(value)} characters long; at most {max_chars} are allowed")
    for k, ch in enumerate(value):
        cat = unicodedata.category(ch)
        if cat in REFUSED_CATEGORIES:
            label = unicodedata.name(ch, "") or "a control character"
            raise ValueError(
                f"{what} {shown(value)}: character {k + 1} is U+{ord(ch):04X} ({label}, "
                f"category {cat}); control, format and line-break characters are not allowed"
            )
    return value


def check_name(value: object, what: str = "name", max_chars: int = MAX_NAME_CHARS) -> str:
    """``value`` if it is a name (see the module docstring) of at most ``max_chars``
    characters, else ValueError naming ``what``."""
    if not isinstance(value, str):
        raise ValueError(f"{what} must be a name (a string), got a {type(value).__name__}")
    if not value.strip():
        raise ValueError(f"{what} must not be empty or blank")
    check_text(value, what, max_chars)
    if value != value.strip():
        raise ValueError(f"{what} {shown(value)}: no spaces at its start or end")
    return value


def _as_arg(parse: Callable[[str], T], text: str) -> T:
    """``parse(text)``, its ValueError as argparse's (``argument --X: reason``, exit 2)."""
    try:
        return parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def argument_type(fn: F) -> F:
    """Mark ``fn`` as an argparse type that parses by this module's rules (the parser
    walk of the tests accepts only marked types for numbers)."""
    fn.wara_type = True  # type: ignore[attr-defined]
    return fn


def is_wara_type(fn: object) -> bool:
    """``fn`` is one of this module's argparse types (the parser walk checks it)."""
    return getattr(fn, "wara_type", False) is True


@argument_type
def integer(text: str) -> int:
    """argparse type: an integer in :data:`INTEGER_SYNTAX`."""
    return _as_arg(parse_integer, text)


@argument_type
def decimal(text: str) -> float:
    """argparse type: a finite decimal in :data:`DECIMAL_SYNTAX`."""
    return _as_arg(parse_decimal, text)


@argument_type
def name(text: str) -> str:
    """argparse type: a name (:func:`check_name`)."""
    return _as_arg(lambda t: check_name(t, "the name"), text)


def _split(text: str, count: int | None, what: str) -> list[str]:
    parts = [s.strip() for s in text.split(",")]
    if parts == [""]:
        parts = []
    if count is not None and len(parts) != count:
        raise ValueError(f"{shown(text)}: expected {count} comma-separated {what}s")
    if not parts:
        raise ValueError(f"{shown(text)}: expected at least one {what}")
    return parts


def _parse_list(
    text: str, count: int | None, what: str, parse: Callable[[str], T]
) -> tuple[T, ...]:
    """``text`` split at commas (``count`` parts when given), each part ``parse``-d; a
    part's ValueError names its place."""
    out = []
    for k, part in enumerate(_split(text, count, what), start=1):
        try:
            out.append(parse(part))
        except ValueError as exc:
            raise ValueError(f"value {k} of {shown(text)}: {exc}") from None
    return tuple(out)


def parse_decimals(text: str, count: int | None = None) -> tuple[float, ...]:
    """``"a,b,c"``: comma-separated decimals (``count`` of them when given)."""
    return _parse_list(text, count, "number", parse_decimal)


def parse_integers(text: str, count: int | None = None) -> tuple[int, ...]:
    """``"0,1,2"``: comma-separated integers (``count`` of them when given)."""
    return _parse_list(text, count, "integer", parse_integer)


def decimals(count: int | None = None) -> Callable[[str], tuple[float, ...]]:
    """argparse type: comma-separated decimals, ``count`` of them when given."""

    @argument_type
    def decimals(text: str) -> tuple[float, ...]:
        return _as_arg(lambda t: parse_decimals(t, count), text)

    return decimals


def integers(count: int | None = None) -> Callable[[str], tuple[int, ...]]:
    """argparse type: comma-separated integers, ``count`` of them when given."""

    @argument_type
    def integers(text: str) -> tuple[int, ...]:
        return _as_arg(lambda t: parse_integers(t, count), text)

    return integers

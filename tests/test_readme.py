"""The README is a reference of at most 200 lines: the two commands as CI runs them, every
relative link resolving (files and anchors), every ``wara`` verb in its CLI table."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from wara.cli import build_parser

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
MAX_LINES = 200

#: The README's main command (the demo), as a user types it on a fresh clone.
DEMO_COMMAND = (
    "python3 -m venv .venv && .venv/bin/pip install -e '.[sim,plot]' && .venv/bin/wara demo"
)

_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
_CODE_SPAN = re.compile(r"`([^`]+)`")


def _text() -> str:
    return README.read_text(encoding="utf-8")


def _code_lines(text: str) -> list[str]:
    """The lines of the Markdown code blocks: indented by four spaces after a blank line
    (outside a fence), or inside a ``` fence."""
    lines = text.splitlines()
    out: list[str] = []
    fenced = False
    in_block = False
    for i, line in enumerate(lines):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced:
            out.append(line)
            continue
        if line.startswith("    ") and (in_block or i == 0 or not lines[i - 1].strip()):
            in_block = True
            out.append(line[4:])
        elif line.strip():
            in_block = False
    return [ln.strip() for ln in out]


def _ci_test_command() -> str:
    """The line of ``.ci/run`` that sets up the venv and runs the test suite."""
    lines = (REPO / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    runs = [ln.strip() for ln in lines if not ln.lstrip().startswith("#") and "-m pytest" in ln]
    assert len(runs) == 1, runs
    return runs[0]


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but ``-`` and ``_`` removed,
    spaces as ``-``."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    found: set[str] = set()
    seen: dict[str, int] = {}
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        if fenced:
            continue
        m = re.match(r"#{1,6} (.+)$", line)
        if m:
            slug = _slug(m.group(1))
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            found.add(slug if n == 0 else f"{slug}-{n}")
    return found


def _cli_rows(text: str) -> list[list[str]]:
    """The code spans of each row's first cell in the table under "## The CLI"."""
    section = text.split("\n## The CLI\n", 1)[1].split("\n## ", 1)[0]
    rows = []
    for line in section.splitlines():
        if line.startswith("| `wara "):
            rows.append(_CODE_SPAN.findall(line.split("|")[1]))
    return rows


def _verbs(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    out: list[tuple[str, ...]] = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out.append((*prefix, name))
                out.extend(_verbs(sub, (*prefix, name)))
    return out


def test_readme_has_at_most_200_lines() -> None:
    n = len(_text().splitlines())
    assert n <= MAX_LINES, f"README.md has {n} lines, at most {MAX_LINES}"


def test_the_two_commands_are_in_the_readme_as_ci_runs_them() -> None:
    code = _code_lines(_text())
    assert DEMO_COMMAND in code
    test_command = _ci_test_command()
    assert test_command == (
        "python3 -m venv .venv && .venv/bin/pip install -q -e '.[dev]' "
        "&& .venv/bin/python -m pytest -n auto"
    )
    assert test_command in code


def bad_links(page: Path, links: list[str]) -> list[str]:
    """The relative links of ``page`` that name no file, or no heading of it."""
    bad = []
    for target in links:
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            bad.append(f"{target}: no such file")
        elif anchor and (file.suffix != ".md" or anchor not in _anchors(file)):
            bad.append(f"{target}: no heading with that anchor")
    return bad


def test_every_relative_link_resolves() -> None:
    links = _LINK.findall(_text())
    assert links
    bad = bad_links(README, links)
    assert not bad, bad


def test_every_verb_is_in_the_cli_table() -> None:
    rows = _cli_rows(_text())
    assert rows
    by_verb: dict[str, list[str]] = {}
    for spans in rows:
        verb = spans[0].split()[1]
        by_verb.setdefault(verb, []).extend(spans)
    verbs = _verbs(build_parser())
    assert len(verbs) > 20
    missing = []
    for path in verbs:
        row = by_verb.get(path[0])
        if row is None:
            missing.append(" ".join(path))
            continue
        if len(path) == 1:
            continue
        # a sub-verb as `wara ctl adjust`, `ctl adjust` or `adjust` in its verb's row
        words = [span.removeprefix("wara ").split() for span in row]
        if not any(tuple(w[: len(f)]) == f for w in words for f in (path, path[1:])):
            missing.append(" ".join(path))
    assert not missing, f"not in README.md's CLI table: {missing}"

"""``wara bench figures``: the figures page and the README's headline table written from
one run of the figure producers, the page's structure, and a run of some producers
keeping the others' figures."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import pytest

from wara.benches.figures import README_BEGIN, README_END, make_figures
from wara.benches.producers import PRODUCERS, Figure, Measured, Output, Producer, t

REPO = Path(__file__).resolve().parents[1]

README = f"# A project\n\nintro\n\n{README_BEGIN}\nold rows\n{README_END}\n\n## Next\n"


def _tree(tmp_path: Path) -> tuple[Path, Path]:
    (tmp_path / "docs").mkdir()
    readme = tmp_path / "README.md"
    readme.write_text(README, encoding="utf-8")
    return tmp_path / "docs" / "figures.md", readme


def _bus(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    return Measured(
        (Figure("load", t(d, "{load_percent:.2f} %"), "50 %"),), t(d, "{load_percent} %")
    )


FAKE = (
    Producer("bus", "Bus", "the bus load", ("wara can busload --json",), _bus, headline="bus load"),
    Producer("broken", "Bus", "a command that prints no JSON", ("wara can busload",), _bus),
    Producer(
        "slow",
        "Wall clock",
        "never run here",
        ("wara soak --minutes 30 --json",),
        _bus,
        realtime=True,
        headline="soak",
    ),
)


def _anchors(page: str) -> set[str]:
    return set(re.findall(r"^#{1,6} ([a-z0-9-]+)$", page, re.M))


def test_the_command_writes_the_page_and_the_readme_table(tmp_path: Path) -> None:
    """As a user runs it, on a subset in the quick form: the page's header names the
    commit, the machine and its load; every producer has its section; the README's
    table between the markers links each row to its section."""
    page, readme = _tree(tmp_path)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "wara",
            "bench",
            "figures",
            "--quick",
            "--only",
            "busload,place-plan",
            "--out",
            str(page),
            "--readme",
            str(readme),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["measured"] == ["busload", "place-plan"] and summary["failed"] == []
    assert re.findall(r"figures \[\d/2\] (\S+): done", proc.stderr) == ["busload", "place-plan"]
    text = page.read_text(encoding="utf-8")
    header = text.split("\n## ", 1)[0]
    for word in ("commit `", "quick form", "cores", "Python", "load average"):
        assert word in header, word
    assert _anchors(text) == {p.name for p in PRODUCERS}
    bus = text.split("### busload\n", 1)[1].split("\n### ", 1)[0]
    assert (
        "`wara can busload --json`" in bus
        and "| default active group | 44.46 % of 500 kbit/s" in bus
    )
    assert "Not measured yet: `wara bench figures --only walk`" in text
    assert "Not measured yet: `wara bench figures --realtime --only soak`" in text
    body = readme.read_text(encoding="utf-8")
    assert body.startswith("# A project\n\nintro\n\n") and body.endswith("\n\n## Next\n")
    table = body.split(README_BEGIN, 1)[1].split(README_END, 1)[0]
    assert "old rows" not in table
    links = re.findall(r"\]\(docs/figures\.md#([a-z0-9-]+)\)", table)
    assert links == ["place-plan", "busload"]  # in the producers' order, measured ones only
    assert "refused, exit 3" in table  # the 9 mm case of the placement target
    assert json.loads(page.with_suffix(".json").read_text())["figures"].keys() == {
        "busload",
        "place-plan",
    }


def test_a_later_run_keeps_the_other_figures_and_names_their_run(tmp_path: Path) -> None:
    page, readme = _tree(tmp_path)
    first = make_figures(out=page, readme=readme, producers=FAKE, say=lambda _: None)
    assert first["measured"] == ["bus"] and first["failed"] == ["broken"]
    text = page.read_text(encoding="utf-8")
    assert "| load | 44.46 % | 50 % |" in text
    assert "**Not measured: `wara can busload` printed no JSON" in text
    assert "Not measured yet: `wara bench figures --realtime --only slow`" in text
    store = json.loads(page.with_suffix(".json").read_text())
    store["runs"] = {"an earlier run": {**next(iter(store["runs"].values())), "commit": "0123abc"}}
    store["figures"]["bus"]["run"] = "an earlier run"
    page.with_suffix(".json").write_text(json.dumps(store))
    second = make_figures(
        out=page, readme=readme, only="broken", producers=FAKE, say=lambda _: None
    )
    assert second["failed"] == ["broken"]
    text = page.read_text(encoding="utf-8")
    bus = text.split("### bus\n", 1)[1].split("\n### ", 1)[0]
    assert "Measured in another run: commit `0123abc`" in bus and "| load | 44.46 % |" in bus
    table = readme.read_text(encoding="utf-8").split(README_BEGIN, 1)[1]
    assert "[bus load](docs/figures.md#bus)" in table and "soak" not in table


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["bench", "figures", "--only", "nosuch"], "no figure named nosuch"),
        (["bench", "planner", "--only", "walk"], "--only goes with `wara bench figures`"),
        (["bench", "planner", "--out", "x.md"], "--out goes with `wara bench figures`"),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from wara.cli import main

    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_a_readme_without_the_markers_is_refused(tmp_path: Path) -> None:
    page, readme = _tree(tmp_path)
    readme.write_text("# no markers\n", encoding="utf-8")
    with pytest.raises(Exception, match="no headline table markers"):
        make_figures(out=page, readme=readme, only="bus", producers=FAKE, say=lambda _: None)


def test_every_producer_has_a_unique_name_and_a_wara_command() -> None:
    names = [p.name for p in PRODUCERS]
    assert len(names) == len(set(names))
    for p in PRODUCERS:
        assert re.fullmatch(r"[a-z][a-z0-9-]*", p.name), p.name
        for cmd in (*p.commands, *p.quick):
            assert cmd.startswith("wara ") and "--json" in cmd, cmd

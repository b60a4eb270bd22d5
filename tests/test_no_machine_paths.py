"""No tracked file holds an absolute path of one developer's machine (a home or work
directory, a pyenv or venv interpreter): such a path works on that machine only and
hides a missing install step elsewhere. External tools are called through
``sys.executable -m ...`` instead. Paths that the product itself defines (``/opt/wara``,
``/etc/wara``, ``/run/wara``, ...) are not of this kind."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: Absolute paths that exist on one developer's machine only.
MACHINE_PATH = re.compile(
    r"(?<![\w.~-])("
    r"/"
    r"work/[\w.-]+"  # split: this file must not hold the paths it looks for
    r"|/root/[\w.-]+"
    r"|/home/(?!wara\b)[\w.-]+/"
    r"|/Users/[\w.-]+/"
    r"|/tmp/pytest-of-[\w.-]+"
    r"|\.pyenv/versions/\d"
    r"|[A-Za-z]:\\Users\\"
    r")"
)


def tracked_text_files() -> list[Path]:
    out = subprocess.run(
        ["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True
    ).stdout.decode()
    files = []
    for name in filter(None, out.split("\0")):
        path = REPO / name
        if path.is_file() and path.suffix not in {".png", ".dbc.gz", ".sqlite", ".nbc", ".nbi"}:
            files.append(path)
    return files


def machine_paths(text: str) -> list[str]:
    return [m.group(0) for m in MACHINE_PATH.finditer(text)]


def test_the_pattern_finds_machine_paths_and_spares_product_paths() -> None:
    # (built from pieces, so that this file holds none of them itself)
    root, work, home = "/" + "root/", "/" + "work/", "/" + "home/"
    assert machine_paths(f"cantools at {root}.venv/bin/cantools") == [root + ".venv"]
    assert machine_paths(f"cd {work}main && make") == [work + "main"]
    assert machine_paths(f"see {home}alice/src/x") == [home + "alice/"]
    assert machine_paths("C:" + "\\Users\\bob") == ["C:" + "\\Users\\"]
    assert machine_paths("/usr/local/.pyenv/" + "versions/3.11.7/bin/python")
    for fine in (
        "/opt/wara/venv/bin/wara",
        "/etc/wara/project.yaml",
        "/var/lib/wara",
        "/home/" + "wara/",
        "tests/" + "work/x",
        "https://example.org/" + "work/x",
        "sys.executable -m cantools",
    ):
        assert machine_paths(fine) == [], fine


def test_no_tracked_file_holds_a_machine_path() -> None:
    # the suite runs from a clone (CI clones the repository): git ls-files must work
    found = []
    for path in tracked_text_files():
        try:
            text = path.read_text(encoding="utf-8")
        except (UnicodeDecodeError, OSError):
            continue
        for lineno, line in enumerate(text.splitlines(), 1):
            for hit in machine_paths(line):
                found.append(f"{path.relative_to(REPO)}:{lineno}: {hit}")
    assert not found, "absolute paths of one machine:\n" + "\n".join(found)

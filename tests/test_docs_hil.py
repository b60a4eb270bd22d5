"""docs/hil.md's YAML snippets, used as the text says: each replaces its sections of a
copy of the shipped project YAML, and the result loads through config/loader.py."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

from config import load_project
from config.loader import default_project_path

DOC = Path(__file__).resolve().parents[1] / "docs" / "hil.md"
SECTION = re.compile(r"^([A-Za-z_]\w*):")


def _snippets() -> list[str]:
    return re.findall(r"^```yaml\n(.*?)^```", DOC.read_text(encoding="utf-8"), re.S | re.M)


def _replace_sections(base: str, snippet: str) -> str:
    """``base`` with each top-level section the snippet has replaced by the snippet's."""
    keys = {m.group(1) for line in snippet.splitlines() if (m := SECTION.match(line))}
    out, skip = [], False
    for line in base.splitlines():
        m = SECTION.match(line)
        if m:
            skip = m.group(1) in keys
        if not skip:
            out.append(line)
    return "\n".join(out) + "\n" + snippet


def test_every_yaml_snippet_of_hil_md_loads_in_the_shipped_project(tmp_path: Path) -> None:
    snippets = _snippets()
    assert snippets, "docs/hil.md has no yaml snippet"
    shipped_text = default_project_path().read_text(encoding="utf-8")
    shipped = yaml.safe_load(shipped_text)
    for i, snippet in enumerate(snippets):
        path = tmp_path / f"hil-{i}.yaml"
        path.write_text(_replace_sections(shipped_text, snippet), encoding="utf-8")
        cfg = load_project(path)  # a duplicate key or a bad value: ConfigError
        for section, keys in yaml.safe_load(snippet).items():
            # the whole section, so that replacing it keeps every shipped setting
            assert set(keys) == set(shipped[section]), (section, set(shipped[section]) - set(keys))
            for key, value in keys.items():
                got = getattr(getattr(cfg, section), key)
                assert got == value or list(got) == value, (section, key, got, value)

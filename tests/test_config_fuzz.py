"""Hypothesis fuzzing of the project YAML: random mutations of the shipped file (types,
values, keys, NaN/inf, duplicates, bytes). Each mutant is accepted with every number
finite and inside the range its key states, or refused with exit 2 in lines that each
name one problem; never a traceback. Bounded: a few seconds per test."""

from __future__ import annotations

import json
import math
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from config import ConfigError, default_project_path, load_project
from tests.cli_helpers import run_main, run_wara

SHIPPED_TEXT = default_project_path().read_text(encoding="utf-8")
SHIPPED: dict[str, Any] = yaml.safe_load(SHIPPED_TEXT)
PREFIX = "wara: configuration error: "
FUZZ = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None
)


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """Every key path of the shipped data (mappings, sequences and leaves)."""
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, (*prefix, i))


PATHS = [p for p in _paths(SHIPPED) if p]
NUMERIC_LINES = [i for i, ln in enumerate(SHIPPED_TEXT.splitlines()) if re.search(r": -?\d", ln)]
KEY_LINES = [i for i, ln in enumerate(SHIPPED_TEXT.splitlines()) if re.match(r"^\s*[a-z_]+:", ln)]

HOSTILE_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1e-300, 1e300, 0.001, 10**30, -(10**30), True, None, "", "12"]),
    st.integers(min_value=-(10**12), max_value=10**12),
    st.text(max_size=12),
    st.lists(st.floats(allow_nan=True), max_size=4),
    st.dictionaries(st.sampled_from(["x", "mass_kg", "id"]), st.integers(), max_size=2),
)
TOKENS = [".inf", "-.inf", ".nan", ".NaN", "1e999", "1.0e+999", "0x1F", "1_000", "0o17", "~",
          "!!str 5", "[1, 2]", "{a: 1}", "&a 1", "*a", "2024-13-45", "'", '"', "\t",
          "1" * 5000]  # fmt: skip


def _get_parent(data: Any, path: tuple[Any, ...]) -> tuple[Any, Any]:
    cur = data
    for part in path[:-1]:
        cur = cur[part]
    return cur, path[-1]


@st.composite
def _data_mutant(draw: st.DrawFn) -> str:
    data = json.loads(json.dumps(SHIPPED))  # a deep copy
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(PATHS))
        try:
            parent, key = _get_parent(data, path)
            old = parent[key]
        except (KeyError, IndexError, TypeError):
            continue  # removed by an earlier mutation
        kind = draw(st.sampled_from(["value", "value", "scale", "delete", "unknown_key"]))
        if kind == "value":
            parent[key] = draw(HOSTILE_VALUES)
        elif kind == "scale" and isinstance(old, int | float) and not isinstance(old, bool):
            parent[key] = old * draw(st.sampled_from([-1, 0, 1e-6, 0.5, 2, 1e3, 1e9]))
        elif kind == "delete":
            del parent[key]
        elif kind == "unknown_key" and isinstance(old, dict):
            old[draw(st.sampled_from(["extra", "mass_kgg", "Safety", "1"]))] = 1
    return yaml.safe_dump(data, sort_keys=False, allow_unicode=True)


@st.composite
def _text_mutant(draw: st.DrawFn) -> bytes:
    lines = SHIPPED_TEXT.splitlines()
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["token", "duplicate", "bytes", "indent"]))
        if kind == "token":
            i = draw(st.sampled_from(NUMERIC_LINES))
            head, _, _ = lines[i].partition(": ")
            lines[i] = f"{head}: {draw(st.sampled_from(TOKENS))}"
        elif kind == "duplicate":
            i = draw(st.sampled_from(KEY_LINES))
            lines.insert(i + 1, lines[i])
        elif kind == "indent":
            i = draw(st.integers(0, len(lines) - 1))
            lines[i] = draw(st.sampled_from(["", " ", "\t", "- "])) + lines[i]
    raw = bytearray("\n".join(lines).encode("utf-8"))
    if kind == "bytes":
        for _ in range(draw(st.integers(1, 8))):
            pos = draw(st.integers(0, len(raw) - 1))
            raw[pos : pos + draw(st.integers(0, 2))] = draw(st.binary(min_size=1, max_size=3))
    return bytes(raw)


def _walk_numbers(value: Any, field: FieldInfo | None, metadata: list[Any], where: str) -> None:
    """Every number of an accepted config is finite and inside its key's stated range."""
    if isinstance(value, BaseModel):
        for name, f in type(value).model_fields.items():
            _walk_numbers(getattr(value, name), f, list(f.metadata), f"{where}.{name}")
    elif isinstance(value, tuple):
        for i, v in enumerate(value):
            _walk_numbers(v, None, [], f"{where}[{i}]")
    elif isinstance(value, float) and not isinstance(value, bool):
        assert math.isfinite(value), where
        for m in metadata:
            for attr, ok in (
                ("gt", lambda b: value > b),
                ("ge", lambda b: value >= b),
                ("lt", lambda b: value < b),
                ("le", lambda b: value <= b),
            ):
                bound = getattr(m, attr, None)
                assert bound is None or ok(bound), (where, value, attr, bound)


def _validate(path: Path) -> tuple[int, str, str]:
    return run_main(["config", "validate", str(path)])


def _check_outcome(path: Path, code: int, out: str, err: str) -> None:
    assert "Traceback" not in err
    if code == 0:
        assert out.startswith(f"{path}: OK (")
        assert err == "" or (len(err.splitlines()) == 1 and ": warning: section(s)" in err)
        cfg = load_project(path)
        _walk_numbers(cfg, None, [], "")
        assert all(math.isfinite(v) for v in _floats(cfg.model_dump()))
    else:
        assert code == 2 and out == ""
        lines = err.splitlines()
        assert lines and all(ln.startswith(PREFIX + str(path)) for ln in lines), err
        assert all(len(ln) < 600 for ln in lines)


def _floats(obj: Any) -> Iterator[float]:
    if isinstance(obj, dict):
        for v in obj.values():
            yield from _floats(v)
    elif isinstance(obj, list | tuple):
        for v in obj:
            yield from _floats(v)
    elif isinstance(obj, float):
        yield obj


@pytest.mark.slow
@FUZZ
@given(text=_data_mutant())
def test_value_type_and_key_mutations(text: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "project.yaml"
        path.write_text(text, encoding="utf-8")
        _check_outcome(path, *_validate(path))


@pytest.mark.slow
@FUZZ
@given(raw=_text_mutant())
def test_token_duplicate_and_byte_mutations(raw: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "project.yaml"
        path.write_bytes(raw)
        _check_outcome(path, *_validate(path))


@settings(max_examples=40, deadline=None, database=None)
@given(text=st.text(max_size=200), nest=st.integers(0, 200))
def test_arbitrary_text(text: str, nest: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "project.yaml"
        path.write_text("[" * nest + text + "]" * nest, encoding="utf-8")
        try:
            load_project(path)
        except ConfigError as exc:
            assert str(path) in str(exc)


@pytest.mark.slow
@settings(max_examples=2, deadline=None, database=None)
@given(text=_data_mutant())
def test_through_a_subprocess(text: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "project.yaml"
        path.write_text(text, encoding="utf-8")
        proc = run_wara(["config", "validate", str(path)])
        _check_outcome(path, proc.returncode, proc.stdout, proc.stderr)


@settings(max_examples=25, deadline=None, database=None)
@given(
    mass=st.floats(1.0, 1e6),
    cog=st.tuples(st.floats(-100, 100), st.floats(-100, 100), st.floats(-100, 100)),
    roll=st.floats(-10, 10),
)
@pytest.mark.slow
def test_accepted_bodies_plan_to_finite_numbers(
    mass: float, cog: tuple[float, float, float], roll: float
) -> None:
    """A body anywhere in its stated range gives a plan of finite numbers (or exit 3), or
    is refused by the loader as a load the pressure limit cannot carry (exit 2: the
    cross-check of config.crosscheck, one line)."""
    data = json.loads(json.dumps(SHIPPED))
    data["layers"]["upper"]["bodies"][0].update(mass_kg=mass, cog_m=list(cog))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "project.yaml"
        path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
        args = ["plan", "--config", str(path), f"--roll-deg={roll}", "--pitch-deg=0", "--json"]
        code, out, err = run_main(args)
        if code == 2:
            assert out == "" and len(err.splitlines()) == 1, err
            assert f"{path}: safety.max_pressure_mpa: " in err and "static load" in err, err
            return
        assert code in (0, 3), err
        result = json.loads(out, parse_constant=lambda c: c)
        bad = [v for v in _floats(result) if not math.isfinite(v)]
        assert bad == [] and "NaN" not in out and "Infinity" not in out

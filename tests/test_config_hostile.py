"""Hostile configuration input: non-finite and implausible numbers, duplicate keys,
defaulted sections, files that are not UTF-8, nest without end, never end (FIFO,
/dev/zero) or are too long. Each is refused in one line per problem with exit 2, or
accepted with a warning where that is the rule; never a traceback."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from config import ConfigError, ProjectConfig, default_project_path, load_project
from config.hil_scenario import load_hil_scenario
from config.scenario import load_scenario, scenario_path
from tests.cli_helpers import run_wara
from wara.cli import main

REPO = Path(__file__).resolve().parents[1]
SHIPPED = default_project_path().read_text(encoding="utf-8")
PREFIX = "wara: configuration error: "


def _cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def _problem_lines(err: str) -> list[str]:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err
    assert lines and all(ln.startswith(PREFIX) for ln in lines), err
    return lines


def _edit(old: str, new: str, text: str = SHIPPED) -> str:
    assert text.count(old) == 1, old
    return text.replace(old, new)


def _write_text(tmp_path: Path, text: str, name: str = "project.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


# ------------------------------------------------------------------ finite, in range


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("  max_pressure_mpa: 24.0", "  max_pressure_mpa: .inf", "safety.max_pressure_mpa"),
        ("  max_sync_error_mm: 2.0", "  max_sync_error_mm: .inf", "safety.max_sync_error_mm"),
        ("  max_twist_mm: 1.5", "  max_twist_mm: .nan", "safety.max_twist_mm"),
        (
            "{name: workpiece, mass_kg: 36350,",
            "{name: workpiece, mass_kg: .inf,",
            "layers.upper.bodies[0].mass_kg",
        ),
        ("  pitch_deg: 0.17", "  pitch_deg: -.inf", "base.pitch_deg"),
        ("cog_m: [0.0, 0.0, 0.5]", "cog_m: [0.0, .nan, 0.5]", "layers.lower.bodies[0].cog_m[1]"),
        ("  loop_rate_hz: 200", "  loop_rate_hz: 0.001", "control.loop_rate_hz"),
        ("  loop_rate_hz: 200", "  loop_rate_hz: 49.9", "control.loop_rate_hz"),
        ("  width_m: 2.0\n", "  width_m: 2.0\n  mass_kg: 3.6e9\n", "workpiece.mass_kg"),
        ("  supply_pressure_mpa: 16.0", "  supply_pressure_mpa: 160", "hydraulics"),
        ("  max_pressure_mpa: 24.0", "  max_pressure_mpa: 240", "safety.max_pressure_mpa"),
        ("  sensor_timeout_ms: 100", "  sensor_timeout_ms: 5e9", "safety.sensor_timeout_ms"),
    ],
)
def test_non_finite_and_implausible_numbers_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], old: str, new: str, key: str
) -> None:
    path = _write_text(tmp_path, _edit(old, new))
    code, out, err = _cli(["config", "validate", str(path)], capsys)
    assert code == 2 and out == ""
    lines = _problem_lines(err)
    assert any(f"{path}: {key}" in ln for ln in lines), err


def test_loop_rate_at_the_edges_of_its_range(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for rate, code in (("50", 0), ("2000", 2), ("2000.5", 2)):
        path = _write_text(tmp_path, _edit("  loop_rate_hz: 200", f"  loop_rate_hz: {rate}"))
        got, _, err = _cli(["config", "validate", str(path)], capsys)
        assert got == code, rate
        # 2000 Hz is inside the key's range, but its bus load is not inside the budget
        # (the cross-check, config.crosscheck); 2000.5 Hz is outside the range
        if rate == "2000":
            assert f"{path}: can.max_bus_load_percent" in err and "control.loop_rate_hz" in err
            assert "expected at most 2000" not in err, err
        if rate == "2000.5":
            assert f"{path}: control.loop_rate_hz" in err, err


def test_plan_with_an_infinite_body_mass_is_a_config_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _write_text(
        tmp_path, _edit("{name: workpiece, mass_kg: 36350,", "{name: workpiece, mass_kg: .inf,")
    )
    args = ["plan", "--config", str(path), "--roll-deg", "1", "--pitch-deg", "0", "--json"]
    code, out, err = _cli(args, capsys)
    assert code == 2 and out == "" and "mass_kg" in err
    assert "NaN" not in out


def _float_bounds(model: type[BaseModel], prefix: str = "") -> list[tuple[str, Any]]:
    """(key path, field metadata) of every float field reachable from ``model``."""
    found: list[tuple[str, Any]] = []

    def walk(name: str, annotation: Any, metadata: list[Any]) -> None:
        origin = getattr(annotation, "__origin__", None)
        args = getattr(annotation, "__args__", ())
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            found.extend(_float_bounds(annotation, name + "."))
        elif annotation is float:
            found.append((name, metadata))
        elif origin is not None or args:
            for i, a in enumerate(args):
                if a is type(None) or a is Ellipsis:
                    continue
                meta = [
                    c
                    for m in getattr(a, "__metadata__", ())
                    for c in (m.metadata if isinstance(m, FieldInfo) else [m])
                ]
                inner = getattr(a, "__origin__", a) if meta else a
                walk(f"{name}[{i}]", inner, meta)

    for fname, field in model.model_fields.items():
        walk(prefix + fname, field.annotation, list(field.metadata))
    return found


def test_every_float_key_of_a_project_states_a_finite_range() -> None:
    fields = _float_bounds(ProjectConfig)
    assert len(fields) > 80
    missing = []
    for name, metadata in fields:
        lo = [v for m in metadata for a in ("gt", "ge") if (v := getattr(m, a, None)) is not None]
        hi = [v for m in metadata for a in ("lt", "le") if (v := getattr(m, a, None)) is not None]
        if not (lo and hi and all(math.isfinite(v) for v in lo + hi)):
            missing.append(name)
    assert missing == []


# ------------------------------------------------------------------ duplicate keys


def test_duplicate_key_names_both_lines(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = _edit("  max_pressure_mpa: 24.0\n", "  max_pressure_mpa: 24.0\n  max_pressure_mpa: 99\n")
    first = text.splitlines().index("  max_pressure_mpa: 24.0") + 1
    path = _write_text(tmp_path, text)
    code, _, err = _cli(["config", "validate", str(path)], capsys)
    assert code == 2
    (line,) = _problem_lines(err)
    assert f"duplicate key 'max_pressure_mpa' on line {first + 1} (first on line {first})" in line


def test_duplicate_key_in_a_flow_mapping_and_a_top_level_section(tmp_path: Path) -> None:
    text = _edit("{order: 1, discretization: zoh,", "{order: 1, discretization: zoh, order: 2,")
    flow = _write_text(tmp_path, text)
    with pytest.raises(ConfigError, match="duplicate key 'order'"):
        load_project(flow)
    section = _write_text(tmp_path, SHIPPED + "\nsafety:\n  max_twist_mm: 99\n")
    with pytest.raises(ConfigError, match="duplicate key 'safety'"):
        load_project(section)


def test_scenario_files_go_through_the_same_loader(tmp_path: Path) -> None:
    text = scenario_path("dual_cylinder").read_text(encoding="utf-8")
    key = next(ln for ln in text.splitlines() if re.match(r"^[a-z_]+:", ln))
    dup = _write_text(tmp_path, text + "\n" + key + "\n", "scenario.yaml")
    with pytest.raises(ConfigError, match="duplicate key"):
        load_scenario(dup)
    hil = _write_text(tmp_path, "events: []\nevents: []\n", "hil.yaml")
    with pytest.raises(ConfigError, match="duplicate key 'events' on line 2"):
        load_hil_scenario(hil)
    with pytest.raises(ConfigError, match="a FIFO"):
        fifo = tmp_path / "fifo.yaml"
        os.mkfifo(fifo)
        load_hil_scenario(fifo)


def test_no_yaml_is_parsed_outside_the_loader() -> None:
    """Every project or scenario YAML (and --fault value) goes through config.loader."""
    offenders = []
    for pkg in ("config", "ipc_app", "hil_sim", "plc_bridge", "wara"):
        for py in sorted((REPO / pkg).rglob("*.py")):
            if py == REPO / "config" / "loader.py":
                continue
            src = py.read_text(encoding="utf-8")
            if re.search(r"yaml\.(safe_load|load|full_load|unsafe_load)\b", src):
                offenders.append(str(py.relative_to(REPO)))
    assert offenders == []


# ------------------------------------------------------------------ defaulted sections


def test_validate_names_the_sections_taken_from_defaults(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = SHIPPED
    for section in ("can", "safety"):
        start = text.index(f"\n{section}:")
        end = text.index("\n\n", start + 1)
        text = text[:start] + text[end:]
    path = _write_text(tmp_path, text)
    code, out, err = _cli(["config", "validate", str(path)], capsys)
    assert code == 0 and ": OK (" in out
    (warning,) = err.splitlines()
    assert warning.endswith("every key at its default (see `wara config show`): can, safety")
    code, _, err = _cli(["config", "validate", str(default_project_path())], capsys)
    assert code == 0 and err == ""  # the shipped project writes every section


# ------------------------------------------------------------------ unreadable files


def _one_line_exit_2(path: Path | str, expected: str) -> None:
    """Through the real entry point in a subprocess: one line, exit 2, quickly."""
    proc = run_wara(["config", "validate", str(path)], timeout_s=60)
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout == "" and "Traceback" not in proc.stderr
    (line,) = proc.stderr.splitlines()
    assert line.startswith(PREFIX) and expected in line, line


@pytest.mark.slow
def test_not_utf8(tmp_path: Path) -> None:
    p = tmp_path / "latin.yaml"
    p.write_bytes(SHIPPED.replace("Airport Link", "Flughafen Zürich").encode("latin-1"))
    _one_line_exit_2(p, f"{p}: not UTF-8 text (byte ")


@pytest.mark.slow
def test_nested_100k_deep(tmp_path: Path) -> None:
    p = _write_text(tmp_path, "project: " + "[" * 100_000 + "]" * 100_000 + "\n")
    _one_line_exit_2(p, "nesting deeper than")
    block = "".join("  " * i + f"k{i}:\n" for i in range(200))
    q = _write_text(tmp_path, block, "q.yaml")
    with pytest.raises(ConfigError, match="nesting deeper than"):
        load_project(q)


@pytest.mark.slow
def test_fifo_does_not_hang(tmp_path: Path) -> None:
    fifo = tmp_path / "project.yaml"
    os.mkfifo(fifo)
    _one_line_exit_2(fifo, f"{fifo}: a FIFO (named pipe), expected a regular file")


@pytest.mark.slow
def test_dev_zero_and_a_directory(tmp_path: Path) -> None:
    _one_line_exit_2("/dev/zero", "/dev/zero: a device, expected a regular file")
    _one_line_exit_2(tmp_path, "a directory, expected a regular file")


@pytest.mark.slow
def test_longer_than_the_bound(tmp_path: Path) -> None:
    p = _write_text(tmp_path, SHIPPED + "#" * (1024 * 1024) + "\n")
    _one_line_exit_2(p, "longer than 1048576 bytes")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("project: {name: 2024-13-45}\n", "YAML error: ValueError: month must be in 1..12"),
        ("seed: 1" + "0" * 5000 + "\n", "YAML error: ValueError: Exceeds the limit"),
        ("a: !!timestamp 'x'\n", "YAML error: AttributeError"),
        ("a: \x00\n", "YAML error: unacceptable character #x0000"),
        ("a: !!python/object:os.system x\n", "could not determine a constructor"),
        ("? [a, b]\n: 1\n", "found unhashable key"),
    ],
)
def test_yaml_the_parser_chokes_on_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, expected: str
) -> None:
    path = _write_text(tmp_path, text)
    code, _, err = _cli(["config", "validate", str(path)], capsys)
    assert code == 2
    (line,) = _problem_lines(err)
    assert expected in line


def test_a_long_value_is_quoted_short(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _write_text(tmp_path, _edit("  pitch_deg: 0.17", "  pitch_deg: '" + "x" * 10_000 + "'"))
    code, _, err = _cli(["config", "validate", str(path)], capsys)
    assert code == 2
    (line,) = _problem_lines(err)
    assert "base.pitch_deg: got 'xxx" in line and len(line) < 300


def test_shipped_project_still_valid_and_show_is_finite(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _cli(["config", "show", "--json"], capsys)
    assert code == 0
    json.loads(out, parse_constant=lambda c: pytest.fail(f"non-finite {c} in config show"))

"""Load and validate project YAML files with messages an engineer can act on.

Every failure raises :class:`ConfigError` whose message names the file, the key path,
the offending value and what was expected, one line per problem, no traceback.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from config.schema import ProjectConfig

M = TypeVar("M", bound=BaseModel)

DEFAULT_PROJECT = "shanghai_airport_link"


class ConfigError(Exception):
    """A configuration file could not be read or does not describe a valid machine.

    Scenarios: the file is missing, the YAML does not parse, a key is unknown or
    misspelt, a value has the wrong type or is physically impossible (negative bore,
    reserve larger than half the stroke, duplicate cylinder id).
    """


def default_project_path() -> Path:
    """The shipped Shanghai Airport Link project YAML."""
    return Path(str(resources.files("config") / "projects" / f"{DEFAULT_PROJECT}.yaml"))


def read_yaml(path: Path) -> Any:
    """Parse a YAML file; errors name the file and the line."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None
    try:
        return yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "?"
        raise ConfigError(f"{path}: YAML syntax error at {where}: {exc.problem}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: YAML error: {exc}") from None


def _key_path(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + part
    return out or "(top level)"


def _lookup(data: Any, loc: tuple[int | str, ...]) -> tuple[bool, Any]:
    cur = data
    for part in loc:
        try:
            cur = cur[part]
        except (KeyError, IndexError, TypeError):
            return False, None
    return True, cur


def format_validation_error(source: str, exc: ValidationError, data: Any) -> str:
    """One line per problem: ``file: key.path: got VALUE: expected ...``."""
    lines = []
    for err in exc.errors(include_url=False):
        loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and "[" in p))
        path = _key_path(loc)
        kind = err["type"]
        msg = err["msg"]
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        if kind == "extra_forbidden":
            lines.append(f"{source}: {path}: unknown key (not part of the schema)")
        elif kind == "missing":
            lines.append(f"{source}: {path}: missing required key")
        elif kind == "value_error":
            lines.append(f"{source}: {path}: {msg}")
        else:
            found, value = _lookup(data, loc)
            got = f"got {value!r}: " if found and not isinstance(value, dict | list) else ""
            lines.append(f"{source}: {path}: {got}expected {msg[0].lower()}{msg[1:]}")
    return "\n".join(lines)


def validate_data(model: type[M], data: Any, source: str) -> M:
    """Validate already-parsed data against a schema model."""
    if not isinstance(data, dict):
        got = type(data).__name__
        raise ConfigError(f"{source}: expected a mapping at the top level, got {got}")
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(source, exc, data)) from None


def load_model(model: type[M], path: str | Path) -> M:
    """Read a YAML file and validate it against ``model``."""
    p = Path(path)
    return validate_data(model, read_yaml(p), str(p))


def load_project(path: str | Path | None = None) -> ProjectConfig:
    """Load a project YAML; ``None`` means the shipped Shanghai Airport Link project."""
    return load_model(ProjectConfig, default_project_path() if path is None else path)

"""Load and validate project YAML files with messages an engineer can act on.

Every failure raises :class:`ConfigError` whose message names the file, the key path,
the offending value and what was expected, one line per problem, no traceback.
"""

from __future__ import annotations

from collections.abc import Collection
from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from config import crosscheck
from config.files import InputFileError, read_text_file
from config.schema import ProjectConfig

M = TypeVar("M", bound=BaseModel)

DEFAULT_PROJECT = "shanghai_airport_link"

#: Largest YAML file read (a project YAML is about 8 KB).
MAX_YAML_BYTES = 1024 * 1024
#: Deepest nesting of mappings and sequences (the project schema needs 4).
MAX_YAML_DEPTH = 32
#: Longest value quoted back in an error message.
MAX_QUOTED_CHARS = 60


class ConfigError(Exception):
    """A configuration file could not be read or does not describe a valid machine.

    Scenarios: the file is missing, the YAML does not parse, a key is unknown or
    misspelt, a value has the wrong type or is physically impossible (negative bore,
    reserve larger than half the stroke, duplicate cylinder id).
    """


#: Keys a project file once had, and where their fact comes from now (a fact has one key).
RETIRED_KEYS: dict[str, str] = {
    "placement.reference_height_m": "a part's reference height is on the invert, derived "
    "from tunnel.inner_diameter_m (the inner radius below the axis)",
    "tunnel.outer_diameter_m": "the lining's outer diameter governs nothing of the machine",
}


def default_project_path() -> Path:
    """The shipped Shanghai Airport Link project YAML."""
    return Path(str(resources.files("config") / "projects" / f"{DEFAULT_PROJECT}.yaml"))


class _Refused(yaml.YAMLError):
    """A YAML document this loader refuses although PyYAML would take it."""


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing duplicate keys and nesting deeper than the bound."""

    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self._depth >= MAX_YAML_DEPTH:
            mark = self.peek_event().start_mark
            raise _Refused(
                f"nesting deeper than {MAX_YAML_DEPTH} levels at line {mark.line + 1}, "
                f"column {mark.column + 1}"
            )
        self._depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            first_line: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    earlier = first_line.get(key)
                except TypeError:  # unhashable: the base class reports it
                    continue
                line = key_node.start_mark.line + 1
                if earlier is not None:
                    raise _Refused(
                        f"duplicate key {_quote(key)} on line {line} (first on line {earlier})"
                    )
                first_line[key] = line
        return super().construct_mapping(node, deep=deep)


def _quote(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= MAX_QUOTED_CHARS else text[: MAX_QUOTED_CHARS - 3] + "..."


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def parse_yaml_text(text: str, source: str) -> Any:
    """Parse YAML text with the project's rules; errors are one line naming ``source``."""
    loader: _Loader | None = None
    try:
        loader = _Loader(text)  # the reader checks the characters here
        return loader.get_single_data()
    except _Refused as exc:
        raise ConfigError(f"{source}: {exc}") from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "?"
        what = _one_line(exc.problem or exc.context or "not YAML")
        raise ConfigError(f"{source}: YAML syntax error at {where}: {what}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{source}: YAML error: {_one_line(str(exc))}") from None
    except Exception as exc:  # hostile text in a third-party parser
        # PyYAML's constructors let ValueError (2024-13-45, a 5000-digit integer),
        # AttributeError (!!timestamp 'x') and the like through: all mean a bad file.
        raise ConfigError(
            f"{source}: YAML error: {type(exc).__name__}: {_one_line(str(exc))[:200]}"
        ) from None
    finally:
        if loader is not None:
            loader.dispose()


def read_yaml(path: Path) -> Any:
    """Read and parse a YAML file (regular file, UTF-8, at most MAX_YAML_BYTES)."""
    try:
        text = read_text_file(path, MAX_YAML_BYTES)
    except InputFileError as exc:
        raise ConfigError(str(exc)) from None
    return parse_yaml_text(text, str(path))


def defaulted_sections(model: type[BaseModel], data: Any) -> list[str]:
    """Top-level sections of ``model`` absent from ``data``, so taken whole from defaults."""
    present = data if isinstance(data, dict) else {}
    return [
        name
        for name, field in model.model_fields.items()
        if not field.is_required() and name not in present
    ]


def _key_path(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + _quote(part)[1:-1]
    return out or "(top level)"


def _lookup(data: Any, loc: tuple[int | str, ...]) -> tuple[bool, Any]:
    cur = data
    for part in loc:
        try:
            cur = cur[part]
        except (KeyError, IndexError, TypeError):
            return False, None
    return True, cur


def _data_loc(loc: tuple[int | str, ...], data: Any) -> tuple[int | str, ...]:
    """``loc`` without pydantic's own parts (``function-after[...]``, a union member's
    type): a part with ``[`` is kept only when it is a key of the data at that place (a
    campaign's dispersion ``cog_m[0]``)."""
    out: list[int | str] = []
    cur: Any = data
    for part in loc:
        is_key = isinstance(cur, dict) and part in cur
        if is_key or not (isinstance(part, str) and "[" in part):
            out.append(part)
            try:
                cur = cur[part]
            except (KeyError, IndexError, TypeError):
                cur = None
    return tuple(out)


def format_validation_error(source: str, exc: ValidationError, data: Any) -> str:
    """One line per problem: ``file: key.path: got VALUE: expected ...``."""
    lines = []
    for err in exc.errors(include_url=False):
        loc = _data_loc(err["loc"], data)
        path = _key_path(loc)
        kind = err["type"]
        msg = err["msg"]
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        if kind == "extra_forbidden" and path in RETIRED_KEYS:
            lines.append(f"{source}: {path}: no longer a key: {RETIRED_KEYS[path]}; leave it out")
        elif kind == "extra_forbidden":
            lines.append(f"{source}: {path}: unknown key (not part of the schema)")
        elif kind == "missing":
            lines.append(f"{source}: {path}: missing required key")
        elif kind == "value_error":
            lines.append(f"{source}: {path}: {_one_line(msg)}")
        else:
            found, value = _lookup(data, loc)
            got = f"got {_quote(value)}: " if found and not isinstance(value, dict | list) else ""
            lines.append(f"{source}: {path}: {got}expected {_one_line(msg[0].lower() + msg[1:])}")
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


def cross_check(cfg: ProjectConfig, source: str, skip: Collection[str] = ()) -> ProjectConfig:
    """Run the cross-checks between keys (:data:`config.crosscheck.RULES`, but those
    named in ``skip``) on a project the schema validated: ConfigError with one line per
    rule broken, ``file: key.a: ... (key.b ...)``."""
    found = crosscheck.problems(cfg, skip)
    if found:
        raise ConfigError("\n".join(f"{source}: {_one_line(p)}" for p in found))
    return cfg


def load_project(path: str | Path | None = None, skip: Collection[str] = ()) -> ProjectConfig:
    """Load a project YAML (``None``: the shipped Shanghai Airport Link project): the
    schema, then the cross-checks between keys (:func:`cross_check`; ``skip``: rules
    left to the caller, which reports on them itself: ``wara can busload``)."""
    p = default_project_path() if path is None else Path(path)
    return cross_check(load_model(ProjectConfig, p), str(p), skip)

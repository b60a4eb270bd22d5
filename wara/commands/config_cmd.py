"""``wara config validate PATH`` and ``wara config show PATH``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

from config import ConfigError, ProjectConfig, load_project
from config.loader import cross_check, defaulted_sections, read_yaml, validate_data


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="validate or show a project configuration")
    verbs = p.add_subparsers(dest="config_command", metavar="VERB")
    verbs.required = True
    v = verbs.add_parser("validate", help="check a project YAML; exit 2 with reasons if invalid")
    v.add_argument("path", help="project YAML file")
    v.set_defaults(func=_validate)
    s = verbs.add_parser("show", help="print the fully resolved configuration (defaults filled)")
    s.add_argument("path", nargs="?", default=None, help="project YAML (default: shipped project)")
    s.add_argument("--json", action="store_true", help="print JSON instead of YAML")
    s.set_defaults(func=_show)


def _validate(args: argparse.Namespace) -> int:
    data = read_yaml(Path(args.path))
    cfg = cross_check(validate_data(ProjectConfig, data, args.path), args.path)
    # the loops' delay margin: the rule needs the controller's model
    # (ipc_app.control.tuning), which the shared schema package may not import
    from ipc_app.control.tuning import delay_margin_problem

    problem = delay_margin_problem(cfg)
    if problem is not None:
        raise ConfigError(f"{args.path}: {problem}")
    defaulted = defaulted_sections(ProjectConfig, data)
    if defaulted:
        # Valid, but a whole section (safety limits, the bus) came from the defaults:
        # say so, so that a forgotten section is a decision and not an accident.
        print(
            f"{args.path}: warning: section(s) not in the file, every key at its default "
            f"(see `wara config show`): {', '.join(defaulted)}",
            file=sys.stderr,
        )
    print(
        f"{args.path}: OK ({cfg.project.name} {cfg.project.section}, "
        f"{len(cfg.cylinders)} cylinders)"
    )
    return 0


def _show(args: argparse.Namespace) -> int:
    cfg = load_project(args.path)
    data = cfg.model_dump(mode="json")
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        print(yaml.safe_dump(data, sort_keys=False), end="")
    return 0

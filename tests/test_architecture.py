"""House rules that keep the architecture honest, checked on the source itself."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _imports(package: str) -> dict[str, set[str]]:
    found: dict[str, set[str]] = {}
    for path in (REPO / package).rglob("*.py"):
        tree = ast.parse(path.read_text(), filename=str(path))
        names: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names.add(node.module.split(".")[0])
        found[str(path.relative_to(REPO))] = names
    return found


def test_hil_sim_never_imports_the_controller() -> None:
    bad = {f: n for f, n in _imports("hil_sim").items() if n & {"ipc_app", "acceptance", "wara"}}
    assert not bad, f"hil_sim must meet ipc_app only on the CAN wire and the config: {bad}"


def test_controller_never_imports_the_simulator() -> None:
    bad = {f: n for f, n in _imports("ipc_app").items() if n & {"hil_sim", "acceptance", "wara"}}
    assert not bad, f"ipc_app must not import hil_sim, acceptance or the CLI: {bad}"


def test_acceptance_stands_alone() -> None:
    """Site QA's package: the project's config (its Table 4 tolerances) and nothing else of
    ours; only the CLI uses it."""
    ours = {"ipc_app", "hil_sim", "plc_bridge", "wara"}
    bad = {f: n for f, n in _imports("acceptance").items() if n & ours}
    assert not bad, f"acceptance may import only config of ours: {bad}"


def test_bridge_and_config_are_leaves() -> None:
    for pkg, allowed in (("plc_bridge", {"config"}), ("config", set())):
        ours = {"ipc_app", "hil_sim", "plc_bridge", "config", "acceptance", "wara"}
        ours -= allowed | {pkg}
        bad = {f: n for f, n in _imports(pkg).items() if n & ours}
        assert not bad, f"{pkg} may import only {allowed or 'nothing'} of ours: {bad}"

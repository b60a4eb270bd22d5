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


#: The planners the service runs: only its planner process may call them
#: (ipc_app/service/worker.py names them for PlannerWorker.call).
PLANNING = {
    "ipc_app.planner": {"plan"},
    "ipc_app.planner.plan": {"plan"},
    "ipc_app.planner.walk": {"plan_walk"},
    "ipc_app.planner.placement": {"plan_from_deviation", "plan_target"},
}


def test_the_service_plans_only_in_its_planner_process() -> None:
    """No module of the service but the worker imports a planning function: the walk,
    the placement target and the attitude trajectory are planned in the planner process
    (``PlannerWorker.call``), never in a thread of the loop's process."""
    bad: dict[str, list[str]] = {}
    for path in (REPO / "ipc_app" / "service").rglob("*.py"):
        if path.name == "worker.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.ImportFrom) and node.module in PLANNING:
                names = [a.name for a in node.names if a.name in PLANNING[node.module]]
                if names:
                    bad.setdefault(path.name, []).extend(names)
    assert not bad, f"planning in the service's process: {bad}"


def test_the_planner_processs_functions_exist() -> None:
    import importlib
    import inspect

    from ipc_app.service import worker

    names = [n for n in dir(worker) if n.startswith("PLAN_") and n.endswith("_FN")]
    assert len(names) == 4
    for name in names:
        module, _, fn = getattr(worker, name).partition(":")
        target = getattr(importlib.import_module(module), fn)
        assert next(iter(inspect.signature(target).parameters)) == "cfg", name

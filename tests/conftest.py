"""Shared fixtures, and the order the suite runs in.

How a test runs is said by its markers (registered in pyproject.toml):

- ``slow``: an end-to-end run, a subprocess, a study, a fuzzer or a campaign (more than
  a few seconds). The fast lane (``-m "not slow"``) leaves these out. On a test that
  takes minutes, ``@pytest.mark.slow(seconds=N)`` (N: about what it takes here) starts
  it before the shorter ones.
- ``realtime``: its verdict depends on the wall clock: a loop, a simulator or two
  processes in real time judged on keeping pace (overruns, jitter, link time-outs), or
  an elapsed time checked against a bound near what it should take (not a hang guard).
  These need the CPUs to themselves.
- ``xdist_group("name")``: tests that share one expensive set-up (a fixture of module
  scope: one run, several tests asserting on it) run on the same worker, one after the
  other, so that the run is made once.

Everything else is deterministic whatever the load (lockstep runs on the simulated clock,
pure functions), so the README's test command runs it on every CPU (``pytest -n auto``):
the slow tests first, longest first, then the others, one test at a time per worker;
then, once every other test has ended and the other workers have stopped, the
``realtime`` tests one after another on one worker (:class:`RealtimeLast`). Without
``-n`` the order is the same.

A new test: ``slow`` if it takes more than a few seconds (with ``seconds=`` if minutes),
``realtime`` if its verdict reads the wall clock; a second test on the same expensive run
takes that run from a module-scoped fixture and both get the same ``xdist_group``.
"""

from __future__ import annotations

import json
import logging
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import structlog
from hypothesis import HealthCheck, settings

from config import ProjectConfig, load_project

REPO = Path(__file__).resolve().parents[1]

# Property tests check what a function computes, not how fast: no deadline per example and
# no health check on slow generation, both measured on the wall clock (on a loaded machine
# an example of tests/test_model.py took 1.2 s against the default 200 ms deadline, and
# hypothesis failed the test as flaky). A test may still set its own deadline as a guard
# against a hang (tests/test_service_ctl_fuzz.py: 10 s).
settings.register_profile("wara", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("wara")

#: The key of xdist's worker input naming the directory where each worker writes how its
#: tests are to be scheduled (:func:`pytest_collection_modifyitems`).
_ORDER_DIR = "wara_order_dir"


@pytest.fixture(scope="session")
def project() -> ProjectConfig:
    """The shipped Shanghai Airport Link project."""
    return load_project()


@pytest.fixture(autouse=True)
def _process_logging_restored() -> Iterator[None]:
    """A command run in this process (``wara.cli.main``) configures its logging as the
    service does (structlog, the root logger's handlers and level): put it back after each
    test, so that no test depends on which test ran before it in the same process."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    config = structlog.get_config()
    yield
    root.handlers[:] = handlers
    root.setLevel(level)
    structlog.configure(**config)


def _group(item: pytest.Item) -> str | None:
    mark = item.get_closest_marker("xdist_group")
    if mark is None:
        return None
    return str(mark.args[0] if mark.args else mark.kwargs.get("name", "default"))


def _phase(item: pytest.Item) -> int:
    """0: slow, 1: the others, 2: real-time."""
    if item.get_closest_marker("realtime") is not None:
        return 2
    return 0 if item.get_closest_marker("slow") is not None else 1


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The run's order: slow (the longest ``seconds=`` first, a group as its longest), the
    others, then the real-time tests; the collection's order within each (so a module's
    tests stay together)."""
    hint: dict[str, float] = {}
    for it in items:
        mark = it.get_closest_marker("slow")
        s = float(mark.kwargs.get("seconds", 0.0)) if mark is not None else 0.0
        hint[it.nodeid] = s
        g = _group(it)
        if g is not None:
            hint[g] = max(hint.get(g, 0.0), s)
    items.sort(key=lambda it: (_phase(it), -hint[_group(it) or it.nodeid]))


@pytest.hookimpl(tryfirst=True)  # before xdist sends the collection to the controller
def pytest_collection_finish(session: pytest.Session) -> None:
    """Under xdist, each worker writes which of the tests it will run are real-time, slow
    and grouped, for the controller's scheduler."""
    workerinput = getattr(session.config, "workerinput", None)
    if workerinput is None or _ORDER_DIR not in workerinput:
        return
    items = session.items
    order = {
        "realtime": [it.nodeid for it in items if _phase(it) == 2],
        "slow": [it.nodeid for it in items if _phase(it) == 0],
        "groups": {it.nodeid: g for it in items if (g := _group(it)) is not None},
    }
    path = Path(workerinput[_ORDER_DIR]) / f"{workerinput['workerid']}.json"
    path.write_text(json.dumps(order), encoding="utf-8")


def pytest_configure(config: pytest.Config) -> None:
    if config.pluginmanager.hasplugin("xdist") and not hasattr(config, "workerinput"):
        config.pluginmanager.register(_XdistOrder(), "wara-xdist-order")


class _XdistOrder:
    """On xdist's controller: the directory for the workers' orders, and
    :class:`RealtimeLast` as the scheduler of ``--dist load`` (what ``-n`` gives)."""

    def __init__(self) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="wara-pytest-order-"))

    def pytest_configure_node(self, node: Any) -> None:
        node.workerinput[_ORDER_DIR] = str(self.dir)

    def pytest_xdist_make_scheduler(self, config: pytest.Config, log: Any) -> Any:
        if config.getoption("dist") != "load":
            return None
        return _realtime_last()(config, log, self.dir)

    def pytest_unconfigure(self) -> None:
        for p in self.dir.glob("*.json"):
            p.unlink()
        self.dir.rmdir()


def _realtime_last() -> type:
    from xdist.scheduler import LoadScheduling

    class RealtimeLast(LoadScheduling):  # type: ignore[misc]
        """xdist's load scheduling in the suite's order, a few tests at a time per worker
        (a group's tests sent together), with the real-time tests held back. Once only
        they are left, one worker gets the first of them as its next test (so that it
        finishes its last other test) and the other workers stop; when they have
        stopped, that worker runs the real-time tests one after another, alone."""

        def __init__(self, config: pytest.Config, log: Any, order_dir: Path) -> None:
            super().__init__(config, log)
            self.order_dir = order_dir
            self.realtime: set[int] = set()
            self.slow: set[int] = set()
            self.group_of: dict[int, str] = {}
            self.held: list[int] = []
            self.rt_node: Any = None
            self.released = False

        @property
        def tests_finished(self) -> bool:
            return (
                not self.held
                and (self.rt_node is None or self.released)
                and bool(super().tests_finished)
            )

        @property
        def has_pending(self) -> bool:
            return bool(self.held) or bool(super().has_pending)

        def schedule(self) -> None:
            if self.collection is None:
                if not self._check_nodes_have_same_collection():
                    self.log("**Different tests collected, aborting run**")
                    return
                self.collection = list(next(iter(self.node2collection.values())))
                node = next(iter(self.node2collection))
                path = self.order_dir / f"{node.gateway.id}.json"
                order = json.loads(path.read_text(encoding="utf-8"))
                index = {nodeid: i for i, nodeid in enumerate(self.collection)}
                self.realtime = {index[n] for n in order["realtime"]}
                self.slow = {index[n] for n in order["slow"]}
                self.group_of = {index[n]: g for n, g in order["groups"].items()}
                self.held = sorted(self.realtime)
                self.pending[:] = [i for i in index.values() if i not in self.realtime]
            for node in self.nodes:
                self.check_schedule(node)

        def check_schedule(self, node: Any, duration: float = 0.0) -> None:
            if node.shutting_down:
                return
            if self.pending:
                # A worker starts a test once it knows the one after it: a slow test
                # waits in the queue behind one other only (so the longest ones go to
                # different workers), a short one behind seven (so the worker never
                # waits for this process between them).
                depth = 2 if self.pending[0] in self.slow else 8
                queued = self.node2pending[node]
                if len(queued) < depth:
                    self._send(node, depth - len(queued))
                return
            if not self.held and self.rt_node is None:
                node.shutdown()
                return
            if self.rt_node is None:
                self.rt_node = node
                self._send_held(node, 1)
                for other in self.nodes:
                    if other is not node:
                        other.shutdown()
            elif node is not self.rt_node:
                node.shutdown()
            self._release()

        def _send(self, node: Any, n: int) -> None:
            """The next ``n`` pending tests, each with the rest of its group after it."""
            ids: list[int] = []
            while self.pending and len(ids) < n:
                i = self.pending.pop(0)
                ids.append(i)
                g = self.group_of.get(i)
                if g is not None:
                    mates = [j for j in self.pending if self.group_of.get(j) == g]
                    self.pending[:] = [j for j in self.pending if self.group_of.get(j) != g]
                    ids.extend(mates)
            self.node2pending[node].extend(ids)
            node.send_runtest_some(ids)

        def _send_held(self, node: Any, n: int) -> None:
            ids, self.held[:n] = self.held[:n], []
            if ids:
                self.node2pending[node].extend(ids)
                node.send_runtest_some(ids)

        def _release(self) -> None:
            """The rest of the real-time tests to their worker, once it is the only one
            left and has ended every other test."""
            node = self.rt_node
            if node is None or self.released or len(self.nodes) > 1:
                return
            if not set(self.node2pending[node]) <= self.realtime:
                return
            self.released = True
            self._send_held(node, len(self.held))
            node.shutdown()

        def remove_node(self, node: Any) -> Any:
            """A worker that stopped (or crashed: its test is returned, the rest of its
            queue goes back, the real-time tests among it held again)."""
            queued = self.node2pending.pop(node)
            if node is self.rt_node:
                self.rt_node, self.released = None, False
            crashitem = None
            if queued:
                assert self.collection is not None
                crashitem = self.collection[queued.pop(0)]
                self.pending[:0] = [i for i in queued if i not in self.realtime]
                self.held = sorted(set(self.held) | (set(queued) & self.realtime))
            for other in self.nodes:
                self.check_schedule(other)
            self._release()
            return crashitem

    return RealtimeLast

"""The lockstep demo's run record against a stored golden record.

Refactors of the service core, the link and the harness must not change behaviour: the
run record (``samples.csv``, ``events.jsonl``) of Example 1 in lockstep is compared
with the one stored in ``tests/golden/lockstep_example1/``.

- Numbers are compared to 1e-6 relative (and 1e-6 absolute, in the column's unit), not
  byte for byte: the simulator's numba kernels may round differently on another CPU, and
  the record keeps 9 significant digits. A behaviour change moves values far more.
- Text, integers and booleans must be equal.
- Keys measured on the wall clock (:data:`WALL_CLOCK_KEYS`) are left out.

Regenerate only on purpose (a behaviour change that is meant), then review the diff::

    WARA_REGENERATE_GOLDEN=1 .venv/bin/python -m pytest tests/test_golden_record.py
"""

from __future__ import annotations

import csv
import gzip
import io
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

import pytest

from config import load_project
from ipc_app.service.core import ServiceCore
from ipc_app.service.modes import Mode
from ipc_app.service.record import EVENTS, SAMPLES, RunRecorder
from wara.examples import EXAMPLES
from wara.harness import Harness

GOLDEN = Path(__file__).parent / "golden" / "lockstep_example1"
WALL_CLOCK_KEYS = frozenset(
    {"solve_time_s", "solve_time_share_of_task_percent", "elapsed_s", "first_t_s", "last_t_s"}
)
REL = 1e-6
ABS = 1e-6

pytestmark = pytest.mark.slow


def record_example1(run_dir: Path) -> None:
    cfg = load_project()
    rec = RunRecorder(run_dir, ServiceCore.record_columns(cfg))
    rec.start()
    demo = Harness(cfg, None, mode="lockstep", record=rec)
    try:
        demo.start()
        assert demo.wait_for(Mode.IDLE, 20.0), demo.fault_note()
        result = demo.run_example(*EXAMPLES[0])
        assert result.passed, result.note
    finally:
        demo.close()
        rec.stop()


def _strip(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in WALL_CLOCK_KEYS}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _differs(a: Any, b: Any) -> bool:
    if isinstance(a, bool) or isinstance(b, bool) or isinstance(a, str) or isinstance(b, str):
        return bool(a != b)
    if isinstance(a, int) and isinstance(b, int):
        return a != b
    if isinstance(a, float | int) and isinstance(b, float | int):
        return not math.isclose(a, b, rel_tol=REL, abs_tol=ABS)
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() != b.keys() or any(_differs(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) != len(b) or any(_differs(x, y) for x, y in zip(a, b, strict=True))
    return bool(a != b)


def _read_samples(text: str) -> tuple[list[str], list[list[str]]]:
    rows = list(csv.reader(io.StringIO(text)))
    return rows[0], rows[1:]


def _cell_differs(a: str, b: str) -> bool:
    try:
        return _differs(float(a), float(b)) if a != b else False
    except ValueError:
        return a != b


def test_lockstep_example1_record_matches_golden(tmp_path: Path) -> None:
    run = tmp_path / "run"
    record_example1(run)
    if os.environ.get("WARA_REGENERATE_GOLDEN") == "1":
        GOLDEN.mkdir(parents=True, exist_ok=True)
        with gzip.open(GOLDEN / (SAMPLES + ".gz"), "wb", compresslevel=9) as out:
            out.write((run / SAMPLES).read_bytes())
        shutil.copyfile(run / EVENTS, GOLDEN / EVENTS)
        pytest.skip("golden record regenerated: review `git diff tests/golden`")

    head, rows = _read_samples((run / SAMPLES).read_text())
    with gzip.open(GOLDEN / (SAMPLES + ".gz"), "rt") as f:
        g_head, g_rows = _read_samples(f.read())
    assert head == g_head, "the run record's columns changed"
    assert len(rows) == len(g_rows), f"{len(rows)} rows, golden {len(g_rows)}"
    for i, (row, g_row) in enumerate(zip(rows, g_rows, strict=True)):
        bad = [
            f"{col}={v} (golden {g})"
            for col, v, g in zip(head, row, g_row, strict=True)
            if _cell_differs(v, g)
        ]
        assert not bad, f"samples.csv row {i + 1} (t_s={row[0]}): " + ", ".join(bad[:6])

    events = [_strip(json.loads(line)) for line in (run / EVENTS).read_text().splitlines()]
    golden = [_strip(json.loads(line)) for line in (GOLDEN / EVENTS).read_text().splitlines()]
    assert [e["kind"] for e in events] == [e["kind"] for e in golden]
    for i, (e, g) in enumerate(zip(events, golden, strict=True)):
        assert not _differs(e, g), f"events.jsonl line {i + 1} differs:\n{e}\ngolden:\n{g}"

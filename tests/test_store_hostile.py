"""Hostile acceptance-store paths (docs/hostile-input.md, "Store paths"): a directory,
a device, a FIFO, a survey CSV, another program's SQLite file or a newer schema as
``--db``. The store is checked (:func:`acceptance.store.check_store`) before anything
moves or is written, by every command with ``--db``: one line, exit 2. Before, ``wara
cycle`` ran the whole cycle and then failed to write the record, and ``wara serve``
started without complaint."""

from __future__ import annotations

import os
import re
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from acceptance.store import SCHEMA_VERSION, AcceptanceStore, StoreError, check_store
from config import load_project
from ipc_app.model.placement import design_pose
from ipc_app.planner.survey import format_survey
from tests.cli_helpers import run_main, run_wara
from wara.cycle import survey_faces

CANNOT = "cannot use as acceptance database"


def _bad(kind: str, tmp_path: Path) -> tuple[Path, str]:
    """A path that is no acceptance store, and the reason it is refused for."""
    if kind == "directory":
        d = tmp_path / "dir"
        d.mkdir()
        return d, f"{CANNOT}: a directory, expected a database file"
    if kind == "dev_zero":
        return Path("/dev/zero"), f"{CANNOT}: a device, expected a database file"
    if kind == "fifo":
        f = tmp_path / "db.fifo"
        os.mkfifo(f)
        return f, f"{CANNOT}: a FIFO (named pipe), expected a database file"
    if kind == "csv":
        f = tmp_path / "survey.csv"
        f.write_text("ring,measured_at\n1,2024-03-05T10:30\n", encoding="utf-8")
        return f, f"{CANNOT}: not an SQLite database"
    if kind == "other_sqlite":
        f = tmp_path / "other.sqlite"
        conn = sqlite3.connect(f)
        conn.execute("CREATE TABLE t (x)")
        conn.close()
        return f, f"{CANNOT}: an SQLite database of another program"
    assert kind == "newer"
    f = tmp_path / "newer.sqlite"
    AcceptanceStore.open(f).close()
    conn = sqlite3.connect(f)
    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    conn.close()
    return f, "is newer than this software understands"


KINDS = ("directory", "dev_zero", "fifo", "csv", "other_sqlite", "newer")


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("create", [True, False])
def test_check_store_refuses_what_is_no_store(tmp_path: Path, kind: str, create: bool) -> None:
    path, why = _bad(kind, tmp_path)

    def files() -> list[Path]:  # SQLite's own -wal / -shm files of a read aside
        return sorted(p for p in tmp_path.rglob("*") if not p.name.endswith(("-wal", "-shm")))

    before = files()
    t0 = time.monotonic()
    with pytest.raises(StoreError) as exc:
        check_store(path, create=create)
    assert time.monotonic() - t0 < 2.0  # a FIFO does not block
    msg = str(exc.value)
    assert msg.startswith(f"{path}: ") and why in msg and "\n" not in msg
    with pytest.raises(StoreError, match=re.escape(why)):
        AcceptanceStore.open(path, create=create)  # the store's own open checks alike
    assert files() == before  # nothing created beside it


def test_check_store_creates_nothing_and_needs_a_place_to_create(tmp_path: Path) -> None:
    new = tmp_path / "a" / "b" / "acc.sqlite"
    assert check_store(new, create=True) == new
    assert not (tmp_path / "a").exists()
    with pytest.raises(StoreError, match="no acceptance database here"):
        check_store(new, create=False)
    (tmp_path / "file").write_text("x")
    with pytest.raises(
        StoreError, match=r"cannot create the acceptance database: .*file is not a directory"
    ):
        check_store(tmp_path / "file" / "acc.sqlite", create=True)
    empty = tmp_path / "empty.sqlite"
    empty.touch()  # SQLite makes an empty file a database
    assert check_store(empty, create=True) == empty
    AcceptanceStore.open(tmp_path / "ok.sqlite").close()
    assert check_store(tmp_path / "ok.sqlite", create=False) == tmp_path / "ok.sqlite"


def _survey(tmp_path: Path) -> Path:
    cfg = load_project(None)
    path = tmp_path / "ring4.csv"
    path.write_text(format_survey(cfg, 4, design_pose(cfg, 4), survey_faces(cfg, 6)))
    return path


def _forbid(monkeypatch: pytest.MonkeyPatch, target: str) -> list[Any]:
    """Replace ``target`` by a spy that fails the test when anything calls it."""
    calls: list[Any] = []

    def spy(*a: Any, **k: Any) -> Any:
        calls.append(a)
        raise AssertionError(f"{target} was called: the store was not checked first")

    monkeypatch.setattr(target, spy)
    return calls


COMMANDS: dict[str, Callable[[Path, Path], list[str]]] = {
    "cycle": lambda db, t: ["cycle", "--lockstep", "--rings", "1", "--db", str(db)],
    "serve": lambda db, t: ["serve", "--db", str(db), "--socket", str(t / "c.sock")],
    "survey-import": lambda db, t: [
        "survey",
        "import",
        str(_survey(t)),
        "--ring",
        "4",
        "--db",
        str(db),
    ],
    "place-plan-from-store": lambda db, t: ["place", "plan", "--from-store", "--db", str(db)],
    "ctl-survey-from-store": lambda db, t: ["ctl", "survey", "--from-store", "--db", str(db)],
    "ctl-cycle-from-store": lambda db, t: [
        "ctl",
        "cycle",
        "--ring",
        "3",
        "--from-store",
        "--db",
        str(db),
    ],
    "acceptance-import": lambda db, t: ["acceptance", "import", str(t / "x.csv"), "--db", str(db)],
    "acceptance-list": lambda db, t: ["acceptance", "list", "--db", str(db)],
    "acceptance-history": lambda db, t: ["acceptance", "history", "3", "--db", str(db)],
}


@pytest.mark.parametrize("kind", ["directory", "dev_zero", "csv"])
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_with_db_refuses_a_bad_store_first(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kind: str, command: str
) -> None:
    monkeypatch.setenv("WARA_CTL_SOCKET", str(tmp_path / "none.sock"))  # no service
    ran = _forbid(monkeypatch, "wara.cycle.run_cycle")
    ran += _forbid(monkeypatch, "wara.commands.serve.run_service")
    path, why = _bad(kind, tmp_path)
    t0 = time.monotonic()
    code, out, err = run_main(COMMANDS[command](path, tmp_path))
    assert time.monotonic() - t0 < 5.0
    assert (code, out, ran) == (2, "", [])
    (line,) = err.splitlines()
    assert f"{path}: {why}" in line, line
    assert line.startswith(f"wara {COMMANDS[command](path, tmp_path)[0]}: error: ")


@pytest.mark.parametrize(
    "argv",
    [
        ["cycle", "--lockstep", "--rings", "1", "--db", "{d}"],
        ["serve", "--db", "{d}", "--socket", "{t}/c.sock", "--duration-s", "5"],
    ],
    ids=["cycle", "serve"],
)
def test_cycle_and_serve_refuse_a_directory_in_a_subprocess(
    tmp_path: Path, argv: list[str]
) -> None:
    d = tmp_path / "dir"
    d.mkdir()
    args = [a.replace("{d}", str(d)).replace("{t}", str(tmp_path)) for a in argv]
    proc = run_wara(args, timeout_s=60)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr == (
        f"wara {argv[0]}: error: {d}: {CANNOT}: a directory, expected a database file\n"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir"]  # no socket, no records


def test_a_poisoned_as_built_pose_in_the_store_is_refused(tmp_path: Path) -> None:
    """A pose written into the store around this software (1e300 mm) gave ``wara place
    plan --from-store`` no plausibility check."""
    db = tmp_path / "acc.sqlite"
    with AcceptanceStore.open(db) as store:
        huge = dict.fromkeys(("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"), 1e300)
        store.attach_plan(4, {"kind": "survey"}, final_attitude={"as_built_pose": huge})
    code, out, err = run_main(["place", "plan", "--from-store", "--db", str(db)])
    assert (code, out) == (2, "")
    (line,) = err.splitlines()
    assert line.startswith(f"wara place: error: {db}: ring 4's as-built pose: the part is 1.")

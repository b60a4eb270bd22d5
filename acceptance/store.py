"""Durable store of ring acceptance records in SQLite.

Guarantees:

- **Nothing acknowledged is lost.** The database runs in WAL mode with
  ``synchronous=FULL``: when :meth:`AcceptanceStore.add`, :meth:`~AcceptanceStore.add_many`
  or :meth:`~AcceptanceStore.attach_plan` returns, the transaction is on disk and survives
  a killed process or a power cut.
- **All or nothing per call.** :meth:`~AcceptanceStore.add_many` (one CSV file) writes
  every record in one ``BEGIN IMMEDIATE`` transaction; a crash or an exception part-way
  leaves none of them.
- **History is kept.** Records are append-only (triggers refuse UPDATE and DELETE).
  Re-recording a ring adds a new record; the ring's *current* record is the one recorded
  last (highest id), earlier ones stay visible with :meth:`~AcceptanceStore.history`.

The controller's plan and final attitude for a ring are kept beside the survey, in their
own append-only table, because the plan exists before the ring is surveyed:
:meth:`~AcceptanceStore.attach_plan`.

Example::

    with AcceptanceStore.open("wara-data/acceptance.sqlite") as store:
        store.add(RingMeasurement(ring=12, measured_at="2024-03-05T10:30", values={...}))
        store.attach_plan(12, {"roll_deg": 2.0, "pitch_deg": 1.0, ...})
        current = store.current(ring_from=1, ring_to=50)
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
import stat
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any

from acceptance.items import ITEMS, ITEMS_BY_KEY, check_ring
from config.files import file_kind

#: Bumped when the table layout changes; a newer database is refused, not guessed at.
SCHEMA_VERSION = 1

#: Seconds a writer waits for another writer (the service, a second CLI) before failing.
BUSY_TIMEOUT_S = 10.0

DB_FILENAME = "acceptance.sqlite"

#: The first bytes of every SQLite database file.
SQLITE_HEADER = b"SQLite format 3\x00"


class StoreError(Exception):
    """The acceptance database cannot be used.

    Scenarios: the file is not an SQLite database, it was written by a newer version of
    this software, it is locked by another writer for longer than the busy timeout, or a
    read-only command was pointed at a path where no database exists.
    """


def default_db_path(environ: Mapping[str, str] | None = None) -> Path:
    """``$WARA_DATA_DIR/acceptance.sqlite``, else ``./wara-data/acceptance.sqlite``."""
    env = os.environ if environ is None else environ
    base = env.get("WARA_DATA_DIR") or "wara-data"
    return Path(base) / DB_FILENAME


def _newer(path: Path, version: int) -> StoreError:
    return StoreError(
        f"{path}: database schema version {version} is newer than this "
        f"software understands ({SCHEMA_VERSION}); update wara"
    )


def check_store(path: str | Path, *, create: bool) -> Path:
    """Check, before anything moves or is written, that ``path`` can be used as the
    acceptance store; the path, or :class:`StoreError` (one line naming the path).

    Every command with ``--db`` calls it first (and :meth:`AcceptanceStore.open` again).
    An existing path must be a regular file that is empty or an SQLite database of this
    software's schema (not newer, not another program's); ``create``: the command writes
    (the file writable, or its directory: the nearest existing one must be a writable
    directory). Without ``create`` the database must exist. Nothing is created here.
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except (FileNotFoundError, NotADirectoryError):  # not there (or under a file)
        st = None
    except OSError as exc:
        raise StoreError(f"{p}: cannot use as acceptance database: {exc.strerror}") from None
    if st is None:
        if not create:
            raise StoreError(
                f"{p}: no acceptance database here (record rings with `wara acceptance add` "
                "or `wara acceptance import` first, or pass --db)"
            )
        parent = p.absolute().parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir():
            raise StoreError(
                f"{p}: cannot create the acceptance database: {parent} is not a directory"
            )
        if not os.access(parent, os.W_OK | os.X_OK):
            raise StoreError(
                f"{p}: cannot create the acceptance database: no permission to write in {parent}"
            )
        return p
    if not stat.S_ISREG(st.st_mode):
        raise StoreError(
            f"{p}: cannot use as acceptance database: {file_kind(st.st_mode)}, "
            "expected a database file"
        )
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
        try:
            head = os.read(fd, len(SQLITE_HEADER))
        finally:
            os.close(fd)
    except OSError as exc:
        raise StoreError(f"{p}: cannot use as acceptance database: {exc.strerror}") from None
    if create and not os.access(p, os.W_OK):
        raise StoreError(f"{p}: no permission to write the acceptance database")
    if not head:
        return p  # an empty file: SQLite makes it a database
    if head != SQLITE_HEADER:
        raise StoreError(
            f"{p}: cannot use as acceptance database: not an SQLite database (a survey CSV "
            "goes to `wara acceptance import FILE`, the database to --db)"
        )
    try:
        conn = sqlite3.connect(f"{p.absolute().as_uri()}?mode=ro", uri=True, timeout=BUSY_TIMEOUT_S)
        try:
            version = conn.execute("PRAGMA user_version").fetchone()[0]
            tables = conn.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()[0]
        finally:
            conn.close()
    except sqlite3.DatabaseError as exc:
        raise StoreError(f"{p}: cannot use as acceptance database: {exc}") from None
    if version > SCHEMA_VERSION:
        raise _newer(p, version)
    if version == 0 and tables:
        raise StoreError(
            f"{p}: cannot use as acceptance database: an SQLite database of another program"
        )
    return p


def _now_utc() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def parse_time(text: str) -> str:
    """Normalise an ISO 8601 time (``2024-03-05T10:30``, ``2024-03-05 10:30:00+08:00``).

    A time without an offset is kept as written: it is the site's local time of the
    survey. Raises ValueError naming the expected form.
    """
    try:
        return datetime.fromisoformat(text.strip()).isoformat()
    except ValueError:
        shown = repr(text) if len(text) <= 40 else repr(text[:37] + "...")
        raise ValueError(
            f"{shown} is not an ISO 8601 time (expected e.g. 2024-03-05T10:30 or "
            "2024-03-05 10:30:00+08:00)"
        ) from None


@dataclass(frozen=True)
class RingMeasurement:
    """One survey of one installed ring, as entered (before it is stored).

    ``values`` maps item keys (see :data:`~acceptance.items.ITEMS`) to the
    measured value; the five linear items are required, the angles may be absent or None
    (not measured). Construction validates and raises ValueError with one reason.
    """

    ring: int
    measured_at: str
    values: Mapping[str, float | None]
    operator: str = ""
    remarks: str = ""

    def __post_init__(self) -> None:
        check_ring(self.ring)
        object.__setattr__(self, "measured_at", parse_time(self.measured_at))
        unknown = sorted(set(self.values) - set(ITEMS_BY_KEY))
        if unknown:
            raise ValueError(f"unknown control item(s) {', '.join(unknown)}")
        clean: dict[str, float | None] = {}
        for item in ITEMS:
            v = self.values.get(item.key)
            if v is None:
                if item.required:
                    raise ValueError(f"{item.key}: missing (required in every ring record)")
                clean[item.key] = None
                continue
            v = float(v)
            if not math.isfinite(v):
                raise ValueError(f"{item.key}: got {v!r}: expected a finite number")
            clean[item.key] = item.check(v)
        object.__setattr__(self, "values", clean)
        for name in ("operator", "remarks"):
            object.__setattr__(self, name, str(getattr(self, name)).strip())

    def same_survey_as(self, other: RingMeasurement) -> bool:
        """True when ``other`` records exactly this survey (used to skip re-imports)."""
        return (
            self.ring == other.ring
            and self.measured_at == other.measured_at
            and dict(self.values) == dict(other.values)
            and self.operator == other.operator
            and self.remarks == other.remarks
        )


@dataclass(frozen=True)
class StoredRecord:
    """A ring record as stored: the measurement plus where and when it was recorded."""

    record_id: int
    measurement: RingMeasurement
    recorded_at: str
    source: str
    import_id: int | None = None

    @property
    def ring(self) -> int:
        return self.measurement.ring

    def to_dict(self) -> dict[str, Any]:
        m = self.measurement
        return {
            "record_id": self.record_id,
            "ring": m.ring,
            "measured_at": m.measured_at,
            "recorded_at": self.recorded_at,
            "values": dict(m.values),
            "operator": m.operator,
            "remarks": m.remarks,
            "source": self.source,
            "import_id": self.import_id,
        }


@dataclass(frozen=True)
class StoredPlan:
    """The controller's plan (e.g. the ``wara plan --json`` object) attached to a ring."""

    plan_id: int
    ring: int
    attached_at: str
    plan: dict[str, Any] = field(default_factory=dict)
    final_attitude: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "plan_id": self.plan_id,
            "ring": self.ring,
            "attached_at": self.attached_at,
            "plan": self.plan,
            "final_attitude": self.final_attitude,
        }


def _ddl() -> list[str]:
    """The statements that create an empty database (schema version 1)."""
    item_cols = ",\n  ".join(f"{i.key} REAL{' NOT NULL' if i.required else ''}" for i in ITEMS)
    stmts = [
        """CREATE TABLE import_batch (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  file TEXT NOT NULL,
  sha256 TEXT NOT NULL,
  imported_at TEXT NOT NULL,
  rows_recorded INTEGER NOT NULL,
  rows_unchanged INTEGER NOT NULL,
  rows_rejected INTEGER NOT NULL
)""",
        f"""CREATE TABLE ring_record (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  ring INTEGER NOT NULL CHECK (ring >= 1),
  measured_at TEXT NOT NULL,
  recorded_at TEXT NOT NULL,
  {item_cols},
  operator TEXT NOT NULL DEFAULT '',
  remarks TEXT NOT NULL DEFAULT '',
  source TEXT NOT NULL,
  import_id INTEGER REFERENCES import_batch(id)
)""",
        "CREATE INDEX ring_record_by_ring ON ring_record (ring, id)",
        """CREATE TABLE ring_plan (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  ring INTEGER NOT NULL CHECK (ring >= 1),
  attached_at TEXT NOT NULL,
  plan_json TEXT NOT NULL,
  final_attitude_json TEXT
)""",
        "CREATE INDEX ring_plan_by_ring ON ring_plan (ring, id)",
    ]
    for table in ("ring_record", "ring_plan", "import_batch"):
        for op in ("UPDATE", "DELETE"):
            stmts.append(
                f"CREATE TRIGGER {table}_no_{op.lower()} BEFORE {op} ON {table} BEGIN "
                f"SELECT RAISE(ABORT, '{table} is append-only: record the ring again'); END"
            )
    stmts.append(f"PRAGMA user_version = {SCHEMA_VERSION}")
    return stmts


_RECORD_COLS = (
    "id, ring, measured_at, recorded_at, "
    + ", ".join(i.key for i in ITEMS)
    + ", operator, remarks, source, import_id"
)


def _row_to_record(row: sqlite3.Row) -> StoredRecord:
    try:
        m = RingMeasurement(
            ring=row["ring"],
            measured_at=row["measured_at"],
            values={i.key: row[i.key] for i in ITEMS},
            operator=row["operator"],
            remarks=row["remarks"],
        )
    except (ValueError, TypeError) as exc:
        # Written around this software (the triggers only refuse UPDATE and DELETE).
        raise StoreError(f"record #{row['id']} in the database is not valid: {exc}") from None
    return StoredRecord(
        record_id=row["id"],
        measurement=m,
        recorded_at=row["recorded_at"],
        source=row["source"],
        import_id=row["import_id"],
    )


def _json_text(obj: Mapping[str, Any], what: str) -> str:
    if not isinstance(obj, Mapping):
        raise ValueError(f"{what}: expected a JSON object (mapping), got {type(obj).__name__}")
    try:
        return json.dumps(dict(obj), sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: not JSON-serialisable: {exc}") from None


class AcceptanceStore:
    """The acceptance database. One instance per thread; open with :meth:`open`."""

    def __init__(self, path: str | Path, *, create: bool = True) -> None:
        self.path = check_store(path, create=create)
        if not self.path.exists():
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise StoreError(f"{self.path}: cannot create: {exc.strerror}") from None
        try:
            # isolation_level=None: no implicit transactions; we BEGIN/COMMIT explicitly.
            self._conn = sqlite3.connect(self.path, timeout=BUSY_TIMEOUT_S, isolation_level=None)
            self._conn.row_factory = sqlite3.Row
            self._conn.execute("PRAGMA journal_mode=WAL")
            self._conn.execute("PRAGMA synchronous=FULL")
            self._conn.execute("PRAGMA foreign_keys=ON")
            self._migrate()
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{self.path}: cannot use as acceptance database: {exc}") from None

    @classmethod
    def open(cls, path: str | Path, *, create: bool = True) -> AcceptanceStore:
        """Open (and with ``create`` make) the database at ``path``, checked first
        (:func:`check_store`)."""
        return cls(path, create=create)

    def __enter__(self) -> AcceptanceStore:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        self._conn.close()

    # ------------------------------------------------------------------ internals

    def _migrate(self) -> None:
        version = self._conn.execute("PRAGMA user_version").fetchone()[0]
        if version == SCHEMA_VERSION:
            return
        if version > SCHEMA_VERSION:
            raise _newer(self.path, version)
        with self._transaction():
            # Re-check under the write lock: another process may have created it.
            if self._conn.execute("PRAGMA user_version").fetchone()[0] == 0:
                for stmt in _ddl():
                    self._conn.execute(stmt)

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        """BEGIN IMMEDIATE ... COMMIT; ROLLBACK on any exception."""
        try:
            self._conn.execute("BEGIN IMMEDIATE")
        except sqlite3.OperationalError as exc:
            raise StoreError(f"{self.path}: cannot start a write: {exc}") from None
        try:
            yield self._conn
        except BaseException:
            self._conn.execute("ROLLBACK")
            raise
        self._conn.execute("COMMIT")

    def _insert_record(
        self, m: RingMeasurement, source: str, import_id: int | None, recorded_at: str
    ) -> int:
        cols = ["ring", "measured_at", "recorded_at", *m.values, "operator", "remarks"]
        cols += ["source", "import_id"]
        vals = [m.ring, m.measured_at, recorded_at, *m.values.values(), m.operator, m.remarks]
        vals += [source, import_id]
        cur = self._conn.execute(
            f"INSERT INTO ring_record ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})",
            vals,
        )
        assert cur.lastrowid is not None
        return cur.lastrowid

    # ------------------------------------------------------------------ writes

    def add(self, measurement: RingMeasurement, *, source: str = "api") -> StoredRecord:
        """Record one ring survey (a new record even if the ring exists: history is kept)."""
        recorded_at = _now_utc()
        with self._transaction():
            rid = self._insert_record(measurement, source, None, recorded_at)
        return StoredRecord(rid, measurement, recorded_at, source)

    def add_many(
        self,
        measurements: Sequence[RingMeasurement],
        *,
        source: str,
        batch: Mapping[str, Any] | None = None,
        sources: Sequence[str] | None = None,
    ) -> tuple[list[StoredRecord], int | None]:
        """Record several surveys in one transaction: all of them or, on any error, none.

        ``batch`` (keys ``file``, ``sha256``, ``rows_unchanged``, ``rows_rejected``)
        logs an import in ``import_batch`` in the same transaction; the new batch id is
        returned with the records. ``sources`` gives a per-record source (e.g. the CSV
        line) instead of ``source``.
        """
        if sources is not None and len(sources) != len(measurements):
            raise ValueError("sources must have one entry per measurement")
        recorded_at = _now_utc()
        out: list[StoredRecord] = []
        import_id: int | None = None
        with self._transaction() as conn:
            if batch is not None:
                cur = conn.execute(
                    "INSERT INTO import_batch (file, sha256, imported_at, rows_recorded, "
                    "rows_unchanged, rows_rejected) VALUES (?, ?, ?, ?, ?, ?)",
                    (
                        str(batch["file"]),
                        str(batch["sha256"]),
                        recorded_at,
                        len(measurements),
                        int(batch.get("rows_unchanged", 0)),
                        int(batch.get("rows_rejected", 0)),
                    ),
                )
                import_id = cur.lastrowid
            for n, m in enumerate(measurements):
                src = sources[n] if sources is not None else source
                rid = self._insert_record(m, src, import_id, recorded_at)
                out.append(StoredRecord(rid, m, recorded_at, src, import_id))
        return out, import_id

    def attach_plan(
        self,
        ring: int,
        plan: Mapping[str, Any],
        *,
        final_attitude: Mapping[str, Any] | None = None,
    ) -> StoredPlan:
        """Attach the controller's plan (and final attitude, when known) to a ring.

        ``plan`` is any JSON object, e.g. the ``wara plan --json`` output;
        ``final_attitude`` e.g. ``{"roll_deg": .., "pitch_deg": .., "z_mm": ..}`` as the
        controller ended. The ring need not be surveyed yet. Attaching again keeps the
        earlier plan in history; :meth:`latest_plan` returns the newest.
        """
        check_ring(ring)
        plan_text = _json_text(plan, "plan")
        att_text = None if final_attitude is None else _json_text(final_attitude, "final_attitude")
        attached_at = _now_utc()
        with self._transaction() as conn:
            cur = conn.execute(
                "INSERT INTO ring_plan (ring, attached_at, plan_json, final_attitude_json) "
                "VALUES (?, ?, ?, ?)",
                (ring, attached_at, plan_text, att_text),
            )
        assert cur.lastrowid is not None
        return StoredPlan(
            cur.lastrowid,
            ring,
            attached_at,
            json.loads(plan_text),
            None if att_text is None else json.loads(att_text),
        )

    # ------------------------------------------------------------------ reads

    def current(
        self, ring_from: int | None = None, ring_to: int | None = None
    ) -> list[StoredRecord]:
        """The current (last recorded) record of each ring in ``[ring_from, ring_to]``."""
        lo = 1 if ring_from is None else ring_from
        hi = 2**62 if ring_to is None else ring_to
        rows = self._conn.execute(
            f"SELECT {_RECORD_COLS} FROM ring_record WHERE id IN "
            "(SELECT MAX(id) FROM ring_record WHERE ring BETWEEN ? AND ? GROUP BY ring) "
            "ORDER BY ring",
            (lo, hi),
        ).fetchall()
        return [_row_to_record(r) for r in rows]

    def history(self, ring: int) -> list[StoredRecord]:
        """Every record of ``ring``, oldest first; the last one is current."""
        rows = self._conn.execute(
            f"SELECT {_RECORD_COLS} FROM ring_record WHERE ring = ? ORDER BY id", (ring,)
        ).fetchall()
        return [_row_to_record(r) for r in rows]

    def plans(self, ring: int) -> list[StoredPlan]:
        """Every plan attached to ``ring``, oldest first."""
        rows = self._conn.execute(
            "SELECT id, ring, attached_at, plan_json, final_attitude_json FROM ring_plan "
            "WHERE ring = ? ORDER BY id",
            (ring,),
        ).fetchall()
        return [
            StoredPlan(
                r["id"],
                r["ring"],
                r["attached_at"],
                json.loads(r["plan_json"]),
                None if r["final_attitude_json"] is None else json.loads(r["final_attitude_json"]),
            )
            for r in rows
        ]

    def latest_plan(self, ring: int) -> StoredPlan | None:
        """The newest plan attached to ``ring``, or None."""
        plans = self.plans(ring)
        return plans[-1] if plans else None

    def rings_with_plan(self) -> set[int]:
        """Ring numbers that have at least one plan attached."""
        return {r[0] for r in self._conn.execute("SELECT DISTINCT ring FROM ring_plan")}

    def record_counts(self) -> dict[int, int]:
        """Ring -> number of records (1 = never re-recorded)."""
        rows = self._conn.execute("SELECT ring, COUNT(*) FROM ring_record GROUP BY ring")
        return {int(r[0]): int(r[1]) for r in rows}

    def record_count(self) -> int:
        """Number of stored records, history included."""
        return int(self._conn.execute("SELECT COUNT(*) FROM ring_record").fetchone()[0])

    def integrity_ok(self) -> bool:
        """SQLite's own consistency check of the file."""
        return bool(self._conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok")

"""Import a survey CSV export: bad rows are rejected with line numbers and reasons.

Semantics (one file = one transaction, whole file or nothing):

- The whole file is read and checked before anything is written (or any database is
  created).
- A file-level problem (file missing, not a regular file, over :data:`MAX_CSV_BYTES`,
  not UTF-8, no header, unknown / duplicate / missing required column) raises
  :class:`CsvFileError`: nothing is written.
- Every bad row is reported as ``line N: reason``; if there is any, **nothing** of the
  file is written. Otherwise every row is written in **one** transaction; a crash
  part-way writes none of the file's rows.
- A ring that appears on more than one row of the same file is ambiguous (which survey
  is right?): all its rows are rejected. Put a re-survey in its own file or use
  ``wara acceptance add``.
- A row identical to the ring's current record (same time, values, operator, remarks)
  is skipped as *unchanged*, so importing a corrected file again only adds the
  corrected rows.

Format: UTF-8 (a BOM as written by spreadsheet programs is fine), comma-separated, one
header row naming the columns (any order, case-insensitive); blank lines and lines whose
first cell starts with ``#`` are ignored. One row is one line: a field may not contain
a line break (a quote left open would otherwise swallow the rows after it). Columns:
``ring``, ``measured_at`` and the five linear items are required; the three angle items,
``operator`` and ``remarks`` are optional. An empty angle cell means "not measured".
Ring numbers and values: :mod:`acceptance.items` (ASCII digits, sign, decimal
point, exponent; a plausible range per item).
"""

from __future__ import annotations

import csv
import hashlib
import io
from dataclasses import dataclass, field
from pathlib import Path

from acceptance.items import ITEM_KEYS, ITEMS, REQUIRED_KEYS, parse_ring
from acceptance.store import AcceptanceStore, RingMeasurement, StoredRecord
from config.files import InputFileError, read_text_file

REQUIRED_COLUMNS: tuple[str, ...] = ("ring", "measured_at", *REQUIRED_KEYS)
OPTIONAL_COLUMNS: tuple[str, ...] = (
    *(k for k in ITEM_KEYS if k not in REQUIRED_KEYS),
    "operator",
    "remarks",
)
#: Column order used when writing a CSV (the example data set).
COLUMNS: tuple[str, ...] = ("ring", "measured_at", *ITEM_KEYS, "operator", "remarks")
#: Largest survey file read (about 100 000 rings).
MAX_CSV_BYTES = 16 * 1024 * 1024


class CsvFileError(Exception):
    """The file as a whole cannot be imported (nothing from it was written).

    Scenarios: the file does not exist, is not a regular file or too long, is not UTF-8
    text, has no header row, or its header names an unknown column, a column twice, or
    lacks a required column.
    """


@dataclass(frozen=True)
class RowError:
    """A rejected row: its first physical line in the file and why."""

    line: int
    reason: str

    def __str__(self) -> str:
        return f"line {self.line}: {self.reason}"


@dataclass(frozen=True)
class ParsedCsv:
    """A checked file: the valid rows with their line numbers, and the rejected ones."""

    source: str
    sha256: str
    rows: list[tuple[int, RingMeasurement]] = field(default_factory=list)
    errors: list[RowError] = field(default_factory=list)


@dataclass(frozen=True)
class ImportResult:
    """What an import did: records written, lines skipped as unchanged, lines rejected."""

    source: str
    recorded: list[StoredRecord]
    unchanged_lines: list[int]
    errors: list[RowError]
    import_id: int | None

    @property
    def ok(self) -> bool:
        return not self.errors


def _header(cells: list[str], source: str, line: int) -> list[str]:
    names = [c.strip().lower() for c in cells]
    known = set(COLUMNS)
    problems = []
    unknown = [n for n in names if n not in known]
    if unknown:
        problems.append(
            f"unknown column(s) {', '.join(repr(n) for n in unknown)} "
            f"(expected columns: {', '.join(COLUMNS)})"
        )
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        problems.append(f"column(s) named twice: {', '.join(dupes)}")
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        problems.append(f"missing required column(s): {', '.join(missing)}")
    if problems:
        raise CsvFileError(f"{source}: header on line {line}: " + "; ".join(problems))
    return names


def parse_csv_text(text: str, source: str = "<csv>") -> ParsedCsv:
    """Check a survey CSV given as text; see the module docstring for the rules."""
    sha = hashlib.sha256(text.encode("utf-8")).hexdigest()
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    header: list[str] | None = None
    candidates: list[tuple[int, RingMeasurement]] = []
    errors: list[RowError] = []
    ring_lines: dict[int, list[int]] = {}
    prev_end = 0
    while True:
        try:
            cells = next(reader)
        except StopIteration:
            break
        except csv.Error as exc:
            line = prev_end + 1
            why = f"unreadable CSV: {exc}"
            if reader.line_num > line:
                why += f" (a quoted field runs on to line {reader.line_num}: unterminated quote?)"
            if header is None:
                raise CsvFileError(f"{source}: line {line}: {why}") from None
            errors.append(RowError(line, why))
            prev_end = reader.line_num
            continue
        line, prev_end = prev_end + 1, reader.line_num
        if reader.line_num > line:
            # A quoted field ran over a line break: most likely a quote left open,
            # which swallowed the row(s) after it. One row is one line.
            if header is None:
                raise CsvFileError(
                    f"{source}: line {line}: a quoted field runs on to line "
                    f"{reader.line_num} (unterminated quote?)"
                )
            errors.append(
                RowError(
                    line,
                    f"a quoted field runs on to line {reader.line_num}, taking lines "
                    f"{line}-{reader.line_num} as one row (unterminated quote? a field may "
                    "not contain a line break)",
                )
            )
            continue
        if not cells or all(c.strip() == "" for c in cells) or cells[0].lstrip().startswith("#"):
            continue
        if header is None:
            header = _header(cells, source, line)
            continue
        if len(cells) != len(header):
            errors.append(RowError(line, f"{len(cells)} fields, but the header has {len(header)}"))
            continue
        row = {name: cell.strip() for name, cell in zip(header, cells, strict=True)}
        reasons: list[str] = []
        ring: int | None = None
        try:
            ring = parse_ring(row["ring"])
            ring_lines.setdefault(ring, []).append(line)
        except ValueError as exc:
            reasons.append(str(exc))
        values: dict[str, float | None] = {}
        for item in ITEMS:
            if item.key not in row:
                continue
            try:
                text = row[item.key]
                values[item.key] = None if text == "" else item.parse(text)
            except ValueError as exc:
                reasons.append(str(exc))
                values[item.key] = 0.0  # placeholder; the row is rejected anyway
        if not row["measured_at"]:
            reasons.append("measured_at: missing (the time of the survey)")
        if reasons or ring is None:
            errors.append(RowError(line, "; ".join(reasons)))
            continue
        try:
            m = RingMeasurement(
                ring=ring,
                measured_at=row["measured_at"],
                values=values,
                operator=row.get("operator", ""),
                remarks=row.get("remarks", ""),
            )
        except ValueError as exc:
            errors.append(RowError(line, str(exc)))
            continue
        candidates.append((line, m))
    if header is None:
        raise CsvFileError(f"{source}: no header row (expected columns: {', '.join(COLUMNS)})")
    dup_rings = {r: lines for r, lines in ring_lines.items() if len(lines) > 1}
    rows = []
    for line, m in candidates:
        if m.ring in dup_rings:
            lines = ", ".join(str(n) for n in dup_rings[m.ring])
            errors.append(
                RowError(
                    line,
                    f"ring {m.ring} appears more than once in this file (lines {lines}); "
                    "one survey per ring per file: put a re-survey in its own file",
                )
            )
        else:
            rows.append((line, m))
    errors.sort(key=lambda e: e.line)
    return ParsedCsv(source=source, sha256=sha, rows=rows, errors=errors)


def parse_csv(path: str | Path) -> ParsedCsv:
    """Read and check a survey CSV file."""
    p = Path(path)
    try:
        text = read_text_file(p, MAX_CSV_BYTES, "utf-8-sig", "export the survey as 'CSV UTF-8'")
    except InputFileError as exc:
        raise CsvFileError(str(exc)) from None
    return parse_csv_text(text, str(p))


def import_parsed(store: AcceptanceStore, parsed: ParsedCsv) -> ImportResult:
    """Write a checked file's rows in one transaction, or none if any row was rejected."""
    if parsed.errors:
        return ImportResult(parsed.source, [], [], parsed.errors, None)
    current = {r.ring: r.measurement for r in store.current()}
    new: list[tuple[int, RingMeasurement]] = []
    unchanged: list[int] = []
    for line, m in parsed.rows:
        prev = current.get(m.ring)
        if prev is not None and prev.same_survey_as(m):
            unchanged.append(line)
        else:
            new.append((line, m))
    if not new:
        return ImportResult(parsed.source, [], unchanged, parsed.errors, None)
    name = Path(parsed.source).name
    recorded, import_id = store.add_many(
        [m for _, m in new],
        source="import",
        sources=[f"import {name} line {line}" for line, _ in new],
        batch={
            "file": parsed.source,
            "sha256": parsed.sha256,
            "rows_unchanged": len(unchanged),
            "rows_rejected": len(parsed.errors),
        },
    )
    return ImportResult(parsed.source, recorded, unchanged, parsed.errors, import_id)


def import_csv(store: AcceptanceStore, path: str | Path) -> ImportResult:
    """Check ``path`` and write its valid rows atomically; raises CsvFileError."""
    return import_parsed(store, parse_csv(path))


def format_csv(rows: list[RingMeasurement], comments: tuple[str, ...] = ()) -> str:
    """Write measurements as a CSV in the import format (``#`` comment lines first)."""
    buf = io.StringIO(newline="")
    for c in comments:
        buf.write(f"# {c}\n" if c else "#\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for m in rows:
        vals = ["" if m.values[k] is None else repr(m.values[k]) for k in ITEM_KEYS]
        w.writerow([m.ring, m.measured_at, *vals, m.operator, m.remarks])
    return buf.getvalue()

"""Hostile survey input: ring numbers and values outside the accepted syntax or the
plausible range, quotes left open, files that are not UTF-8, never end or do not exist.
Each is refused with its line number, one line each, exit 2, and nothing of the file
is written (no database is created either); never a traceback."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path
from subprocess import CompletedProcess
from typing import Any

import pytest

from acceptance.csv_import import COLUMNS, parse_csv_text
from acceptance.store import AcceptanceStore, RingMeasurement
from tests.cli_helpers import run_wara
from wara.cli import main

HEADER = ",".join(COLUMNS)
GOOD = {
    "vertical_misalignment_mm": "1.0",
    "horizontal_misalignment_mm": "-2.0",
    "max_gap_mm": "3.0",
    "centreline_deviation_x_mm": "0.5",
    "centreline_deviation_y_mm": "-0.5",
}


def _row(ring: Any, **cells: str) -> str:
    vals = {**GOOD, **cells}
    return ",".join(
        [str(ring), "2024-03-04T08:00", *(vals.get(c, "") for c in COLUMNS[2:-2]), "op", ""]
    )


def _import(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], lines: list[str], db: Path | None = None
) -> tuple[int, Path, Path, list[str]]:
    path = tmp_path / "survey.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    db = db or tmp_path / "acc.sqlite"
    code = main(["acceptance", "import", str(path), "--db", str(db)])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, path, db, err.splitlines()


def _count(db: Path) -> int:
    if not db.exists():
        return 0
    with AcceptanceStore.open(db, create=False) as s:
        return s.record_count()


@pytest.mark.parametrize(
    ("ring", "expected"),
    [
        ("1" * 20, "is not a ring number"),
        ("1_0", "is not a ring number"),
        ("\u0661\u0662", "is not a ring number"),  # Arabic-Indic 12
        ("\uff11\uff12", "is not a ring number"),  # full-width 12
        ("+12", "is not a ring number"),
        ("12.0", "is not a ring number"),
        ("100000", "expected a whole number from 1 to 99999"),
        ("0", "expected a whole number from 1 to 99999"),
    ],
)
def test_ring_numbers_outside_the_syntax_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], ring: str, expected: str
) -> None:
    code, path, db, err = _import(tmp_path, capsys, [HEADER, _row(1), _row(ring)])
    assert code == 2
    assert err[0].startswith(f"{path}: line 3: ring: ") and expected in err[0]
    assert len(err) == 2 and "nothing imported" in err[1]
    assert _count(db) == 0


@pytest.mark.parametrize(
    "value",
    ["1_0", "\u0661\u0662", "1e308", "-1e308", "1e999", "inf", "-Infinity", "nan", "0x10",
     "8,5", "8.5.1", "", "1e", "e5", "8 5", "81", "-80.5"],
)  # fmt: skip
def test_values_outside_the_syntax_or_range_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str
) -> None:
    cell = f'"{value}"' if "," in value else value
    code, path, db, err = _import(
        tmp_path, capsys, [HEADER, _row(1), _row(2, vertical_misalignment_mm=cell)]
    )
    assert code == 2, value
    assert err[0].startswith(f"{path}: line 3: vertical_misalignment_mm: "), err
    assert _count(db) == 0


@pytest.mark.parametrize("value", ["8", "-8.5", "+8.5", ".5", "5.", "1e-05", "-1.5E+1", "80"])
def test_accepted_number_syntax(value: str) -> None:
    parsed = parse_csv_text("\n".join([HEADER, _row(1, vertical_misalignment_mm=value)]))
    assert parsed.errors == []
    assert parsed.rows[0][1].values["vertical_misalignment_mm"] == float(value)


def test_plausible_range_per_item() -> None:
    cases = {
        "max_gap_mm": ("100", "100.1"),
        "centreline_deviation_x_mm": ("-50", "-50.01"),
        "pitch_angle_deg": ("10", "10.5"),
    }
    for key, (ok, bad) in cases.items():
        assert parse_csv_text("\n".join([HEADER, _row(1, **{key: ok})])).errors == [], key
        (err,) = parse_csv_text("\n".join([HEADER, _row(1, **{key: bad})])).errors
        assert f"{key}: got {float(bad)!r}: outside the plausible range" in err.reason


def test_store_api_refuses_an_implausible_value() -> None:
    values = {k: float(v) for k, v in GOOD.items()}
    with pytest.raises(ValueError, match="outside the plausible range"):
        RingMeasurement(ring=1, measured_at="2024-03-04", values={**values, "max_gap_mm": 1e308})
    with pytest.raises(ValueError, match="from 1 to 99999"):
        RingMeasurement(ring=10**20, measured_at="2024-03-04", values=values)


def test_an_unterminated_quote_does_not_swallow_the_next_row(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    open_quote = _row(2) + '"segment K, re-grouted'
    # The quote closes at the end of line 4, so lines 3-4 parse as one valid row.
    lines = [HEADER, _row(1), open_quote, _row(3), _row(4) + 'grouted"', _row(5)]
    code, path, db, err = _import(tmp_path, capsys, lines)
    assert code == 2
    assert err[0] == (
        f"{path}: line 3: a quoted field runs on to line 5, taking lines 3-5 as one row "
        "(unterminated quote? a field may not contain a line break)"
    )
    assert _count(db) == 0
    # Closed by a quote the CSV reader refuses, and at the end of the file.
    for tail in ([_row(3), _row(4) + '"x"y'], [_row(3)]):
        code, path, db, err = _import(tmp_path, capsys, [HEADER, _row(1), open_quote, *tail])
        assert code == 2 and err[0].startswith(f"{path}: line 3: ") and _count(db) == 0
        assert "unterminated quote?" in err[0], err


def test_one_bad_row_imports_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rows = [HEADER, *(_row(r) for r in range(1, 40)), _row(40, max_gap_mm="-1")]
    code, path, db, err = _import(tmp_path, capsys, rows)
    assert code == 2 and _count(db) == 0
    assert err == [
        f"{path}: line 41: max_gap_mm: got -1.0: expected a value >= 0 (mm)",
        f"{path}: nothing imported: 1 row(s) rejected (a file is imported whole or not at all)",
    ]
    code, _, _, _ = _import(tmp_path, capsys, rows[:-1])
    assert code == 0 and _count(db) == 39


def test_missing_file_creates_no_database(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db = tmp_path / "new" / "acc.sqlite"
    db.parent.mkdir()
    code = main(["acceptance", "import", str(tmp_path / "missing.csv"), "--db", str(db)])
    (line,) = capsys.readouterr().err.splitlines()
    assert code == 2 and "file not found (nothing imported)" in line
    assert not db.exists() and list(db.parent.iterdir()) == []


def _subprocess_import(tmp_path: Path, path: Path | str) -> CompletedProcess[str]:
    db = tmp_path / "sub.sqlite"
    proc = run_wara(["acceptance", "import", str(path), "--db", str(db)], timeout_s=60)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert not db.exists()
    return proc


@pytest.mark.slow
def test_not_utf8_fifo_dev_zero_and_too_long_are_one_line(tmp_path: Path) -> None:
    latin = tmp_path / "latin.csv"
    latin.write_bytes((HEADER + "\n" + _row(1).replace("op", "Müller") + "\n").encode("latin-1"))
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    big = tmp_path / "big.csv"
    big.write_text(HEADER + "\n" + "#" * (17 * 1024 * 1024) + "\n")
    for path, expected in (
        (latin, "not UTF-8 text (byte "),
        (fifo, "a FIFO (named pipe), expected a regular file"),
        ("/dev/zero", "a device, expected a regular file"),
        (big, "longer than 16777216 bytes"),
    ):
        (line,) = _subprocess_import(tmp_path, path).stderr.splitlines()
        assert expected in line and "(nothing imported)" in line


def test_cli_add_uses_the_same_syntax_and_range(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db = tmp_path / "acc.sqlite"
    base = ["acceptance", "add", "12", "--db", str(db), "--measured-at", "2024-03-05T10:30"]
    vals = [f"--{k.replace('_', '-')}={v}" for k, v in GOOD.items()]
    for bad in (
        ["--vertical-misalignment-mm=1e308"],
        ["--vertical-misalignment-mm=inf"],
        ["--vertical-misalignment-mm=1_0"],
        ["--vertical-misalignment-mm=\u0661"],
    ):
        with pytest.raises(SystemExit) as exc:
            main([*base, *vals, *bad])
        assert exc.value.code == 2
        (line,) = capsys.readouterr().err.splitlines()
        assert "argument --vertical-misalignment-mm: vertical_misalignment_mm: " in line
    for ring in ("1_0", "\u0661\u0662", "1" * 20):
        with pytest.raises(SystemExit) as exc:
            main(["acceptance", "add", ring, *base[3:], *vals])
        assert exc.value.code == 2
        assert "is not a ring number" in capsys.readouterr().err
    for verb in (["history", "1_0"], ["list", "--from", "\u0661"], ["list", "--to", "1" * 20]):
        with pytest.raises(SystemExit) as exc:
            main(["acceptance", *verb, "--db", str(db)])
        assert exc.value.code == 2
    assert not db.exists()


def test_report_on_a_record_written_around_the_software_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, db, _ = _import(tmp_path, capsys, [HEADER, _row(1), _row(2)])
    assert code == 0
    conn = sqlite3.connect(db)
    conn.execute(
        "INSERT INTO ring_record (ring, measured_at, recorded_at, vertical_misalignment_mm, "
        "horizontal_misalignment_mm, max_gap_mm, centreline_deviation_x_mm, "
        "centreline_deviation_y_mm, operator, remarks, source) "
        "VALUES (3, '2024-03-04T08:00:00', 'now', 1e308, 0, 0, 0, 0, '', '', 'sqlite3')"
    )
    conn.commit()
    conn.close()
    out = tmp_path / "report"
    code = main(["acceptance", "report", "--db", str(db), "--out", str(out)])
    (line,) = capsys.readouterr().err.splitlines()
    assert code == 2 and "record #3 in the database is not valid" in line

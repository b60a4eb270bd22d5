"""Hypothesis fuzzing of the survey CSV import: random rows (ring numbers, values and
times in and out of the accepted syntax), quotes, encodings. Each file is imported
whole, with every value finite and in its plausible range, or refused with exit 2, one
line per rejected row and nothing written (no database created); never a traceback.
Bounded: a few seconds per test."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from acceptance.csv_import import COLUMNS
from acceptance.items import ITEMS, ITEMS_BY_KEY, MAX_RING
from acceptance.store import AcceptanceStore
from tests.cli_helpers import run_main, run_wara

FUZZ = settings(
    max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None
)
HOSTILE_NUMBERS = ["1_0", "\u0661\u0662", "\uff18", "1e308", "-1e308", "inf", "nan", "NaN",
                   "-Infinity", "0x1F", "8,5", "1e", ".", "+", "--1", "1" * 400, "8.5.1",
                   "\u00bd", "²", "0e0", "-0", "+.5", "5.", "1E-3"]  # fmt: skip
HOSTILE_TIMES = ["tomorrow", "2024-13-45", "\u0662\u0660\u0662\u0664-03-05", "2024-03-05T25:00",
                 "9999-12-31T23:59:59+23:59", "0001-01-01", "2024-03-05T10:30Z", ""]  # fmt: skip
NASTY_TEXT = st.text(alphabet=st.sampled_from('ab ,"\n\r\t#\x00\u00fc\u0661;'), max_size=12)


def _value_cell(key: str) -> st.SearchStrategy[str]:
    lim = ITEMS_BY_KEY[key].plausible_abs
    lo = 0.0 if not ITEMS_BY_KEY[key].signed else -lim
    valid = st.one_of(st.floats(lo, lim).map(repr), st.floats(lo, lim).map(lambda v: f"{v:.2f}"))
    return st.one_of(
        valid,
        valid,
        valid,
        valid,
        valid,
        valid,
        st.floats(allow_nan=True, allow_infinity=True).map(repr),
        st.sampled_from(HOSTILE_NUMBERS),
        NASTY_TEXT,
    )


RING_CELL = st.one_of(
    st.integers(1, MAX_RING).map(str),
    st.integers(1, MAX_RING).map(str),
    st.integers(1, MAX_RING).map(str),
    st.integers(-(10**25), 10**25).map(str),
    st.sampled_from(["1_0", "\u0661\u0662", "007", "+5", "5.0", " 5 ", "0", "1" * 20]),
    NASTY_TEXT,
)
TIME_CELL = st.one_of(
    st.datetimes().map(lambda d: d.isoformat(timespec="minutes")),
    st.datetimes().map(lambda d: d.isoformat(timespec="minutes")),
    st.sampled_from(HOSTILE_TIMES),
)


@st.composite
def _row(draw: st.DrawFn, columns: list[str]) -> list[str]:
    cells = []
    for c in columns:
        if c == "ring":
            cells.append(draw(RING_CELL))
        elif c == "measured_at":
            cells.append(draw(TIME_CELL))
        elif c in ITEMS_BY_KEY:
            empty_ok = not ITEMS_BY_KEY[c].required
            cells.append("" if empty_ok and draw(st.booleans()) else draw(_value_cell(c)))
        else:
            cells.append(draw(NASTY_TEXT))
    return cells


def _quote(cell: str, how: str) -> str:
    if how == "always" or (how == "needed" and any(ch in cell for ch in ',"\n\r')):
        return '"' + cell.replace('"', '""') + '"'
    return cell


@st.composite
def _csv_bytes(draw: st.DrawFn) -> bytes:
    optional = [c for c in COLUMNS if c not in ("ring", "measured_at") and c not in
                {i.key for i in ITEMS if i.required}]  # fmt: skip
    columns = [c for c in COLUMNS if c not in optional or draw(st.booleans())]
    columns = draw(st.permutations(columns))
    header = [draw(st.sampled_from([c, c.upper(), f" {c} "])) for c in columns]
    quoting = draw(st.sampled_from(["needed", "always", "never"]))
    lines = [",".join(_quote(h, quoting) for h in header)]
    for row in draw(st.lists(_row(list(columns)), max_size=6)):
        line = ",".join(_quote(c, quoting) for c in row)
        if draw(st.integers(0, 9)) == 0:  # a stray quote somewhere in the line
            pos = draw(st.integers(0, len(line)))
            line = line[:pos] + '"' + line[pos:]
        lines.append(line)
        if draw(st.integers(0, 9)) == 0:
            lines.append(draw(st.sampled_from(["", "# comment", ",,,", "#"])))
    text = draw(st.sampled_from(["\n", "\r\n"])).join(lines) + draw(st.sampled_from(["", "\n"]))
    encoding = draw(st.sampled_from(["utf-8", "utf-8", "utf-8-sig", "utf-16", "latin-1", "cp1252"]))
    raw = bytearray(text.encode(encoding, errors="replace"))
    if raw and draw(st.integers(0, 9)) == 0:
        pos = draw(st.integers(0, len(raw) - 1))
        raw[pos : pos + 1] = draw(st.binary(min_size=1, max_size=3))
    return bytes(raw)


def _check_import(csv_path: Path, db: Path, code: int, out: str, err: str) -> None:
    assert "Traceback" not in err
    if code == 2:
        assert not db.exists()  # nothing written, not even an empty database
        lines = err.splitlines()
        assert lines and all(
            ln.startswith((f"{csv_path}: ", f"wara acceptance: error: {csv_path}: "))
            for ln in lines
        ), err
        return
    assert code == 0 and err == "", err
    if not db.exists():  # a header-only file: nothing to write
        assert " 0 row(s) recorded" in out
        return
    with AcceptanceStore.open(db, create=False) as store:
        for rec in store.current():
            assert 1 <= rec.ring <= MAX_RING
            for item in ITEMS:
                v = rec.measurement.values[item.key]
                if v is None:
                    assert not item.required
                    continue
                assert math.isfinite(v) and abs(v) <= item.plausible_abs
                assert item.signed or v >= 0


@pytest.mark.slow
@FUZZ
@given(raw=_csv_bytes())
def test_random_rows_quotes_and_encodings(raw: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        csv_path, db = Path(tmp) / "survey.csv", Path(tmp) / "acc.sqlite"
        csv_path.write_bytes(raw)
        code, out, err = run_main(["acceptance", "import", str(csv_path), "--db", str(db)])
        _check_import(csv_path, db, code, out, err)
        event(f"exit {code}" + (" with rows" if db.exists() else ""))


@settings(max_examples=40, deadline=None, database=None)
@given(
    rows=st.lists(
        st.tuples(st.floats(-80, 80), st.floats(0, 100), st.floats(-50, 50), st.floats(-10, 10)),
        min_size=1,
        max_size=5,
    )
)
@pytest.mark.slow
def test_valid_files_import_exactly(rows: list[tuple[float, float, float, float]]) -> None:
    """Values written as Python writes floats (``repr``: exponents too) come back exact."""
    lines = [",".join(COLUMNS)]
    for ring, (v, gap, x, pitch) in enumerate(rows, start=1):
        values = [repr(v), repr(v), repr(gap), repr(x), repr(x), repr(pitch), "", ""]
        lines.append(",".join([str(ring), "2024-03-04T08:00", *values, "op", "r"]))
    with tempfile.TemporaryDirectory() as tmp:
        csv_path, db = Path(tmp) / "survey.csv", Path(tmp) / "acc.sqlite"
        csv_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
        code, _, err = run_main(["acceptance", "import", str(csv_path), "--db", str(db)])
        assert code == 0, err
        with AcceptanceStore.open(db, create=False) as store:
            got = [
                (m.values["vertical_misalignment_mm"], m.values["max_gap_mm"])
                for m in (r.measurement for r in store.current())
            ]
        assert got == [(v, gap) for v, gap, _, _ in rows]


@pytest.mark.slow
@settings(max_examples=2, deadline=None, database=None)
@given(raw=_csv_bytes())
def test_through_a_subprocess_and_the_report(raw: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        csv_path, db = Path(tmp) / "survey.csv", Path(tmp) / "acc.sqlite"
        csv_path.write_bytes(raw)
        proc = run_wara(["acceptance", "import", str(csv_path), "--db", str(db)])
        _check_import(csv_path, db, proc.returncode, proc.stdout, proc.stderr)
        if proc.returncode == 0 and db.exists():
            code, _, err = run_main(["acceptance", "report", "--db", str(db), "--out", tmp + "/r"])
            assert code in (0, 1) and "Traceback" not in err

"""Judge ring records against the project's tolerances and count pass rates.

Rules (the same in the CLI, the JSON summary and the HTML report):

- An item **passes** when ``|value| <= limit``: exactly on the limit passes, anything
  above fails. Signed items (misalignments, centreline deviations, angles) carry a
  direction and are judged by magnitude, so -8.0 mm passes an 8 mm limit and -8.1 mm
  fails. Values are compared as recorded, without rounding.
- An item whose limit is not set in the project YAML (``null``; the paper's angle limits
  were lost) is reported as **no limit set**, never as pass, and is left out of every
  pass rate.
- An item with a limit but no value is **not measured**.
- A ring **passes** when every item with a limit passes; it **fails** when any fails;
  otherwise (nothing failed but something with a limit was not measured) it is
  **incomplete**, which is not a pass.
- Item pass rate = passes / (passes + fails) for that item. Overall pass rate = rings
  passed / rings in the report. The check pass rate counts every judged item of every
  ring (passes / judged checks).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from acceptance.items import ITEMS, ControlItem
from acceptance.store import StoredRecord
from config.schema import Acceptance


class Status(StrEnum):
    PASS = "pass"
    FAIL = "fail"
    NO_LIMIT = "no limit set"
    NOT_MEASURED = "not measured"


class RingVerdict(StrEnum):
    PASS = "pass"
    FAIL = "fail"
    INCOMPLETE = "incomplete"


def limits_from(acceptance: Acceptance) -> dict[str, float | None]:
    """Item key -> limit from the project YAML's ``acceptance`` section (None: not set)."""
    return {i.key: getattr(acceptance, i.key) for i in ITEMS}


def judge_value(value: float | None, limit: float | None) -> Status:
    """Judge one value; see the module docstring."""
    if limit is None:
        return Status.NO_LIMIT
    if value is None:
        return Status.NOT_MEASURED
    return Status.PASS if abs(value) <= limit else Status.FAIL


@dataclass(frozen=True)
class RingResult:
    """One ring's current record judged item by item."""

    record: StoredRecord
    statuses: dict[str, Status]
    has_plan: bool = False

    @property
    def ring(self) -> int:
        return self.record.ring

    @property
    def verdict(self) -> RingVerdict:
        s = set(self.statuses.values())
        if Status.FAIL in s:
            return RingVerdict.FAIL
        if Status.NOT_MEASURED in s:
            return RingVerdict.INCOMPLETE
        return RingVerdict.PASS

    def to_dict(self) -> dict[str, Any]:
        m = self.record.measurement
        return {
            "ring": self.ring,
            "verdict": str(self.verdict),
            "record_id": self.record.record_id,
            "measured_at": m.measured_at,
            "operator": m.operator,
            "remarks": m.remarks,
            "has_plan": self.has_plan,
            "items": {
                k: {"value": m.values[k], "status": str(s)} for k, s in self.statuses.items()
            },
        }


def _rate(num: int, den: int) -> float | None:
    return None if den == 0 else num / den


@dataclass(frozen=True)
class ItemSummary:
    """Counts for one control item over the rings of the report."""

    item: ControlItem
    limit: float | None
    measured: int
    passed: int
    failed: int
    not_measured: int
    failed_rings: tuple[int, ...]
    max_abs: float | None

    @property
    def judged(self) -> int:
        return self.passed + self.failed

    @property
    def pass_rate(self) -> float | None:
        """passes / judged; None when there is no limit or nothing was judged."""
        return _rate(self.passed, self.judged)

    def to_dict(self) -> dict[str, Any]:
        return {
            "label": self.item.label,
            "unit": self.item.unit,
            "limit": self.limit,
            "judged": self.judged if self.limit is not None else None,
            "status": "judged" if self.limit is not None else str(Status.NO_LIMIT),
            "measured": self.measured,
            "passed": self.passed,
            "failed": self.failed,
            "not_measured": self.not_measured,
            "pass_rate": self.pass_rate,
            "failed_rings": list(self.failed_rings),
            "max_abs": self.max_abs,
        }


@dataclass(frozen=True)
class Summary:
    """The report's numbers: per ring, per item and overall."""

    rings: tuple[RingResult, ...]
    items: tuple[ItemSummary, ...]
    ring_from: int | None
    ring_to: int | None

    @property
    def rings_passed(self) -> int:
        return sum(r.verdict is RingVerdict.PASS for r in self.rings)

    @property
    def rings_failed(self) -> int:
        return sum(r.verdict is RingVerdict.FAIL for r in self.rings)

    @property
    def rings_incomplete(self) -> int:
        return sum(r.verdict is RingVerdict.INCOMPLETE for r in self.rings)

    @property
    def ring_pass_rate(self) -> float | None:
        return _rate(self.rings_passed, len(self.rings))

    @property
    def checks_judged(self) -> int:
        return sum(i.judged for i in self.items)

    @property
    def checks_passed(self) -> int:
        return sum(i.passed for i in self.items)

    @property
    def check_pass_rate(self) -> float | None:
        return _rate(self.checks_passed, self.checks_judged)

    def overall_dict(self) -> dict[str, Any]:
        return {
            "rings": len(self.rings),
            "first_ring": self.rings[0].ring if self.rings else None,
            "last_ring": self.rings[-1].ring if self.rings else None,
            "rings_passed": self.rings_passed,
            "rings_failed": self.rings_failed,
            "rings_incomplete": self.rings_incomplete,
            "ring_pass_rate": self.ring_pass_rate,
            "failed_rings": [r.ring for r in self.rings if r.verdict is RingVerdict.FAIL],
            "checks_judged": self.checks_judged,
            "checks_passed": self.checks_passed,
            "check_pass_rate": self.check_pass_rate,
        }

    def to_dict(self) -> dict[str, Any]:
        return {
            "range": {"from": self.ring_from, "to": self.ring_to},
            "overall": self.overall_dict(),
            "items": {i.item.key: i.to_dict() for i in self.items},
            "rings": [r.to_dict() for r in self.rings],
        }


def judge_ring(
    record: StoredRecord, limits: Mapping[str, float | None], has_plan: bool = False
) -> RingResult:
    """Judge every item of one record."""
    values = record.measurement.values
    statuses = {i.key: judge_value(values[i.key], limits[i.key]) for i in ITEMS}
    return RingResult(record, statuses, has_plan)


def summarize(
    records: Sequence[StoredRecord],
    acceptance: Acceptance,
    *,
    ring_from: int | None = None,
    ring_to: int | None = None,
    rings_with_plan: set[int] | frozenset[int] = frozenset(),
) -> Summary:
    """Judge each ring's current record and count per item and overall."""
    limits = limits_from(acceptance)
    rings = tuple(
        judge_ring(r, limits, r.ring in rings_with_plan)
        for r in sorted(records, key=lambda r: r.ring)
    )
    items = []
    for item in ITEMS:
        vals = [r.record.measurement.values[item.key] for r in rings]
        measured = [v for v in vals if v is not None]
        st = [r.statuses[item.key] for r in rings]
        items.append(
            ItemSummary(
                item=item,
                limit=limits[item.key],
                measured=len(measured),
                passed=st.count(Status.PASS),
                failed=st.count(Status.FAIL),
                not_measured=st.count(Status.NOT_MEASURED),
                failed_rings=tuple(r.ring for r in rings if r.statuses[item.key] is Status.FAIL),
                max_abs=max((abs(v) for v in measured), default=None),
            )
        )
    return Summary(rings, tuple(items), ring_from, ring_to)

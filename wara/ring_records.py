"""The ring cycle's acceptance records: the service's :class:`RingRecords` sink on the
acceptance store (``wara serve``, ``wara cycle``; docs/placement.md)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any

from acceptance.store import AcceptanceStore, RingMeasurement


class StoreRecords:
    """Writes a cycle's ring record into the acceptance store at ``db_path`` (opened per
    record: the service does not hold the file open between rings): the Table 4 values
    as a record of source ``cycle``, and the plan and the cycle's figures attached, the
    as-built pose as its ``final_attitude`` (where ``wara place plan --from-store`` and
    the next ring's cycle find it)."""

    def __init__(self, db_path: Path, *, operator: str, remarks: str = "") -> None:
        self.db_path, self.operator, self.remarks = Path(db_path), operator, remarks

    def write(self, ring: int, values: dict[str, float | None], attached: dict[str, Any]) -> str:
        plan = {k: v for k, v in attached.items() if k != "as_built_pose"}
        with AcceptanceStore.open(self.db_path, create=True) as store:
            store.add(
                RingMeasurement(
                    ring,
                    dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                    dict(values),
                    operator=self.operator,
                    remarks=self.remarks,
                ),
                source="cycle",
            )
            store.attach_plan(
                ring, plan, final_attitude={"as_built_pose": attached["as_built_pose"]}
            )
        return str(self.db_path)

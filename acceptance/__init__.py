"""Ring acceptance records and the quality report.

- :mod:`.items`: the control items of paper Table 4, one vocabulary end to end.
- :mod:`.store`: the durable SQLite store (WAL, append-only history per ring).
- :mod:`.csv_import`: survey CSV parsing with per-line reasons, atomic per file.
- :mod:`.judge`: pass/fail against the project's tolerances, pass rates.
- :mod:`.report`: PNG plots per item and one self-contained HTML page.
- :mod:`.example`: the synthetic 50-ring example data set (fixed seed).

The service attaches the controller's plan to a ring with
:meth:`AcceptanceStore.attach_plan`.
"""

from acceptance.items import ITEMS, ControlItem
from acceptance.store import (
    AcceptanceStore,
    RingMeasurement,
    StoredPlan,
    StoredRecord,
    StoreError,
    default_db_path,
)

__all__ = [
    "ITEMS",
    "AcceptanceStore",
    "ControlItem",
    "RingMeasurement",
    "StoreError",
    "StoredPlan",
    "StoredRecord",
    "default_db_path",
]

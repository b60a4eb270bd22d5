"""Count the outcomes of many hostile inputs drawn from the fuzz strategies.

    python -m tests.fuzz_census [N]      # N inputs of each kind (default 1000), JSON on stdout

Each project-YAML mutant goes through ``wara config validate``, each survey file through
``wara acceptance import --db NEW``, in this process. An outcome is the exit code, or
``traceback`` for an exception escaping :func:`wara.cli.main`, refined by what an
accepted input left behind (a non-finite config number, a database after a refusal).
docs/hostile-input.md quotes its figures.
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, given, settings

from config import load_project
from tests.cli_helpers import run_main
from tests.test_acceptance_fuzz import _csv_bytes
from tests.test_config_fuzz import _data_mutant, _floats, _text_mutant


def _yaml_outcome(path: Path) -> str:
    try:
        code, _, _ = run_main(["config", "validate", str(path)])
    except Exception as exc:  # the census counts what the tests forbid
        return f"traceback {type(exc).__name__}"
    if code == 0 and not all(math.isfinite(v) for v in _floats(load_project(path).model_dump())):
        return "accepted non-finite"
    return f"exit {code}"


def _csv_outcome(path: Path, db: Path) -> str:
    try:
        code, _, _ = run_main(["acceptance", "import", str(path), "--db", str(db)])
    except Exception as exc:
        return f"traceback {type(exc).__name__}"
    return f"exit {code}" + (", database created" if code != 0 and db.exists() else "")


def census(n: int) -> dict[str, Any]:
    counts: dict[str, Counter[str]] = {"yaml_data": Counter(), "yaml_text": Counter()}
    counts["csv"] = Counter()
    run = settings(
        max_examples=n, deadline=None, database=None, suppress_health_check=list(HealthCheck)
    )

    def yaml_case(kind: str, raw: bytes) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "project.yaml"
            path.write_bytes(raw)
            counts[kind][_yaml_outcome(path)] += 1

    @run
    @given(_data_mutant())
    def data(text: str) -> None:
        yaml_case("yaml_data", text.encode("utf-8"))

    @run
    @given(_text_mutant())
    def text(raw: bytes) -> None:
        yaml_case("yaml_text", raw)

    @run
    @given(_csv_bytes())
    def csv(raw: bytes) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "survey.csv"
            path.write_bytes(raw)
            counts["csv"][_csv_outcome(path, Path(tmp) / "acc.sqlite")] += 1

    data()
    text()
    csv()
    return {kind: dict(c.most_common()) for kind, c in counts.items()}


if __name__ == "__main__":
    print(json.dumps(census(int(sys.argv[1]) if len(sys.argv) > 1 else 1000), indent=2))

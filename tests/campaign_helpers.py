"""A small campaign spec for the tests: four short runs with a dispersion, a simulator
parameter and a random event, so that every kind of drawn column is in the table."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

SMALL_SPEC: dict[str, Any] = {
    "name": "test campaign",
    "kind": "fault",  # a PLC stall of tens of ms: beyond a scan's lateness
    "seed": 11,
    "run": {"targets": 1, "roll_deg": [-0.5, 0.5], "pitch_deg": [-0.3, 0.3]},
    "dispersions": {
        "hydraulics.bulk_modulus_mpa": {"dist": "uniform", "low": 500, "high": 1200},
        "layers.upper.bodies[0].mass_kg": {
            "dist": "normal",
            "mean": 1.0,
            "std": 0.02,
            "factor": True,
        },
    },
    "simulator": {"sensors.position.noise_um": {"dist": "uniform", "low": 0.5, "high": 2.0}},
    "events": [
        {
            "event": {"kind": "plc_stall"},
            "probability": 0.5,
            "start_s": {"dist": "uniform", "low": 0.5, "high": 2.0},
            "duration_s": {"dist": "uniform", "low": 0.01, "high": 0.04},
        }
    ],
    "requirement": {"runs": 4},
}


def write_spec(tmp: Path, data: dict[str, Any] | None = None, name: str = "spec.yaml") -> Path:
    path = tmp / name
    path.write_text(yaml.safe_dump(SMALL_SPEC if data is None else data, sort_keys=False))
    return path


def same_rows(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> list[str]:
    """The differences between two result tables, volatile columns left out."""
    from wara.campaign.run import VOLATILE_COLUMNS

    diffs = []
    if len(a) != len(b):
        return [f"{len(a)} rows vs {len(b)}"]
    for x, y in zip(a, b, strict=True):
        for k in x:
            if k in VOLATILE_COLUMNS:
                continue
            u, v = x[k], y.get(k)
            nan = isinstance(u, float) and isinstance(v, float) and math.isnan(u) and math.isnan(v)
            if not (nan or u == v):
                diffs.append(f"run {x['run']} {k}: {u!r} vs {v!r}")
    return diffs

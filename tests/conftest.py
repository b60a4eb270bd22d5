"""Shared fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

from config import ProjectConfig, load_project

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture(scope="session")
def project() -> ProjectConfig:
    """The shipped Shanghai Airport Link project."""
    return load_project()

"""The acceptance report's HTML page opens in a headless browser without errors.

Needs Chromium (Debian: ``apt-get install -y chromium``); skipped with a reason where it
is absent. The page marks ``<body data-report-check="ok">`` on load once every embedded
plot decoded; any console message (this Chromium logs JS errors, "Uncaught ..." and
console.* calls as ``CONSOLE`` lines) counts as a failure. A deliberately broken page
checks that the check itself can fail.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from acceptance import report
from acceptance.example import shipped_example_path
from wara.cli import main

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def _browser() -> str | None:
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        _browser() is None,
        reason="no headless Chromium on this machine (Debian: apt-get install -y chromium)",
    ),
]


def _open_in_browser(page: Path, profile: Path) -> tuple[str, list[str]]:
    """Load ``page`` headless; return the DOM after load and the console lines."""
    browser = _browser()
    assert browser is not None
    cmd = [
        browser,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={profile}",
        "--enable-logging=stderr",
        "--v=0",
        "--virtual-time-budget=5000",
        "--dump-dom",
        page.resolve().as_uri(),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=90)
    assert proc.returncode == 0, proc.stderr[-2000:]
    console = [line for line in proc.stderr.splitlines() if "CONSOLE" in line or "Uncaught" in line]
    return proc.stdout, console


def _check(dom: str) -> str | None:
    m = re.search(r'<body[^>]*data-report-check="([^"]*)"', dom)
    return m.group(1) if m else None


def test_report_page_opens_without_errors(tmp_path: Path) -> None:
    db = tmp_path / "acc.sqlite"
    assert main(["acceptance", "import", str(shipped_example_path()), "--db", str(db)]) == 0
    out = tmp_path / "report"
    assert main(["acceptance", "report", "--db", str(db), "--out", str(out)]) == 0
    dom, console = _open_in_browser(out / "report.html", tmp_path / "profile")
    assert console == [], f"browser console reported: {console}"
    assert _check(dom) == "ok", "the page's load check did not pass (images not decoded?)"
    assert "48 of 50 rings pass" in dom


def test_browser_check_catches_a_broken_page(tmp_path: Path) -> None:
    page = tmp_path / "broken.html"
    broken = '<img src="data:image/png;base64,AAAA"><script>notDefined();</script>'
    page.write_text(_report_script_page().replace("<!--IMG-->", broken))
    dom, console = _open_in_browser(page, tmp_path / "profile")
    assert any("Uncaught" in line for line in console)
    assert _check(dom) == "broken-images:1"


def _report_script_page() -> str:
    """A minimal page with the report's own load check (taken from the module)."""
    return (
        f"<!DOCTYPE html><html><head><script>{report.PAGE_SCRIPT}</script></head>"
        "<body><!--IMG--></body></html>"
    )

"""Start-up failures of `wara serve` and `wara hil`: one line on stderr, exit 2, no traceback,
and no run record left behind (the bus and the socket are opened before the recorder)."""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import structlog
import yaml

from config.loader import default_project_path
from wara.cli import main


@pytest.fixture(autouse=True)
def _restore_logging() -> Iterator[None]:
    """`wara serve` configures logging for the process; put it back for the next tests."""
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    yield
    root.setLevel(level)
    root.handlers[:] = handlers
    structlog.reset_defaults()


@pytest.fixture
def short_tmp() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="wara-start-") as d:  # AF_UNIX: short paths
        yield Path(d)


def _project(tmp: Path, **can: Any) -> str:
    data = yaml.safe_load(default_project_path().read_text())
    data["can"].update(can)
    path = tmp / "project.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


BAD_BUSES = {
    "socketcan on a missing channel": {"interface": "socketcan", "channel": "nosuchcan7"},
    "wara_udp on a channel that is not multicast": {
        "interface": "wara_udp",
        "channel": "10.1.2.3",
    },
    "udp_multicast on a host name": {"interface": "udp_multicast", "channel": "localhost"},
}


def _one_line(err: str, prefix: str) -> str:
    assert err.count("\n") == 1 and err.startswith(prefix), err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize("can", BAD_BUSES.values(), ids=BAD_BUSES.keys())
def test_serve_with_a_bus_that_cannot_open(
    short_tmp: Path, can: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    records = short_tmp / "runs"
    code = main(
        [
            "serve",
            "--config",
            _project(short_tmp, **can),
            "--record-dir",
            str(records),
            "--socket",
            str(short_tmp / "ctl.sock"),
            "--duration-s",
            "1",
        ]
    )
    err = _one_line(capsys.readouterr().err, "wara serve: error: ")
    assert code == 2 and can["channel"] in err
    assert not records.exists()
    assert not (short_tmp / "ctl.sock").exists()


def test_serve_with_a_socket_path_that_is_a_regular_file(
    short_tmp: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    records, sock = short_tmp / "runs", short_tmp / "ctl.sock"
    sock.write_text("not a socket\n")
    code = main(["serve", "--record-dir", str(records), "--socket", str(sock), "--duration-s", "1"])
    err = _one_line(capsys.readouterr().err, "wara serve: error: ")
    assert code == 2 and "exists and is not a socket" in err
    assert not records.exists()
    assert sock.read_text() == "not a socket\n"  # left alone


def test_serve_with_a_record_dir_that_cannot_be_written(
    short_tmp: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = short_tmp / "file"
    blocker.write_text("")
    code = main(
        [
            "serve",
            "--record-dir",
            str(blocker / "runs"),
            "--socket",
            str(short_tmp / "ctl.sock"),
            "--duration-s",
            "1",
        ]
    )
    err = _one_line(capsys.readouterr().err, "wara serve: error: cannot write the run record")
    assert code == 2 and "--record-dir" in err
    assert not (short_tmp / "ctl.sock").exists()


@pytest.mark.parametrize("can", BAD_BUSES.values(), ids=BAD_BUSES.keys())
def test_hil_with_a_bus_that_cannot_open(
    short_tmp: Path, can: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["hil", "--config", _project(short_tmp, **can), "--duration", "1", "--quiet"])
    err = _one_line(capsys.readouterr().err, "wara hil: error: ")
    assert code == 2 and can["channel"] in err

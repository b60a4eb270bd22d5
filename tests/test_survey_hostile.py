"""Hostile survey input (docs/hostile-input.md, "Survey files and poses"): files that
never end, hang, are huge, not UTF-8 or carry more points than a request takes, read by
``wara survey import``, ``wara place plan --survey`` and ``wara ctl survey`` through one
reader; coordinates, names, fitted and given poses that are not plausible; and replies
of the control channel that would carry NaN. Each is refused in one line with its
reason (exit 2 for bad input, 1 for a refused fit or request), never a traceback,
nothing written."""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from pathlib import Path
from typing import Any

import pytest

from config import load_project
from config.schema import ProjectConfig
from ipc_app.model.placement import Pose, compose, design_pose
from ipc_app.planner.survey import (
    MAX_NAME_CHARS,
    SurveyError,
    SurveyPoint,
    as_built_problems,
    fit_survey,
    format_survey,
    parse_survey_text,
)
from ipc_app.service.ctl import CtlError, _line, dispatch, parse, request
from ipc_app.service.requests import MAX_SURVEY_POINTS
from tests.cli_helpers import run_main, run_wara
from wara.cycle import survey_faces

RING = 4
HEADER = "point,face_y_m,face_z_m,x_m,y_m,z_m"


@pytest.fixture(scope="module")
def cfg() -> ProjectConfig:
    return load_project(None)


def _good(cfg: ProjectConfig, n: int = 6, pose: Pose | None = None) -> list[str]:
    """The lines of a survey of ring 4's part at ``pose`` (default its design)."""
    p = design_pose(cfg, RING) if pose is None else pose
    return format_survey(cfg, RING, p, survey_faces(cfg, n)).splitlines()


def _write(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _set(line: str, column: str, value: str) -> str:
    cells = line.split(",")
    cells[HEADER.split(",").index(column)] = value
    return ",".join(cells)


@pytest.fixture
def no_service(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``wara ctl`` pointed at a socket nobody listens on: a refusal that names the file
    came before any connection."""
    sock = tmp_path / "none.sock"
    monkeypatch.setenv("WARA_CTL_SOCKET", str(sock))
    return sock


def _special(kind: str, tmp_path: Path) -> tuple[Path, str]:
    """A file that is not a survey: where it is, and the reason it is refused for."""
    if kind == "dev_zero":
        return Path("/dev/zero"), "a device, expected a regular file"
    if kind == "fifo":
        fifo = tmp_path / "survey.fifo"
        os.mkfifo(fifo)  # no writer: a plain open would hang
        return fifo, "a FIFO (named pipe), expected a regular file"
    if kind == "directory":
        return tmp_path, "a directory, expected a regular file"
    if kind == "huge":
        big = tmp_path / "big.csv"
        with big.open("wb") as f:
            f.truncate(200 * 1024 * 1024)  # 200 MB (sparse): refused after 1 MiB
        return big, "longer than 1048576 bytes"
    if kind == "latin1":
        bad = tmp_path / "latin1.csv"
        bad.write_bytes(f"{HEADER}\nP\xf61,0,0.2,8,0,-6\n".encode("latin-1"))
        return bad, f"not UTF-8 text (byte {len(HEADER) + 2})"
    assert kind == "missing"
    return tmp_path / "missing.csv", "file not found"


KINDS = ("dev_zero", "fifo", "directory", "huge", "latin1", "missing")


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(
    "argv",
    [
        ["survey", "import", "{}", "--ring", "4"],
        ["place", "plan", "--ring", "5", "--survey", "{}"],
        ["ctl", "survey", "{}"],
    ],
    ids=["survey-import", "place-plan", "ctl-survey"],
)
def test_a_file_that_is_not_a_survey_is_refused_at_once_by_every_reader(
    tmp_path: Path, no_service: Path, kind: str, argv: list[str]
) -> None:
    path, why = _special(kind, tmp_path)
    t0 = time.monotonic()
    code, out, err = run_main([a.replace("{}", str(path)) for a in argv])
    assert time.monotonic() - t0 < 2.0
    assert code == 2 and out == ""
    (line,) = err.splitlines()
    assert line.startswith(f"wara {argv[0]}: error: {path}: {why}"), line


@pytest.mark.parametrize("kind", ["dev_zero", "fifo"])
def test_wara_ctl_survey_refuses_a_device_and_a_fifo_in_a_subprocess(
    tmp_path: Path, kind: str
) -> None:
    path, why = _special(kind, tmp_path)
    t0 = time.monotonic()
    proc = run_wara(["ctl", "--socket", str(tmp_path / "none.sock"), "survey", str(path)])
    assert time.monotonic() - t0 < 10.0  # a fresh interpreter on a loaded machine
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.startswith(f"wara ctl: error: {path}: {why}")
    assert proc.stderr.count("\n") == 1


def test_more_points_than_a_request_carries_are_refused_before_sending(
    tmp_path: Path, cfg: ProjectConfig, no_service: Path
) -> None:
    for n in (MAX_SURVEY_POINTS + 1, 16_667):
        pts = [f"Q{k},{(k % 80) * 0.1 - 4.0:.1f},{(k // 80) * 0.01:.2f},8,0,-6" for k in range(n)]
        path = _write(tmp_path / f"many{n}.csv", [HEADER, *pts])
        code, _, err = run_main(["ctl", "survey", str(path)])
        assert code == 2
        assert err == (
            f"wara ctl: error: {path}: {n} points; a survey request carries at most "
            f"{MAX_SURVEY_POINTS}\n"
        )
    # the limit itself goes on to the (absent) service
    pts = [f"Q{k},{(k % 20) * 0.4 - 4.0:.1f},{(k // 20) * 0.2:.1f},8,0,-6" for k in range(200)]
    code, _, err = run_main(["ctl", "survey", str(_write(tmp_path / "200.csv", [HEADER, *pts]))])
    assert code == 2 and "no W-ARa service listening" in err


def test_a_request_over_the_line_limit_is_refused_before_connecting(tmp_path: Path) -> None:
    with pytest.raises(CtlError, match="over the control channel's limit of 65536") as exc:
        request(
            "audit", socket_path=tmp_path / "none.sock", user="a", action="b", result="x" * 70_000
        )
    assert "no W-ARa service" not in str(exc.value)


@pytest.mark.parametrize(
    ("column", "value", "why"),
    [
        ("z_m", "1e308", "z_m: 1e+308 m is outside -10000..10000 m"),
        ("x_m", "-2e7", "x_m: -2e+07 m is outside -1e+07..1e+07 m"),
        ("face_y_m", "1e200", "face_y_m: 1e+200 m is outside -100..100 m"),
        ("face_z_m", "-101", "face_z_m: -101 m is outside -100..100 m"),
        ("y_m", "nan", "y_m: 'nan' is not a number"),
        ("z_m", "1_0", "z_m: '1_0' is not a number"),
        ("z_m", "\u0664", "z_m: '\u0664' is not a number"),
        ("x_m", "1e999", "x_m: '1e999' is not a finite number"),
    ],
)
def test_a_coordinate_out_of_its_range_is_refused_naming_its_line_and_column(
    tmp_path: Path, cfg: ProjectConfig, column: str, value: str, why: str
) -> None:
    """Six finite points and one coordinate of 1e308 gave a NaN pose, accepted (exit 0);
    with --db a ValueError traceback and an empty database; wara place plan a
    traceback; huge face values numpy RuntimeWarnings and a message blaming face_y_m,
    face_z_m of all the points."""
    lines = _good(cfg)
    lines[6] = _set(lines[6], column, value)
    path = _write(tmp_path / "s.csv", lines)
    db = tmp_path / "new.sqlite"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning fails the test
        for argv, prog in [
            (["survey", "import", str(path), "--ring", "4", "--db", str(db)], "survey"),
            (["place", "plan", "--ring", "5", "--survey", str(path)], "place"),
        ]:
            code, out, err = run_main(argv)
            assert (code, out) == (2, ""), argv
            assert err.startswith(f"wara {prog}: error: {path}: line 7: {why}"), err
            assert err.count("\n") == 1 and err.endswith("\n")
    assert not db.exists()


def test_every_bad_line_is_named_and_the_list_is_bounded(
    tmp_path: Path, cfg: ProjectConfig
) -> None:
    lines = _good(cfg)
    bad = [HEADER, *(_set(lines[1 + k % 6], "point", f"B{k}") for k in range(6))]
    bad += [_set(_set(lines[1], "point", f"X{k}"), "z_m", "1e308") for k in range(30)]
    code, _, err = run_main(
        ["survey", "import", str(_write(tmp_path / "s.csv", bad)), "--ring", "4"]
    )
    got = err.splitlines()
    assert code == 2 and len(got) == 21
    assert got[0].endswith("line 8: z_m: 1e+308 m is outside -10000..10000 m")
    assert got[-1].endswith("s.csv: 10 more bad line(s) not listed")


@pytest.mark.parametrize(
    ("name", "why"),
    [
        ("P\x1b[31mRED", "character 2 is U+001B"),
        ("P\u202eevil", "character 2 is U+202E"),  # right-to-left override
        ("P\x07", "character 2 is U+0007"),
        ("P" * (MAX_NAME_CHARS + 1), f"at most {MAX_NAME_CHARS} are allowed"),
    ],
)
def test_a_point_name_with_control_characters_is_refused_and_not_echoed_raw(
    tmp_path: Path, cfg: ProjectConfig, no_service: Path, name: str, why: str
) -> None:
    lines = _good(cfg)
    lines[3] = _set(lines[3], "point", name)
    path = _write(tmp_path / "s.csv", lines)
    for argv in (["survey", "import", str(path), "--ring", "4"], ["ctl", "survey", str(path)]):
        code, out, err = run_main(argv)
        assert code == 2 and out == "", argv
        (line,) = err.splitlines()
        assert f"{path}: line 4: point: name " in line and why in line
        assert all(c.isprintable() for c in line), repr(line)  # escaped, never raw


def test_a_name_of_other_scripts_is_a_name(cfg: ProjectConfig) -> None:
    lines = _good(cfg)
    lines[1] = _set(lines[1], "point", "Punkt-Ö 1")
    pts = parse_survey_text("\n".join(lines))
    assert pts[0].name == "Punkt-Ö 1" and fit_survey(cfg, RING, pts).accepted


def test_a_fit_turned_or_moved_off_its_ring_is_refused_with_its_reason(
    tmp_path: Path, cfg: ProjectConfig
) -> None:
    """The fitted pose's plausibility: an angle over 10 deg (the deviation form's bound)
    was accepted before; a part moved off its ring was refused, and still is."""
    design = design_pose(cfg, RING)
    turned = compose(design, Pose(0.0, 0.0, 0.0, math.radians(15.0), 0.0, 0.0))
    path = _write(tmp_path / "turned.csv", _good(cfg, pose=turned))
    code, out, err = run_main(["survey", "import", str(path), "--ring", "4"])
    assert code == 1 and err == "" and "REFUSED" in out
    assert "Refused: the fitted pose: the part is turned roll +15.0 deg from its design" in out
    moved = Pose(design.x, design.y + 0.06, *design[2:])
    fit = fit_survey(
        cfg, RING, parse_survey_text(format_survey(cfg, RING, moved, survey_faces(cfg, 6)))
    )
    assert not fit.accepted and "60 mm across" in fit.reasons[0]


@pytest.mark.parametrize(
    "pose",
    [
        Pose(math.nan, 0, 0, 0, 0, 0),
        Pose(0, 0, math.inf, 0, 0, 0),
        Pose(1e300, 1e300, 1e300, 1e300, 1e300, 1e300),
    ],
)
def test_an_as_built_pose_that_is_not_finite_or_plausible_has_a_reason(
    cfg: ProjectConfig, pose: Pose
) -> None:
    (why,) = as_built_problems(cfg, RING, pose)[:1]
    assert "ring 4" in why
    assert as_built_problems(cfg, RING, design_pose(cfg, RING)) == []


def test_a_survey_point_is_checked_when_it_is_built(cfg: ProjectConfig) -> None:
    """The service builds the points of a ``survey`` request as the parser does: the
    same checks (names, ranges) refuse them."""
    with pytest.raises(ValueError, match="z_m: 1e\\+308 m is outside"):
        SurveyPoint(1, "P1", (0.0, 0.2), (8.0, 0.0, 1e308))
    with pytest.raises(ValueError, match="U\\+001B"):
        SurveyPoint(1, "P\x1b", (0.0, 0.2), (8.0, 0.0, -6.0))
    with pytest.raises(SurveyError, match="line 2: z_m"):
        parse_survey_text(f"{HEADER}\nP1,0,0.2,8,0,1e308\n")


# ---------------------------------------------------------------- the control channel


def _handlers(monkeypatch: pytest.MonkeyPatch) -> Any:
    """The service's handlers on a core whose cycle would take anything (a spy)."""
    from ipc_app.service.app import service_handlers

    calls: list[tuple[str, Any]] = []

    class Core:
        cfg = load_project(None)

        def request_cycle(self, *a: Any, **k: Any) -> dict[str, Any]:
            calls.append(("cycle", a))
            return {"ok": True}

        def submit_survey(self, **k: Any) -> dict[str, Any]:
            calls.append(("survey", k))
            return {"ok": True}

    class Records:
        def write(self, *a: Any) -> str:
            return ""

    return service_handlers(lambda: Core(), lambda: None, records=Records()), calls  # type: ignore[arg-type,return-value]


def test_a_cycle_with_an_implausible_previous_part_is_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``previous_pose`` of six 1e300 and a ``previous_deviation`` of 1e300 had no check."""
    handlers, calls = _handlers(monkeypatch)
    out = dispatch(
        handlers,
        b'{"cmd": "cycle", "ring": 3, "previous_pose": [1e300, 1e300, 1e300, 1e300, 1e300, 1e300]}',
    )
    assert out["ok"] is False and out["code"] == "bad_request"
    assert out["error"].startswith("cycle refused: previous_pose: ") and "ring 2" in out["error"]
    out = dispatch(
        handlers, b'{"cmd": "cycle", "ring": 3, "previous_deviation": [1e300, 0, 0, 0, 0]}'
    )
    assert out["code"] == "bad_request"
    assert out["error"] == "'previous_deviation': at most 50 mm and 10 deg (a typo, not a survey)"
    cfg = load_project(None)
    d = design_pose(cfg, 2).to_dict()
    good = json.dumps({"cmd": "cycle", "ring": 3, "previous_pose": list(d.values())}).encode()
    assert dispatch(handlers, good) == {"ok": True}
    assert [c[0] for c in calls] == ["cycle"]


def test_survey_points_out_of_range_in_a_request_are_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    handlers, calls = _handlers(monkeypatch)
    pts = [["P1", 0, 0.2, 8, 0, -6], ["P2", 1, 0.2, 8, 1, 1e300]]
    out = dispatch(handlers, json.dumps({"cmd": "survey", "points": pts}).encode())
    assert out == {
        "ok": False,
        "code": "bad_request",
        "error": "survey: point 2: z_m: 1e+300 m is outside -10000..10000 m",
    }
    pts[1] = ["P\u001b[2J", 1, 0.2, 8, 1, -6]
    out = dispatch(handlers, json.dumps({"cmd": "survey", "points": pts}).encode())
    assert "U+001B" in out["error"] and "\x1b" not in out["error"]
    assert calls == []


def test_no_reply_carries_nan_or_infinity() -> None:
    """A reply with NaN was sent as ``NaN`` (not JSON); now it is an ``internal`` error."""
    for bad in (math.nan, math.inf, -math.inf):
        raw = _line({"ok": True, "rms_residual_mm": bad, "nested": {"v": [1.0]}})
        reply = json.loads(raw, parse_constant=lambda c, raw=raw: pytest.fail(f"{c} in {raw!r}"))
        assert reply == {
            "ok": False,
            "error": "reply could not be encoded: a value that is not a finite number",
            "code": "internal",
        }
    assert json.loads(_line({"ok": True, "v": 1.5})) == {"ok": True, "v": 1.5}
    assert parse(b'{"cmd": "survey", "pose": [NaN, 0, 0, 0, 0, 0]}')["code"] == "bad_request"  # type: ignore[index]


def test_no_reply_of_a_live_server_carries_nan(tmp_path: Path) -> None:
    from ipc_app.service.ctl import CtlHandlers, CtlServer

    handlers = CtlHandlers(
        adjust=lambda r, p: {"roll_deg": math.nan},
        status=lambda *a: {"mode": "IDLE"},
        stop=dict,
        reset=dict,
    )
    with CtlServer(handlers, tmp_path / "ctl.sock"):
        reply = request("adjust", socket_path=tmp_path / "ctl.sock", roll_deg=1.0, pitch_deg=2.0)
    assert reply["ok"] is False and reply["code"] == "internal"
    assert "not a finite number" in reply["error"]

"""``wara acceptance``: ring acceptance records and the quality report (docs/acceptance.md).

Verbs::

    wara acceptance add RING --measured-at T --vertical-misalignment-mm V ... [--operator NAME]
    wara acceptance import FILE.csv            # whole file in one transaction, or nothing
    wara acceptance report --out DIR [--from N --to M] [--json]
    wara acceptance list [--from N --to M] [--json]
    wara acceptance history RING [--json]
    wara acceptance attach-plan RING PLAN.json [--final-attitude ATT.json]
    wara acceptance example [--out FILE]       # the synthetic 50-ring example CSV

Every verb takes ``--db PATH`` (default ``$WARA_DATA_DIR/acceptance.sqlite``, else
``./wara-data/acceptance.sqlite``); the judging verbs take ``--config YAML`` (default:
the shipped project). Exit codes: 0 done, 1 nothing to report, 2 bad arguments, rows
rejected on import (nothing imported), unusable file or database.

The logic lives in :mod:`acceptance`; this module only parses and prints.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

from acceptance.csv_import import CsvFileError, ImportResult, import_parsed, parse_csv
from acceptance.example import example_csv_text
from acceptance.items import ITEMS, ControlItem, parse_ring
from acceptance.judge import RingVerdict, Status, Summary, judge_ring, limits_from, summarize
from acceptance.report import ReportMeta, report_dict, write_report
from acceptance.store import (
    AcceptanceStore,
    RingMeasurement,
    StoreError,
    check_store,
    default_db_path,
)
from config import ProjectConfig, default_project_path, load_project
from config.files import InputFileError, read_input_file
from config.numbers import argument_type
from wara.cli import EXIT_FAILED, EXIT_OK, EXIT_USAGE, UsageError
from wara.extras import require

#: Largest plan or attitude JSON read.
MAX_JSON_BYTES = 1024 * 1024


@argument_type
def _ring_arg(text: str) -> int:
    """argparse type of a ring number: the CSV's syntax (no ``1_0``, no other scripts)."""
    try:
        return parse_ring(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _value_arg(item: ControlItem) -> Callable[[str], float]:
    """argparse type of an item's value: the CSV's number syntax and plausible range."""

    @argument_type
    def parse(text: str) -> float:
        try:
            return item.parse(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    parse.__name__ = item.key  # argparse names the type in its message
    return parse


def _guarded(verb: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """A database that turns out unusable while reading is a one-line error, exit 2."""

    @functools.wraps(verb)
    def run(args: argparse.Namespace) -> int:
        try:
            return verb(args)
        except StoreError as exc:
            raise UsageError(str(exc)) from None

    return run


def _add_db(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--db",
        default=None,
        metavar="PATH",
        help="acceptance database (default: $WARA_DATA_DIR/acceptance.sqlite, else "
        "./wara-data/acceptance.sqlite)",
    )


def _add_config(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config", default=None, metavar="YAML", help="project YAML (default: shipped project)"
    )


def _add_range(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--from",
        dest="ring_from",
        type=_ring_arg,
        default=None,
        metavar="N",
        help="first ring (default: the lowest recorded)",
    )
    p.add_argument(
        "--to",
        dest="ring_to",
        type=_ring_arg,
        default=None,
        metavar="M",
        help="last ring (default: the highest recorded)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("acceptance", help="ring acceptance records and the quality report")
    verbs = p.add_subparsers(dest="acceptance_command", metavar="VERB")
    verbs.required = True

    a = verbs.add_parser("add", help="record one ring survey (re-recording keeps the history)")
    a.add_argument("ring", type=_ring_arg, help="ring number (>= 1)")
    a.add_argument(
        "--measured-at",
        default=None,
        metavar="TIME",
        help="ISO 8601 time of the survey (default: now, local time with offset)",
    )
    for item in ITEMS:
        a.add_argument(
            f"--{item.key.replace('_', '-')}",
            dest=item.key,
            type=_value_arg(item),
            required=item.required,
            metavar=item.unit.upper(),
            help=f"{item.label} ({item.unit}){'' if item.required else ', if measured'}",
        )
    a.add_argument("--operator", default="", help="who surveyed")
    a.add_argument("--remarks", default="", help="free text")
    _add_db(a)
    _add_config(a)
    a.set_defaults(func=_guarded(_add))

    i = verbs.add_parser(
        "import",
        help="import a survey CSV in one transaction; if any row is bad, each is listed with "
        "its line number, nothing is written and the exit code is 2",
    )
    i.add_argument("file", help="CSV file (format: docs/acceptance.md)")
    i.add_argument("--json", action="store_true", help="print the outcome as JSON")
    _add_db(i)
    i.set_defaults(func=_guarded(_import))

    r = verbs.add_parser(
        "report", help="pass/fail per ring and item, pass rates, PNG plots and an HTML page"
    )
    _add_range(r)
    r.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="directory for report.html, summary.json and one PNG per item",
    )
    r.add_argument("--json", action="store_true", help="print the summary as JSON")
    _add_db(r)
    _add_config(r)
    r.set_defaults(func=_guarded(_report))

    ls = verbs.add_parser("list", help="the current record of each ring, judged")
    _add_range(ls)
    ls.add_argument("--json", action="store_true", help="JSON output")
    _add_db(ls)
    _add_config(ls)
    ls.set_defaults(func=_guarded(_list))

    h = verbs.add_parser("history", help="every record of one ring and its attached plans")
    h.add_argument("ring", type=_ring_arg, help="ring number")
    h.add_argument("--json", action="store_true", help="JSON output")
    _add_db(h)
    h.set_defaults(func=_guarded(_history))

    ap = verbs.add_parser(
        "attach-plan", help="attach the controller's plan (e.g. `wara plan --json`) to a ring"
    )
    ap.add_argument("ring", type=_ring_arg, help="ring number")
    ap.add_argument("plan", help="JSON file with the plan object ('-' for stdin)")
    ap.add_argument(
        "--final-attitude",
        default=None,
        metavar="JSON",
        help="JSON file with the controller's final attitude",
    )
    _add_db(ap)
    ap.set_defaults(func=_guarded(_attach_plan))

    ex = verbs.add_parser("example", help="write the synthetic 50-ring example CSV")
    ex.add_argument("--out", default=None, metavar="FILE", help="file (default: stdout)")
    ex.set_defaults(func=_example)


# ---------------------------------------------------------------------- helpers


def _db_path(args: argparse.Namespace) -> Path:
    return Path(args.db) if args.db else default_db_path()


def _open(args: argparse.Namespace, *, create: bool) -> AcceptanceStore:
    try:
        return AcceptanceStore.open(_db_path(args), create=create)
    except StoreError as exc:
        raise UsageError(str(exc)) from None


def _check_range(args: argparse.Namespace) -> None:
    lo, hi = args.ring_from, args.ring_to
    if (lo is not None and lo < 1) or (hi is not None and hi < 1):
        raise UsageError("--from/--to: ring numbers start at 1")
    if lo is not None and hi is not None and lo > hi:
        raise UsageError(f"--from {lo} is after --to {hi}")


def _fmt_value(v: float | None, unit: str) -> str:
    return "-" if v is None else f"{v:g} {unit}"


def _read_json_object(path: str, what: str) -> dict[str, Any]:
    try:
        if path == "-":
            text = sys.stdin.read(MAX_JSON_BYTES + 1)
            if len(text) > MAX_JSON_BYTES:
                raise UsageError(f"{what} on stdin: longer than {MAX_JSON_BYTES} characters")
        else:
            text = read_input_file(path, MAX_JSON_BYTES).decode("utf-8")
    except InputFileError as exc:
        raise UsageError(f"{what} {exc}") from None
    except UnicodeDecodeError as exc:
        raise UsageError(f"{what} {path}: not UTF-8 text (byte {exc.start})") from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise UsageError(f"{what} {path}: not JSON: line {exc.lineno}: {exc.msg}") from None
    except RecursionError:
        raise UsageError(f"{what} {path}: not JSON this program reads: nested too deeply") from None
    if not isinstance(obj, dict):
        raise UsageError(f"{what} {path}: expected a JSON object, got {type(obj).__name__}")
    return obj


# ---------------------------------------------------------------------- verbs


def _add(args: argparse.Namespace) -> int:
    project = load_project(args.config)
    measured_at = args.measured_at or datetime.now().astimezone().isoformat(timespec="seconds")
    try:
        m = RingMeasurement(
            ring=args.ring,
            measured_at=measured_at,
            values={i.key: getattr(args, i.key) for i in ITEMS},
            operator=args.operator,
            remarks=args.remarks,
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    with _open(args, create=True) as store:
        earlier = len(store.history(m.ring))
        rec = store.add(m, source="cli add")
    result = judge_ring(rec, limits_from(project.acceptance))
    again = f" (re-recorded: {earlier} earlier record(s) kept)" if earlier else ""
    print(f"ring {m.ring}: recorded as #{rec.record_id}{again}: {result.verdict}")
    for item in ITEMS:
        st = result.statuses[item.key]
        if st is Status.FAIL:
            limit = getattr(project.acceptance, item.key)
            print(f"  {item.label}: {m.values[item.key]:g} {item.unit}, limit {limit:g}: fail")
        elif st is Status.NOT_MEASURED:
            print(f"  {item.label}: not measured (the project sets a limit)")
    return EXIT_OK


def _import(args: argparse.Namespace) -> int:
    try:
        check_store(_db_path(args), create=True)  # usable, but not created yet
        parsed = parse_csv(args.file)  # before the database is opened (or created)
    except StoreError as exc:
        raise UsageError(str(exc)) from None
    except CsvFileError as exc:
        raise UsageError(f"{exc} (nothing imported)") from None
    if parsed.errors:  # nothing will be written: no database to open or create
        res = ImportResult(parsed.source, [], [], parsed.errors, None)
    else:
        with _open(args, create=True) as store:
            res = import_parsed(store, parsed)
    if args.json:
        print(
            json.dumps(
                {
                    "file": res.source,
                    "import_id": res.import_id,
                    "recorded": len(res.recorded),
                    "recorded_rings": [r.ring for r in res.recorded],
                    "unchanged_lines": res.unchanged_lines,
                    "rejected": [{"line": e.line, "reason": e.reason} for e in res.errors],
                },
                indent=2,
            )
        )
    else:
        for err in res.errors:
            print(f"{res.source}: {err}", file=sys.stderr)
        if res.errors:
            print(
                f"{res.source}: nothing imported: {len(res.errors)} row(s) rejected "
                "(a file is imported whole or not at all)",
                file=sys.stderr,
            )
        else:
            batch = f" (import #{res.import_id})" if res.import_id is not None else ""
            print(
                f"{res.source}: {len(res.recorded)} row(s) recorded{batch}, "
                f"{len(res.unchanged_lines)} unchanged (already recorded identically)"
            )
    return EXIT_OK if res.ok else EXIT_USAGE


def summary_of(
    store: AcceptanceStore,
    project: ProjectConfig,
    ring_from: int | None = None,
    ring_to: int | None = None,
) -> Summary:
    """The store's current records judged against the project's Table 4 (the report's)."""
    return summarize(
        store.current(ring_from, ring_to),
        project.acceptance,
        ring_from=ring_from,
        ring_to=ring_to,
        rings_with_plan=store.rings_with_plan(),
    )


def report_meta(project: ProjectConfig, config_path: str | None, db: Path) -> ReportMeta:
    """Where the report's numbers came from (its header)."""
    return ReportMeta(
        project=f"{project.project.name} {project.project.section}".strip(),
        config_source=config_path or f"shipped project {default_project_path().name}",
        database=str(db),
    )


def _summary_for(args: argparse.Namespace, store: AcceptanceStore) -> Any:
    project = load_project(args.config)
    _check_range(args)
    return project, summary_of(store, project, args.ring_from, args.ring_to)


def _report(args: argparse.Namespace) -> int:
    require("matplotlib", "wara acceptance report")
    with _open(args, create=False) as store:
        project, summary = _summary_for(args, store)
    if not summary.rings:
        print("wara acceptance report: no ring records in that range", file=sys.stderr)
        return EXIT_FAILED
    meta = report_meta(project, args.config, _db_path(args))
    files = write_report(summary, args.out, meta)
    if args.json:
        print(json.dumps(report_dict(summary, meta), indent=2))
    else:
        ov = summary.overall_dict()
        rate = ov["ring_pass_rate"]
        print(
            f"rings {ov['first_ring']}-{ov['last_ring']}: {ov['rings_passed']}/{ov['rings']} "
            f"pass ({100 * rate:.1f} %), failed rings: "
            f"{', '.join(map(str, ov['failed_rings'])) or 'none'}"
        )
        for it in summary.items:
            if it.limit is None:
                print(f"  {it.item.label}: no limit set ({it.measured} measured)")
            else:
                pr = "-" if it.pass_rate is None else f"{100 * it.pass_rate:.1f} %"
                print(f"  {it.item.label}: {it.passed}/{it.judged} pass ({pr})")
        print(f"wrote {files.html}, {files.summary_json} and {len(files.plots)} plot(s)")
    return EXIT_OK


def _list(args: argparse.Namespace) -> int:
    with _open(args, create=False) as store:
        _, summary = _summary_for(args, store)
        counts = store.record_counts()
    if args.json:
        out = [{**r.to_dict(), "records": counts.get(r.ring, 0)} for r in summary.rings]
        print(json.dumps(out, indent=2))
        return EXIT_OK
    for r in summary.rings:
        over = [
            f"{i.label} {r.record.measurement.values[i.key]:g} {i.unit}"
            for i in ITEMS
            if r.statuses[i.key] is Status.FAIL
        ]
        n = counts.get(r.ring, 0)
        hist = f" [{n} records]" if n > 1 else ""
        why = f": {'; '.join(over)}" if r.verdict is RingVerdict.FAIL else ""
        print(f"ring {r.ring:>4}  {r.record.measurement.measured_at}  {r.verdict}{why}{hist}")
    return EXIT_OK


def _history(args: argparse.Namespace) -> int:
    with _open(args, create=False) as store:
        records = store.history(args.ring)
        plans = store.plans(args.ring)
    if args.json:
        print(
            json.dumps(
                {
                    "ring": args.ring,
                    "records": [r.to_dict() for r in records],
                    "plans": [p.to_dict() for p in plans],
                },
                indent=2,
            )
        )
        return EXIT_OK if records or plans else EXIT_FAILED
    if not records and not plans:
        print(f"ring {args.ring}: no records")
        return EXIT_FAILED
    for n, rec in enumerate(records):
        m = rec.measurement
        tag = "current" if n == len(records) - 1 else "superseded"
        print(
            f"#{rec.record_id} ({tag}) measured {m.measured_at}, recorded {rec.recorded_at}, "
            f"by {m.operator or '-'} via {rec.source}"
        )
        for item in ITEMS:
            print(f"    {item.label}: {_fmt_value(m.values[item.key], item.unit)}")
        if m.remarks:
            print(f"    remarks: {m.remarks}")
    for p in plans:
        att = "" if p.final_attitude is None else f", final attitude {json.dumps(p.final_attitude)}"
        print(f"plan #{p.plan_id} attached {p.attached_at}{att}")
    return EXIT_OK


def _attach_plan(args: argparse.Namespace) -> int:
    plan = _read_json_object(args.plan, "plan")
    att = None
    if args.final_attitude is not None:
        att = _read_json_object(args.final_attitude, "final attitude")
    with _open(args, create=True) as store:
        try:
            stored = store.attach_plan(args.ring, plan, final_attitude=att)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    print(f"ring {stored.ring}: plan #{stored.plan_id} attached")
    return EXIT_OK


def _example(args: argparse.Namespace) -> int:
    text = example_csv_text()
    if args.out is None:
        sys.stdout.write(text)
    else:
        Path(args.out).write_text(text, encoding="utf-8")
        print(f"wrote {args.out} (synthetic example: 50 rings)")
    return EXIT_OK

"""``wara commission PROJECT.yaml --out DIR``: the controls engineer's dossier of one
tunnel project (docs/commissioning.md).

    wara commission config/projects/metro_light_part.yaml --out dossier/
    wara commission my.yaml --quick --out dossier/           # 1 step, 1 ring, no campaign
    wara commission my.yaml --runs 50 --workers 2 --out dossier/

Writes ``DIR/commission.html`` (one self-contained page) and ``DIR/commission.json``
(each item with its verdict); the children's output in ``DIR/logs/``. Exit 0 only if the
project is fit to commission (every item fit, skipped or not applicable), 1 otherwise
with one line per reason an item is not fit; 2 a project file that does not load (the
YAML, the schema: its error in one line per problem) or bad arguments.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from config.numbers import integer
from wara.cli import EXIT_FAILED, EXIT_OK, UsageError, check_walk_steps, stop_on_sigterm

#: the most rings of a dossier's cycle (``wara cycle``'s limit)
MAX_RINGS = 50
#: the most runs of a dossier's campaign (a verification campaign is ``wara campaign run``)
MAX_RUNS = 10_000


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "commission",
        help="the dossier of a project: cross-checks, capacity, delay margins, budgets, "
        "walk, ring cycles, campaign; fit or not",
        description="Every check of a tunnel project in one self-contained HTML page and "
        "a JSON summary (docs/commissioning.md). Exit 0 only if fit to commission.",
    )
    p.add_argument("project", metavar="PROJECT.yaml", help="the project YAML")
    p.add_argument("--out", required=True, metavar="DIR", help="where the page and JSON go")
    p.add_argument("--steps", type=integer, default=None, help="steps of the walk (default 3)")
    p.add_argument("--rings", type=integer, default=None, help="rings of the cycle (default 4)")
    p.add_argument(
        "--runs", type=integer, default=None, help="runs of the campaign (default 20; 0: skip)"
    )
    eng = p.add_mutually_exclusive_group()
    eng.add_argument("--scheduler", metavar="ADDR", help="the campaign on a running Dask scheduler")
    eng.add_argument("--workers", type=integer, metavar="N", help="the campaign's local workers")
    p.add_argument(
        "--quick",
        action="store_true",
        help="1 step, 1 ring, no campaign, no lockstep delay hold (what the tests run)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress line on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from config.loader import read_yaml, validate_data
    from config.schema import ProjectConfig
    from wara.commission import Settings

    quick = args.quick
    s = Settings(
        steps=args.steps if args.steps is not None else (1 if quick else 3),
        rings=args.rings if args.rings is not None else (1 if quick else 4),
        runs=args.runs if args.runs is not None else (0 if quick else 20),
        workers=args.workers,
        scheduler=args.scheduler,
        delay_hold=not quick,
        progress=not args.quiet,
    )
    check_walk_steps(s.steps)
    if not 1 <= s.rings <= MAX_RINGS:
        raise UsageError(f"--rings must be within 1..{MAX_RINGS}, got {s.rings}")
    if not 0 <= s.runs <= MAX_RUNS:
        raise UsageError(f"--runs must be within 0..{MAX_RUNS}, got {s.runs}")
    if s.workers is not None and not 1 <= s.workers <= 256:
        raise UsageError(f"--workers must be 1..256, got {s.workers}")
    # the schema alone: a project that breaks a cross-check is that item's verdict
    path = args.project
    cfg = validate_data(ProjectConfig, read_yaml(Path(path)), path)
    out = Path(args.out)
    try:  # before anything runs: a directory the dossier cannot be written to refuses now
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {out}: {exc.strerror or exc}") from None
    camp = out / "campaign"
    if s.runs and camp.exists() and any(camp.iterdir()):
        raise UsageError(f"--out {out}: holds a campaign of an earlier dossier: use a new --out")

    from wara.commission import NOT_FIT, commission
    from wara.commission_page import write

    stop_on_sigterm()  # the child runs end with the command
    items, summary = commission(cfg, path, out, s)
    page, js = write(items, summary, out)
    for it in items:
        first = f": {it.reasons[0]}" if it.reasons else ""
        print(f"{it.name:<14} {it.status:<15}{first}"[:200])
    print(f"dossier: {page} (JSON: {js})")
    if summary["fit"]:
        print(f"{cfg.project.name}: FIT to commission")
        return EXIT_OK
    for it in items:
        if it.status == NOT_FIT:
            for r in it.reasons:
                print(f"wara commission: not fit: {it.name}: {r}", file=sys.stderr)
    return EXIT_FAILED

"""``wara campaign run|report|replay|tune``: verification campaigns (docs/campaigns.md)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from config.numbers import integer
from wara.cli import EXIT_FAILED, EXIT_OK, UsageError, stop_on_sigterm
from wara.extras import require_campaign


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("campaign", help="Monte-Carlo verification campaigns on Dask")
    verbs = p.add_subparsers(dest="verb", metavar="VERB", parser_class=type(p))
    verbs.required = True

    r = verbs.add_parser("run", help="run a campaign spec into a directory")
    r.add_argument("spec", metavar="SPEC", help="campaign spec YAML")
    where = r.add_mutually_exclusive_group(required=True)
    where.add_argument("--out", metavar="DIR", help="a new (or empty) results directory")
    where.add_argument("--resume", metavar="DIR", help="run only the runs missing in DIR")
    eng = r.add_mutually_exclusive_group()
    eng.add_argument("--scheduler", metavar="ADDR", help="a running Dask scheduler")
    eng.add_argument("--workers", type=integer, metavar="N", help="local worker processes")
    r.add_argument("--json", action="store_true", help="print the outcome as JSON")
    r.set_defaults(func=_run)

    rep = verbs.add_parser("report", help="verdict, worst runs, drivers, HTML page")
    rep.add_argument("dir", metavar="DIR")
    rep.add_argument("--json", action="store_true")
    rep.add_argument("--no-html", action="store_true", help="skip DIR/report.html")
    rep.set_defaults(func=_report)

    rp = verbs.add_parser("replay", help="run one run of a campaign again, with plots")
    rp.add_argument("dir", metavar="DIR")
    rp.add_argument("run", type=integer, metavar="RUN")
    rp.add_argument("--plot", metavar="OUTDIR", help="write OUTDIR/demo.png")
    rp.add_argument("--json", action="store_true")
    rp.set_defaults(func=_replay)

    t = verbs.add_parser("tune", help="Optuna over tune.parameters, campaigns as trials")
    t.add_argument("spec", metavar="SPEC")
    t.add_argument("--out", metavar="DIR", required=True, help="a directory per trial")
    eng = t.add_mutually_exclusive_group()
    eng.add_argument("--scheduler", metavar="ADDR")
    eng.add_argument("--workers", type=integer, metavar="N")
    t.add_argument("--trials", type=integer, metavar="N", help="default: the spec's tune.trials")
    t.add_argument("--runs", type=integer, metavar="N", help="runs per trial (default: spec's)")
    t.add_argument("--json", action="store_true")
    t.set_defaults(func=_tune)


def _check_workers(n: int | None) -> None:
    if n is not None and not 1 <= n <= 256:
        raise UsageError(f"--workers must be 1..256, got {n}")


def _run(args: argparse.Namespace) -> int:
    require_campaign()
    _check_workers(args.workers)
    from wara.campaign.engine import run_campaign
    from wara.campaign.spec import load_campaign

    c = load_campaign(args.spec)
    out = Path(args.resume or args.out)
    stop_on_sigterm()
    o = run_campaign(
        c,
        out,
        scheduler=args.scheduler,
        workers=args.workers,
        resume=args.resume is not None,
        progress=True,
    )
    result: dict[str, Any] = {
        "out": str(o.out),
        "runs": o.total,
        "done_before": o.done_before,
        "written": o.written,
        "failures_written": o.failures,
        "missing": o.missing,
        "errors": {str(k): v for k, v in o.errors.items()},
        "elapsed_s": round(o.elapsed_s, 2),
        "workers": o.workers,
    }
    if args.json:
        print(json.dumps(result, indent=2))
    elif o.done_before == o.total:
        print(
            f"{o.out}: all {o.total} runs were already done, nothing to run; "
            f"wara campaign report {o.out} gives the verdict"
        )
    else:
        print(
            f"{o.written} runs written ({o.done_before} before) of {o.total} in "
            f"{o.elapsed_s:.1f} s on {o.workers} workers, {o.failures} of them failed; "
            f"results: {o.out / 'results.parquet'}"
        )
        for i, err in sorted(o.errors.items())[:5]:
            print(f"run {i} did not complete: {err}", file=sys.stderr)
    if o.missing:
        print(
            f"wara campaign: {len(o.missing)} runs missing; wara campaign run "
            f"{args.spec} --resume {o.out} runs them",
            file=sys.stderr,
        )
        return EXIT_FAILED
    return EXIT_OK


def _report(args: argparse.Namespace) -> int:
    require_campaign()
    from wara.campaign.report import render_text, summary, write_html

    out = Path(args.dir)
    s = summary(out)
    if not args.no_html:
        from wara.extras import require

        require("matplotlib", "the campaign report's plots")
        s["html"] = str(write_html(out))
    print(json.dumps(s, indent=2, default=_nan) if args.json else render_text(s))
    if not args.json and "html" in s:
        print(f"report: {s['html']}")
    return EXIT_OK if s["verdict"]["shown"] else EXIT_FAILED


def _nan(v: Any) -> Any:
    return None if isinstance(v, float) and math.isnan(v) else str(v)


def _replay(args: argparse.Namespace) -> int:
    require_campaign()
    from wara.campaign.engine import campaign_of_dir, read_results
    from wara.campaign.run import VOLATILE_COLUMNS, run_one

    out = Path(args.dir)
    c = campaign_of_dir(out)
    if not 0 <= args.run < c.run_count:
        raise UsageError(f"RUN must be 0..{c.run_count - 1}, got {args.run}")
    payload = json.loads((out / "spec.json").read_text())
    row = run_one(
        c,
        args.run,
        overrides=payload.get("overrides"),
        plot_dir=Path(args.plot) if args.plot else None,
    )
    stored = next((r for r in read_results(out) if r["run"] == args.run), None)
    same = None
    if stored is not None:
        same = all(_same(stored[k], row.get(k)) for k in stored if k not in VOLATILE_COLUMNS)
    if args.json:
        print(json.dumps({"row": row, "same_as_campaign": same}, indent=2, default=_nan))
    else:
        for k, v in row.items():
            print(f"{k}: {v}")
        print(
            "same as the campaign's row: "
            + ("not in the campaign yet" if same is None else ("yes" if same else "NO"))
        )
        if args.plot:
            pngs = sorted(Path(args.plot).glob("*.png"))
            print("plots: " + (", ".join(str(p) for p in pngs) or "none for this run kind"))
    return EXIT_OK if row["passed"] else EXIT_FAILED


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


def _tune(args: argparse.Namespace) -> int:
    require_campaign()
    from wara.extras import require

    require("optuna", "wara campaign tune")
    _check_workers(args.workers)
    from wara.campaign.engine import dask_client, payload_of
    from wara.campaign.spec import load_campaign
    from wara.campaign.tune import tune

    c = load_campaign(args.spec)
    stop_on_sigterm()
    for name, v in (("--trials", args.trials), ("--runs", args.runs)):
        if v is not None and v < 1:
            raise UsageError(f"{name} must be at least 1, got {v}")
    with dask_client(args.scheduler, args.workers, payload_of(c)) as client:
        res = tune(c, Path(args.out), client=client, trials=args.trials, runs=args.runs)
    if args.json:
        print(json.dumps(res, indent=2, default=_nan))
    else:
        v = res["verdict"]
        print(
            f"# wara campaign tune: best of {len(res['trials'])} trials (trial "
            f"{res['best_trial']}), {res['metric']} at the percentile {res['figure']:.4g}"
        )
        print(
            f"# its campaign: {v['runs']} runs, {v['failures']} failed, pass probability "
            f">= {v['lower_bound']:.4f} at {v['confidence']:.0%}"
        )
        print(res["fragment"], end="")
    return EXIT_OK if res["verdict"]["failures"] == 0 else EXIT_FAILED

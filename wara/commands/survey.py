"""``wara survey import``: the as-built pose of a part from points on its front joint face.

    wara survey import ring4-face.csv --ring 4 [--json] [--db PATH]

The file format is in :mod:`ipc_app.planner.survey` and docs/placement.md. Exit 0: the
fit is accepted (with ``--db`` its pose is attached to the ring in the acceptance store,
where ``wara place plan --from-store`` finds it); 1: the fit is refused (residual too
large, or not this ring's part); 2: the file or a point is bad (each bad line named).
"""

from __future__ import annotations

import argparse
import json

from acceptance.items import check_ring
from acceptance.store import AcceptanceStore, StoreError, check_store
from config import units
from config.numbers import integer
from ipc_app.planner.survey import SurveyError, SurveyFit, read_survey
from wara.cli import EXIT_FAILED, EXIT_OK, UsageError
from wara.commands.place import _placement_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "survey",
        help="as-built pose of a part from a total-station or laser survey",
        description="The as-built pose of a part from a survey of its front joint face.",
    )
    verbs = p.add_subparsers(dest="verb", metavar="VERB")
    verbs.required = True
    imp = verbs.add_parser(
        "import",
        help="fit the part's pose to a survey CSV (>= 4 points) and report the residual",
        description="Fit the as-built pose (least squares) to the points of a survey CSV.",
    )
    imp.add_argument("file", metavar="FILE.csv")
    imp.add_argument("--ring", type=integer, required=True, help="the surveyed part's ring")
    imp.add_argument("--config", default=None, help="project YAML (default: shipped Shanghai)")
    imp.add_argument(
        "--db", default=None, metavar="PATH", help="attach the accepted pose to the ring here"
    )
    imp.add_argument("--json", action="store_true", help="print one JSON object")
    imp.set_defaults(func=run_import)


def run_import(args: argparse.Namespace) -> int:
    try:
        check_ring(args.ring)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    cfg = _placement_config(args.config)
    try:
        if args.db:  # before the fit: a store that cannot be used refuses at once
            check_store(args.db, create=True)
        fit = read_survey(cfg, args.ring, args.file)
    except (SurveyError, StoreError) as exc:  # one line per problem
        raise UsageError(str(exc)) from None
    if fit.accepted and args.db:
        try:
            with AcceptanceStore.open(args.db, create=True) as store:
                store.attach_plan(
                    args.ring,
                    {"kind": "survey", "file": str(args.file), **_summary(fit)},
                    final_attitude={"as_built_pose": fit.pose.to_dict()},
                )
        except StoreError as exc:
            raise UsageError(str(exc)) from None
    print(json.dumps(fit.to_dict(), indent=2) if args.json else render(fit))
    return EXIT_OK if fit.accepted else EXIT_FAILED


def _summary(fit: SurveyFit) -> dict[str, float]:
    return {
        "points": len(fit.points),
        "rms_residual_mm": units.to_mm(fit.rms_residual_m),
    }


def render(fit: SurveyFit) -> str:
    d = fit.to_dict()
    lines = [
        f"ring {fit.ring}: {len(fit.points)} points, RMS residual "
        f"{d['rms_residual_mm']:.3f} mm (max {d['max_residual_mm']:.3f} mm): "
        + ("ACCEPTED" if fit.accepted else "REFUSED"),
        "as-built pose in the ring's tunnel frame: "
        + ", ".join(f"{k} {v:+.3f}" for k, v in d["as_built_pose"].items()),
        "deviation from the design: "
        + ", ".join(f"{k} {v:+.3f}" for k, v in d["deviation"].items()),
    ]
    lines += [f"  {k}: {v:.3f} mm" for k, v in d["residuals_mm"].items()]
    lines += [f"Refused: {r}" for r in fit.reasons]
    return "\n".join(lines)

"""``wara hil``: the stand-in PLC and rig on the configured CAN bus (docs/hil.md).

Examples::

    wara hil --config project.yaml                   # real time, bus from can.*
    wara hil --scenario config/scenarios/hil_faults_example.yaml --duration 30
    wara hil --fault "drop:rate=0.2,messages=[PLC_RodPos_*],start_s=5,end_s=10"
    wara hil --lockstep --duration 5                 # virtual time, as fast as it goes

Real time (default) is for a controller in another process (``can.interface:
udp_multicast`` or ``socketcan`` vcan0); lockstep runs in virtual time, deterministic
from the seed (in-process controllers use :class:`hil_sim.simulator.HilSimulator`).
The rig (:func:`rig_scenario`): ``--rig``, else the scenario's ``plant.contact`` where it
sets one, else the walking rig for a project that walks (``frames`` and ``walking``),
the attitude rig otherwise. ``--site-socket PATH``: the crane and the crew's acts from
another process (:mod:`hil_sim.site`).
A status line shows simulated time, realtime factor, PLC state and the faults active.
Under ``$NOTIFY_SOCKET`` (systemd ``Type=notify``, ``wara demo --two-process``) it says
``READY=1`` with the second status line: after its first PLC scans (and the plant's
first-use compiles) and one status interval of steady running.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import threading
import time
from typing import Any

from config import ProjectConfig, load_project
from config.hil_scenario import EVENT_KINDS, HilScenario, load_hil_scenario
from config.loader import parse_yaml_text, validate_data
from config.numbers import decimal, integer
from ipc_app.service.sdnotify import SystemdNotifier
from plc_bridge.errors import BridgeError
from wara.cli import UsageError
from wara.extras import require_realtime_simulator


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("hil", help="HIL simulator: the PLC and the rig over CAN")
    p.add_argument("--config", default=None, help="project YAML (default: shipped project)")
    p.add_argument("--scenario", default=None, help="HIL scenario YAML (events, faults, plant)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--realtime", action="store_true", help="pace by the wall clock (default)")
    mode.add_argument("--lockstep", action="store_true", help="virtual time, as fast as possible")
    p.add_argument("--duration", type=decimal, default=None, help="simulated seconds to run")
    p.add_argument("--seed", type=integer, default=None, help="overrides the scenario's seed")
    p.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="KIND[:KEY=VALUE,...]",
        help=f"add an event as in the scenario's events list; kinds: {', '.join(EVENT_KINDS)}",
    )
    p.add_argument(
        "--status-interval", type=decimal, default=1.0, help="seconds between status lines"
    )
    p.add_argument("--quiet", action="store_true", help="no status line")
    p.add_argument(
        "--rig",
        choices=RIGS,
        default=None,
        help="walking: the body on its eight legs, feet on the invert; attitude: the two "
        "layers on rigid legs, which cannot walk (default: the scenario's plant.contact if it "
        "sets it, else walking for a project with frames and walking sections)",
    )
    p.add_argument(
        "--site-socket",
        default=None,
        metavar="PATH",
        help="serve the crane's and the crew's acts (part, bolt, load) on this Unix socket, "
        "one JSON object a line (docs/hil.md)",
    )
    p.add_argument(
        "--cpus",
        default=None,
        metavar="N[,N...]",
        help="run on these CPUs only (e.g. beside a service whose loop has another CPU)",
    )
    p.set_defaults(func=_run)


def set_cpus(spec: str) -> list[int]:
    """Pin this process (and the threads it starts later) to the CPUs in ``spec``."""
    try:
        cpus = sorted({int(v) for v in spec.split(",") if v.strip()})
    except ValueError:
        raise UsageError(f"--cpus {spec!r}: expected CPU numbers, e.g. 1 or 2,3") from None
    if not cpus:
        raise UsageError(f"--cpus {spec!r}: expected CPU numbers, e.g. 1 or 2,3")
    try:
        os.sched_setaffinity(0, cpus)
    except (OSError, ValueError) as exc:
        allowed = sorted(os.sched_getaffinity(0))
        raise UsageError(f"--cpus {spec!r}: {exc} (this process may use {allowed})") from None
    return cpus


#: The rigs ``--rig`` chooses between.
RIGS = ("walking", "attitude")


def rig_scenario(cfg: ProjectConfig, scenario: HilScenario, rig: str | None) -> HilScenario:
    """``scenario`` with its rig: ``rig`` when given, else the scenario's own
    ``plant.contact`` when it sets one, else the walking rig for a project that walks."""
    if rig is None:
        if "contact" in scenario.plant.model_fields_set:
            return scenario
        rig = "walking" if cfg.walks else "attitude"
    plant = scenario.plant.model_copy(update={"contact": rig == "walking"})
    return scenario.model_copy(update={"plant": plant})


def parse_fault(spec: str) -> dict[str, Any]:
    """``"drop:rate=0.2,messages=[PLC_Status],start_s=1"`` -> an event mapping."""
    kind, _, rest = spec.partition(":")
    event: dict[str, Any] = {"kind": kind.strip()}
    for item in re.split(r",(?![^\[]*\])", rest) if rest.strip() else []:
        key, eq, value = item.partition("=")
        if not eq:
            raise UsageError(f"--fault {spec!r}: expected KEY=VALUE, got {item!r}")
        event[key.strip()] = parse_yaml_text(value, f"--fault {spec!r}")
    return event


def scenario_with_faults(base: HilScenario, faults: list[str]) -> HilScenario:
    if not faults:
        return base
    data = base.model_dump(mode="json")
    data["events"] = [*data["events"], *(parse_fault(f) for f in faults)]
    return validate_data(HilScenario, data, "--fault")


def _interrupt(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt


def _run(args: argparse.Namespace) -> int:
    from hil_sim.simulator import HilSimulator

    if args.cpus is not None:
        set_cpus(args.cpus)  # first, so every thread started later inherits it
    cfg = load_project(args.config)
    scenario = scenario_with_faults(load_hil_scenario(args.scenario), args.fault)
    scenario = rig_scenario(cfg, scenario, args.rig)
    if scenario.plant.contact and not cfg.walks:
        raise UsageError(
            "the walking rig needs the project's frames and walking sections "
            f"({cfg.project.name} has {'no walking' if cfg.walking is None else 'no frames'}); "
            "--rig attitude"
        )
    duration = args.duration if args.duration is not None else scenario.duration_s
    if args.lockstep and duration is None:
        raise UsageError("--lockstep needs --duration (or duration_s in the scenario)")
    if not args.lockstep:
        require_realtime_simulator()
    try:
        sim = HilSimulator(cfg, None, scenario, seed=args.seed)
    except (ValueError, BridgeError) as exc:  # a scenario mistake; a bus that cannot open
        raise UsageError(str(exc)) from None
    site = None
    if args.site_socket is not None:
        from hil_sim.site import SiteServer

        site = SiteServer(sim, args.site_socket)
        try:
            site.start()
        except OSError as exc:
            sim.close()
            raise UsageError(f"--site-socket {args.site_socket}: {exc.strerror or exc}") from None
    between = site.between_scans if site is not None else None
    tty = sys.stderr.isatty()
    notifier = SystemdNotifier.from_env()
    shown = 0

    def show(s: HilSimulator) -> None:
        nonlocal shown
        shown += 1
        if shown == 2:
            notifier.ready(f"PLC scanning, t={s.t_s:.1f} s")
        if not args.quiet:
            end = "\r" if tty else "\n"
            print(s.status_line(), end=end, file=sys.stderr, flush=True)

    print(
        f"wara hil: {cfg.project.name} on can {cfg.can.interface}:{cfg.can.channel}, "
        f"{'lockstep' if args.lockstep else 'real time'}, scenario {scenario.name!r}, "
        f"{'walking' if scenario.plant.contact else 'attitude'} rig, seed {sim.seed}",
        file=sys.stderr,
    )
    t0 = time.monotonic()
    if threading.current_thread() is threading.main_thread():
        # SIGTERM (systemd, `wara demo --two-process`) stops like Ctrl-C: bus closed, summary.
        signal.signal(signal.SIGTERM, _interrupt)
    try:
        if args.lockstep:
            assert duration is not None
            chunk = max(1, round(args.status_interval / sim.cycle_s))
            n = round(duration / sim.cycle_s)
            done = 0
            while done < n:
                k = min(chunk, n - done)
                sim.step(k * sim.cycle_s)
                if between is not None:
                    between()
                done += k
                show(sim)
        else:
            sim.run_realtime(
                duration,
                on_status=show,
                status_interval_s=args.status_interval,
                between_scans=between,
            )
    except KeyboardInterrupt:
        pass
    finally:
        if site is not None:
            site.close()
        sim.close()
        notifier.close()
    if tty and not args.quiet:
        print(file=sys.stderr)
    wall = time.monotonic() - t0
    print(
        f"wara hil: simulated {sim.t_s:.3f} s in {wall:.3f} s wall "
        f"(compute realtime factor {sim.realtime_factor:.2f}x)",
        file=sys.stderr,
    )
    return 0

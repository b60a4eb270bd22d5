"""The two-process form: the simulator and the service as two processes, as on site.

The HIL simulator (``wara hil --realtime``) and the IPC service (``wara serve``) run as
two processes on a UDP multicast CAN bus (``wara_udp`` by default, python-can's
``udp_multicast`` with ``--transport udp_multicast``), inside a private network namespace
so the multicast traffic never reaches the host's network. What runs on the pair:
the attitude examples (:mod:`wara.two_process_examples`, ``wara demo --two-process``),
the ring cycle (:mod:`wara.two_process_cycle`, ``wara demo --two-process --rings N``),
the soak (``wara soak``) and the OPC UA bench. This module is the pair itself:

1. :func:`run_in_netns` (the command, in the caller's namespace) writes a copy of the
   project YAML with ``can.interface`` the transport on :data:`MULTICAST_GROUP`, makes
   the namespace with ``unshare --user --map-root-user --net``, gives it a loopback with
   multicast routed to it (:data:`NETNS_SETUP`) and re-executes the command with
   ``--inside-netns`` in it; from outside, every thread of both processes gets SCHED_FIFO.
   No namespace (no user namespaces, no ``unshare``/``ip``): :class:`NetnsUnavailable`,
   one line, exit 2.
2. :func:`service_and_simulator` (inside) starts the simulator, then the service, and
   hands the caller the service's control socket (as ``wara ctl`` drives it); on exit
   both are stopped with SIGTERM (kill after a timeout).

Decisions (docs/realtime.md, "Two processes"):

- readiness: the simulator says ``READY=1`` on ``$NOTIFY_SOCKET`` (sd_notify, a socket
  of the demo's) after a status interval of steady running; the service is ready when
  its status over the control socket says IDLE.
- the loop: the service publishes :meth:`FixedRateLoop.stats` every 5 s (p50/p99/max
  over the last 4096 cycles = 20.5 s at 200 Hz; ``overruns`` counts from the loop's
  start). Start-up is the time up to the stats report in force once the service is IDLE
  (the first one if none was published yet): that report is the *baseline*
  (:class:`LoopWatch`). Overruns are counted from it (the total since the loop started
  is reported too, nothing is dropped). ``compute_p99_ms`` and ``jitter_p99_ms`` are the
  *worst* of all reports after the baseline (the windows overlap, so every cycle of the
  run is in at least one), not just the last one.
"""

from __future__ import annotations

import contextlib
import os
import re
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

import yaml

from config import load_project, units
from config.loader import default_project_path, read_yaml
from config.schema import ProjectConfig
from ipc_app.service.ctl import CtlError, request
from ipc_app.service.interlocks import Interlock
from plc_bridge.link import Fault

REPO = Path(__file__).resolve().parents[1]

#: The cross-process CAN interfaces the demo can run on, and its default.
TRANSPORTS = ("wara_udp", "udp_multicast")
DEFAULT_TRANSPORT = "wara_udp"
#: Multicast group of the demo's bus (administratively scoped IPv4, inside the namespace).
MULTICAST_GROUP = "239.74.163.2"
#: Run inside the new namespace before anything else: loopback up, multicast routed to it.
NETNS_SETUP = "ip link set lo up && ip link set lo multicast on && ip route add 239.0.0.0/8 dev lo"
UNSHARE = ("unshare", "--user", "--map-root-user", "--net")

#: The loop goal: compute p99 below this fraction of the period.
COMPUTE_P99_GOAL_FRACTION = 0.20
Progress = Callable[[str], None]


class NetnsUnavailable(Exception):
    """The private network namespace cannot be made here (the message says why)."""


class TwoProcessError(Exception):
    """A process of the demo did not come up or died (the message says which and why);
    ``faults``: the service's latched faults as data where it stopped in the safe state
    (its status's ``faults``: interlock, where), else empty."""

    def __init__(self, message: str, faults: list[dict[str, Any]] | None = None) -> None:
        super().__init__(message)
        self.faults = list(faults or [])


# --------------------------------------------------------------------------- outside


def netns_problem() -> str | None:
    """None if a private network namespace with multicast on lo can be made, else why."""
    for tool in ("unshare", "ip", "sh"):
        if shutil.which(tool) is None:
            return f"{tool} not found on PATH"
    try:
        probe = subprocess.run(
            [*UNSHARE, "sh", "-c", NETNS_SETUP],
            capture_output=True,
            text=True,
            timeout=15,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"cannot run unshare: {exc}"
    if probe.returncode != 0:
        err = " ".join(probe.stderr.split()) or f"exit code {probe.returncode}"
        return f"cannot make a private network namespace (unshare --user --net): {err}"
    return None


#: The service's interlocks that stop it on a silent PLC (its heartbeat, its sensors' frames).
_SILENT_PLC = (Interlock.PLC_HEARTBEAT, Interlock.SENSOR_TIMEOUT)


def silent_process_stop(faults: Any) -> bool:
    """Whether latched ``faults`` (the status's ``faults``, as data: ``interlock``,
    ``where``) are a stop on a silent process alone, and at least one: the service's PLC
    heartbeat and sensor timeouts, or the PLC's ``IPC_TIMEOUT``. On the 2-core
    development machine a process of the pair is now and then kept off its CPU for some
    100 ms, a cause not established (docs/realtime.md, "Limits"; decision 0030); the
    machine stops on it, as it should."""
    if not isinstance(faults, list) or not faults:
        return False
    return all(
        f.get("interlock") in _SILENT_PLC
        or (f.get("interlock") == Interlock.PLC_FAULT and f.get("where") == Fault.IPC_TIMEOUT.name)
        for f in faults
    )


def loop_cpus(cfg: ProjectConfig, available: Sequence[int]) -> list[int]:
    """The CPU for the service's loop thread when the demo places the processes: the
    project's own ``control.realtime.cpu_affinity`` if it sets one, else the first of
    ``available`` when there are at least two (none on one CPU)."""
    if cfg.control.realtime.cpu_affinity:
        return list(cfg.control.realtime.cpu_affinity)
    return [min(available)] if len(available) >= 2 else []


def simulator_cpus(cfg: ProjectConfig, available: Sequence[int]) -> list[int]:
    """The simulator's CPUs: the available ones the loop thread is not pinned to."""
    pinned = set(cfg.control.realtime.cpu_affinity)
    rest = sorted(set(available) - pinned)
    return rest if pinned and rest else []


def multicast_config(
    config_path: str | Path | None,
    out_path: Path,
    transport: str = DEFAULT_TRANSPORT,
    *,
    pin: bool = False,
) -> ProjectConfig:
    """Copy the project YAML to ``out_path`` with the bus on ``transport``; validated.

    ``pin``: the service's loop thread gets a CPU of its own (:func:`loop_cpus`, written
    as ``control.realtime.cpu_affinity``); the simulator then runs on the others; and
    unless the project says otherwise the CPUs stay out of deep idle states while the
    loop runs (``control.realtime.cpu_wakeup_latency_us`` 0, as docs/deploy.md has it
    for the IPC).
    """
    src = Path(config_path) if config_path is not None else default_project_path()
    cfg = load_project(src)  # a bad config is the user's error (exit 2), reported against src
    data = read_yaml(src)
    can_block = data.setdefault("can", {})
    can_block["interface"] = transport
    can_block["channel"] = MULTICAST_GROUP
    if pin:
        cpus = loop_cpus(cfg, sorted(os.sched_getaffinity(0)))
        rt = data.setdefault("control", {}).setdefault("realtime", {})
        if cpus:
            rt["cpu_affinity"] = cpus
        if cfg.control.realtime.cpu_wakeup_latency_us is None:
            rt["cpu_wakeup_latency_us"] = 0  # as on the IPC: steps start on a warm CPU
    out_path.write_text(
        "# written by `wara demo --two-process` from "
        + str(src)
        + "\n"
        + yaml.safe_dump(data, sort_keys=False),
        encoding="utf-8",
    )
    return load_project(out_path)


def _env() -> dict[str, str]:
    """The environment of every child: the repo on PYTHONPATH so ``-m wara`` finds it."""
    env = dict(os.environ)
    paths = [str(REPO), *filter(None, env.get("PYTHONPATH", "").split(os.pathsep))]
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
    return env


def run_in_netns(
    wara_args: Sequence[str],
    config_path: str | None,
    *,
    keep_dir: Path | None = None,
    transport: str = DEFAULT_TRANSPORT,
    pin: bool = True,
) -> int:
    """Re-run ``wara <wara_args> --inside-netns DIR --config DIR/project.yaml`` in a
    private network namespace (the project YAML copied with the bus on ``transport``,
    see :func:`multicast_config`); its exit code. The inner run prints on this
    process's stdout. Raises :class:`NetnsUnavailable` when the namespace cannot be made.
    """
    problem = netns_problem()
    if problem is not None:
        raise NetnsUnavailable(problem)
    with contextlib.ExitStack() as stack:
        if keep_dir is None:
            work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="wara-demo2-")))
        else:  # keep the YAML, both logs and the run record (for a look afterwards)
            work = keep_dir.resolve()
            work.mkdir(parents=True, exist_ok=True)
        multicast_config(config_path, work / "project.yaml", transport, pin=pin)
        inner = [
            sys.executable,
            "-m",
            "wara",
            *wara_args,
            "--inside-netns",
            str(work),
            "--config",
            str(work / "project.yaml"),
        ]
        script = f"{NETNS_SETUP} && exec {' '.join(_quote(a) for a in inner)}"
        proc = subprocess.Popen([*UNSHARE, "sh", "-c", script], env=_env())
        stop = threading.Event()
        promoter = threading.Thread(target=_promote, args=(proc.pid, stop), daemon=True)
        promoter.start()
        try:
            return proc.wait()
        finally:
            stop.set()
            promoter.join(5.0)


#: The processes of the pair (by their ``wara`` verb) that get SCHED_FIFO.
_PAIR_VERBS = (b"hil", b"serve")


def _promote(root_pid: int, stop: threading.Event) -> None:
    """From outside the namespace (inside it the user namespace has no CAP_SYS_NICE):
    every thread of the simulator and the service processes under ``root_pid`` at the
    demo's SCHED_FIFO priority, as the one-process demo does (docs/service.md), checked
    every 0.5 s for new threads; not the planner processes. Refused: said once, on
    stderr, and the run goes on under the normal scheduler."""
    from wara.harness import RT_PRIORITY, fifo_all_threads

    told = False
    while not stop.wait(0.5):
        for pid in _descendants(root_pid):
            try:
                argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if len(argv) < 4 or argv[1:3] != [b"-m", b"wara"] or argv[3] not in _PAIR_VERBS:
                continue
            above = _pinned_alone(pid) if argv[3] == b"serve" else None
            rep = fifo_all_threads(RT_PRIORITY, pid, above)
            if rep.refused and not told:
                told = True
                print(f"wara: SCHED_FIFO refused: {rep.refused[0]}", file=sys.stderr)


def _pinned_alone(pid: int) -> Callable[[int], bool]:
    """Whether a thread of process ``pid`` runs on fewer CPUs than the process: the
    service's loop thread, which pins itself (``control.realtime.cpu_affinity``). It
    gets the priority above the service's other threads: at one priority a thread
    busy outside the GIL on the loop's CPU would hold the loop off until it blocks."""
    try:
        whole = os.sched_getaffinity(pid)
    except OSError:
        return lambda tid: False

    def pinned(tid: int) -> bool:
        try:
            return os.sched_getaffinity(tid) < whole
        except OSError:
            return False

    return pinned


def _descendants(root_pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(entry.name))
    out: list[int] = []
    todo = [root_pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def _quote(arg: str) -> str:
    import shlex

    return shlex.quote(arg)


# --------------------------------------------------------------------------- inside


class Child:
    """One child process with its stderr in a log file."""

    def __init__(
        self,
        name: str,
        argv: Sequence[str],
        log_path: Path,
        env: dict[str, str] | None = None,
    ) -> None:
        """``env``: set in the child's environment besides :func:`_env`."""
        self.name = name
        self.log_path = log_path
        self._log: IO[bytes] = open(log_path, "wb")  # noqa: SIM115 (closed in stop())
        self.proc = subprocess.Popen(
            list(argv),
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env=_env() | (env or {}),
            cwd=REPO,
        )

    def check_alive(self) -> None:
        code = self.proc.poll()
        if code is not None:
            raise TwoProcessError(
                f"the {self.name} exited with code {code}: {self.tail(3)} (log {self.log_path})"
            )

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGTERM, wait, SIGKILL on timeout; the exit code (negative: killed)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        self._log.close()
        return int(self.proc.returncode)

    def tail(self, n: int) -> str:
        with contextlib.suppress(OSError):
            lines = self.log_path.read_text(errors="replace").strip().splitlines()
            return " | ".join(line.strip() for line in lines[-n:])
        return ""


class Service:
    """The service seen through its control socket."""

    def __init__(self, child: Child, socket_path: Path) -> None:
        self.child = child
        self.socket_path = socket_path

    def call(self, cmd: str, **args: Any) -> dict[str, Any]:
        self.child.check_alive()
        return request(cmd, socket_path=self.socket_path, timeout_s=30.0, **args)

    def status(self) -> dict[str, Any]:
        return self.call("status")

    def wait(
        self, pred: Callable[[dict[str, Any]], bool], timeout_s: float, poll_s: float = 0.25
    ) -> dict[str, Any] | None:
        """Poll the status until ``pred`` holds; the status, or None on timeout."""
        end = time.monotonic() + timeout_s
        while True:
            st = self.status()
            if pred(st):
                return st
            if time.monotonic() >= end:
                return None
            time.sleep(poll_s)


#: The simulator's site socket and the service's run records, in the work directory.
SITE_SOCKET = "site.sock"
RUNS_DIR = "runs"
#: How long the simulator may take to start (first numba compile on a fresh machine).
SIM_START_TIMEOUT_S = 240.0


class NotifySocket:
    """A socket of ours to give a child as ``$NOTIFY_SOCKET`` (sd_notify's datagrams)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))

    def wait_ready(self, child: Child, timeout_s: float) -> None:
        """Until ``child`` sends ``READY=1``; :class:`TwoProcessError` if it exits first or
        does not within ``timeout_s``."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            child.check_alive()
            readable = select.select([self.sock], [], [], 0.2)[0]
            if readable and b"READY=1" in self.sock.recv(4096).split(b"\n"):
                return
        raise TwoProcessError(f"the {child.name} was not ready within {timeout_s:g} s")

    def close(self) -> None:
        self.sock.close()
        with contextlib.suppress(OSError):
            self.path.unlink()


def _wait_socket(child: Child, path: Path, timeout_s: float) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        child.check_alive()
        if path.exists():
            with contextlib.suppress(CtlError):
                request("status", socket_path=path, timeout_s=5.0)
                return
        time.sleep(0.1)
    raise TwoProcessError(f"the service's control socket {path} did not answer in {timeout_s} s")


class LoopWatch:
    """Collects the service's loop reports (one per ``stats_every_s``) after a baseline."""

    def __init__(self) -> None:
        self.baseline: dict[str, Any] | None = None
        self.reports: list[dict[str, Any]] = []
        self.last: dict[str, Any] = {}

    def see(self, status: dict[str, Any]) -> None:
        loop = status.get("loop") or {}
        if not loop or loop.get("cycles") == self.last.get("cycles"):
            return
        self.last = loop
        if self.baseline is None:
            self.baseline = loop
        else:
            self.reports.append(loop)

    def wait_reports(self, svc: Service, n: int, timeout_s: float) -> bool:
        """Read the status until the baseline and ``n`` reports after it are seen;
        False after ``timeout_s``."""

        def enough(st: dict[str, Any]) -> bool:
            self.see(st)
            return self.baseline is not None and len(self.reports) >= n

        return svc.wait(enough, timeout_s, poll_s=0.2) is not None

    def measured_s(self, period_s: float) -> float:
        if self.baseline is None or not self.reports:
            return 0.0
        return (self.reports[-1]["cycles"] - self.baseline["cycles"]) * period_s

    def summary(self, period_s: float) -> dict[str, Any]:
        base = self.baseline or {}
        reps = self.reports
        last = reps[-1] if reps else base

        def worst(key: str) -> float | None:
            vals = [float(r[key]) for r in reps if key in r]
            return max(vals) if vals else None

        compute_p99 = worst("compute_p99_ms")
        period_ms = units.to_ms(period_s)
        overruns_total = last.get("overruns")
        overruns = (
            None
            if overruns_total is None or not reps
            else int(overruns_total) - int(base.get("overruns", 0))
        )
        fraction = None if compute_p99 is None else compute_p99 / period_ms
        return {
            "jitter_p99_ms": worst("jitter_p99_ms"),
            "compute_p99_ms": compute_p99,
            "compute_p99_fraction": fraction,
            "compute_p50_ms": worst("compute_p50_ms"),
            "compute_max_ms": worst("compute_max_ms"),
            "compute_cpu_p99_ms": worst("compute_cpu_p99_ms"),
            "jitter_max_ms": worst("jitter_max_ms"),
            "overruns": overruns,
            "overruns_total": overruns_total,
            "overruns_startup": base.get("overruns"),
            "skipped_periods": (
                None
                if not reps
                else int(last.get("skipped_periods", 0)) - int(base.get("skipped_periods", 0))
            ),
            "cycles": last.get("cycles"),
            "measured_cycles": (int(last["cycles"]) - int(base["cycles"]) if reps and base else 0),
            "measured_s": self.measured_s(period_s),
            "reports": len(reps),
            "period_ms": period_ms,
            "realtime_refused": last.get("realtime_refused", []),
        }


def sim_realtime_factor(log_text: str) -> float | None:
    found = re.findall(r"compute realtime factor ([0-9.]+)x", log_text)
    return float(found[-1]) if found else None


@contextlib.contextmanager
def service_and_simulator(
    workdir: Path,
    config_path: str,
    say: Progress,
    codes: dict[str, int],
    *,
    rig: str = "attitude",
    site: bool = False,
    db: Path | None = None,
    service_env: dict[str, str] | None = None,
) -> Iterator[tuple[Service, Child, dict[str, Any]]]:
    """Start the simulator, then the service (once the simulated PLC runs), wait for the
    service's IDLE; yields (service, simulator, placement). On exit both are stopped
    with SIGTERM and their exit codes are put into ``codes``.

    ``rig``: the simulator's (``wara hil --rig``); ``site``: it serves the crane's and
    the crew's acts on ``workdir/site.sock`` (:data:`SITE_SOCKET`); ``db``: the
    service's acceptance store (default ``workdir/acceptance.sqlite``);
    ``service_env``: set in the service's environment."""
    cfg = load_project(config_path)
    if cfg.can.interface not in TRANSPORTS:
        raise TwoProcessError(f"{config_path}: can.interface must be one of {TRANSPORTS}")
    sock = workdir / "ctl.sock"
    wara = [sys.executable, "-m", "wara"]
    say(f"simulator and service on {cfg.can.interface} {cfg.can.channel}:{cfg.can.udp_port}")
    sim_cpus = simulator_cpus(cfg, sorted(os.sched_getaffinity(0)))
    placement: dict[str, Any] = {
        "service_loop_cpus": list(cfg.control.realtime.cpu_affinity),
        "simulator_cpus": sim_cpus,
    }
    if sim_cpus:
        say(f"service loop on CPU {placement['service_loop_cpus']}, simulator on {sim_cpus}")
    sim_argv = [*wara, "hil", "--realtime", "--config", config_path, "--status-interval", "2"]
    sim_argv += ["--rig", rig]
    if site:
        sim_argv += ["--site-socket", str(workdir / SITE_SOCKET)]
    if sim_cpus:
        sim_argv += ["--cpus", ",".join(map(str, sim_cpus))]
    notify = NotifySocket(workdir / "hil-notify.sock")
    sim = Child("simulator", sim_argv, workdir / "hil.log", {"NOTIFY_SOCKET": str(notify.path)})
    svc_child: Child | None = None
    try:
        # The simulator compiles its plant on first use (numba; tens of seconds on a fresh
        # machine): start the service only once the simulated PLC is on the wire, or the
        # service's start-up window would rightly end ABORTED.
        say("waiting for the simulator to run")
        notify.wait_ready(sim, SIM_START_TIMEOUT_S)
        svc_child = Child(
            "service",
            [
                *wara,
                "serve",
                "--config",
                config_path,
                "--socket",
                str(sock),
                "--record-dir",
                str(workdir / RUNS_DIR),
                "--db",
                str(db if db is not None else workdir / "acceptance.sqlite"),
            ],
            workdir / "service.log",
            service_env,
        )
        svc = Service(svc_child, sock)
        _wait_socket(svc_child, sock, 60.0)
        say("waiting for the service to be IDLE")
        st = svc.wait(lambda s: s.get("mode") in ("IDLE", "ABORTED"), 60.0)
        if st is None or st.get("mode") != "IDLE":
            raise TwoProcessError(
                f"service did not come up: {st and (st.get('mode'), st.get('fault_reasons'))}",
                faults=(st or {}).get("faults"),
            )
        say("IDLE; waiting for the first loop report (end of start-up)")
        yield svc, sim, placement
    finally:
        if svc_child is not None:
            codes["service"] = svc_child.stop()
        codes["simulator"] = sim.stop()
        notify.close()
        say(f"stopped: service exit {codes.get('service')}, simulator exit {codes['simulator']}")


def setting_lines(out: dict[str, Any]) -> list[str]:
    """A two-process run's bus, its load, the simulator's real-time factor and the
    placement of the processes, as lines of its table."""
    rtf = out.get("simulator_realtime_factor")
    return [
        f"bus: {out['bus']}; bus load {out['bus_load_percent']:.1f} %; simulator "
        + ("n/a" if rtf is None else f"{rtf:.1f}x")
        + " real time (compute)",
        placement_line(out.get("placement") or {}),
    ]


def placement_line(pl: dict[str, Any]) -> str:
    if pl.get("simulator_cpus"):
        return (
            f"placement: service loop thread on CPU {pl['service_loop_cpus']}, "
            f"simulator on CPU {pl['simulator_cpus']}"
        )
    return "placement: left to the scheduler (--no-pin, or one CPU)"

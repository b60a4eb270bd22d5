"""Running a campaign on Dask distributed: ``wara campaign run``.

Each Dask task is one whole run (:func:`wara.campaign.run.run_one`), never a control
cycle. The client writes each finished run as its own Parquet file
(``DIR/runs/run-000042.parquet``, written to a temporary name and renamed: a file is
there whole or not at all), and compacts them into ``DIR/results.parquet``, one row per
run, sorted by run index. A run is identified by its index: a file already there is
never written again, so a run redone after its worker was killed counts once, and
``--resume DIR`` submits only the indices that have no file.

Workers: an embedded :class:`distributed.LocalCluster` of worker processes (one thread
each) by default, or any cluster through its scheduler address. :class:`WarmUp`, a
worker plugin, loads the compiled plant (numba's on-disk cache) and starts the
worker's planner process for the campaign's project once per worker, before its first
task.

A worker of any shape gives the right table: the runs of one worker process take turns
(:data:`_RUN_LOCK`), since they share its planner process and the in-process virtual
CAN channels; a worker with more threads is told once that only one of them runs at a
time. What cannot work is refused before anything is submitted (:func:`check_workers`):
a daemon worker process, which may not start the planner's process.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import multiprocessing
import os
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from distributed import WorkerPlugin

from config import ConfigError
from config.schema import ProjectConfig
from wara.campaign.spec import Campaign, CampaignSpec
from wara.cli import UsageError
from wara.progress import Progress

RUNS_DIR = "runs"
RESULTS = "results.parquet"
MANIFEST = "campaign.json"


# --------------------------------------------------------------------------- payload


def payload_of(c: Campaign) -> dict[str, Any]:
    """What a worker needs to run any run of the campaign (the project travels with it:
    a remote worker need not have the file)."""
    return {
        "spec": c.spec.model_dump(mode="json"),
        "project": c.project.model_dump(mode="json"),
        "source": c.source,
    }


def fingerprint(payload: dict[str, Any]) -> str:
    text = json.dumps({"spec": payload["spec"], "project": payload["project"]}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# --------------------------------------------------------------------------- worker side

#: A campaign planner's time limit per request (the service's is 10 s). In lockstep the
#: simulated time stands still while the planner works, so its wall time never shows in
#: a run; only a timeout would, and on a loaded machine that is the machine's, not the
#: tuning's.
PLANNER_TIMEOUT_S = 120.0

_CAMPAIGNS: dict[str, Campaign] = {}
_PLANNERS: dict[str, Any] = {}
#: One run at a time in a worker process, whatever its thread count (see the module
#: docstring): two runs at once would share its planner and its virtual CAN channels.
_RUN_LOCK = threading.Lock()


class WorkerShapeError(UsageError):
    """A Dask worker on which a campaign run cannot work (one line, exit 2)."""


def _worker_campaign(payload: dict[str, Any]) -> Campaign:
    key = fingerprint(payload)
    c = _CAMPAIGNS.get(key)
    if c is None:
        project = ProjectConfig.model_validate(payload["project"])
        spec = CampaignSpec.model_validate(payload["spec"])
        c = Campaign(spec, payload["source"], Path("."), project=project)
        path = Path(tempfile.gettempdir()) / f"wara-campaign-project-{key}.yaml"
        if not path.exists():
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(yaml.safe_dump(payload["project"], sort_keys=False))
            os.replace(tmp, path)
        c.project_path = str(path)
        _CAMPAIGNS[key] = c
    return c


def _planner(project_file: str) -> Any:
    """This worker process's planner for ``project_file`` (started once, kept)."""
    from ipc_app.service.worker import PlannerWorker

    p = _PLANNERS.get(project_file)
    if p is None:
        if multiprocessing.current_process().daemon:
            raise RuntimeError(
                "the Dask worker is a daemon process and cannot start the planner process: "
                "start the workers with DASK_DISTRIBUTED__WORKER__DAEMON=False"
            )
        p = PlannerWorker(project_file, timeout_s=PLANNER_TIMEOUT_S)
        p.start()
        _PLANNERS[project_file] = p
    return p


def campaign_task(
    payload: dict[str, Any], index: int, overrides: dict[str, float] | None = None
) -> dict[str, Any]:
    """One Dask task: run ``index`` of the campaign, its result row."""
    from wara.campaign.run import run_one

    with _RUN_LOCK:
        c = _worker_campaign(payload)
        return run_one(
            c,
            index,
            planner=_planner(c.project_file),
            overrides=overrides,
            worker=f"{socket.gethostname()}:{os.getpid()}",
        )


def warm_up(payload: dict[str, Any] | None = None) -> float:
    """Load the compiled plant, start the planner for the campaign's project (the one
    its tasks use; the shipped project without a payload) in this process and plan once
    (seconds taken)."""
    t0 = time.perf_counter()
    from config import load_project
    from config.loader import default_project_path
    from wara.harness import Harness

    with _RUN_LOCK:
        path = str(default_project_path()) if payload is None else _project_file(payload)
        planner = _planner(path)
        h = Harness(load_project(path), path, mode="lockstep", planner=planner, trace=False)
        try:
            h.advance(0.05)
            h.sim.truth()
        finally:
            h.close()
        # one plan: the planner process's imports and first solve done before the first task
        planner.submit(0, 0.5, 0.2)
        while planner.busy:
            time.sleep(0.01)
        planner.poll()
    return time.perf_counter() - t0


def _project_file(payload: dict[str, Any]) -> str:
    return _worker_campaign(payload).project_file


def worker_shape() -> dict[str, Any]:
    """What :func:`check_workers` asks each worker: is its process a daemon."""
    return {"daemon": bool(multiprocessing.current_process().daemon), "pid": os.getpid()}


def check_workers(client: Any) -> list[str]:
    """Refuse (:class:`WorkerShapeError`, one line) a cluster with a worker on which a
    run cannot work; the notes to show for workers that work, but not at full speed."""
    info = client.scheduler_info()["workers"]
    if not info:
        raise WorkerShapeError(f"the Dask scheduler {client.scheduler.address} has no workers")
    shapes = client.run(worker_shape)
    daemons = sorted(addr for addr, shape in shapes.items() if shape["daemon"])
    if daemons:
        more = f" (and {len(daemons) - 1} more)" if len(daemons) > 1 else ""
        raise WorkerShapeError(
            f"Dask worker {daemons[0]}{more} is a daemon process, which cannot start the "
            "planner process a run needs: start the workers with "
            "DASK_DISTRIBUTED__WORKER__DAEMON=False in their environment"
        )
    notes = []
    for addr, w in sorted(info.items()):
        n = int(w.get("nthreads", 1))
        if n > 1:
            notes.append(
                f"Dask worker {addr} has {n} threads: its runs take turns, one at a time "
                f"(a run needs its process to itself); `dask worker ADDR --nworkers {n} "
                "--nthreads 1` runs as many at once"
            )
    return notes


def close_planners() -> None:
    while _PLANNERS:
        _, p = _PLANNERS.popitem()
        p.close()


class WarmUp(WorkerPlugin):
    """Dask worker plugin: :func:`warm_up` when the worker starts, the planners closed
    when it stops."""

    name = "wara-campaign-warm-up"

    def __init__(self, payload: dict[str, Any] | None = None) -> None:
        self.payload = payload

    def setup(self, worker: Any) -> None:
        from ipc_app.service.logs import configure_logging

        # the service's log: errors only (a run's warnings are in its row)
        configure_logging("ERROR")
        if multiprocessing.current_process().daemon:
            return  # refused by check_workers before any task
        worker.wara_warm_up_s = warm_up(self.payload)

    def teardown(self, worker: Any) -> None:
        close_planners()


# --------------------------------------------------------------------------- results


def run_file(out: Path, index: int) -> Path:
    return out / RUNS_DIR / f"run-{index:06d}.parquet"


def done_indices(out: Path) -> set[int]:
    d = out / RUNS_DIR
    if not d.is_dir():
        return set()
    return {int(p.stem.split("-")[1]) for p in d.glob("run-*.parquet")}


def write_row(out: Path, row: dict[str, Any]) -> bool:
    """Write one run's row (atomically); False if that run is already written."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = run_file(out, int(row["run"]))
    if path.exists():
        return False
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    pq.write_table(pa.Table.from_pylist([row]), tmp)
    os.replace(tmp, path)
    return True


def compact(out: Path) -> Path:
    """``DIR/results.parquet`` from the run files: one row per run, sorted by run."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    files = sorted((out / RUNS_DIR).glob("run-*.parquet"))
    tables = [pq.read_table(f) for f in files]
    table = pa.concat_tables(tables, promote_options="default") if tables else pa.table({})
    if tables:
        table = table.sort_by("run")
    path = out / RESULTS
    tmp = path.with_name(RESULTS + ".tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)
    return path


def read_results(out: Path) -> list[dict[str, Any]]:
    """The rows, from the compacted table (compacted first if runs are newer)."""
    import pyarrow.parquet as pq

    path = out / RESULTS
    runs = out / RUNS_DIR
    newest = max((p.stat().st_mtime for p in runs.glob("run-*.parquet")), default=0.0)
    if not path.exists() or path.stat().st_mtime < newest:
        if not runs.is_dir():
            raise ConfigError(f"{out}: not a campaign directory (no {RUNS_DIR}/)")
        compact(out)
    rows: list[dict[str, Any]] = pq.read_table(path).to_pylist()
    return rows


# --------------------------------------------------------------------------- manifest


def write_manifest(out: Path, c: Campaign, payload: dict[str, Any]) -> None:
    """``DIR/campaign.json`` (what the directory holds) and ``DIR/spec.json`` (the spec
    and project it ran, for the report and ``replay``)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / RUNS_DIR).mkdir(exist_ok=True)
    manifest = {
        "name": c.spec.name,
        "fingerprint": fingerprint(payload),
        "runs": c.run_count,
        "seed": c.spec.seed,
        "source": c.source,
    }
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
    (out / "spec.json").write_text(json.dumps(payload, indent=1) + "\n")


def read_manifest(out: Path) -> dict[str, Any]:
    path = out / MANIFEST
    if not path.is_file():
        raise ConfigError(f"{out}: not a campaign directory (no {MANIFEST})")
    data: dict[str, Any] = json.loads(path.read_text())
    return data


def campaign_of_dir(out: Path) -> Campaign:
    """The campaign a directory ran (from its ``spec.json``)."""
    path = out / "spec.json"
    if not path.is_file():
        raise ConfigError(f"{out}: not a campaign directory (no spec.json)")
    # as a worker builds it: the planner reads the project the directory ran
    return _worker_campaign(json.loads(path.read_text()))


# --------------------------------------------------------------------------- cluster


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the cluster's processes start: they inherit it (and Python
    keeps an ignored SIGINT), so a Ctrl-C reaches this process alone, which shuts the
    cluster down, instead of printing a KeyboardInterrupt traceback in every worker."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def dask_client(
    scheduler: str | None = None,
    workers: int | None = None,
    payload: dict[str, Any] | None = None,
    say: Callable[[str], None] | None = None,
) -> Iterator[Any]:
    """A client on the cluster at ``scheduler``, else on an embedded LocalCluster of
    ``workers`` worker processes (default: the CPUs) over TCP on localhost; its workers
    checked (:func:`check_workers`; ``say`` gets the notes) and warmed up for the
    campaign of ``payload``."""
    import dask
    from distributed import Client, LocalCluster

    def ready(client: Any) -> Any:
        for note in check_workers(client):
            (say or _stderr)(note)
        client.register_plugin(WarmUp(payload))
        return client

    if scheduler is not None:
        client = Client(scheduler)
        try:
            yield ready(client)
        finally:
            client.close()
        return
    n = workers or os.cpu_count() or 1
    with dask.config.set({"distributed.worker.daemon": False, "logging.distributed": "error"}):
        with _sigint_ignored():
            cluster = LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                protocol="tcp://",
                host="127.0.0.1",
                dashboard_address=":0",
                silence_logs=40,
            )
        try:
            client = Client(cluster)
            try:
                yield ready(client)
            finally:
                client.close()
        finally:
            cluster.close()


def _stderr(line: str) -> None:
    print(f"wara campaign: {line}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- running


@dataclass
class Outcome:
    """What one ``run_campaign`` call did."""

    out: Path
    total: int
    done_before: int
    written: int = 0
    failures: int = 0
    missing: list[int] = field(default_factory=list)
    errors: dict[int, str] = field(default_factory=dict)
    elapsed_s: float = 0.0
    task_s: float = 0.0
    workers: int = 0
    #: per worker (its address): when (seconds from the first submit) the client got its
    #: last run
    last_done_s: dict[str, float] = field(default_factory=dict)

    @property
    def tail_s(self) -> float:
        """Worker-seconds idle after each worker's last run until the campaign's end
        (no run left for it: the campaign's granularity, not the engine)."""
        idle = sum(self.elapsed_s - t for t in self.last_done_s.values())
        return idle + self.elapsed_s * max(0, self.workers - len(self.last_done_s))

    @property
    def gap_share(self) -> float | None:
        """The engine's own overhead as a share of task time: the workers' time that is
        neither a run nor the tail (scheduling, transfer, the client writing Parquet)."""
        if not self.task_s:
            return None
        return (self.workers * self.elapsed_s - self.tail_s - self.task_s) / self.task_s

    @property
    def complete(self) -> bool:
        return not self.missing


def prepare_dir(out: Path, c: Campaign, payload: dict[str, Any], resume: bool) -> set[int]:
    """Check ``out`` against the campaign; the run indices already written."""
    if resume:
        old = read_manifest(out)
        if old["fingerprint"] != fingerprint(payload):
            raise ConfigError(
                f"{out}: was run with another spec or project (fingerprint "
                f"{old['fingerprint']}, this spec {fingerprint(payload)}): resume it with "
                "the same spec, or start a new directory"
            )
    elif out.exists() and any(out.iterdir()) and not _fresh(out, payload):
        raise ConfigError(f"{out}: exists and is not empty: use --resume {out}, or a new --out")
    write_manifest(out, c, payload)
    return done_indices(out)


def _fresh(out: Path, payload: dict[str, Any]) -> bool:
    """``out`` holds only this campaign's manifest, no run (a start that failed)."""
    try:
        same = read_manifest(out)["fingerprint"] == fingerprint(payload)
    except (ConfigError, ValueError, KeyError):
        return False
    return same and not done_indices(out)


def run_campaign(
    c: Campaign,
    out: Path,
    *,
    client: Any = None,
    scheduler: str | None = None,
    workers: int | None = None,
    resume: bool = False,
    overrides: dict[str, float] | None = None,
    progress: bool = True,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> Outcome:
    """Run the campaign's missing runs into ``out``; see the module docstring."""
    from distributed import as_completed

    payload = payload_of(c)
    if overrides:
        payload["overrides"] = dict(overrides)
    done = prepare_dir(out, c, payload, resume)
    total = c.run_count
    todo = [i for i in range(total) if i not in done]
    prior = _failures(out, done)
    outcome = Outcome(out, total, len(done))
    if not todo:  # a finished directory resumed: no cluster for nothing
        compact(out)
        return outcome
    with contextlib.ExitStack() as stack:
        if client is None:
            client = stack.enter_context(dask_client(scheduler, workers, payload))
        bar = Progress(total, len(done), prior, enabled=progress)
        t0 = time.monotonic()  # from the first submit: the engine warmed up
        outcome.workers = len(client.scheduler_info()["workers"])
        tag = fingerprint(payload)
        futures = {
            client.submit(
                campaign_task, payload, i, overrides, key=f"wara-run-{tag}-{i}", retries=0
            ): i
            for i in todo
        }
        bar.show()
        for fut in as_completed(list(futures)):
            i = futures[fut]
            try:
                row = fut.result()
            except Exception as exc:  # the run did not complete: nothing written
                outcome.errors[i] = f"{type(exc).__name__}: {exc}"
                continue
            if write_row(out, row):
                outcome.written += 1
                outcome.task_s += float(row["wall_s"])
                outcome.last_done_s[str(row.get("worker"))] = time.monotonic() - t0
                failed = not row["passed"]
                outcome.failures += int(failed)
                bar.update(failed)
                if on_row is not None:
                    on_row(row)
            fut.release()
        outcome.elapsed_s = time.monotonic() - t0
    bar.finish()
    compact(out)
    outcome.missing = sorted(set(range(total)) - done_indices(out))
    return outcome


def _failures(out: Path, done: set[int]) -> int:
    if not done:
        return 0
    import pyarrow.parquet as pq

    return sum(
        not pq.read_table(run_file(out, i), columns=["passed"]).column(0)[0].as_py() for i in done
    )

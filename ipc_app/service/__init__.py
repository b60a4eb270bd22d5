"""The IPC service's infrastructure: loop, modes, planning worker, control socket, records.

``wara serve`` wires these pieces with the CAN bridge and the controllers; each piece
is usable and tested on its own. Threads and processes of a running service::

    main thread        start-up, then waits for SIGTERM
    wara-loop          FixedRateLoop: step() = read CAN -> interlocks -> controllers
                       -> write CAN; the only thread at SCHED_FIFO (control.realtime)
    wara-planner       PlannerWorker's supervisor; the planner runs in its own process
    wara-ctl           CtlServer: the local socket (one selector thread, status and stop
                       answered there); wara-ctl-worker-N (at most 4): adjust and reset
    wara-record        RunRecorder's writer: CSV rows, JSONL events, fsync
    (logging)          QueueListener: renders structlog JSON lines to stderr/journal

Suggested wiring (the loop thread only calls non-blocking methods)::

    handle = configure_logging("INFO")                         # logs.py
    notifier = SystemdNotifier.from_env()                      # sdnotify.py
    modes = ModeMachine(active_causes=interlocks.active)       # modes.py
    worker = PlannerWorker(config_path); worker.start()        # worker.py
    recorder = RunRecorder(new_run_dir(data_dir / "runs"), COLUMNS); recorder.start()
    ctl = CtlServer(CtlHandlers(adjust, status, stop, reset), socket_path); ctl.start()
    loop = FixedRateLoop(step, cfg.control.period_s, realtime=cfg.control.realtime,
                         on_stats=lambda s: log.info("loop_stats", **s))
    modes.boot_complete()                                      # STOPPED -> IDLE, valves closed
    freeze_startup_heap(); loop.start()
    notifier.ready("IDLE")

    def step(k, t):                    # in wara-loop
        frame = bus.read()             # read
        # interlocks -> modes.fault(cause) ; result = worker.poll() -> plan_ready /
        # plan_failed / fault ; references from result.reference(t - t_motion_start)
        # controllers only if modes.valves_enabled, else valves closed
        bus.write(commands)            # write
        recorder.sample(t, row); notifier.watchdog(t) if notifier.watchdog_due(t) else None

    # the ctl handlers run in wara-ctl threads: adjust() calls modes.request_adjust and
    # hands (roll, pitch) to the loop (a queue, or worker.submit with the measured start)

Shutdown: ``notifier.stopping()``, ``ctl.stop()``, ``loop.stop()`` (then valves closed),
``worker.close()``, ``recorder.stop()``, ``handle.stop()``.

Modules: :mod:`.core` (the step and the service's requests), :mod:`.motion`,
:mod:`.manager` and :mod:`.motions` (the motions behind one interface, the active one),
:mod:`.requests` (every request's limits, the typed reply), :mod:`.cycle` (the ring
cycle), :mod:`.modes` (operator state machine), :mod:`.interlocks`, :mod:`.machine_io`,
:mod:`.loop` (fixed-rate loop, RT settings, statistics), :mod:`.worker` (planner
process), :mod:`.ctl`, :mod:`.ctl_protocol`, :mod:`.ctl_client` (control socket, its
protocol table, the client), :mod:`.status`, :mod:`.record` (run record and reader),
:mod:`.logs` (non-blocking JSON logs), :mod:`.sdnotify` (systemd notify and watchdog).
Deployment: ``deploy/``, docs/deploy.md.
"""

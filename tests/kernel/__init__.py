"""Tests that need a Linux kernel with SocketCAN (``vcan0``); marked ``kernel``.

They run inside a throw-away VM: ``python3 tests/kernel/run_in_vm.py`` (docs/kernel-tests.md).
Outside it they are skipped with a reason that says so, unless this machine has ``vcan0``
itself (the tests that change the system, such as ``deploy/install.sh``, run only in
the VM, where ``WARA_KERNEL_VM=1``).
"""

from __future__ import annotations

import os

from plc_bridge.bus import socketcan_available

#: The one command that runs every ``kernel`` test in the VM.
VM_COMMAND = "python3 tests/kernel/run_in_vm.py"


def in_vm() -> bool:
    """True inside the VM that ``run_in_vm.py`` boots (set by its guest script)."""
    return os.environ.get("WARA_KERNEL_VM") == "1"


def vcan_skip_reason(channel: str = "vcan0") -> str | None:
    """None where ``channel`` can be opened, else why not and how to run the test."""
    problem = socketcan_available(channel)
    if problem is None:
        return None
    return f"socketcan: {problem}; these run in the kernel VM: {VM_COMMAND}"


def vm_only_reason() -> str | None:
    """None in the VM; else the reason a test that changes the system is skipped."""
    if in_vm():
        return None
    return f"changes the system (users, /etc, /opt): runs only in the kernel VM: {VM_COMMAND}"

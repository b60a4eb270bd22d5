"""tests/kernel/run_in_vm.py on this host: what it runs by default, what the guest does,
and the one-line skip where the VM cannot start (the VM itself runs in .ci/run)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.kernel import run_in_vm

REPO = Path(__file__).resolve().parents[1]


def test_default_run_covers_every_module_with_kernel_tests() -> None:
    paths = set(run_in_vm.KERNEL_TEST_PATHS)
    assert "tests/kernel" in paths
    marked = {
        str(p.relative_to(REPO))
        for p in (REPO / "tests").glob("test_*.py")
        if re.search(r"mark\.kernel\b", p.read_text())
    }
    assert "tests/test_plc_link.py" in marked  # the SocketCAN class
    assert marked <= paths, marked - paths
    for p in paths:
        assert (REPO / p).exists(), p


def test_guest_script_brings_up_vcan0_then_runs_the_command_in_the_repo(tmp_path: Path) -> None:
    script = run_in_vm.guest_script(
        [sys.executable, "-m", "pytest", "-k", "a b"], tmp_path / "booted", tmp_path / "w"
    )
    lines = script.splitlines()
    assert lines[0].startswith("echo ok > ") and str(tmp_path / "booted") in lines[0]
    assert "ip link add dev vcan0 type vcan" in script and "exit 1" in script
    assert f"cd {REPO}" in lines
    assert "export WARA_KERNEL_VM=1" in script
    assert lines[-1] == f"exec {sys.executable} -m pytest -k 'a b'"  # exec: its exit code
    # the caches prewarmed on this machine, found in the guest under the same settings
    for key, value in run_in_vm.CACHE_ENV.items():
        assert f"export {key}={value}" in lines, key
    assert str(REPO / "out") in run_in_vm.CACHE_ENV["NUMBA_CACHE_DIR"]  # shared read-write


def test_qemu_gets_threaded_tcg_and_few_serial_ports() -> None:
    tcg = run_in_vm.qemu_opts(kvm=False)
    assert tcg[:2] == ["-accel", "tcg,thread=multi"]
    assert "virtio-serial-pci.max_ports=2" in tcg
    assert "-accel" not in run_in_vm.qemu_opts(kvm=True)  # virtme-ng picks KVM itself


@pytest.mark.slow  # compiles the plant: half a minute
def test_prewarm_fills_the_numba_cache_the_guest_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cache = tmp_path / "numba"
    monkeypatch.setitem(run_in_vm.CACHE_ENV, "NUMBA_CACHE_DIR", str(cache))
    monkeypatch.setitem(run_in_vm.CACHE_ENV, "MPLCONFIGDIR", str(tmp_path / "mpl"))
    run_in_vm.prewarm()
    assert any(cache.rglob("*.nbi")), "no numba cache index written"


def _elf(path: Path, segment_types: list[int]) -> Path:
    """A 64-bit little-endian ELF header and program header table, nothing else."""
    head = bytearray(64)
    head[:6] = b"\x7fELF\x02\x01"
    head[32:40] = (64).to_bytes(8, "little")  # e_phoff
    head[54:56] = (56).to_bytes(2, "little")  # e_phentsize
    head[56:58] = len(segment_types).to_bytes(2, "little")  # e_phnum
    table = b"".join(t.to_bytes(4, "little") + bytes(52) for t in segment_types)
    path.write_bytes(bytes(head) + table)
    return path


def test_static_busybox_check_reads_the_elf_header(tmp_path: Path) -> None:
    assert run_in_vm.is_static_elf(str(_elf(tmp_path / "static", [1, 1, 4])))  # PT_LOAD, NOTE
    assert not run_in_vm.is_static_elf(str(_elf(tmp_path / "dynamic", [6, 3, 1])))  # PT_INTERP
    assert not run_in_vm.is_static_elf(sys.executable)  # this interpreter: dynamic
    assert not run_in_vm.is_static_elf(__file__)  # not an ELF at all
    assert not run_in_vm.is_static_elf(str(tmp_path / "absent"))


def test_vm_that_cannot_start_is_one_skip_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(run_in_vm, "missing_packages", lambda: ["qemu-system-x86"])
    assert run_in_vm.main(["--no-install"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == ["kernel tests: skipped: missing qemu-system-x86 (--no-install)"]
    assert run_in_vm.main(["--no-install", "--require"]) == 1


def test_script_help_runs_as_a_program() -> None:
    proc = subprocess.run(
        [sys.executable, str(REPO / "tests" / "kernel" / "run_in_vm.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0 and "--no-install" in proc.stdout, proc.stderr


def test_hil_test_judges_with_the_demos_attitude_tolerance() -> None:
    from tests.kernel import test_hil_vcan
    from wara.examples import ATTITUDE_TOL_DEG

    assert test_hil_vcan.ATTITUDE_TOL_DEG == ATTITUDE_TOL_DEG

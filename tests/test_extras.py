"""The optional parts of the install (pyproject's ``sim`` and ``plot`` extras): without
them the commands that need one say which to install (one line, exit 2, nothing done),
and the simulator runs its plant as plain Python."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.cli_helpers import run_main

PLOT_HINT = "install with pip install -e '.[plot]'"
SIM_HINT = "install with pip install -e '.[sim]'"


@pytest.fixture
def no_matplotlib(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib: ImportError


@pytest.fixture
def no_numba(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "numba", None)


def _one_line_error(code: int, out: str, err: str, hint: str) -> None:
    assert code == 2 and out == ""
    assert len(err.splitlines()) == 1 and err.rstrip().endswith(hint), err


@pytest.mark.usefixtures("no_matplotlib")
def test_plots_without_matplotlib_name_the_extra(tmp_path: Path) -> None:
    _one_line_error(
        *run_main(["demo", "--attitude", "--lockstep", "--plot", str(tmp_path)]), PLOT_HINT
    )
    # the ring demo writes the acceptance report: it says so before anything runs
    _one_line_error(*run_main(["demo", "--lockstep", "--out", str(tmp_path / "d")]), PLOT_HINT)
    assert not (tmp_path / "d").exists()
    png = tmp_path / "study.png"
    _one_line_error(*run_main(["sim", "dual-cylinder", "--plot", str(png)]), PLOT_HINT)
    assert not png.exists()


def test_acceptance_report_without_matplotlib_names_the_extra(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    db, out = tmp_path / "a.sqlite", tmp_path / "report"
    code, _, err = run_main(["acceptance", "add", "1", *_ring_values(), "--db", str(db)])
    assert code == 0, err
    for name in [m for m in sys.modules if m.startswith("matplotlib")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    _one_line_error(
        *run_main(["acceptance", "report", "--db", str(db), "--out", str(out)]), PLOT_HINT
    )
    assert not out.exists()
    # the rest of the package works without it
    code, listing, err = run_main(["acceptance", "list", "--db", str(db)])
    assert code == 0 and "ring    1" in listing, err


def _ring_values() -> list[str]:
    return [
        "--vertical-misalignment-mm", "1",
        "--horizontal-misalignment-mm", "1",
        "--max-gap-mm", "1",
        "--centreline-deviation-x-mm", "1",
        "--centreline-deviation-y-mm", "1",
    ]  # fmt: skip


@pytest.mark.usefixtures("no_numba")
@pytest.mark.parametrize(
    "argv",
    [
        ["demo", "--realtime"],
        ["demo", "--attitude"],
        ["demo", "--two-process"],
        ["hil", "--duration", "1"],
        ["soak", "--minutes", "1"],
    ],
)
def test_real_time_simulator_without_numba_names_the_extra(argv: list[str]) -> None:
    _one_line_error(*run_main(argv), SIM_HINT)


_PLAIN = """
import json, sys
sys.modules["numba"] = None
from hil_sim._jit import HAVE_NUMBA
from config.scenario import load_scenario
from wara.studies.dual_cylinder import run_study
run = run_study(load_scenario(None), "ladrc", duration_s=0.1)
print(json.dumps({"numba": HAVE_NUMBA, "x": run.position_m.tolist(), "p": run.p_a_pa.tolist()}))
"""


@pytest.mark.slow
def test_simulator_runs_without_numba_with_the_same_results() -> None:
    """hil_sim._jit's fallback: the plant's source as plain Python, the same figures."""
    from config.scenario import load_scenario
    from wara.studies.dual_cylinder import run_study

    proc = subprocess.run(
        [sys.executable, "-c", _PLAIN], capture_output=True, text=True, timeout=300, check=False
    )
    assert proc.returncode == 0, proc.stderr
    plain = json.loads(proc.stdout)
    assert plain["numba"] is False
    compiled = run_study(load_scenario(None), "ladrc", duration_s=0.1)
    np.testing.assert_allclose(plain["x"], compiled.position_m, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(plain["p"], compiled.p_a_pa, rtol=1e-12, atol=1e-6)

"""The optional parts of the install (pyproject's extras) and the one line that says which
to install when a command needs one that is missing.

``sim`` (numba) compiles the HIL simulator's plant; without it the same source runs as
plain Python (:mod:`hil_sim._jit`), only slower. ``plot`` (matplotlib) draws ``--plot``
figures and the acceptance report; ``opcua`` (asyncua) runs the OPC UA server;
``campaign`` (Dask distributed, pyarrow, optuna) runs verification campaigns
(``wara campaign``). The IPC's install (``deploy/install.sh``) has none of them unless
asked for.
"""

from __future__ import annotations

import importlib

from wara.cli import UsageError

#: The extra that installs each optional module.
EXTRA_OF = {
    "numba": "sim",
    "matplotlib": "plot",
    "distributed": "campaign",
    "pyarrow": "campaign",
    "optuna": "campaign",
    "asyncua": "opcua",
}


def install_hint(module: str) -> str:
    return f"install with pip install -e '.[{EXTRA_OF[module]}]'"


def require(module: str, needed_for: str) -> None:
    """Raise :class:`UsageError` (one line, exit 2) when ``module`` cannot be imported:
    ``<needed_for> needs <module>, which is not installed: install with ...``."""
    try:
        importlib.import_module(module)
    except ImportError:
        raise UsageError(
            f"{needed_for} needs {module}, which is not installed: {install_hint(module)}"
        ) from None


def require_realtime_simulator() -> None:
    """The simulator in real time needs numba: plain Python runs its plant about 50 times
    slower (a fraction of real time), so the PLC it stands in for would fall silent."""
    require("numba", "the simulator in real time")


def require_campaign() -> None:
    """``wara campaign`` runs on Dask distributed and writes Parquet (the ``campaign``
    extra)."""
    for module in ("distributed", "pyarrow"):
        require(module, "wara campaign")

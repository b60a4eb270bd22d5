"""Simulation studies that close the loop between ipc_app controllers and the hil_sim plant.

The studies' choices and defaults live here, light, for the ``wara sim`` parser (``wara
--help`` imports every verb's module, not the studies).
"""

from typing import Literal

ControllerKind = Literal["ladrc", "pid"]
#: the dual-cylinder study's controllers
CONTROLLERS: tuple[ControllerKind, ...] = ("ladrc", "pid")
#: extra position delays tested by default (ms)
DEFAULT_DELAYS_MS: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0)

"""Control laws of the IPC: LADRC, the PID baseline and group synchronization.

>>> from ipc_app.control import LADRC
>>> ctrl = LADRC(order=1, b0=0.05, wc=20.0, wo=80.0, dt=1e-3, u_min=-1.0, u_max=1.0)
>>> ctrl.reset(0.1)
>>> round(ctrl.update(0.1, 0.1), 12)
0.0
"""

from ipc_app.control.ladrc import LADRC, eso_matrices
from ipc_app.control.pid import PID
from ipc_app.control.plant_gain import cylinder_b0
from ipc_app.control.sync import Controller, SyncGroup, SyncScheme, ring_neighbours, sync_errors

__all__ = [
    "LADRC",
    "PID",
    "Controller",
    "SyncGroup",
    "SyncScheme",
    "cylinder_b0",
    "eso_matrices",
    "ring_neighbours",
    "sync_errors",
]

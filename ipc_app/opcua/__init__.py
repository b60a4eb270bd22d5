"""The OPC UA server beside the IPC service (the ``opcua`` extra: asyncua).

:mod:`~ipc_app.opcua.server` is the server (its own process: ``python -m ipc_app.opcua``),
:mod:`~ipc_app.opcua.model` the information model as data, :mod:`~ipc_app.opcua.users`
the users file, :mod:`~ipc_app.opcua.pki` the certificates, and
:mod:`~ipc_app.opcua.process` starts and watches the server process for ``wara serve``
and ``wara demo --opcua``. Only ``server`` and ``pki`` need asyncua. docs/opcua.md.
"""

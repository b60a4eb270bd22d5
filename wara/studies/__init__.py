"""Simulation studies that close the loop between ipc_app controllers and the hil_sim plant."""

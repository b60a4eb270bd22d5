"""The controller on the IPC: model, planner, control loops, service."""

"""The IPC controller application."""

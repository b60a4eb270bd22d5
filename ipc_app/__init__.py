"""The IPC controller application."""

import importlib

from config import crosscheck

# The service loads its project with every cross-check between keys, those of its own
# statics and of the CAN bridge's bus load included (config.crosscheck).
crosscheck.set_importer(importlib.import_module)

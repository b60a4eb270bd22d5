"""The ``wara`` command line: the composition root of the project.

``ipc_app`` (the controller) and ``hil_sim`` (the stand-in PLC and rig) never import each
other; they meet on the CAN wire (``plc_bridge``) and in the ``config`` schema. Only this
package, which wires whole runs together (the demo, the studies, the benchmarks), may
import both.
"""

import importlib

from config import crosscheck

# Every project this package loads runs every cross-check between keys, those that
# plc_bridge and ipc_app provide included (config.crosscheck; imported when first needed).
crosscheck.set_importer(importlib.import_module)

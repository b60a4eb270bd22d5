"""The stand-in PLC and hydraulic rig (hardware-in-the-loop simulator)."""

"""Device adapters, one module per device family.

Drivers speak transports only (pyserial, pymodbus, python-can) and never import hilbench.
The simulated rig needs no driver module: ``driver = "sim"`` in a rig config selects the
simulated plant inside hilbench.
"""

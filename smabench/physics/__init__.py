"""Physics core: wire parameters, heat balance, loop models, identification, plant simulation.

Pure numpy functions over arrays plus O(1) online steppers for the control loop; no I/O here.
"""

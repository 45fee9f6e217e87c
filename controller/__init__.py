"""The stability controller: ``core`` is the pure algorithm (no I/O, no clock), ``runtime`` the CAN
process around it.
"""

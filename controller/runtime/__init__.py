"""The controller on the bus: node logic, CAN process, output envelope, plausibility, checkpoints,
live rerun sink.
"""

"""Linearised-per-step NMPC: the condensed OSQP QP and the controller that runs it (paper eq.
21-24).
"""

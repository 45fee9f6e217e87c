"""Yaw-rate / sideslip references: Algorithm 1 on the learned model, and the linear steady state.
"""

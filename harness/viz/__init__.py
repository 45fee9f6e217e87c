"""Plots (matplotlib) and rerun recordings of runs."""

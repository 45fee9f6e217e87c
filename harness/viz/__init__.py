"""Plots (matplotlib), rerun recordings and progress bars of runs."""

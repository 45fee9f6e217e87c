"""Run data, KPIs, model fidelity, FMVSS 126 scoring and course geometry (no processes started
here).
"""

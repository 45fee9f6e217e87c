"""Run data, KPIs, model fidelity, FMVSS 126 scoring, course geometry, a run's diagnostics and
the v_max bisection (no processes started here).
"""

"""A run's report: the run (harness/run), its KPIs and verdicts (harness/analysis), its plots
and rerun recording (harness/viz), and metrics.json."""

"""``rhonn-harness paper``: the paper's Section IV study, its reference numbers, claims and report.
"""

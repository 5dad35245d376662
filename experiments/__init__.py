"""Reproductions of the paper's experiments (Fig. 3, 5, 6, Table I) and the baselines.

Each module runs as ``python -m experiments.NAME`` from the repository root and writes
PNG plots and a markdown report into ``docs/results/``.  ``python -m experiments.run``
runs them all (``make experiments``).
"""

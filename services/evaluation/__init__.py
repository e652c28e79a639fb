"""Evaluation: everything that measures the pipeline and that no deployed service runs.

Metrics (tangent error), the two baselines, our pipeline in-process, ``handkse eval``/``tune``,
the simulated robot trials and, under :mod:`services.evaluation.drills`, the fault drills.
Runtime packages never import from here (``tests/test_imports.py`` checks it).
"""

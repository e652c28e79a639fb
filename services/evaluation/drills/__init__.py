"""Fault drills: crash, restart or cut parts of a running pipeline and measure the recovery.

:mod:`~services.evaluation.drills.faults` runs the drills; :mod:`~services.evaluation.drills.linkproxy`
is the TCP proxy whose link they cut. Neither is part of a deployed service.
"""

"""What a simulated robot trial is (Table III): the objects, methods and one result row.

Shared by :mod:`services.evaluation.robot_trials` (runs the trials) and
:mod:`services.evaluation.robot_plots` (draws them), so neither imports the other.
"""

from __future__ import annotations

from dataclasses import dataclass

OBJECTS = ("key", "window_lock")
METHODS = ("ours", "regal", "screwmimic")
PARTICIPANT = 3
LABELS = {"ours": "Ours", "regal": "Regal et al.-style", "screwmimic": "ScrewMimic-style"}


@dataclass(frozen=True)
class TrialRow:
    """One simulated trial. Angles in degrees, distances in cm, forces in N."""

    object: str
    seed: int
    method: str
    type_est: str
    axis_angle_deg: float
    axis_offset_cm: float      # distance of the estimated axis from the true one at the grasp
    success: bool
    reason: str
    articulated_deg: float
    peak_force_n: float
    mean_force_n: float
    peak_torque_nm: float
    duration_s: float

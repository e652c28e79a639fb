"""OMIP joint filters: rigid, prismatic and revolute EKFs and the disconnected hypothesis.

Spec: docs/estimation.md#joint-measurement and the filter sections after it, with every departure
from OMIP.
One module per joint; :mod:`.geometry` holds the shared pure functions.

Frames and conventions: every quantity lives in the reference frame ``frame`` (camera or world; the
environment, OMIP's RRB, is static with pose I). A filter sees the hand's left displacement from the
measured reference pose (the first pose of the demonstration), ``D = T_frame_hand(t) @
inv(T_frame_hand(t0))`` (4x4), or, for the prismatic filter, the displacement of the hand origin.
Covariances are of left perturbations ``T = Exp(d) T_hat`` in ``frame``; twists are linear first
``(v, w)``; metres, radians, seconds.

Axis error state (docs/estimation.md#axis-error-state): a unit axis is a nominal vector ``u``
plus a 2-DOF tangent-plane error
``b`` in an orthonormal basis ``B = [t1 t2]`` (3x2) of the plane orthogonal to ``u``:
``u(b) = Exp(u x (B b)) u``, so ``du/db = B`` at ``b = 0``. After each correction ``b`` is folded into
``u`` and ``B`` is rotated along (parallel transport): no spherical-coordinate singularity at the poles.
Published covariances use the deterministic :func:`tangent_basis` of the published axis instead.

Reference error (beyond OMIP): every measurement is taken relative to the same measured reference
pose, whose error is therefore common to all of them. The prismatic filter carries the offset ``o``
of the reference position and the revolute filter the correction ``E`` of the reference pose as
constant states with the reference covariance as prior, instead of OMIP's ``Ad(D) Sigma(t0)
Ad(D)^T`` added to every frame's R (which biases the axis towards the noisy reference point).

Every filter has ``predict(dt)`` / ``update(z, R)`` (Joseph form, ``solve`` not ``inv``), keeps the
last innovation ``y`` and its covariance ``S``, scores its hypothesis on history samples
(``history_errors``) and predicts the delta at a joint value (``predicted_delta``).
"""

from services.kinematics.filters.disconnected import DISCONNECTED_COVARIANCE, DisconnectedJoint
from services.kinematics.filters.geometry import (
    axis_basis_change,
    excess_sigmas,
    inflated_noise,
    prismatic_noise_inflation,
    prismatic_twist_jacobian,
    revolute_delta,
    revolute_left_jacobian,
    revolute_noise_inflation,
    revolute_twist,
    revolute_twist_jacobian,
    rotate_axis,
    rotation_angles_from_trace,
    tangent_basis,
)
from services.kinematics.filters.prismatic import PrismaticJoint
from services.kinematics.filters.revolute import RevoluteJoint
from services.kinematics.filters.rigid import RigidJoint

JOINT_TYPES: tuple[str, ...] = ("rigid", "prismatic", "revolute", "disconnected")

__all__ = [
    "DISCONNECTED_COVARIANCE",
    "JOINT_TYPES",
    "DisconnectedJoint",
    "PrismaticJoint",
    "RevoluteJoint",
    "RigidJoint",
    "axis_basis_change",
    "excess_sigmas",
    "inflated_noise",
    "prismatic_noise_inflation",
    "prismatic_twist_jacobian",
    "revolute_delta",
    "revolute_left_jacobian",
    "revolute_noise_inflation",
    "revolute_twist",
    "revolute_twist_jacobian",
    "rotate_axis",
    "rotation_angles_from_trace",
    "tangent_basis",
]

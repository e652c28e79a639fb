"""What the viewers draw, as plain arrays: handkse messages in, points, lines, ellipsoids out.

numpy only (no viewer library), shared by the Rerun view and the Foxglove export. Every point is
in the ``frame_id`` of its message (metres); quaternions are ``[x, y, z, w]``, the order both
viewers use. Uncertainties are drawn at ``n_sigma`` standard deviations.

Uncertainty conventions (docs/protocol.md):

- ``HandBody.covariance`` is over the left perturbation ``T = Exp(delta) T_hat`` with ``delta``
  linear first. To first order the hand origin moves by ``rho + phi x t``, so its 3x3 position
  covariance is ``G P G^T`` with ``G = [I, -[t]x]`` (the plain upper-left block would ignore how
  orientation error swings the origin).
- The first two coordinates of a joint's covariance are the axis error in a tangent basis of the
  axis (radians of tilt). The tilt of ``b`` is ``|b|`` whatever the basis, so the largest
  eigenvalue of that 2x2 block gives a basis-free circular cone that contains the ``n_sigma``
  ellipse of axis directions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import CameraIntrinsics, Hand, KinematicModel, LandmarkStates
from services.common.se3 import quat_wxyz_from_matrix, skew, so3_exp

Array = NDArray[np.float64]
Colors = NDArray[np.uint8]

DEFAULT_N_SIGMA = 2.0
MAX_CONE_HALF_ANGLE_RAD = math.radians(80.0)  # wider than this a "cone" says only "no idea"

# MediaPipe hand skeleton (landmark order of docs/protocol.md): wrist to each finger, and the palm.
HAND_BONES: tuple[tuple[int, int], ...] = (
    (0, 1), (1, 2), (2, 3), (3, 4),
    (0, 5), (5, 6), (6, 7), (7, 8),
    (5, 9), (9, 10), (10, 11), (11, 12),
    (9, 13), (13, 14), (14, 15), (15, 16),
    (13, 17), (0, 17), (17, 18), (18, 19), (19, 20),
)

# HandBody landmark status 0 untracked, 1 used, 2 rejected as outlier this step, 3 excluded (wrist).
STATUS_NAMES = ("untracked", "used", "outlier", "excluded")
STATUS_COLORS: Colors = np.array([[140, 140, 140, 255], [40, 200, 90, 255], [235, 50, 40, 255],
                                  [70, 130, 240, 255]], np.uint8)
# One colour per joint type (8-bit RGB), the same in the live view and in Foxglove recordings.
TYPE_COLORS: dict[str, tuple[int, int, int]] = {
    "rigid": (150, 150, 150), "prismatic": (60, 140, 255), "revolute": (255, 140, 30),
    "disconnected": (200, 60, 200), "unknown": (230, 230, 230)}
_LOW_VISIBILITY = np.array([70, 80, 190, 255], float)
_HIGH_VISIBILITY = np.array([255, 215, 40, 255], float)


def quat_xyzw_from_matrix(R: Array) -> Array:
    """Unit quaternion ``[x, y, z, w]`` (``w >= 0``) of a 3x3 rotation matrix."""
    w, x, y, z = quat_wxyz_from_matrix(np.asarray(R, float))
    return np.array([x, y, z, w])


# --- colours ---


def visibility_colors(visibility: NDArray[np.floating]) -> Colors:
    """(N, 4) RGBA: blue for visibility 0 through yellow for 1 (values clipped to [0, 1])."""
    v = np.clip(np.nan_to_num(np.asarray(visibility, float)), 0.0, 1.0)[:, None]
    return np.rint(_LOW_VISIBILITY + v * (_HIGH_VISIBILITY - _LOW_VISIBILITY)).astype(np.uint8)


def status_colors(status: NDArray[np.integer]) -> Colors:
    """(N, 4) RGBA of HandBody landmark statuses (0..3; see ``STATUS_NAMES``)."""
    return STATUS_COLORS[np.clip(np.asarray(status, int), 0, 3)]


# --- landmarks ---


@dataclass(frozen=True)
class LandmarkPoints:
    """The landmarks that have a 3-D position: ``points`` (K, 3) m, ``ids`` (K,) landmark index
    (0..20), ``colors`` (K, 4) RGBA."""

    points: Array
    ids: NDArray[np.int64]
    colors: Colors


def detected_landmarks(hand: Hand) -> LandmarkPoints:
    """A detected hand's landmarks with depth (NaN rows dropped), coloured by visibility."""
    points = np.asarray(hand.points, float)
    keep = np.isfinite(points).all(axis=1)
    ids = np.flatnonzero(keep)
    return LandmarkPoints(points[keep], ids, visibility_colors(hand.visibility)[keep])


def tracked_landmarks(landmarks: LandmarkStates) -> LandmarkPoints:
    """The tracker's landmark estimates that have a position, coloured by their status."""
    points = np.asarray(landmarks.points, float)
    keep = np.isfinite(points).all(axis=1)
    ids = np.flatnonzero(keep)
    return LandmarkPoints(points[keep], ids, status_colors(landmarks.status)[keep])


def project_points(points_camera: Array, intrinsics: CameraIntrinsics) -> Array:
    """Pinhole projection of (N, 3) camera-frame points (x right, y down, z forward) to (N, 2)
    pixels ``(u, v)``; NaN for points without depth or not in front of the camera."""
    p = np.asarray(points_camera, float)
    out = np.full((p.shape[0], 2), np.nan)
    front = np.isfinite(p).all(axis=1) & (p[:, 2] > 1e-9)
    z = p[front, 2]
    out[front, 0] = intrinsics.fx * p[front, 0] / z + intrinsics.cx
    out[front, 1] = intrinsics.fy * p[front, 1] / z + intrinsics.cy
    return out


def hand_pixels(hand: Hand, intrinsics: CameraIntrinsics | None,
                T_world_camera: Array | None = None) -> Array | None:
    """(21, 2) image coordinates of a hand: its own ``pixels`` when the detector sent them,
    otherwise its 3-D points projected with ``intrinsics`` (points in "world" are first mapped
    to the camera with ``T_world_camera``); None when neither is available."""
    if hand.pixels is not None:
        return np.asarray(hand.pixels, float)
    if intrinsics is None:
        return None
    points = np.asarray(hand.points, float)
    if T_world_camera is not None:
        T = np.asarray(T_world_camera, float)
        points = (points - T[:3, 3]) @ T[:3, :3]  # R^T (p - t), row-wise
    return project_points(points, intrinsics)


# --- uncertainty ---


@dataclass(frozen=True)
class Ellipsoid:
    """An ``n_sigma`` ellipsoid: ``center`` (3,), ``half_sizes`` (3,) m along the columns of
    ``rotation`` (3x3, det +1), ``quat_xyzw`` the same rotation as a quaternion."""

    center: Array
    half_sizes: Array
    rotation: Array
    quat_xyzw: Array


def ellipsoid_from_covariance(center: Array, covariance: Array,
                              n_sigma: float = DEFAULT_N_SIGMA) -> Ellipsoid:
    """Ellipsoid of a 3x3 covariance: principal axes = eigenvectors, half sizes =
    ``n_sigma * sqrt(eigenvalue)`` (negative round-off eigenvalues count as 0)."""
    P = np.asarray(covariance, float)
    if P.shape != (3, 3) or not np.isfinite(P).all():
        raise ValueError(f"covariance must be a finite 3x3 matrix, got shape {P.shape}")
    eigenvalues, V = np.linalg.eigh(0.5 * (P + P.T))
    if np.linalg.det(V) < 0.0:
        V[:, 0] = -V[:, 0]  # an eigenvector's sign is free; make the frame right-handed
    half = n_sigma * np.sqrt(np.clip(eigenvalues, 0.0, None))
    return Ellipsoid(np.asarray(center, float).copy(), half, V, quat_xyzw_from_matrix(V))


def body_position_covariance(T_frame_hand: Array, covariance: Array) -> Array:
    """3x3 covariance of the hand origin in the frame, from a HandBody's 12x12 covariance (its
    6x6 pose block over the left perturbation, linear first): ``G P G^T``, ``G = [I, -[t]x]``."""
    t = np.asarray(T_frame_hand, float)[:3, 3]
    G = np.hstack([np.eye(3), -skew(t)])
    P = np.asarray(covariance, float)[:6, :6]
    cov: Array = G @ P @ G.T
    return cov


def body_ellipsoid(T_frame_hand: Array, covariance: Array,
                   n_sigma: float = DEFAULT_N_SIGMA) -> Ellipsoid:
    """The hand origin's position uncertainty as an ellipsoid centred on the origin."""
    return ellipsoid_from_covariance(np.asarray(T_frame_hand, float)[:3, 3],
                                     body_position_covariance(T_frame_hand, covariance), n_sigma)


def cone_half_angle(axis_covariance: Array, n_sigma: float = DEFAULT_N_SIGMA) -> float:
    """Half-angle [rad] of the circular cone containing the ``n_sigma`` axis directions, from the
    2x2 tangent-basis block of a joint covariance; capped at ``MAX_CONE_HALF_ANGLE_RAD``."""
    P = np.asarray(axis_covariance, float)
    if P.shape != (2, 2) or not np.isfinite(P).all():
        raise ValueError(f"axis covariance must be a finite 2x2 matrix, got shape {P.shape}")
    largest = float(np.linalg.eigvalsh(0.5 * (P + P.T))[-1])
    return min(n_sigma * math.sqrt(max(largest, 0.0)), MAX_CONE_HALF_ANGLE_RAD)


def perpendicular_basis(axis: Array) -> tuple[Array, Array]:
    """Two unit vectors ``e1, e2`` with ``(e1, e2, axis)`` right-handed orthonormal (drawing only:
    any such pair works)."""
    u = np.asarray(axis, float)
    helper = np.eye(3)[int(np.argmin(np.abs(u)))]
    e1 = np.cross(helper, u)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def cone_lines(apex: Array, axis: Array, half_angle: float, length: float, rays: int = 8,
               segments: int = 48) -> list[Array]:
    """A cone as line strips: the rim circle ``length`` along ``axis`` from ``apex`` (first
    strip, closed) and ``rays`` lines from the apex to the rim."""
    u = np.asarray(axis, float)
    e1, e2 = perpendicular_basis(u)
    centre = np.asarray(apex, float) + length * u
    radius = length * math.tan(half_angle)
    angles = np.linspace(0.0, 2.0 * math.pi, segments + 1)
    rim = centre + radius * (np.cos(angles)[:, None] * e1 + np.sin(angles)[:, None] * e2)
    step = segments // rays
    return [rim] + [np.vstack([apex, rim[i]]) for i in range(0, segments, step)]


# --- the kinematic model ---


@dataclass
class JointRange:
    """The range of joint values demonstrated so far, ``lo <= 0 <= hi`` (q = 0 is the reference).

    Starts over when the model's type changes, when ``updates`` goes down (a reset), or when the
    reference position jumps by more than ``restart_distance_m`` (a new demonstration; the
    estimator refines the reference by millimetres on every update).
    """

    type: str = ""
    lo: float = 0.0
    hi: float = 0.0
    updates: int = 0
    reference: Array = field(default_factory=lambda: np.full(3, np.nan))
    restart_distance_m: float = 0.02

    def update(self, model: KinematicModel) -> tuple[float, float]:
        q = joint_value(model)
        reference = np.asarray(model.reference_pose, float)[:3, 3]
        moved = not np.linalg.norm(reference - self.reference) <= self.restart_distance_m  # NaN: first
        if model.type != self.type or model.updates < self.updates or moved:
            self.type, self.lo, self.hi = model.type, 0.0, 0.0
        self.reference = reference.copy()
        self.updates = model.updates
        if q is not None:
            self.lo, self.hi = min(self.lo, q), max(self.hi, q)
        return self.lo, self.hi


def joint_value(model: KinematicModel) -> float | None:
    """``q`` of the model's own type (m or rad); None for rigid, disconnected and unknown."""
    if model.type == "revolute" and model.revolute is not None:
        return float(model.revolute.q)
    if model.type == "prismatic" and model.prismatic is not None:
        return float(model.prismatic.q)
    return None


@dataclass(frozen=True)
class JointGeometry:
    """A joint model drawn in its frame.

    ``type`` revolute or prismatic; ``axis`` (3,) unit; ``origin`` (3,): for revolute the point of
    the axis nearest the reference hand position, for prismatic that position (the arrow's tail);
    ``segment`` (2, 3): the axis line's end points (revolute) or the arrow's tail and head
    (prismatic); ``cone`` the uncertainty cone(s) as line strips, ``cone_half_angle_rad``;
    ``sweep`` (n, 3): the reference hand position swept over the demonstrated range (an arc
    about the axis, or the stroke along it); ``point_ellipsoid`` (revolute only) where the axis
    passes: the covariance of ``point`` (the 3x3 block after the axis coordinates) without its
    along-axis part, centred on ``origin`` (the published point, nearest the frame origin, can be
    far from the object; the axis direction's own uncertainty is the cone).
    """

    type: str
    axis: Array
    origin: Array
    segment: Array
    cone: list[Array]
    cone_half_angle_rad: float
    sweep: Array
    point_ellipsoid: Ellipsoid | None


def joint_geometry(model: KinematicModel, q_range: tuple[float, float] = (0.0, 0.0),
                   n_sigma: float = DEFAULT_N_SIGMA, axis_length_m: float = 0.3,
                   arc_points: int = 64) -> JointGeometry | None:
    """Geometry of the model's current type; None when it has no axis (rigid, disconnected,
    unknown). ``q_range`` ``(lo, hi)`` is the demonstrated range (:class:`JointRange`)."""
    reference = np.asarray(model.reference_pose, float)[:3, 3]
    lo, hi = min(q_range[0], 0.0), max(q_range[1], 0.0)
    half = 0.5 * axis_length_m
    if model.type == "revolute" and model.revolute is not None:
        r = model.revolute
        u = np.asarray(r.axis, float)
        point = np.asarray(r.point, float)
        origin = point + u * float(u @ (reference - point))
        angles = np.linspace(lo, hi, arc_points)
        arm = reference - origin
        sweep = np.array([origin + so3_exp(u * a) @ arm for a in angles])
        alpha = cone_half_angle(r.covariance[:2, :2], n_sigma)
        cone = cone_lines(origin, u, alpha, half) + cone_lines(origin, -u, alpha, half)
        # where the axis passes near the hand: the point's covariance moved along the axis to
        # the origin (I - u u^T removes the along-axis part, which does not move the line)
        across = np.eye(3) - np.outer(u, u)
        passes = ellipsoid_from_covariance(origin, across @ r.covariance[2:5, 2:5] @ across, n_sigma)
        return JointGeometry("revolute", u, origin, np.vstack([origin - half * u, origin + half * u]),
                             cone, alpha, sweep, passes)
    if model.type == "prismatic" and model.prismatic is not None:
        p = model.prismatic
        u = np.asarray(p.axis, float)
        alpha = cone_half_angle(p.covariance[:2, :2], n_sigma)
        sweep = np.vstack([reference + lo * u, reference + hi * u])
        return JointGeometry("prismatic", u, reference.copy(),
                             np.vstack([reference, reference + half * u]),
                             cone_lines(reference, u, alpha, half), alpha, sweep, None)
    return None


def pose_translation_quat(T: Array) -> tuple[Array, Array]:
    """``(translation (3,), quat_xyzw (4,))`` of a 4x4 pose ``T_a_b``."""
    T = np.asarray(T, float)
    return T[:3, 3].copy(), quat_xyzw_from_matrix(T[:3, :3])

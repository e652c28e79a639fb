"""Synthetic hand demonstrations with ground truth for the ten objects of the ICRA-25 dataset.

``generate(object_name, participant, seed)`` is deterministic in its arguments. It composes:

- the object preset (:mod:`services.synthetic.objects`): joint, range, grasp, occlusion level;
- the participant (:mod:`services.synthetic.hand`): hand size, grasp style, slip, finger flexing;
- a human articulation plan and 30 Hz frame timing with jitter and drops
  (:mod:`services.synthetic.motion`);
- a camera 0.4-1.0 m from the object and the detector observation model
  (:mod:`services.synthetic.camera`).

Ground truth (all poses 4x4 ``float64``, ``T_a_b`` maps points in b to a; ``c`` = camera):

- ``T_camera_part[k] = exp(q[k] * xi_c) @ T_camera_part[0]`` with ``xi_c`` the unit joint twist in
  the camera frame (``JointTruth.twist()``), ``T_camera_part[0] = T_camera_object``;
- ``T_part_hand[k]``: where the hand holds the part; constant up to a small slip that
  accumulates with the articulation (rotation about the grasp point and a translation);
- ``T_camera_hand[k] = T_camera_part[k] @ T_part_hand[k]`` (hand frame as in ``hand.py``: origin at
  the wrist landmark, x distal, y radial, z dorsal);
- ``landmarks_true[k] = T_camera_hand[k] * landmarks_hand[k]``, where ``landmarks_hand`` are the
  noise-free landmarks in the hand frame (fingers flex slightly, so they change over time);
- ``grasp_points[k]``: the part-fixed grasp point, exactly on the joint's path.

So the hand displacement equals the joint motion up to the slip:
``T_camera_hand[k] @ inv(T_part_hand[k]) == exp((q[k] - q[0]) xi_c) @ T_camera_hand[0] @
inv(T_part_hand[0])``, and all of the above agree to ~1e-12.

The tuning/evaluation split follows the paper (section IV.A.3): tuning on valve, tension belt,
window lock and flap latch by participants 1 and 2; evaluation on all ten objects by participant 3.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import se3_adjoint, se3_exp, se3_inverse, so3_exp
from services.synthetic import camera as cam
from services.synthetic import hand as hd
from services.synthetic import motion as mo
from services.synthetic.objects import OBJECTS, ObjectPreset, preset

Array = NDArray[np.float64]

# The paper's participants (section IV.A.3): 1 and 2 for tuning, 3 for evaluation. The hand model
# takes any id >= 1; the command line offers these three.
PARTICIPANTS: tuple[int, ...] = (1, 2, 3)
TUNING_OBJECTS: tuple[str, ...] = ("valve", "tension_belt", "window_lock", "flap_latch")
TUNING_SPLIT: list[tuple[str, int]] = [(o, p) for o in TUNING_OBJECTS for p in (1, 2)]
EVALUATION_SPLIT: list[tuple[str, int]] = [(o, 3) for o in OBJECTS]

CAMERA_DISTANCE_M = (0.4, 1.0)


@dataclass(frozen=True, eq=False)
class JointTruth:
    """The true joint, in the camera frame.

    ``axis`` (3,) unit; ``point`` (3,): for a revolute joint the axis point closest to the camera
    origin, for a prismatic joint the grasp point at the first frame (a point on the line through
    the grasp). ``q`` (N,) joint value per delivered frame (rad or m), ``q = 0`` at the start of
    the demonstration; positive ``q`` moves the part by ``exp(q * twist())``.
    """

    type: Literal["prismatic", "revolute"]
    axis: Array
    point: Array
    q: Array

    def twist(self) -> Array:
        """Unit joint twist ``[v, w]`` (6,) in the camera frame (linear first)."""
        if self.type == "prismatic":
            return np.concatenate([self.axis, np.zeros(3)])
        return np.concatenate([np.cross(self.point, self.axis), self.axis])


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Noise-free state of a demonstration, one row per delivered frame (camera frame ``c``)."""

    T_camera_hand: Array       # (N, 4, 4)
    T_camera_part: Array       # (N, 4, 4)
    T_part_hand: Array         # (N, 4, 4)
    T_camera_object: Array     # (4, 4) the object base (= part at q = 0)
    landmarks_hand: Array      # (N, 21, 3) in the hand frame [m]
    landmarks_true: Array      # (N, 21, 3) in the camera frame [m]
    grasp_points: Array        # (N, 3) part-fixed grasp point in the camera frame [m]
    joint: JointTruth
    frame_index: NDArray[np.int64]   # (N,) index on the nominal 30 Hz grid (gaps = dropped)
    occluded: NDArray[np.bool_]      # (N, 21) see camera.Observation
    missing: NDArray[np.bool_]       # (N, 21)
    depth_outlier: NDArray[np.bool_]  # (N, 21)
    swapped: NDArray[np.bool_]       # (N, 21)


@dataclass(frozen=True, eq=False)
class Demonstration:
    """One synthetic demonstration: the detector's landmark stream plus the ground truth.

    Stream (what a real detector would publish, per delivered frame, camera frame):
    ``stamps_ns`` (N,) int64 capture times; ``points`` (N, 21, 3) float32 [m], NaN without depth;
    ``visibility`` (N, 21) float32; ``pixels`` (N, 21, 2) float32; ``score`` (N,) float32;
    ``handedness`` ("right").
    """

    object_name: str
    participant: int
    seed: int
    stamps_ns: NDArray[np.int64]
    points: NDArray[np.float32]
    visibility: NDArray[np.float32]
    pixels: NDArray[np.float32]
    handedness: str
    score: NDArray[np.float32]
    truth: GroundTruth
    intrinsics: cam.Intrinsics

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])


def _look_at(eye: Array, target: Array) -> Array:
    """``T_object_camera`` (4, 4) of a camera at ``eye`` looking at ``target`` (object z up)."""
    zc = target - eye
    zc = zc / np.linalg.norm(zc)
    xc = np.cross(zc, np.array([0.0, 0.0, 1.0]))
    xc = xc / np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    T = np.eye(4)
    T[:3, :3] = np.stack([xc, yc, zc], axis=1)
    T[:3, 3] = eye
    return T


def _place_camera(rng: np.random.Generator, p: ObjectPreset, landmarks_o: Array,
                  K: cam.Intrinsics) -> Array:
    """``T_camera_object``: 0.4-1.0 m from the object, in front, with the hand in view."""
    flat = landmarks_o.reshape(-1, 3)
    centre = flat.mean(axis=0)
    best: Array | None = None
    best_inside = -1.0
    for _ in range(64):
        d = rng.uniform(*CAMERA_DISTANCE_M)
        el = np.deg2rad(rng.uniform(*p.view_elevation_deg))
        az = np.deg2rad(rng.uniform(*p.view_azimuth_deg))
        direction = np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])
        eye = d * direction
        target = centre + rng.uniform(-0.03, 0.03, 3)
        T_o_c = _look_at(eye, target)
        T_c_o = se3_inverse(T_o_c)
        pts = flat @ T_c_o[:3, :3].T + T_c_o[:3, 3]
        if np.any(pts[:, 2] < 0.2):
            continue
        px = cam.project(pts, K)
        inside = float(np.mean((px[:, 0] > 20) & (px[:, 0] < K.width - 20)
                               & (px[:, 1] > 20) & (px[:, 1] < K.height - 20)))
        if inside > best_inside:
            best, best_inside = T_c_o, inside
        if inside >= 0.99:
            break
    if best is None:
        raise RuntimeError(f"no camera pose sees the hand for {p.name}")
    return best


def _slip(rng: np.random.Generator, part: hd.Participant, progress: Array, t: Array,
          centre_h: Array) -> Array:
    """Slip poses (N, 4, 4) in the hand frame: ``T_part_hand = T_part_hand0 @ slip``.

    Slip accumulates with the articulation ``progress`` (N,) in [0, 1] along a random direction,
    plus a slow wander of 15 % of its size; rotations are about the grasp point ``centre_h``.
    """
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    shift = rng.standard_normal(3)
    shift /= np.linalg.norm(shift)
    wander = hd.smooth_noise(rng, t, 0.7, 6) * 0.15
    rot = (progress[:, None] * axis + wander[:, :3]) * part.slip_rotation_rad
    trans = (progress[:, None] * shift + wander[:, 3:]) * part.slip_translation_m
    out = np.empty((len(t), 4, 4))
    for k in range(len(t)):
        T = hd.rotation_about_point(rot[k], centre_h)
        T[:3, 3] += trans[k]
        out[k] = T
    return out


def generate(object_name: str, participant: int, seed: int = 0, *,
             duration_scale: float = 1.0) -> Demonstration:
    """Generate one demonstration of ``object_name`` by ``participant`` (deterministic by seed).

    ``duration_scale`` stretches every rest and stroke (more frames, same ranges).
    """
    p = preset(object_name)
    part = hd.participant(participant)
    if duration_scale <= 0:
        raise ValueError(f"duration_scale must be positive, got {duration_scale}")
    obj_id = OBJECTS.index(object_name)
    rng = np.random.default_rng(np.random.SeedSequence(
        [0x48414E44, zlib.crc32(object_name.encode()), participant, seed, obj_id]))
    K = cam.AZURE_KINECT_COLOR_720P

    # Motion and frame timing.
    q_range = p.range_nominal * part.range_factor * rng.uniform(1 - p.range_spread,
                                                               1 + p.range_spread)
    plan = mo.plan_articulation(rng, q_range, p.stroke_duration_s * part.duration_factor,
                                duration_scale)
    frames = mo.sample_frame_times(rng, plan.duration_s)
    t = frames.t
    q, dq = plan.evaluate(t)

    # Hand: posture, slight flexing (tightening with articulation speed), grasp point.
    posture = hd.participant_posture(part, p.grasp_type)
    speed = np.abs(dq)
    activity = speed / max(float(speed.max()), 1e-12)
    angles = hd.flexion_trajectory(rng, posture, t, activity, part.flex_amplitude_rad)
    landmarks_h = hd.landmarks_from_angles(part.shape, angles)
    g_h = hd.grasp_point(hd.landmarks_from_angles(part.shape, posture), p.grasp_type, part.shape)

    # Grasp pose on the part at q = 0 (preset orientation + participant/demo variation).
    R_o_h = p.hand_rotation_object()
    jitter = rng.normal(0.0, np.deg2rad(4.0), 3)
    R_o_h = so3_exp(np.asarray(part.grasp_rotation_rad) + jitter) @ R_o_h
    T_part_hand0 = np.eye(4)
    T_part_hand0[:3, :3] = R_o_h
    T_part_hand0[:3, 3] = np.asarray(p.grasp) - R_o_h @ g_h
    progress = np.abs(q) / q_range
    T_part_hand = T_part_hand0[None] @ _slip(rng, part, progress, t, g_h)

    # Part motion in the object frame, camera placement.
    xi_o = p.twist_object()
    T_o_part = np.stack([se3_exp(qk * xi_o) for qk in q])
    T_o_hand = T_o_part @ T_part_hand
    lm_o = np.einsum("nij,nkj->nki", T_o_hand[:, :3, :3], landmarks_h) + T_o_hand[:, None, :3, 3]
    T_c_o = _place_camera(rng, p, lm_o, K)

    xi_c = se3_adjoint(T_c_o) @ xi_o
    T_c_part = np.stack([se3_exp(qk * xi_c) @ T_c_o for qk in q])
    T_c_hand = T_c_part @ T_part_hand
    lm_c = (np.einsum("nij,nkj->nki", T_c_hand[:, :3, :3], landmarks_h)
            + T_c_hand[:, None, :3, 3])
    g_part = np.asarray(p.grasp)
    grasp_c = np.einsum("nij,j->ni", T_c_part[:, :3, :3], g_part) + T_c_part[:, :3, 3]

    axis_c = xi_c[3:] if p.joint_type == "revolute" else xi_c[:3]
    axis_c = axis_c / np.linalg.norm(axis_c)
    if p.joint_type == "revolute":
        pt = T_c_o[:3, :3] @ np.asarray(p.point) + T_c_o[:3, 3]
        pt = pt - (pt @ axis_c) * axis_c
    else:
        pt = T_c_o[:3, :3] @ g_part + T_c_o[:3, 3]
    joint = JointTruth(type=p.joint_type, axis=axis_c, point=pt, q=q.copy())

    obs = cam.observe_landmarks(rng, lm_c, T_c_hand[:, :3, :3], t, p.occlusion,
                                part.shape.radii(), part.shape.palm_length(), K)

    start_ns = int(rng.integers(10**9, 10**12))
    stamps = start_ns + np.round(t * 1e9).astype(np.int64)
    truth = GroundTruth(
        T_camera_hand=T_c_hand, T_camera_part=T_c_part, T_part_hand=T_part_hand,
        T_camera_object=T_c_o, landmarks_hand=landmarks_h, landmarks_true=lm_c,
        grasp_points=grasp_c, joint=joint, frame_index=frames.frame_index,
        occluded=obs.occluded, missing=obs.missing, depth_outlier=obs.depth_outlier,
        swapped=obs.swapped)
    return Demonstration(
        object_name=object_name, participant=participant, seed=seed, stamps_ns=stamps,
        points=obs.points, visibility=obs.visibility, pixels=obs.pixels, handedness="right",
        score=obs.score, truth=truth, intrinsics=K)


def save_npz(demo: Demonstration, path: str | Path) -> None:
    """Write ``demo`` to a compressed ``.npz`` file (arrays only, no pickles).

    numpy appends ``.npz`` to a path without that suffix; pass the same name to
    :func:`load_npz`.
    """
    arrays: dict[str, NDArray[np.generic]] = {
        "object_name": np.array(demo.object_name), "participant": np.array(demo.participant),
        "seed": np.array(demo.seed), "handedness": np.array(demo.handedness),
        "stamps_ns": demo.stamps_ns, "points": demo.points, "visibility": demo.visibility,
        "pixels": demo.pixels, "score": demo.score,
        "intrinsics": np.array([demo.intrinsics.fx, demo.intrinsics.fy, demo.intrinsics.cx,
                                demo.intrinsics.cy, demo.intrinsics.width,
                                demo.intrinsics.height]),
        "joint_type": np.array(demo.truth.joint.type), "joint_axis": demo.truth.joint.axis,
        "joint_point": demo.truth.joint.point, "joint_q": demo.truth.joint.q,
    }
    for f in fields(GroundTruth):
        if f.name != "joint":
            arrays["truth_" + f.name] = getattr(demo.truth, f.name)
    np.savez_compressed(Path(path), **arrays)  # type: ignore[arg-type]


def load_npz(path: str | Path) -> Demonstration:
    """Read a demonstration written by :func:`save_npz`."""
    with np.load(Path(path), allow_pickle=False) as z:
        intr = z["intrinsics"]
        joint = JointTruth(type=str(z["joint_type"]), axis=z["joint_axis"],  # type: ignore[arg-type]
                           point=z["joint_point"], q=z["joint_q"])
        truth_kw = {f.name: z["truth_" + f.name] for f in fields(GroundTruth) if f.name != "joint"}
        truth = GroundTruth(joint=joint, **truth_kw)
        return Demonstration(
            object_name=str(z["object_name"]), participant=int(z["participant"]),
            seed=int(z["seed"]), stamps_ns=z["stamps_ns"], points=z["points"],
            visibility=z["visibility"], pixels=z["pixels"], handedness=str(z["handedness"]),
            score=z["score"], truth=truth,
            intrinsics=cam.Intrinsics(fx=float(intr[0]), fy=float(intr[1]), cx=float(intr[2]),
                                      cy=float(intr[3]), width=int(intr[4]),
                                      height=int(intr[5])))

"""Where the camera stands and how the hand sits on the part (grasp pose, slip).

Object frame ``o`` as in :mod:`services.synthetic.objects`; hand frame ``h`` as in
:mod:`services.synthetic.hand`; 4x4 poses ``T_a_b`` map points in b to a; metres, radians.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import se3_inverse, so3_exp
from services.synthetic import camera as cam
from services.synthetic import hand as hd
from services.synthetic.objects import ObjectPreset

Array = NDArray[np.float64]

CAMERA_DISTANCE_M = (0.4, 1.0)
GRASP_JITTER_RAD = np.deg2rad(4.0)


def look_at(eye: Array, target: Array) -> Array:
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


def place_camera(rng: np.random.Generator, p: ObjectPreset, landmarks_o: Array,
                 K: cam.Intrinsics,
                 distance_m: tuple[float, float] = CAMERA_DISTANCE_M) -> Array:
    """``T_camera_object``: ``distance_m`` from the object, in front, with the hand in view.

    Up to 64 viewpoints drawn from the preset's elevation/azimuth ranges, looking at the
    landmarks' centroid (+-3 cm); the first with 99 % of the landmarks (all frames) inside the
    image (20 px margin) and none nearer than 0.2 m wins, else the best.
    """
    flat = landmarks_o.reshape(-1, 3)
    centre = flat.mean(axis=0)
    best: Array | None = None
    best_inside = -1.0
    for _ in range(64):
        d = rng.uniform(*distance_m)
        el = np.deg2rad(rng.uniform(*p.view_elevation_deg))
        az = np.deg2rad(rng.uniform(*p.view_azimuth_deg))
        direction = np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])
        eye = d * direction
        target = centre + rng.uniform(-0.03, 0.03, 3)
        T_o_c = look_at(eye, target)
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


def slip(rng: np.random.Generator, part: hd.Participant, progress: Array, t: Array,
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


def grasp_pose(rng: np.random.Generator, p: ObjectPreset, part: hd.Participant,
               g_h: Array) -> Array:
    """``T_part_hand`` (4, 4) at q = 0: the preset's hand orientation turned by the
    participant's grasp rotation and a N(0, 4 deg) jitter per axis, ``g_h`` on ``p.grasp``."""
    R_o_h = p.hand_rotation_object()
    jitter = rng.normal(0.0, GRASP_JITTER_RAD, 3)
    R_o_h = so3_exp(np.asarray(part.grasp_rotation_rad) + jitter) @ R_o_h
    T = np.eye(4)
    T[:3, :3] = R_o_h
    T[:3, 3] = np.asarray(p.grasp) - R_o_h @ g_h
    return T


def regrasp_pose(rng: np.random.Generator, T_part_hand: Array, g_h: Array) -> Array:
    """A new grasp of the same held point: ``T_part_hand`` turned by N(0, 4 deg) per axis
    about the hand's grasp point ``g_h`` (the held point stays on the handle)."""
    return T_part_hand @ hd.rotation_about_point(rng.normal(0.0, GRASP_JITTER_RAD, 3), g_h)

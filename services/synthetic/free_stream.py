"""A hand that never touches anything: waving, pointing, resting and moving about (60 s).

For measuring false contact phases. The hand moves in a workspace box 0.6-0.9 m in front of
the camera (the palm centre within +-22 cm across, +-12 cm up/down, +-15 cm in depth);
episodes follow each other until the duration is reached, drawn with probabilities rest 0.3,
wave 0.2, point 0.25, move 0.25:

- ``rest``: 1-4 s still (relaxed fingers, an unsupported hand's drift and tremor,
  :data:`services.synthetic.free_motion.REST_TREMOR`);
- ``wave``: 1.5-4 s open hand swinging sideways at 1.5-3 Hz, 4-12 cm and 15-35 deg about the
  forearm, fading in and out;
- ``point``: a minimum-jerk move of 10-30 cm into a pointing posture, then a 0.5-2 s hold;
- ``move``: a minimum-jerk move to a random pose of the workspace, the fingers changing to a
  random free posture (open, relaxed or pointing) on the way.

Orientations: fingers roughly up (within ~25 deg per axis of the image's up), the back of the
hand towards the camera or, one time in three, the palm. The ground truth has no joint and no
contact phase (``segments == ()``, every frame "free"); ``joint`` is a rigid placeholder named
"none" and ``grasp_points`` are NaN.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import so3_exp
from services.synthetic import camera as cam
from services.synthetic import hand as hd
from services.synthetic import postures as ps
from services.synthetic.demonstration import Demonstration, GroundTruth, JointTruth
from services.synthetic.free_motion import (
    REST_TREMOR,
    leg_duration,
    leg_poses,
    perturbed,
    progress,
    tremor,
)
from services.synthetic.motion import minimum_jerk, sample_frame_times

Array = NDArray[np.float64]

EPISODES = ("rest", "wave", "point", "move")
EPISODE_PROBABILITIES = (0.3, 0.2, 0.25, 0.25)
FREE_OBJECT_NAME = "free"


BOX_M = np.array([0.22, 0.12, 0.15])   # half sizes of the workspace (camera x, y, z)


def _random_pose(rng: np.random.Generator, centre: Array, g_h: Array) -> Array:
    c = centre + rng.uniform(-BOX_M, BOX_M)
    x = np.array([rng.normal(0.0, 0.4), -1.0, rng.normal(0.0, 0.4)])
    x /= np.linalg.norm(x)
    z = -c / np.linalg.norm(c) + rng.normal(0.0, 0.6, 3)
    if rng.random() < 1.0 / 3.0:
        z = -z
    z -= (z @ x) * x
    z /= np.linalg.norm(z)
    R = np.stack([x, np.cross(z, x), z], axis=1)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ g_h
    return T


def generate_free(participant: int, seed: int = 0, duration_s: float = 60.0,
                  hand: str | None = None) -> Demonstration:
    """The free-motion stream (module docstring) of ``participant``, deterministic by seed."""
    if duration_s <= 0.0:
        raise ValueError(f"duration must be positive, got {duration_s}")
    root = np.random.SeedSequence([0x46524545, participant, seed])
    r_plan, r_frames, r_motion, r_obs, r_stamps = (np.random.default_rng(s)
                                                    for s in root.spawn(5))
    part = hd.participant(participant)
    other = "left" if part.dominant_hand == "right" else "right"
    side = hand or (part.dominant_hand if r_plan.random() < 0.75 else other)
    postures = {name: ps.free_posture(name, part) for name in ps.FREE_POSTURES}
    # The palm centre moves in the box; fingers point up, so the box sits a little low.
    centre = np.array([0.0, 0.06, r_plan.uniform(0.6, 0.9)])
    g_h = np.array([0.06, 0.0, -0.03]) * part.shape.hand_length_m / 0.19  # palm centre

    # Episodes: (kind, t0, t1, parameters) with their end poses and postures.
    episodes: list[tuple[str, float, float, dict[str, object]]] = []
    T = _random_pose(r_plan, centre, g_h)
    fingers = "relaxed"
    t = 0.0
    while t < duration_s:
        kind = str(r_plan.choice(EPISODES, p=EPISODE_PROBABILITIES))
        start = {"T": T, "fingers": fingers}
        if kind == "rest":
            d = r_plan.uniform(1.0, 4.0)
            episodes.append((kind, t, t + d, {**start, "to": fingers}))
        elif kind == "wave":
            d = r_plan.uniform(1.5, 4.0)
            episodes.append((kind, t, t + d, {
                **start, "to": "open", "f": r_plan.uniform(1.5, 3.0),
                "amp": r_plan.uniform(0.04, 0.12), "rot": np.deg2rad(r_plan.uniform(15, 35))}))
            fingers = "open"
        else:
            target = fingers = "point" if kind == "point" else str(
                r_plan.choice(ps.FREE_POSTURES))
            T1 = _random_pose(r_plan, centre, g_h)
            if kind == "point":
                c0 = T[:3, :3] @ g_h + T[:3, 3]
                step = r_plan.standard_normal(3)
                step *= r_plan.uniform(0.10, 0.30) / np.linalg.norm(step)
                c1 = np.clip(c0 + step, centre - BOX_M, centre + BOX_M)
                T1[:3, 3] = c1 - T1[:3, :3] @ g_h
            dist = float(np.linalg.norm((T1[:3, 3] + T1[:3, :3] @ g_h) - (T[:3, 3] + T[:3, :3] @ g_h)))
            d = leg_duration(r_plan, dist, part.duration_factor)
            episodes.append(("leg", t, t + d, {**start, "to": target, "T1": T1}))
            T = T1
            t += d
            if kind == "point":
                d = r_plan.uniform(0.5, 2.0)
                episodes.append(("rest", t, t + d, {"T": T, "fingers": target, "to": target}))
            t += d if kind == "point" else 0.0
            continue
        t += d

    frames = sample_frame_times(r_frames, duration_s)
    times = frames.t
    n = len(times)
    T_c_hand = np.empty((n, 4, 4))
    angles = np.empty((n, 5, 4))
    starts = np.array([e[1] for e in episodes])
    which = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, len(episodes) - 1)
    for i, (kind, t0, t1, prm) in enumerate(episodes):
        rows = np.flatnonzero(which == i)
        if not len(rows):
            continue
        tt = times[rows]
        tau = np.clip((tt - t0) / (t1 - t0), 0.0, 1.0)
        T0 = np.asarray(prm["T"])
        a0, a1 = postures[str(prm["fingers"])], postures[str(prm["to"])]
        if kind == "rest":
            pert = tremor(r_motion, np.concatenate([[t0], tt]), REST_TREMOR)
            poses = perturbed(np.broadcast_to(T0, (len(tt), 4, 4)), (pert - pert[0])[1:], g_h)
            sf = np.zeros(len(tt))
        elif kind == "wave":
            env = np.sin(np.pi * tau) ** 2
            phase = np.sin(2.0 * np.pi * float(prm["f"]) * (tt - t0))  # type: ignore[arg-type]
            lateral = np.cross(T0[:3, 0], T0[:3, 2])
            rot = so3_exp((env * phase * float(prm["rot"]))[:, None] * T0[:3, 0][None])  # type: ignore[arg-type]
            poses = np.tile(T0, (len(tt), 1, 1))
            poses[:, :3, :3] = rot @ T0[:3, :3]
            c = (T0[:3, :3] @ g_h + T0[:3, 3])[None] + (env * phase * float(
                prm["amp"]))[:, None] * lateral[None]  # type: ignore[arg-type]
            poses[:, :3, 3] = c - np.einsum("nij,j->ni", poses[:, :3, :3], g_h)
            sf = minimum_jerk(tau / 0.25)
        else:
            poses = leg_poses(T0, np.asarray(prm["T1"]), progress(tt, t0, t1), g_h, np.zeros(3))
            sf = minimum_jerk(tau)
        T_c_hand[rows] = poses
        angles[rows] = ps.blend(a0, a1, sf)
    angles += hd.smooth_noise(r_motion, times, 0.5, 20).reshape(n, 5, 4) * (
        0.7 * part.flex_amplitude_rad)

    landmarks_h = ps.landmarks_for_side(part.shape, angles, "right")
    M = np.diag([-1.0, 1.0, 1.0, 1.0])
    if side == "left":  # the mirror image of the right-hand stream
        T_c_hand = M @ T_c_hand @ np.diag([1.0, 1.0, -1.0, 1.0])
        landmarks_h = landmarks_h @ np.diag([1.0, 1.0, -1.0])
    lm_c = np.einsum("nij,nkj->nki", T_c_hand[:, :3, :3], landmarks_h) + T_c_hand[:, None, :3, 3]
    K = cam.AZURE_KINECT_COLOR_720P
    R_obs = T_c_hand[:, :3, :3] if side == "right" else T_c_hand[:, :3, :3] @ np.diag(
        [1.0, -1.0, -1.0])
    obs = cam.observe_landmarks(r_obs, lm_c, R_obs, times, 0.0, part.shape.radii(),
                                part.shape.palm_length(), K)
    px = cam.project(lm_c, K)
    in_view = ((px[..., 0] >= 0) & (px[..., 0] < K.width) & (px[..., 1] >= 0)
               & (px[..., 1] < K.height)).mean(axis=1)
    present = in_view >= 0.5
    points, vis, pixels, score = obs.points.copy(), obs.visibility.copy(), obs.pixels.copy(), \
        obs.score.copy()
    points[~present] = np.nan
    vis[~present] = 0.0
    pixels[~present] = np.nan
    score[~present] = 0.0

    start_ns = int(r_stamps.integers(10**9, 10**12))
    stamps = start_ns + np.round(times * 1e9).astype(np.int64)
    T_c_o = np.eye(4)
    T_c_o[:3, 3] = centre
    T_c_part = np.broadcast_to(T_c_o, (n, 4, 4)).copy()
    none = JointTruth(type="rigid", axis=np.zeros(3), point=centre.copy(), q=np.zeros(n),
                      name="none")
    truth = GroundTruth(
        T_camera_hand=T_c_hand, T_camera_part=T_c_part,
        T_part_hand=np.linalg.inv(T_c_part) @ T_c_hand, T_camera_object=T_c_o,
        landmarks_hand=landmarks_h, landmarks_true=lm_c, grasp_points=np.full((n, 3), np.nan),
        joint=none, frame_index=frames.frame_index, occluded=obs.occluded, missing=obs.missing,
        depth_outlier=obs.depth_outlier, swapped=obs.swapped, joints=(none,),
        T_camera_parts=T_c_part[None], segments=(), phase=np.full(n, "free", dtype="<U7"),
        segment_index=np.full(n, -1, dtype=np.int64), finger_angles=angles, hand_side=side)
    return Demonstration(
        object_name=FREE_OBJECT_NAME, participant=participant, seed=seed, stamps_ns=stamps,
        points=points, visibility=vis, pixels=pixels, handedness=side, score=score, truth=truth,
        intrinsics=K, variant="free", present=present, labels=np.full(n, side))

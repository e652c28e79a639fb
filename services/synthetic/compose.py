"""Compose a demonstration from its timeline: hand poses, fingers, camera, observation, truth.

Every split and variant except the paper split's ``cut`` goes through :func:`compose`
(docs/synthetic.md). Steps, all in the object frame ``o`` until the camera is placed:

1. the scene (one joint, or two for a ``sequence``), its size spread and the hand side;
2. the timeline (:mod:`services.synthetic.timeline`) and the 30 Hz frame times with jitter and
   drops (:mod:`services.synthetic.motion`);
3. contacts: the part follows the joint plan, the hand holds it with slip (and still-hold
   tremor), the fingers flex and tighten with the articulation speed, all continuous from the
   moment the fingers close;
4. legs: minimum-jerk free motion between the evaluated contact poses, fingers blending between
   postures with a slow wander that vanishes at the ends of each leg;
5. the camera (distance per preset, 0.4-1.8 m), the same observation model as the paper split,
   with the occlusion level fading from the object's to none over the first 10 cm away from
   the handle;
6. presence: the hand is not detected during a gap, nor while less than half of its landmarks
   project into the image;
7. a left hand is the mirror image of the right-hand scene (docs/synthetic.md#left-hands).

Random draws come from separate streams per concern (a child of one seed sequence per
demonstration), so changing one concern never moves the draws of another.
"""

from __future__ import annotations

import zlib

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import se3_adjoint, se3_inverse, so3_exp
from services.synthetic import camera as cam
from services.synthetic import hand as hd
from services.synthetic import postures as ps
from services.synthetic.demonstration import (
    PHASE_CONTACT,
    PHASE_FREE,
    ContactSegment,
    Demonstration,
    GroundTruth,
    JointTruth,
)
from services.synthetic.free_motion import (
    HOLD_TREMOR,
    REST_TREMOR,
    leg_poses,
    perturbed,
    progress,
    tremor,
    with_grasp_point,
)
from services.synthetic.household import SEQUENCE_PARTNERS
from services.synthetic.motion import minimum_jerk, sample_frame_times
from services.synthetic.objects import ObjectPreset, scaled
from services.synthetic.placement import place_camera, slip
from services.synthetic.splits import GAPS, VARIANTS, preset
from services.synthetic.timeline import FingerRef, PoseRef, Scene, Timeline, plan_timeline

Array = NDArray[np.float64]

_STREAMS = ("side", "scale", "timeline", "frames", "slip", "fingers", "legs", "camera",
            "observe", "stamps")
OCCLUSION_FADE_M = 0.10
MIN_IN_VIEW_FRACTION = 0.5
MIRROR_CAMERA = np.diag([-1.0, 1.0, 1.0, 1.0])   # x_c -> -x_c
MIRROR_OBJECT = np.diag([-1.0, 1.0, 1.0, 1.0])   # x_o -> -x_o
MIRROR_HAND = np.diag([1.0, 1.0, -1.0, 1.0])     # z_h -> -z_h


def _rngs(object_name: str, participant: int, seed: int, variant: str,
          gap: str | None) -> dict[str, np.random.Generator]:
    root = np.random.SeedSequence([0x57484F4C, zlib.crc32(object_name.encode()), participant,
                                   seed, VARIANTS.index(variant),
                                   0 if gap is None else 1 + GAPS.index(gap)])
    return {n: np.random.default_rng(s)
            for n, s in zip(_STREAMS, root.spawn(len(_STREAMS)), strict=True)}


def _outward(p: ObjectPreset) -> Array:
    """Unit direction (3,) in ``o`` from the object towards the middle of its viewpoints."""
    el = np.deg2rad(np.mean(p.view_elevation_deg))
    az = np.deg2rad(np.mean(p.view_azimuth_deg))
    return np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])


def scene_for(object_name: str, variant: str, factor: float) -> Scene:
    """The joints of ``object_name`` for ``variant``, sizes scaled by ``factor``."""
    main = scaled(preset(object_name), factor)
    if variant != "sequence":
        return Scene((main,), (None,))
    partner = SEQUENCE_PARTNERS[object_name]
    other = scaled(partner.preset, factor)
    first, second = (other, main) if partner.partner_first else (main, other)
    return Scene((first, second), (1 if partner.mounted else None, None))


class _Evaluator:
    """Evaluates a timeline at the frame times ``t`` (hand poses, finger angles in ``o``)."""

    def __init__(self, tl: Timeline, scene: Scene, part: hd.Participant,
                 postures: tuple[Array, ...], g_h: tuple[Array, ...], t: Array,
                 rng: dict[str, np.random.Generator]) -> None:
        self.tl, self.scene, self.part, self.postures, self.g_h = tl, scene, part, postures, g_h
        self.t = t
        self.rng = rng
        n = len(t)
        self.T_o_hand = np.full((n, 4, 4), np.nan)
        self.angles = np.full((n, 5, 4), np.nan)
        self.item = np.full(n, -1)
        items = tl.items()
        starts = np.array([it[0] for it in items])
        self.item = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(items) - 1)
        self.items = items
        self.start_pose: dict[int, Array] = {}
        self.end_pose: dict[int, Array] = {}
        self.start_angles: dict[int, Array] = {}
        self.end_angles: dict[int, Array] = {}

    def q(self, t: Array) -> Array:
        """Joint values (J, M) at times ``t``."""
        return np.stack([self.tl.joint_plan(j).evaluate(t)[0]
                         for j in range(len(self.scene.presets))])

    @staticmethod
    def _bounded(t0: float, tt: Array, t1: float) -> Array:
        """``[t0, tt..., t1]`` kept non-decreasing (the last frame may come after ``t1``: the
        frame grid has capture jitter)."""
        hi = max(t1, float(tt[-1])) if len(tt) else t1
        return np.concatenate([[min(t0, float(tt[0])) if len(tt) else t0], tt, [hi]])

    def rows(self, kind: str, index: int) -> NDArray[np.int64]:
        i = self.items.index(next(it for it in self.items if it[2] == kind and it[3] == index))
        return np.flatnonzero(self.item == i)

    def contacts(self) -> None:
        for c in self.tl.contacts:
            rows = self.rows("contact", c.index)
            tt = self._bounded(c.t0, self.t[rows], c.t1)
            T_parts = self.scene.part_poses(self.q(tt))
            p = self.scene.presets[c.joint]
            g_h = self.g_h[c.joint]
            q, dq = self.tl.joint_plan(c.joint).evaluate(tt)
            rigid = p.joint_type == "rigid"
            prog = np.zeros(len(tt)) if rigid else np.abs(q - q[0]) / self.tl.q_ranges[c.joint]
            s = slip(self.rng["slip"], self.part, prog, tt, g_h)
            T_ph = c.T_part_hand0[None] @ se3_inverse(s[0])[None] @ s
            if rigid:
                pert = tremor(self.rng["slip"], tt, HOLD_TREMOR)
                T_ph = perturbed(T_ph, pert - pert[0], g_h)
            T_o_hand = T_parts[c.joint] @ T_ph
            speed = np.abs(dq)
            activity = speed / max(float(speed.max()), 1e-12)
            angles = hd.flexion_trajectory(self.rng["fingers"], self.postures[c.joint], tt,
                                           activity, self.part.flex_amplitude_rad)
            self.T_o_hand[rows] = T_o_hand[1:-1]
            self.angles[rows] = angles[1:-1]
            self.start_pose[c.index], self.end_pose[c.index] = T_o_hand[0], T_o_hand[-1]
            self.start_angles[c.index], self.end_angles[c.index] = angles[0], angles[-1]

    def _pose(self, ref: PoseRef) -> Array:
        A = (self.start_pose if ref.at == "start" else self.end_pose)[ref.contact]
        g_h = self.g_h[self.tl.contacts[ref.contact].joint]
        R = A[:3, :3]
        c = R @ g_h + A[:3, 3] + ref.shift_o + R @ ref.shift_h
        return with_grasp_point(so3_exp(ref.turn) @ R, c, g_h)

    def _fingers(self, ref: FingerRef) -> Array:
        if ref.posture is not None:
            return ref.posture
        return (self.start_angles if ref.at == "start" else self.end_angles)[ref.contact]

    def legs(self) -> None:
        for i, leg in enumerate(self.tl.legs):
            rows = self.rows("leg", i)
            if not len(rows):
                continue
            tt = self.t[rows]
            k = leg.end.contact if not leg.still else leg.start.contact
            g_h = self.g_h[self.tl.contacts[k].joint]
            Ta, Tb = self._pose(leg.start), self._pose(leg.end)
            if leg.still:
                pert = tremor(self.rng["legs"], self._bounded(leg.t0, tt, leg.t1), REST_TREMOR)
                pert = pert - (pert[-1] if leg.anchor_end else pert[0])
                poses = perturbed(np.broadcast_to(Ta, (len(tt), 4, 4)), pert[1:-1], g_h)
            else:
                ca = Ta[:3, :3] @ g_h + Ta[:3, 3]
                cb = Tb[:3, :3] @ g_h + Tb[:3, 3]
                d = cb - ca
                dist = float(np.linalg.norm(d))
                side = leg.bump_dir - (leg.bump_dir @ d) * d / max(dist * dist, 1e-12)
                n = float(np.linalg.norm(side))
                bump = leg.bump_fraction * dist * side / n if n > 1e-9 else np.zeros(3)
                poses = leg_poses(Ta, Tb, progress(tt, leg.t0, leg.t1), g_h, bump)
            tau = (tt - leg.t0) / (leg.t1 - leg.t0)
            a, b = leg.finger_window
            sf = minimum_jerk((tau - a) / (b - a))
            wander = hd.smooth_noise(self.rng["fingers"], tt, 0.5, 20).reshape(-1, 5, 4)
            wander *= 0.7 * self.part.flex_amplitude_rad * np.sin(np.pi * tau)[:, None, None]
            self.T_o_hand[rows] = poses
            self.angles[rows] = ps.blend(self._fingers(leg.fingers_start),
                                         self._fingers(leg.fingers_end), sf) + wander


def _joint_truth(p: ObjectPreset, T_c_o: Array, q: Array) -> JointTruth:
    grasp_c = T_c_o[:3, :3] @ np.asarray(p.grasp) + T_c_o[:3, 3]
    if p.joint_type == "rigid":
        return JointTruth(type="rigid", axis=np.zeros(3), point=grasp_c, q=q, name=p.name)
    xi_c = se3_adjoint(T_c_o) @ p.twist_object()
    if p.joint_type == "prismatic":
        axis = xi_c[:3] / np.linalg.norm(xi_c[:3])
        return JointTruth(type="prismatic", axis=axis, point=grasp_c, q=q, name=p.name)
    axis = xi_c[3:] / np.linalg.norm(xi_c[3:])
    pt = T_c_o[:3, :3] @ np.asarray(p.point) + T_c_o[:3, 3]
    return JointTruth(type="revolute", axis=axis, point=pt - (pt @ axis) * axis, q=q,
                      name=p.name)


def _mirror_joint(j: JointTruth) -> JointTruth:
    M = MIRROR_CAMERA[:3, :3]
    axis = M @ j.axis if j.type != "revolute" else -(M @ j.axis)
    return JointTruth(type=j.type, axis=axis, point=M @ j.point, q=j.q, name=j.name)


def compose(object_name: str, participant: int, seed: int, *, variant: str = "cut",
            gap: str | None = None, hand: str | None = None,
            duration_scale: float = 1.0) -> Demonstration:
    """One demonstration (module docstring); arguments as
    :func:`services.synthetic.generator.generate`."""
    rng = _rngs(object_name, participant, seed, variant, gap)
    part = hd.participant(participant)
    other = "left" if part.dominant_hand == "right" else "right"
    draw_side = part.dominant_hand if rng["side"].random() < 0.75 else other
    side = hand or draw_side
    main = preset(object_name)
    factor = 1.0 + rng["scale"].uniform(-main.scale_spread, main.scale_spread)
    scene = scene_for(object_name, variant, factor)
    postures = tuple(hd.participant_posture(part, p.grasp_type) for p in scene.presets)
    g_h = tuple(hd.grasp_point(hd.landmarks_from_angles(part.shape, a), p.grasp_type, part.shape)
                for a, p in zip(postures, scene.presets, strict=True))
    tl = plan_timeline(rng["timeline"], variant, gap, scene, part, _outward(main), g_h,
                       ps.free_posture("open", part), ps.free_posture("relaxed", part),
                       duration_scale)
    frames = sample_frame_times(rng["frames"], tl.duration_s)
    t = frames.t
    ev = _Evaluator(tl, scene, part, postures, g_h, t, rng)
    ev.contacts()
    ev.legs()
    if np.isnan(ev.T_o_hand).any() or np.isnan(ev.angles).any():
        raise AssertionError("timeline left frames without a hand pose")
    q = ev.q(t)
    T_o_parts = scene.part_poses(q)
    landmarks_h = hd.landmarks_from_angles(part.shape, ev.angles)
    T_o_hand = ev.T_o_hand
    lm_o = np.einsum("nij,nkj->nki", T_o_hand[:, :3, :3], landmarks_h) + T_o_hand[:, None, :3, 3]

    K = cam.AZURE_KINECT_COLOR_720P
    distance = (max(p.camera_distance_m[0] for p in scene.presets),
                max(p.camera_distance_m[1] for p in scene.presets))
    T_c_o = place_camera(rng["camera"], main, lm_o, K, distance)

    # Contact phases, occlusion level, held points (object frame).
    n = len(t)
    phase = np.full(n, PHASE_FREE, dtype="<U7")
    seg_index = np.full(n, -1, dtype=np.int64)
    level = np.zeros(n)
    for c in tl.contacts:
        rows = ev.rows("contact", c.index)
        phase[rows] = PHASE_CONTACT
        seg_index[rows] = c.index
        held = np.einsum("nij,j->ni", T_o_parts[c.joint, :, :3, :3], c.grasp_part) \
            + T_o_parts[c.joint, :, :3, 3]
        g = g_h[c.joint]
        hand_pt = np.einsum("nij,j->ni", T_o_hand[:, :3, :3], g) + T_o_hand[:, :3, 3]
        fade = np.clip(1.0 - np.linalg.norm(hand_pt - held, axis=1) / OCCLUSION_FADE_M, 0, 1)
        occ = scene.presets[c.joint].occlusion
        level = np.maximum(level, occ * fade)
        level[rows] = occ
    final = tl.contacts[-1].joint
    final_contacts = [c for c in tl.contacts if c.joint == final]
    handle = np.zeros(n, dtype=np.int64)
    for i, c in enumerate(final_contacts):
        handle[t >= c.t0] = i
    grasp_o = np.stack([final_contacts[h].grasp_part for h in handle])

    # To the camera frame (and the mirror image for a left hand).
    T_c_parts = T_c_o[None, None] @ T_o_parts
    T_c_hand = T_c_o[None] @ T_o_hand
    joints = tuple(_joint_truth(p, T_c_o, q[j]) for j, p in enumerate(scene.presets))
    grasp_part = [c.grasp_part for c in tl.contacts]
    if side == "left":
        T_c_o = MIRROR_CAMERA @ T_c_o @ MIRROR_OBJECT
        T_c_parts = MIRROR_CAMERA @ T_c_parts @ MIRROR_OBJECT
        T_c_hand = MIRROR_CAMERA @ T_c_hand @ MIRROR_HAND
        landmarks_h = landmarks_h @ MIRROR_HAND[:3, :3]
        joints = tuple(_mirror_joint(j) for j in joints)
        grasp_o = grasp_o @ MIRROR_OBJECT[:3, :3]
        grasp_part = [MIRROR_OBJECT[:3, :3] @ g for g in grasp_part]
    lm_c = (np.einsum("nij,nkj->nki", T_c_hand[:, :3, :3], landmarks_h)
            + T_c_hand[:, None, :3, 3])
    grasp_c = np.einsum("nij,nj->ni", T_c_parts[final, :, :3, :3], grasp_o) \
        + T_c_parts[final, :, :3, 3]

    # The detector: back of the hand = hand z for a right hand, -z for a left one.
    R_obs = T_c_hand[:, :3, :3] if side == "right" else T_c_hand[:, :3, :3] @ np.diag(
        [1.0, -1.0, -1.0])
    obs = cam.observe_landmarks(rng["observe"], lm_c, R_obs, t, level, part.shape.radii(),
                                part.shape.palm_length(), K)
    undetected = np.zeros(n, dtype=bool)
    for i, leg in enumerate(tl.legs):
        if not leg.detected:
            undetected[ev.rows("leg", i)] = True
    if tl.dropout is not None:
        undetected |= (t >= tl.dropout[0]) & (t < tl.dropout[1])
    px = cam.project(lm_c, K)
    in_view = ((px[..., 0] >= 0) & (px[..., 0] < K.width) & (px[..., 1] >= 0)
               & (px[..., 1] < K.height) & (lm_c[..., 2] > 0.0)).mean(axis=1)
    present = ~undetected & (in_view >= MIN_IN_VIEW_FRACTION) & (lm_c[..., 2].mean(axis=1) > 0.25)
    points, vis, pixels, score = obs.points.copy(), obs.visibility.copy(), obs.pixels.copy(), \
        obs.score.copy()
    points[~present] = np.nan
    vis[~present] = 0.0
    pixels[~present] = np.nan
    score[~present] = 0.0

    start_ns = int(rng["stamps"].integers(10**9, 10**12))
    stamps = start_ns + np.round(t * 1e9).astype(np.int64)
    segments = []
    for c in tl.contacts:
        rows = ev.rows("contact", c.index)
        segments.append(ContactSegment(
            index=c.index, joint=c.joint, start=int(rows[0]), end=int(rows[-1]),
            start_ns=int(stamps[rows[0]]), end_ns=int(stamps[rows[-1]]),
            onset_ns=start_ns + round(c.t0 * 1e9),
            release_ns=start_ns + round(c.t1 * 1e9), grasp_part=grasp_part[c.index]))
    T_c_part = T_c_parts[final]
    truth = GroundTruth(
        T_camera_hand=T_c_hand, T_camera_part=T_c_part,
        T_part_hand=se3_inverse_stack(T_c_part) @ T_c_hand, T_camera_object=T_c_o,
        landmarks_hand=landmarks_h, landmarks_true=lm_c, grasp_points=grasp_c,
        joint=joints[final], frame_index=frames.frame_index, occluded=obs.occluded,
        missing=obs.missing, depth_outlier=obs.depth_outlier, swapped=obs.swapped,
        joints=joints, T_camera_parts=T_c_parts, segments=tuple(segments), phase=phase,
        segment_index=seg_index, finger_angles=ev.angles, hand_side=side,
        undetected=undetected, gap=gap)
    return Demonstration(
        object_name=object_name, participant=participant, seed=seed, stamps_ns=stamps,
        points=points, visibility=vis, pixels=pixels, handedness=side, score=score,
        truth=truth, intrinsics=K, variant=variant, present=present,
        labels=np.full(n, side))


def se3_inverse_stack(T: Array) -> Array:
    """Inverses (N, 4, 4) of rigid poses (N, 4, 4)."""
    out = np.tile(np.eye(4), (len(T), 1, 1))
    Rt = np.transpose(T[:, :3, :3], (0, 2, 1))
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    return out

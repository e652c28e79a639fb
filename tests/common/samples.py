"""One valid example of every message type, with seeded random content."""

from __future__ import annotations

import dataclasses

import numpy as np

from services.common import protocol as p
from services.common.se3 import se3_exp


def _rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed)


def hand_landmarks(seed: int = 0) -> p.HandLandmarks:
    rng = _rng(seed)
    points = rng.normal(0, 0.05, (21, 3)).astype("<f4") + np.float32(0.6)
    points[3] = np.nan
    hand = p.Hand(handedness="right", score=0.9, points=points,
                  visibility=rng.uniform(0, 1, 21).astype("<f4"),
                  pixels=rng.uniform(0, 700, (21, 2)).astype("<f4"))
    return p.HandLandmarks(seq=7, stamp_ns=1_700_000_000_000_000_000, frame_id="camera",
                           hands=(hand,))


def hand_body(seed: int = 0) -> p.HandBody:
    rng = _rng(seed)
    A = rng.normal(size=(12, 12))
    return p.HandBody(seq=3, stamp_ns=123, frame_id="world", initialized=True,
                      pose=se3_exp(rng.normal(size=6)), twist=rng.normal(size=6),
                      covariance=A @ A.T, motion_model="kinematic",
                      landmarks=p.LandmarkStates(
                          points=rng.normal(size=(21, 3)).astype("<f4"),
                          variance=rng.uniform(0, 1, 21).astype("<f4"),
                          status=rng.integers(0, 4, 21).astype("|u1")))


def kinematic_model(seed: int = 0) -> p.KinematicModel:
    rng = _rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    probs = rng.uniform(0.01, 1, 4)
    probs /= probs.sum()
    P7 = rng.normal(size=(7, 7))
    P4 = rng.normal(size=(4, 4))
    return p.KinematicModel(
        seq=11, stamp_ns=99, type="revolute",
        probabilities=dict(zip(p.JOINT_TYPES, probs.tolist(), strict=True)),
        prismatic=p.PrismaticParams(axis=axis, q=0.01, dq=-0.2, covariance=P4 @ P4.T),
        revolute=p.RevoluteParams(axis=axis, point=rng.normal(size=3), q=3.5, dq=0.4,
                                  covariance=P7 @ P7.T),
        reference_pose=se3_exp(rng.normal(size=6)), updates=42)


def rgbd_frame(seed: int = 0) -> p.RgbdFrame:
    rng = _rng(seed)
    w, h = 8, 6
    return p.RgbdFrame(
        seq=1, stamp_ns=5,
        color=p.ColorImage(encoding="bgr8", width=w, height=h,
                           data=rng.integers(0, 255, w * h * 3, dtype=np.uint8).tobytes()),
        depth=p.DepthImage(encoding="u16", width=w, height=h, scale_m=0.001,
                           data=rng.integers(0, 4000, w * h, dtype="<u2").tobytes()),
        intrinsics=p.CameraIntrinsics(fx=600.0, fy=600.0, cx=4.0, cy=3.0, width=w, height=h),
        T_world_camera=se3_exp(rng.normal(size=6)))


def robot_state(seed: int = 0) -> p.RobotState:
    rng = _rng(seed)
    return p.RobotState(q=rng.normal(size=7), dq=rng.normal(size=7),
                        T_base_ee=se3_exp(rng.normal(size=6)), wrench=rng.normal(size=6),
                        mode="articulating", backend="mujoco",
                        T_base_target=se3_exp(rng.normal(size=6)))


def all_messages(seed: int = 0) -> list[p.Message]:
    return [
        rgbd_frame(seed), hand_landmarks(seed), hand_body(seed), kinematic_model(seed),
        robot_state(seed),
        dataclasses.replace(hand_landmarks(seed), frame_id="world",
                            T_world_camera=se3_exp(_rng(seed).normal(size=6))),
        p.ArticulateRequest(amount=3.14, duration_s=10.0, model=kinematic_model(seed),
                            dry_run=True),
        p.ArticulateRequest(amount=0.05, duration_s=4.0),
        p.ArticulateResult(success=False, reason="force_limit", articulated=0.3,
                           peak_force_n=71.0, mean_force_n=20.5, duration_s=2.0),
        p.Ack(ok=True, message="done"),
        p.ServiceStats(service="tracker", uptime_s=12.5, received=10, published=9, dropped=1,
                       rejected={"bad_msgpack": 2},
                       latency_ms={"step": {"p50": 0.2, "p99": 0.9}}),
        p.ServiceStats(service="tracker", uptime_s=1.0, skipped={"no_hand": 3}),
    ]

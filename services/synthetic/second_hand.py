"""An idle second hand in view: resting still, detected every frame, labelled either way.

Who it is: with probability 0.7 the demonstrator's other hand (the opposite side, same hand
shape), otherwise a second person's hand (either side, another participant's shape). It rests
in a relaxed posture, back of the hand towards the camera (within ~60 deg), somewhere in the
lower 70 % of the image at the depth of the demonstration +15/-25 cm, at least 12 cm from every
landmark of the manipulating hand in every frame (else the farthest of 300 candidate places);
it never moves.

Its detections come from the same observation model as the manipulating hand (occlusion level
0.05: nothing in front of it), plus a slowly varying score offset (Ornstein-Uhlenbeck, 0.04,
time constant 1 s), so it often scores higher than the partly occluded manipulating hand.

Labels (``mode``; docs/synthetic.md#second-hand):

- ``opposite``: it is reported with the opposite handedness of the manipulating hand;
- ``same``: both hands are reported with the manipulating hand's handedness;
- ``flipping``: each hand's label flips to the wrong side in short runs (enter with probability
  0.12 per frame, leave with 0.4: ~23 % of the frames), independently per hand, so the two
  labels are sometimes equal and sometimes swapped.

The placement, noise and labels are drawn from streams seeded by the demonstration alone, so
the manipulating hand's stream is exactly the one without the idle hand (only its reported
labels change, under ``flipping``), and the three modes share the same idle hand.
"""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np
from numpy.typing import NDArray

from services.synthetic import camera as cam
from services.synthetic import hand as hd
from services.synthetic import postures as ps
from services.synthetic.demonstration import Demonstration, HandTrack, SecondHandTruth

Array = NDArray[np.float64]

MIN_DISTANCE_M = 0.12
OTHER_PERSON_PROBABILITY = 0.3
FLIP_ENTER, FLIP_EXIT = 0.12, 0.4
SCORE_OFFSET_STD = 0.04
IDLE_OCCLUSION = 0.05


def _other(side: str) -> str:
    return "left" if side == "right" else "right"


def _flips(rng: np.random.Generator, n: int) -> NDArray[np.bool_]:
    """Two-state Markov chain (N,): True while the label is flipped."""
    out = np.zeros(n, dtype=bool)
    state = False
    u = rng.random(n)
    for k in range(n):
        state = (u[k] < FLIP_ENTER) if not state else (u[k] >= FLIP_EXIT)
        out[k] = state
    return out


def _place(rng: np.random.Generator, lm_h: Array, side: str, manip: Array,
           K: cam.Intrinsics) -> Array:
    """``T_camera_hand`` (4, 4) of the idle hand (module docstring), best of 300 candidates."""
    centre_m = np.nanmean(manip.reshape(-1, 3), axis=0)
    flat = manip.reshape(-1, 3)
    best, best_d = None, -1.0
    for _ in range(300):
        u = rng.uniform(0.12, 0.88) * K.width
        v = rng.uniform(0.30, 0.92) * K.height
        z = float(np.clip(centre_m[2] + rng.uniform(-0.25, 0.15), 0.4, 2.2))
        c = cam.back_project(np.array([u, v]), np.array(z), K)
        to_cam = -c / np.linalg.norm(c)
        dorsal = to_cam + 0.6 * rng.standard_normal(3)
        dorsal /= np.linalg.norm(dorsal)
        if dorsal @ to_cam < 0.5:
            continue
        x = rng.standard_normal(3)
        x -= (x @ dorsal) * dorsal
        x /= np.linalg.norm(x)
        zc = dorsal if side == "right" else -dorsal
        R = np.stack([x, np.cross(zc, x), zc], axis=1)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = c - R @ lm_h.mean(axis=0)
        lm = lm_h @ R.T + T[:3, 3]
        px = cam.project(lm, K)
        if not (np.all(px[:, 0] > 15) and np.all(px[:, 0] < K.width - 15)
                and np.all(px[:, 1] > 15) and np.all(px[:, 1] < K.height - 15)):
            continue
        d = float(np.min(np.linalg.norm(flat[:, None] - lm[None], axis=-1)))
        if d > best_d:
            best, best_d = T, d
        if d >= MIN_DISTANCE_M:
            break
    if best is None:
        raise RuntimeError("no place in view for the idle hand")
    return best


def with_idle_hand(demo: Demonstration, mode: str) -> Demonstration:
    """``demo`` with an idle second hand in view labelled by ``mode`` (module docstring)."""
    if mode not in ("opposite", "same", "flipping"):
        raise ValueError(f"idle hand mode must be opposite, same or flipping, got {mode!r}")
    if demo.second is not None:
        raise ValueError("the demonstration already has a second hand")
    root = np.random.SeedSequence([0x49444C45, zlib.crc32(demo.object_name.encode()),
                                   demo.participant, demo.seed,
                                   zlib.crc32(demo.variant.encode()),
                                   zlib.crc32(str(demo.truth.gap).encode())])
    r_who, r_place, r_obs, r_score, r_labels = (np.random.default_rng(s) for s in root.spawn(5))
    tr = demo.truth
    n = len(demo)
    if r_who.random() < OTHER_PERSON_PROBABILITY:
        part = hd.participant(100 + demo.participant)
        side = "left" if r_who.random() < 0.5 else "right"
    else:
        part = hd.participant(demo.participant)
        side = _other(tr.hand_side)
    angles = ps.free_posture("relaxed", part) + r_who.normal(0.0, np.deg2rad(5.0), (5, 4))
    lm_h = ps.landmarks_for_side(part.shape, angles, side)
    K = demo.intrinsics
    T = _place(r_place, lm_h, side, tr.landmarks_true, K)
    T_all = np.broadcast_to(T, (n, 4, 4)).copy()
    lm_c = np.broadcast_to(lm_h @ T[:3, :3].T + T[:3, 3], (n, 21, 3)).copy()
    R_obs = T_all[:, :3, :3] if side == "right" else T_all[:, :3, :3] @ np.diag([1.0, -1, -1])
    t = (demo.stamps_ns - demo.stamps_ns[0]) * 1e-9
    obs = cam.observe_landmarks(r_obs, lm_c, R_obs, t, IDLE_OCCLUSION, part.shape.radii(),
                                part.shape.palm_length(), K)
    offset = SCORE_OFFSET_STD * hd.smooth_noise(r_score, t, 1.0, 1)[:, 0]
    score = np.clip(obs.score + offset, 0.0, 1.0).astype(np.float32)

    assert demo.labels is not None
    manip_labels = demo.labels.copy()
    base = np.array([_other(str(s)) for s in manip_labels])
    if mode == "same":
        idle_labels = manip_labels.copy()
    elif mode == "opposite":
        idle_labels = base
    else:
        flip_m = _flips(r_labels, n)
        flip_i = _flips(r_labels, n)
        idle_labels = np.where(flip_i, manip_labels, base)
        manip_labels = np.where(flip_m, base, manip_labels)
    second = HandTrack(present=np.ones(n, dtype=bool), labels=idle_labels, score=score,
                       points=obs.points, visibility=obs.visibility, pixels=obs.pixels)
    truth = dataclasses.replace(tr, second_hand=SecondHandTruth(
        side=side, label_mode=mode, T_camera_hand=T_all, landmarks_hand=lm_h,
        landmarks_true=lm_c, occluded=obs.occluded))
    return dataclasses.replace(demo, second=second, labels=manip_labels, truth=truth)

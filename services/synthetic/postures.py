"""Hand postures away from a grasp, posture blending, left hands and chirality.

Angles are the (5, 4) joint angles of :func:`services.synthetic.hand.landmarks_from_angles`
(rows thumb, index, middle, ring, pinky) in radians; landmarks are in the hand frame ``h``.

Free postures (our choice of values, degrees; no published posture table was used):

- ``open``: the pre-shape of a reach at its widest aperture, fingers nearly straight and
  spread, thumb abducted;
- ``relaxed``: a hand hanging or resting without a task, fingers gently curled;
- ``point``: index extended, the other fingers curled, thumb over the middle finger.

Left hands
    A left hand is the mirror image of a right hand. In the hand frame (x distal, y towards the
    thumb, ``z = x * y``) the mirror is ``D = diag(1, 1, -1)``: a left hand's landmarks are
    ``D`` times the right hand's for the same angles, and its ``z`` points to the palm, not the
    back of the hand (docs/synthetic.md#left-hands). :func:`chirality` tells the two apart from
    the landmarks alone.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from services.synthetic import hand as hd

Array = NDArray[np.float64]

# Rows thumb (CMC abduction, CMC opposition, MCP, IP), index..pinky (ab/adduction, MCP, PIP, DIP).
_FREE_POSTURES_DEG: dict[str, tuple[tuple[float, float, float, float], ...]] = {
    "open": ((45.0, 5.0, 5.0, 5.0), (8.0, 5.0, 8.0, 5.0), (1.0, 5.0, 8.0, 5.0),
             (-6.0, 6.0, 8.0, 5.0), (-12.0, 8.0, 10.0, 6.0)),
    "relaxed": ((25.0, 20.0, 15.0, 15.0), (2.0, 25.0, 35.0, 20.0), (0.0, 30.0, 40.0, 22.0),
                (-2.0, 32.0, 42.0, 22.0), (-4.0, 35.0, 45.0, 24.0)),
    "point": ((35.0, 45.0, 30.0, 30.0), (2.0, 5.0, 5.0, 3.0), (0.0, 70.0, 95.0, 50.0),
              (-2.0, 75.0, 95.0, 50.0), (-4.0, 78.0, 90.0, 50.0)),
}
FREE_POSTURES: tuple[str, ...] = tuple(_FREE_POSTURES_DEG)

MIRROR_HAND = np.diag([1.0, 1.0, -1.0])  # right <-> left in the hand frame


def free_posture(name: str, participant: hd.Participant) -> Array:
    """Angles (5, 4) [rad] of the free posture ``name`` with the participant's flexion bias."""
    if name not in _FREE_POSTURES_DEG:
        raise ValueError(f"unknown posture {name!r}; known: {', '.join(FREE_POSTURES)}")
    angles = np.deg2rad(np.array(_FREE_POSTURES_DEG[name], dtype=float))
    bias = np.asarray(participant.flexion_bias_rad)
    angles[1:, 1:] += 0.5 * bias[1:, None]
    return angles


def blend(a: Array, b: Array, s: Array) -> Array:
    """Angles (N, 5, 4) moving from ``a`` (5, 4) to ``b`` (5, 4) with progress ``s`` (N,) in [0, 1]."""
    s = np.asarray(s, dtype=float)[:, None, None]
    return (1.0 - s) * a[None] + s * b[None]


def landmarks_for_side(shape: hd.HandShape, angles: Array, side: str) -> Array:
    """Landmarks (..., 21, 3) in ``h`` of a ``side`` ("left"/"right") hand with ``angles``."""
    lm = hd.landmarks_from_angles(shape, angles)
    if side == "right":
        return lm
    if side == "left":
        return lm @ MIRROR_HAND
    raise ValueError(f"hand side must be 'left' or 'right', got {side!r}")


def chirality(landmarks: Array) -> Array:
    """+1 for a right hand, -1 for a left hand (...,) from landmarks (..., 21, 3) in any frame.

    The palm normal ``n = (index MCP - wrist) x (pinky MCP - wrist)`` points to the palm of a
    right hand and to the back of a left hand; curled fingers bend towards the palm. The sign of
    ``n . (fingertip centroid - MCP centroid)`` is the chirality (0 for a perfectly flat hand).
    """
    lm = np.asarray(landmarks, dtype=float)
    n = np.cross(lm[..., 5, :] - lm[..., 0, :], lm[..., 17, :] - lm[..., 0, :])
    bend = lm[..., [8, 12, 16, 20], :].mean(axis=-2) - lm[..., [5, 9, 13, 17], :].mean(axis=-2)
    return np.sign(np.einsum("...i,...i->...", n, bend))


def aperture(landmarks: Array) -> Array:
    """Mean fingertip distance (...,) [m] from the palm centre (wrist and the four MCPs).

    Large for an open hand, small for a closed grasp; a frame-independent closure cue.
    """
    lm = np.asarray(landmarks, dtype=float)
    palm = lm[..., [0, 5, 9, 13, 17], :].mean(axis=-2)
    tips = lm[..., [4, 8, 12, 16, 20], :]
    return np.linalg.norm(tips - palm[..., None, :], axis=-1).mean(axis=-1)

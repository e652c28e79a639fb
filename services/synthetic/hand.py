"""A 21-landmark kinematic hand with anthropometric bone lengths, participants and grasps.

Hand frame ``h`` (all positions here, metres): origin at the wrist landmark (0), **x** from the
wrist towards the middle-finger MCP (distal), **y** towards the thumb (radial), **z = x * y**
(dorsal, out of the back of the hand). Hands are built as right hands; flexion bends fingers
towards -z (the palm side). A left hand is the mirror image (``services.synthetic.postures``).

Landmark order is MediaPipe's (docs/protocol.md, HandLandmarks): 0 wrist; thumb 1 CMC, 2 MCP,
3 IP, 4 tip; index 5-8, middle 9-12, ring 13-16, pinky 17-20 (MCP, PIP, DIP, tip).

Bone lengths
    Kinematic segment lengths (joint centre to joint centre, distal segment to the tip) are
    fractions of the hand length HL (wrist crease to middle fingertip), from the regression
    table of Buchholz, Armstrong & Goldstein, "Anthropometric data for describing the
    kinematics of the human hand", Ergonomics 35(3):261-273, 1992 (values as commonly
    reproduced from their table; not re-checked against the printed paper):

    ======  ==========  ========  ======  ======
    digit   metacarpal  proximal  middle  distal
    ======  ==========  ========  ======  ======
    thumb   0.251       0.196     --      0.158
    index   0.374       0.265     0.143   0.097
    middle  0.373       0.277     0.170   0.108
    ring    0.336       0.259     0.165   0.107
    little  0.295       0.206     0.117   0.093
    ======  ==========  ========  ======  ======

    The finger metacarpals start at the carpometacarpal row, about 0.07 HL distal of the wrist
    landmark (our placement). Knuckle spacing scales with the hand breadth HB; MCP joint centres
    span ~0.68 HB from index to little finger (our placement).

Hand sizes
    Hand length of US adults, ANSUR (Gordon et al., 1988/1989 anthropometric survey): men about
    194 +- 10 mm, women about 180 +- 10 mm; hand breadth about 0.45 HL. Participants draw their
    hand length from N(187 mm, 11 mm), clipped to [165, 210] mm (a mixed population).

Finger thickness (used by the camera model for the skin-surface depth and for depth-edge
outliers): half-thickness of the digit at each landmark, ~6.5 mm at the tips to ~11 mm at the
knuckles and ~18 mm at the wrist for HL = 190 mm, scaled with HL (approximate, from hand-tool
anthropometry such as Vergara et al. 2018, "Dorsal and palmar aspect dimensions of hand
anthropometry for designing hand tools and protections", finger breadths ~16-21 mm).

Participants are seeded by their id alone, so participant 3 has the same hand and style for every
object and demonstration seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import NUM_LANDMARKS
from services.common.se3 import so3_exp
from services.synthetic.objects import GraspType

Array = NDArray[np.float64]

LANDMARK_NAMES: tuple[str, ...] = (
    "wrist",
    "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
    "index_mcp", "index_pip", "index_dip", "index_tip",
    "middle_mcp", "middle_pip", "middle_dip", "middle_tip",
    "ring_mcp", "ring_pip", "ring_dip", "ring_tip",
    "pinky_mcp", "pinky_pip", "pinky_dip", "pinky_tip",
)
# Landmark type per index: wrist, thumb_base (CMC), thumb_mcp, thumb_ip, tip, mcp, pip, dip.
LANDMARK_TYPES: tuple[str, ...] = (
    "wrist", "thumb_cmc", "thumb_mcp", "thumb_ip", "tip",
    "mcp", "pip", "dip", "tip",
    "mcp", "pip", "dip", "tip",
    "mcp", "pip", "dip", "tip",
    "mcp", "pip", "dip", "tip",
)
# Parent landmark of each landmark (-1 for the wrist): bones are (parent, child) pairs.
PARENT: tuple[int, ...] = (-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19)
# Finger chains (landmark indices, base to tip); 0 = thumb, 1 = index, ..., 4 = pinky.
CHAINS: tuple[tuple[int, int, int, int], ...] = (
    (1, 2, 3, 4), (5, 6, 7, 8), (9, 10, 11, 12), (13, 14, 15, 16), (17, 18, 19, 20),
)

# Buchholz et al. 1992: segment length / hand length (see module docstring).
THUMB_SEGMENTS = (0.251, 0.196, 0.158)
FINGER_SEGMENTS = (
    (0.374, 0.265, 0.143, 0.097),
    (0.373, 0.277, 0.170, 0.108),
    (0.336, 0.259, 0.165, 0.107),
    (0.295, 0.206, 0.117, 0.093),
)
_CARPAL_OFFSET_HL = 0.07          # wrist landmark -> CMC row along x, in HL
_MCP_Y_HB = (0.35, 0.12, -0.12, -0.33)        # MCP lateral positions, in HB
_MCP_Z_HL = (0.0, 0.012, 0.006, -0.012)       # slight dorsal arch of the knuckles, in HL
_FINGER_FAN_DEG = (6.0, 0.0, -6.0, -12.0)     # finger directions in the palm plane
_THUMB_CMC = (0.12, 0.32, -0.07)              # (x in HL, y in HB, z in HB)
_THUMB_BASE_DEG = 40.0                        # metacarpal angle from x towards y, in the palm

# Half-thickness of the digit at each landmark for HL = 0.19 m [m] (module docstring).
_RADIUS_190 = np.array([
    0.018,
    0.014, 0.011, 0.009, 0.008,
    0.011, 0.0095, 0.0080, 0.0068,
    0.011, 0.0095, 0.0080, 0.0068,
    0.0105, 0.0090, 0.0075, 0.0065,
    0.0100, 0.0085, 0.0070, 0.0060,
])

HAND_LENGTH_MEAN_M = 0.187
HAND_LENGTH_STD_M = 0.011


@dataclass(frozen=True)
class HandShape:
    """Static geometry of one hand (hand frame ``h``, metres)."""

    hand_length_m: float
    hand_breadth_m: float

    def __post_init__(self) -> None:
        if not 0.12 <= self.hand_length_m <= 0.25:
            raise ValueError(f"hand length {self.hand_length_m} m is not a human hand")
        if not 0.3 <= self.hand_breadth_m / self.hand_length_m <= 0.6:
            raise ValueError(f"hand breadth {self.hand_breadth_m} m implausible for its length")

    def mcp_positions(self) -> Array:
        """Finger MCP joint centres (4, 3), index to pinky, in ``h``."""
        hl, hb = self.hand_length_m, self.hand_breadth_m
        out = np.zeros((4, 3))
        for f in range(4):
            fan = np.deg2rad(_FINGER_FAN_DEG[f])
            meta = FINGER_SEGMENTS[f][0] * hl
            out[f] = (_CARPAL_OFFSET_HL * hl + meta * np.cos(fan), _MCP_Y_HB[f] * hb,
                      _MCP_Z_HL[f] * hl)
        return out

    def thumb_cmc(self) -> Array:
        """Thumb CMC joint centre (3,) in ``h``."""
        hl, hb = self.hand_length_m, self.hand_breadth_m
        return np.array([_THUMB_CMC[0] * hl, _THUMB_CMC[1] * hb, _THUMB_CMC[2] * hb])

    def finger_segments(self) -> Array:
        """Proximal, middle, distal segment lengths (4, 3) of index..pinky [m]."""
        return np.array([s[1:] for s in FINGER_SEGMENTS]) * self.hand_length_m

    def thumb_segments(self) -> Array:
        """Thumb metacarpal, proximal, distal lengths (3,) [m]."""
        return np.array(THUMB_SEGMENTS) * self.hand_length_m

    def radii(self) -> Array:
        """Half-thickness of the digit at each landmark (21,) [m]."""
        return _RADIUS_190 * (self.hand_length_m / 0.19)

    def palm_length(self) -> float:
        """Wrist-to-middle-MCP distance [m] (the "palm size" used to scale 2-D detector errors)."""
        return float(np.linalg.norm(self.mcp_positions()[1]))


def landmarks_from_angles(shape: HandShape, angles: Array) -> Array:
    """Forward kinematics: joint angles (..., 5, 4) [rad] -> landmarks (..., 21, 3) in ``h`` [m].

    ``angles[..., 0, :]`` is the thumb: CMC palmar abduction (out of the palm, towards -z), CMC
    opposition (rotation about z towards the little finger), MCP flexion, IP flexion.
    ``angles[..., f, :]`` for f = 1..4 (index..pinky): MCP ab/adduction (about z), MCP, PIP and DIP
    flexion. Flexion of a finger with in-palm direction ``d0`` bends it to
    ``cos(phi) d0 - sin(phi) z`` for the cumulative angle ``phi``, so bone lengths never change.
    """
    angles = np.asarray(angles, dtype=float)
    batch = angles.shape[:-2]
    out = np.zeros((*batch, NUM_LANDMARKS, 3))
    ez = np.array([0.0, 0.0, 1.0])

    mcps = shape.mcp_positions()
    segs = shape.finger_segments()
    for f in range(4):
        a = angles[..., f + 1, :]
        fan = np.deg2rad(_FINGER_FAN_DEG[f]) + a[..., 0]
        d0 = np.stack([np.cos(fan), np.sin(fan), np.zeros_like(fan)], axis=-1)
        base = CHAINS[f + 1][0]
        p = np.broadcast_to(mcps[f], (*batch, 3)).copy()
        out[..., base, :] = p
        phi = np.zeros(batch)
        for s in range(3):
            phi = phi + a[..., s + 1]
            d = np.cos(phi)[..., None] * d0 - np.sin(phi)[..., None] * ez
            p = p + segs[f, s] * d
            out[..., base + s + 1, :] = p

    # Thumb: metacarpal direction from the two CMC angles, then flexion in the thumb's bending
    # plane (towards the palm centre and the fingers).
    t_seg = shape.thumb_segments()
    a = angles[..., 0, :]
    base_dir = np.deg2rad(_THUMB_BASE_DEG) - a[..., 1]
    t0 = np.stack([np.cos(base_dir) * np.cos(a[..., 0]), np.sin(base_dir) * np.cos(a[..., 0]),
                   -np.sin(a[..., 0])], axis=-1)
    w = np.array([-0.2, -1.0, -0.8])
    bend = w - (t0 @ w)[..., None] * t0
    bend = bend / np.linalg.norm(bend, axis=-1, keepdims=True)
    cmc = np.broadcast_to(shape.thumb_cmc(), (*batch, 3))
    out[..., 1, :] = cmc
    p = cmc + t_seg[0] * t0
    out[..., 2, :] = p
    phi = np.zeros(batch)
    for s in range(2):
        phi = phi + a[..., 2 + s]
        d = np.cos(phi)[..., None] * t0 + np.sin(phi)[..., None] * bend
        p = p + t_seg[1 + s] * d
        out[..., 3 + s, :] = p
    return out


# Nominal grasp postures [deg]: rows thumb, index, middle, ring, pinky (see landmarks_from_angles).
# The thumb row is only the starting point of :func:`solve_thumb`, which places the thumb tip on
# the grasp's contact target.
_POSTURES_DEG: dict[str, tuple[tuple[float, float, float, float], ...]] = {
    # Cylindrical power grasp of a bar or rim ~2-3 cm thick; thumb over the index finger.
    "power": ((35.0, 30.0, 20.0, 20.0), (2.0, 35.0, 85.0, 45.0), (0.0, 38.0, 88.0, 45.0),
              (-2.0, 42.0, 88.0, 45.0), (-4.0, 46.0, 85.0, 45.0)),
    # Tip pinch of a small knob/edge; the other fingers loosely curled.
    "pinch": ((35.0, 30.0, 15.0, 20.0), (0.0, 50.0, 65.0, 30.0), (0.0, 50.0, 65.0, 30.0),
              (-2.0, 52.0, 68.0, 35.0), (-4.0, 56.0, 70.0, 35.0)),
    # Tripod: thumb, index and middle tips on a tab.
    "tripod": ((35.0, 30.0, 15.0, 20.0), (2.0, 48.0, 62.0, 28.0), (-2.0, 50.0, 62.0, 28.0),
               (-3.0, 52.0, 68.0, 35.0), (-5.0, 56.0, 70.0, 35.0)),
    # Lateral (key) pinch: thumb pad on the radial side of the curled index finger.
    "key_pinch": ((15.0, 10.0, 20.0, 20.0), (0.0, 55.0, 80.0, 40.0), (0.0, 65.0, 85.0, 45.0),
                  (-2.0, 68.0, 85.0, 45.0), (-4.0, 70.0, 85.0, 45.0)),
    # Hook: fingers curled at PIP/DIP around a bar or into a recess, knuckles almost straight;
    # the thumb rests alongside the index metacarpal (not opposed).
    "hook": ((10.0, 5.0, 10.0, 10.0), (2.0, 15.0, 85.0, 50.0), (0.0, 15.0, 88.0, 50.0),
             (-2.0, 18.0, 88.0, 50.0), (-4.0, 22.0, 85.0, 50.0)),
}

_THUMB_BOUNDS_DEG = ((-10.0, 80.0), (-30.0, 90.0), (-10.0, 75.0), (-20.0, 90.0))


def posture_angles(grasp_type: GraspType) -> Array:
    """Nominal joint angles (5, 4) [rad] of a grasp type (see :func:`landmarks_from_angles`)."""
    return np.deg2rad(np.array(_POSTURES_DEG[grasp_type], dtype=float))


def thumb_target(landmarks: Array, grasp_type: GraspType, shape: HandShape) -> Array:
    """Where the thumb tip landmark goes (3,) in ``h``, from the finger landmarks (21, 3).

    pinch: 1.4 cm from the index tip (pads touching); tripod: the same from the index/middle
    tip midpoint; key_pinch: 1.5 cm radial of the index middle phalanx; power: over the index
    middle phalanx on the palm side (thumb wrapped around the bar); hook: 2 cm radial of the
    index PIP, slightly proximal (thumb resting alongside, not opposed). Offsets scale with HL.
    """
    s = shape.hand_length_m / 0.19
    lm = landmarks
    if grasp_type == "hook":
        return lm[6] + s * np.array([-0.01, 0.018, -0.008])
    if grasp_type == "pinch":
        return lm[8] + s * np.array([-0.005, 0.010, -0.008])
    if grasp_type == "tripod":
        return 0.5 * (lm[8] + lm[12]) + s * np.array([-0.005, 0.012, -0.008])
    if grasp_type == "key_pinch":
        return 0.5 * (lm[6] + lm[7]) + s * np.array([0.0, 0.015, 0.0])
    return 0.5 * (lm[6] + lm[7]) + s * np.array([-0.01, 0.012, 0.012])


def solve_thumb(shape: HandShape, angles: Array, target: Array) -> Array:
    """Angles (5, 4) with the thumb row changed so the thumb tip reaches ``target`` (3,) [m].

    Least squares on the tip position with a weak pull towards the given thumb angles, within
    anatomical bounds (_THUMB_BOUNDS_DEG).
    """
    from scipy.optimize import least_squares

    a0 = np.array(angles, dtype=float)
    prior = a0[0].copy()

    def residual(x: Array) -> Array:
        a = a0.copy()
        a[0] = x
        tip = landmarks_from_angles(shape, a)[4]
        return np.concatenate([(tip - target) / 0.002, (x - prior) / np.deg2rad(60.0)])

    lo = np.deg2rad([b[0] for b in _THUMB_BOUNDS_DEG])
    hi = np.deg2rad([b[1] for b in _THUMB_BOUNDS_DEG])
    sol = least_squares(residual, np.clip(prior, lo, hi), bounds=(lo, hi))
    out = a0.copy()
    out[0] = sol.x
    return out


def grasp_point(landmarks: Array, grasp_type: GraspType, shape: HandShape) -> Array:
    """Grasp point (3,) in ``h`` from landmarks (21, 3) of the grasp posture.

    pinch: midpoint of thumb and index tips; tripod: centroid of thumb, index and middle tips;
    key_pinch: midpoint of the thumb tip and the index middle phalanx; power: centre of the
    cylinder held between palm and curled fingers (mean of index..ring MCPs and PIPs, 0.06 HL
    towards the palm); hook: the crook of the curled fingers (mean of index..ring PIPs and DIPs,
    0.05 HL towards the palm).
    """
    lm = landmarks
    if grasp_type == "hook":
        crook = lm[[6, 7, 10, 11, 14, 15]].mean(axis=0)
        return crook - np.array([0.0, 0.0, 0.05 * shape.hand_length_m])
    if grasp_type == "pinch":
        return 0.5 * (lm[4] + lm[8])
    if grasp_type == "tripod":
        return (lm[4] + lm[8] + lm[12]) / 3.0
    if grasp_type == "key_pinch":
        return 0.5 * (lm[4] + 0.5 * (lm[6] + lm[7]))
    centre = lm[[5, 9, 13, 6, 10, 14]].mean(axis=0)
    return centre - np.array([0.0, 0.0, 0.06 * shape.hand_length_m])


@dataclass(frozen=True)
class Participant:
    """One demonstrator: hand size and manipulation style (deterministic from the id)."""

    participant_id: int
    shape: HandShape
    # Added to every flexion angle of each digit (5,) [rad]: tighter or looser grasps.
    flexion_bias_rad: tuple[float, ...]
    # Rotation vector [rad] applied to the preset hand orientation about the grasp point.
    grasp_rotation_rad: tuple[float, float, float]
    # Multiplies stroke durations (> 1: slower participant).
    duration_factor: float
    # Multiplies the demonstrated range of motion.
    range_factor: float
    # Amplitude of slow finger flexion changes during manipulation [rad].
    flex_amplitude_rad: float
    # Slip of the grasp on the part over a full stroke: rotation [rad] and translation [m].
    slip_rotation_rad: float
    slip_translation_m: float
    # The hand this participant uses by preference ("left" / "right").
    dominant_hand: str = "right"


# Left-handed participants (ids >= 4 only: the paper's participants 1-3 demonstrate with their
# right hands, docs/synthetic.md#participants).
LEFT_HANDED_PARTICIPANTS = frozenset({5, 7, 9})


def participant(participant_id: int) -> Participant:
    """The participant ``participant_id`` (any int >= 1); seeded by the id only."""
    if participant_id < 1:
        raise ValueError(f"participant ids start at 1, got {participant_id}")
    rng = np.random.default_rng(np.random.SeedSequence([0x50415254, participant_id]))
    hl = float(np.clip(rng.normal(HAND_LENGTH_MEAN_M, HAND_LENGTH_STD_M), 0.165, 0.21))
    hb = hl * float(np.clip(rng.normal(0.45, 0.015), 0.41, 0.49))
    flex = rng.normal(0.0, np.deg2rad(6.0), 5)
    rot = rng.normal(0.0, np.deg2rad(8.0), 3)
    return Participant(
        participant_id=participant_id,
        shape=HandShape(hand_length_m=hl, hand_breadth_m=hb),
        flexion_bias_rad=tuple(float(x) for x in flex),
        grasp_rotation_rad=(float(rot[0]), float(rot[1]), float(rot[2])),
        duration_factor=float(np.exp(rng.normal(0.0, 0.15))),
        range_factor=float(np.clip(rng.normal(1.0, 0.06), 0.88, 1.12)),
        flex_amplitude_rad=float(np.deg2rad(rng.uniform(2.0, 5.0))),
        slip_rotation_rad=float(np.deg2rad(rng.uniform(1.0, 4.0))),
        slip_translation_m=float(rng.uniform(0.001, 0.003)),
        dominant_hand="left" if participant_id in LEFT_HANDED_PARTICIPANTS else "right",
    )


def participant_posture(p: Participant, grasp_type: GraspType) -> Array:
    """Grasp posture (5, 4) [rad] of participant ``p``.

    Nominal finger angles plus the participant's flexion bias; then the thumb is solved to its
    contact target (:func:`thumb_target`), so a tighter grip moves the thumb with the fingers.
    """
    angles = posture_angles(grasp_type).copy()
    bias = np.asarray(p.flexion_bias_rad)
    angles[1:, 1:] += bias[1:, None]
    angles[0, 2:] += bias[0]
    target = thumb_target(landmarks_from_angles(p.shape, angles), grasp_type, p.shape)
    return solve_thumb(p.shape, angles, target)


def smooth_noise(rng: np.random.Generator, t: Array, time_constant_s: float, dim: int) -> Array:
    """Unit-variance Ornstein-Uhlenbeck samples (len(t), dim) at the increasing times ``t`` [s]."""
    out = np.zeros((len(t), dim))
    x = rng.standard_normal(dim)
    prev = float(t[0]) if len(t) else 0.0
    for k, tk in enumerate(t):
        phi = np.exp(-(float(tk) - prev) / time_constant_s)
        x = phi * x + np.sqrt(1.0 - phi * phi) * rng.standard_normal(dim)
        out[k] = x
        prev = float(tk)
    return out


def flexion_trajectory(rng: np.random.Generator, posture: Array, t: Array, activity: Array,
                       amplitude_rad: float) -> Array:
    """Joint angles (N, 5, 4) [rad] of a hand that keeps its grasp but flexes slightly.

    Each flexion angle wanders as a slow Ornstein-Uhlenbeck process (time constant 0.5 s) with
    standard deviation ``amplitude_rad``, and all flexions tighten by up to ``amplitude_rad``
    with the normalised articulation speed ``activity`` (N,) in [0, 1] (grip force rises while
    the part moves). Ab/adduction wanders at a third of the amplitude.
    """
    n = len(t)
    wander = smooth_noise(rng, t, 0.5, 20).reshape(n, 5, 4) * amplitude_rad
    wander[:, :, 0] *= 1.0 / 3.0
    wander[:, 0, 0] *= 3.0  # thumb CMC abduction is a flexion-like DOF
    tighten = np.zeros((n, 5, 4))
    tighten[:, :, 1:] = amplitude_rad * np.asarray(activity, dtype=float)[:, None, None]
    tighten[:, 0, :2] = 0.0
    return posture[None] + wander + tighten


def rotation_about_point(rotvec: Array, centre: Array) -> Array:
    """4x4 pose rotating by ``rotvec`` [rad] about ``centre`` (3,): ``x -> R (x - c) + c``."""
    R = so3_exp(np.asarray(rotvec, dtype=float))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre
    return T

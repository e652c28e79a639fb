"""What a synthetic demonstration is: the detector's stream of hands plus its ground truth.

All vectors and poses in the camera frame ``c`` (OpenCV axes, metres) unless a name says
otherwise; 4x4 ``float64`` poses ``T_a_b`` map points in b to a; one row per delivered frame.
The fields of the original single-hand, cut-at-grasp model keep their meaning (the
**manipulating hand** and the **final joint**); the rest is additive (docs/synthetic.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from services.synthetic import camera as cam

Array = NDArray[np.float64]
JointKind = Literal["prismatic", "revolute", "rigid"]

PHASE_FREE = "free"
PHASE_CONTACT = "contact"


@dataclass(frozen=True, eq=False)
class JointTruth:
    """One true joint, in the camera frame.

    ``axis`` (3,) unit (zeros for a rigid hold); ``point`` (3,): for a revolute joint the axis
    point closest to the camera origin, for a prismatic joint (and a rigid hold) the grasp point
    at the first frame. ``q`` (N,) joint value per delivered frame (rad or m), 0 at the first
    frame; positive ``q`` moves the part by ``exp(q * twist())``. A joint carried by another
    (a latch on a door) is described while its carrier is at rest, i.e. during its own contact.
    """

    type: JointKind
    axis: Array
    point: Array
    q: Array
    name: str = ""

    def twist(self) -> Array:
        """Unit joint twist ``[v, w]`` (6,) in the camera frame (linear first); 0 for rigid."""
        if self.type == "rigid":
            return np.zeros(6)
        if self.type == "prismatic":
            return np.concatenate([self.axis, np.zeros(3)])
        return np.concatenate([np.cross(self.point, self.axis), self.axis])


@dataclass(frozen=True, eq=False)
class ContactSegment:
    """One contact phase: the hand holds the part of ``joints[joint]``.

    ``start`` / ``end``: first and last row (inclusive) of the phase; ``start_ns`` / ``end_ns``
    their stamps. ``onset_ns`` / ``release_ns``: the exact moments the fingers closed on the
    handle and began to open (between frames). ``grasp_part`` (3,): the held point in the part
    frame of the joint (part frame = object frame at q = 0).
    """

    index: int
    joint: int
    start: int
    end: int
    start_ns: int
    end_ns: int
    onset_ns: int
    release_ns: int
    grasp_part: Array


@dataclass(frozen=True, eq=False)
class SecondHandTruth:
    """The idle second hand: where it really is (it never moves) and how it is labelled."""

    side: str                 # the hand it really is: "left" / "right"
    label_mode: str           # "opposite", "same" or "flipping" (docs/synthetic.md#second-hand)
    T_camera_hand: Array      # (N, 4, 4), all rows equal
    landmarks_hand: Array     # (21, 3) in its hand frame [m]
    landmarks_true: Array     # (N, 21, 3), all rows equal
    occluded: NDArray[np.bool_]  # (N, 21) see camera.Observation


@dataclass(frozen=True, eq=False)
class HandTrack:
    """One hand's detections over the frames (what the detector reports, camera frame)."""

    present: NDArray[np.bool_]       # (N,) detected in this frame
    labels: NDArray[np.str_]         # (N,) reported handedness "left" / "right"
    score: NDArray[np.float32]       # (N,) in [0, 1]; 0 where absent
    points: NDArray[np.float32]      # (N, 21, 3) [m], NaN without depth or where absent
    visibility: NDArray[np.float32]  # (N, 21) in [0, 1]; 0 where absent
    pixels: NDArray[np.float32]      # (N, 21, 2) [px], NaN where absent


@dataclass(frozen=True)
class Detection:
    """One hand as the detector delivers it in one frame (``HandLandmarks.hands`` item).

    ``source`` is ground truth, not on the wire: 0 the manipulating hand, 1 the second hand.
    """

    handedness: str
    score: float
    points: NDArray[np.float32]
    visibility: NDArray[np.float32]
    pixels: NDArray[np.float32]
    source: int


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Noise-free state of a demonstration, one row per delivered frame (camera frame ``c``).

    ``joint``, ``T_camera_part`` and ``grasp_points`` describe the **final** joint (the one of
    the last contact phase: what a ``get`` after the demonstration should answer); ``joints``,
    ``T_camera_parts`` and ``segments`` describe every joint and contact phase.
    """

    T_camera_hand: Array       # (N, 4, 4) the manipulating hand, free or in contact
    T_camera_part: Array       # (N, 4, 4) the final joint's part
    T_part_hand: Array         # (N, 4, 4) = inv(T_camera_part) @ T_camera_hand
    T_camera_object: Array     # (4, 4) the object base (= every part at q = 0)
    landmarks_hand: Array      # (N, 21, 3) in the hand frame [m]
    landmarks_true: Array      # (N, 21, 3) in the camera frame [m]
    grasp_points: Array        # (N, 3) the final joint's held point, on its path [m]
    joint: JointTruth
    frame_index: NDArray[np.int64]   # (N,) index on the nominal 30 Hz grid (gaps = dropped)
    occluded: NDArray[np.bool_]      # (N, 21) see camera.Observation
    missing: NDArray[np.bool_]       # (N, 21)
    depth_outlier: NDArray[np.bool_]  # (N, 21)
    swapped: NDArray[np.bool_]       # (N, 21)
    # Additive (defaults: one joint, one contact phase over the whole stream).
    joints: tuple[JointTruth, ...] = ()
    T_camera_parts: Array | None = None        # (J, N, 4, 4)
    segments: tuple[ContactSegment, ...] = ()
    phase: NDArray[np.str_] | None = None      # (N,) "free" / "contact"
    segment_index: NDArray[np.int64] | None = None  # (N,) index into segments, -1 when free
    finger_angles: Array | None = None         # (N, 5, 4) [rad], hand.landmarks_from_angles
    hand_side: str = "right"                   # the manipulating hand really is
    undetected: NDArray[np.bool_] | None = None  # (N,) hand deliberately not detected (gap)
    gap: str | None = None                     # None, "dropout" or "regrasp"
    second_hand: SecondHandTruth | None = None

    def __post_init__(self) -> None:
        n = self.T_camera_hand.shape[0]
        if not self.joints:
            object.__setattr__(self, "joints", (self.joint,))
        if self.T_camera_parts is None:
            object.__setattr__(self, "T_camera_parts", self.T_camera_part[None])
        if self.phase is None:
            object.__setattr__(self, "phase", np.full(n, PHASE_CONTACT, dtype="<U7"))
        if self.segment_index is None:
            object.__setattr__(self, "segment_index", np.zeros(n, dtype=np.int64))
        if self.undetected is None:
            object.__setattr__(self, "undetected", np.zeros(n, dtype=bool))

    def segment_grasp_points(self, i: int) -> Array:
        """Held point (M, 3) over the rows of contact phase ``i``, on its joint's path [m]."""
        seg = self.segments[i]
        assert self.T_camera_parts is not None
        T = self.T_camera_parts[seg.joint, seg.start:seg.end + 1]
        out: Array = np.einsum("nij,j->ni", T[:, :3, :3], seg.grasp_part) + T[:, :3, 3]
        return out

    def segment_joint(self, i: int) -> JointTruth:
        """The joint of contact phase ``i``."""
        return self.joints[self.segments[i].joint]


@dataclass(frozen=True, eq=False)
class Demonstration:
    """One synthetic demonstration: the detector's landmark stream plus the ground truth.

    Stream of the manipulating hand (per delivered frame, camera frame): ``stamps_ns`` (N,) int64
    capture times; ``points`` (N, 21, 3) float32 [m], NaN without depth (whole rows NaN where the
    hand is not detected, see ``present``); ``visibility`` (N, 21) float32; ``pixels`` (N, 21, 2)
    float32; ``score`` (N,) float32; ``handedness``: the side of the manipulating hand. Additive:
    ``present`` (N,) whether the manipulating hand is detected, ``labels`` (N,) the handedness
    the detector reports for it (it may flip), ``second`` the idle second hand's detections, and
    :meth:`detections` for everything one frame delivers.
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
    variant: str = "cut"
    present: NDArray[np.bool_] | None = None
    labels: NDArray[np.str_] | None = None
    second: HandTrack | None = field(default=None)

    def __post_init__(self) -> None:
        n = len(self)
        if self.present is None:
            object.__setattr__(self, "present", np.ones(n, dtype=bool))
        if self.labels is None:
            object.__setattr__(self, "labels", np.full(n, self.handedness))

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    def detections(self, i: int) -> tuple[Detection, ...]:
        """The hands the detector delivers in frame ``i``, highest score first."""
        assert self.present is not None and self.labels is not None
        out = []
        if self.present[i]:
            out.append(Detection(handedness=str(self.labels[i]), score=float(self.score[i]),
                                 points=self.points[i], visibility=self.visibility[i],
                                 pixels=self.pixels[i], source=0))
        s = self.second
        if s is not None and s.present[i]:
            out.append(Detection(handedness=str(s.labels[i]), score=float(s.score[i]),
                                 points=s.points[i], visibility=s.visibility[i],
                                 pixels=s.pixels[i], source=1))
        out.sort(key=lambda d: -d.score)
        return tuple(out)


_STREAM = ("stamps_ns", "points", "visibility", "pixels", "score", "present", "labels")
_TRUTH_ARRAYS = ("T_camera_hand", "T_camera_part", "T_part_hand", "T_camera_object",
                 "landmarks_hand", "landmarks_true", "grasp_points", "frame_index", "occluded",
                 "missing", "depth_outlier", "swapped", "T_camera_parts", "phase",
                 "segment_index", "undetected")
_SEGMENT_INTS = ("index", "joint", "start", "end", "start_ns", "end_ns", "onset_ns",
                 "release_ns")


def save_npz(demo: Demonstration, path: str | Path) -> None:
    """Write ``demo`` to a compressed ``.npz`` file (arrays only, no pickles).

    numpy appends ``.npz`` to a path without that suffix; pass the same name to
    :func:`load_npz`.
    """
    tr = demo.truth
    K = demo.intrinsics
    arrays: dict[str, NDArray[np.generic]] = {
        "object_name": np.array(demo.object_name), "participant": np.array(demo.participant),
        "seed": np.array(demo.seed), "handedness": np.array(demo.handedness),
        "variant": np.array(demo.variant),
        "intrinsics": np.array([K.fx, K.fy, K.cx, K.cy, K.width, K.height]),
        "joint_type": np.array(tr.joint.type), "joint_axis": tr.joint.axis,
        "joint_point": tr.joint.point, "joint_q": tr.joint.q,
        "joints_type": np.array([j.type for j in tr.joints]),
        "joints_name": np.array([j.name for j in tr.joints]),
        "joints_axis": np.array([j.axis for j in tr.joints]),
        "joints_point": np.array([j.point for j in tr.joints]),
        "joints_q": np.array([j.q for j in tr.joints]),
        "joint_index": np.array(next(i for i, j in enumerate(tr.joints) if j is tr.joint)),
        "hand_side": np.array(tr.hand_side), "gap": np.array(tr.gap or ""),
        "segments_grasp_part": np.array([s.grasp_part for s in tr.segments]).reshape(-1, 3),
    }
    for name in _STREAM:
        arrays[name] = getattr(demo, name)
    for name in _TRUTH_ARRAYS:
        arrays["truth_" + name] = getattr(tr, name)
    if tr.finger_angles is not None:
        arrays["truth_finger_angles"] = tr.finger_angles
    for name in _SEGMENT_INTS:
        arrays["segments_" + name] = np.array([getattr(s, name) for s in tr.segments], np.int64)
    if demo.second is not None and tr.second_hand is not None:
        for name in ("present", "labels", "score", "points", "visibility", "pixels"):
            arrays["second_" + name] = getattr(demo.second, name)
        sh = tr.second_hand
        arrays["second_side"] = np.array(sh.side)
        arrays["second_label_mode"] = np.array(sh.label_mode)
        for name in ("T_camera_hand", "landmarks_hand", "landmarks_true", "occluded"):
            arrays["second_truth_" + name] = getattr(sh, name)
    np.savez_compressed(Path(path), **arrays)  # type: ignore[arg-type]


def load_npz(path: str | Path) -> Demonstration:
    """Read a demonstration written by :func:`save_npz`."""
    with np.load(Path(path), allow_pickle=False) as z:
        intr = z["intrinsics"]
        joints = tuple(
            JointTruth(type=str(t), axis=a, point=p, q=q, name=str(n))  # type: ignore[arg-type]
            for t, n, a, p, q in zip(z["joints_type"], z["joints_name"], z["joints_axis"],
                                     z["joints_point"], z["joints_q"], strict=True))
        final = joints[int(z["joint_index"])]
        segments = tuple(
            ContactSegment(**{k: int(z["segments_" + k][i]) for k in _SEGMENT_INTS},
                           grasp_part=z["segments_grasp_part"][i])
            for i in range(len(z["segments_index"])))
        second_truth = None
        second = None
        if "second_present" in z:
            second = HandTrack(**{k: z["second_" + k] for k in (
                "present", "labels", "score", "points", "visibility", "pixels")})
            second_truth = SecondHandTruth(
                side=str(z["second_side"]), label_mode=str(z["second_label_mode"]),
                **{k: z["second_truth_" + k] for k in (
                    "T_camera_hand", "landmarks_hand", "landmarks_true", "occluded")})
        truth = GroundTruth(
            joint=final, joints=joints, segments=segments,
            finger_angles=z.get("truth_finger_angles"),
            hand_side=str(z["hand_side"]), gap=str(z["gap"]) or None, second_hand=second_truth,
            **{name: z["truth_" + name] for name in _TRUTH_ARRAYS})
        return Demonstration(
            object_name=str(z["object_name"]), participant=int(z["participant"]),
            seed=int(z["seed"]), handedness=str(z["handedness"]), truth=truth,
            intrinsics=cam.Intrinsics(fx=float(intr[0]), fy=float(intr[1]), cx=float(intr[2]),
                                      cy=float(intr[3]), width=int(intr[4]),
                                      height=int(intr[5])),
            variant=str(z["variant"]), second=second,
            **{name: z[name] for name in _STREAM})


def cut_to_segment(demo: Demonstration, i: int) -> Demonstration:
    """The rows of contact phase ``i`` as a demonstration of their own ("cut at grasp and
    release"): same stream values, same noise, one contact phase over every row.

    ``joint`` becomes phase ``i``'s joint and ``T_camera_part`` / ``grasp_points`` its part and
    held point; joint values keep their values (``q`` starts where the phase starts, not at 0).
    """
    tr = demo.truth
    seg = tr.segments[i]
    rows = slice(seg.start, seg.end + 1)
    m = seg.end - seg.start + 1
    assert tr.T_camera_parts is not None
    joints = tuple(JointTruth(type=j.type, axis=j.axis, point=j.point, q=j.q[rows], name=j.name)
                   for j in tr.joints)
    T_part = tr.T_camera_parts[seg.joint, rows]
    inv = np.linalg.inv(T_part)
    one = ContactSegment(index=0, joint=seg.joint, start=0, end=m - 1, start_ns=seg.start_ns,
                         end_ns=seg.end_ns, onset_ns=seg.onset_ns, release_ns=seg.release_ns,
                         grasp_part=seg.grasp_part)
    sh = tr.second_hand
    second_truth = None if sh is None else SecondHandTruth(
        side=sh.side, label_mode=sh.label_mode, T_camera_hand=sh.T_camera_hand[rows],
        landmarks_hand=sh.landmarks_hand, landmarks_true=sh.landmarks_true[rows],
        occluded=sh.occluded[rows])
    truth = GroundTruth(
        T_camera_hand=tr.T_camera_hand[rows], T_camera_part=T_part,
        T_part_hand=inv @ tr.T_camera_hand[rows], T_camera_object=tr.T_camera_object,
        landmarks_hand=tr.landmarks_hand[rows], landmarks_true=tr.landmarks_true[rows],
        grasp_points=tr.segment_grasp_points(i), joint=joints[seg.joint],
        frame_index=tr.frame_index[rows], occluded=tr.occluded[rows], missing=tr.missing[rows],
        depth_outlier=tr.depth_outlier[rows], swapped=tr.swapped[rows], joints=joints,
        T_camera_parts=tr.T_camera_parts[:, rows], segments=(one,),
        phase=np.full(m, PHASE_CONTACT, dtype="<U7"), segment_index=np.zeros(m, np.int64),
        finger_angles=None if tr.finger_angles is None else tr.finger_angles[rows],
        hand_side=tr.hand_side, undetected=None if tr.undetected is None else tr.undetected[rows],
        gap=tr.gap, second_hand=second_truth)
    s = demo.second
    second = None if s is None else HandTrack(
        present=s.present[rows], labels=s.labels[rows], score=s.score[rows],
        points=s.points[rows], visibility=s.visibility[rows], pixels=s.pixels[rows])
    assert demo.present is not None and demo.labels is not None
    return Demonstration(
        object_name=demo.object_name, participant=demo.participant, seed=demo.seed,
        stamps_ns=demo.stamps_ns[rows], points=demo.points[rows],
        visibility=demo.visibility[rows], pixels=demo.pixels[rows], handedness=demo.handedness,
        score=demo.score[rows], truth=truth, intrinsics=demo.intrinsics, variant="cut",
        present=demo.present[rows], labels=demo.labels[rows], second=second)

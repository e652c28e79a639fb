"""Synthetic demonstrations as bus traffic: HandLandmarks messages with their capture stamps."""

from __future__ import annotations

import numpy as np

from services.common.keys import Keys
from services.common.protocol import Hand, HandLandmarks
from services.common.recording import RecordedMessage
from services.synthetic.generator import Demonstration, generate


def landmark_messages(demo: Demonstration) -> list[HandLandmarks]:
    """One HandLandmarks per delivered frame, camera frame, ``stamp_ns`` = capture time.

    Each message carries every hand the frame's detector output has
    (:meth:`Demonstration.detections`: the manipulating hand and an idle second hand, highest
    score first); a frame in which no hand is detected carries an empty ``hands`` list, as the
    detector service publishes it.
    """
    out = []
    for i, stamp in enumerate(demo.stamps_ns):
        hands = tuple(
            Hand(handedness=h.handedness, score=float(np.clip(h.score, 0.0, 1.0)),
                 points=np.ascontiguousarray(h.points, "<f4"),
                 visibility=np.ascontiguousarray(np.clip(h.visibility, 0, 1), "<f4"),
                 pixels=np.ascontiguousarray(h.pixels, "<f4"))
            for h in demo.detections(i))
        out.append(HandLandmarks(seq=i, stamp_ns=int(stamp), frame_id="camera", hands=hands))
    return out


def demonstration_recording(demo: Demonstration, rig: str = "default") -> list[RecordedMessage]:
    """The demonstration as recorded messages (log time = capture time)."""
    key = Keys(rig).hand_landmarks
    return [RecordedMessage(key=key, payload=m.to_msgpack(), log_time_ns=m.stamp_ns,
                            publish_time_ns=m.stamp_ns, schema=HandLandmarks.SCHEMA)
            for m in landmark_messages(demo)]


def synthetic_recording(object_name: str, participant: int = 3, seed: int = 0,
                        rig: str = "default", *, variant: str = "cut",
                        idle_hand: str | None = None, gap: str | None = None,
                        hand: str | None = None) -> list[RecordedMessage]:
    """Generate a demonstration and return it as recorded messages for ``replay``.

    Keyword arguments as :func:`services.synthetic.generator.generate`; the defaults give the
    paper split's cut demonstration, as before.
    """
    demo = generate(object_name, participant, seed, variant=variant, idle_hand=idle_hand,
                    gap=gap, hand=hand)
    return demonstration_recording(demo, rig)

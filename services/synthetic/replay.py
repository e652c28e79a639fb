"""Synthetic demonstrations as bus traffic: HandLandmarks messages with their capture stamps."""

from __future__ import annotations

import numpy as np

from services.common.keys import Keys
from services.common.protocol import Hand, HandLandmarks
from services.common.recording import RecordedMessage
from services.synthetic.generator import Demonstration, generate


def landmark_messages(demo: Demonstration) -> list[HandLandmarks]:
    """One HandLandmarks per delivered frame, camera frame, ``stamp_ns`` = capture time."""
    out = []
    for i, stamp in enumerate(demo.stamps_ns):
        hand = Hand(handedness=demo.handedness, score=float(demo.score[i]),
                    points=np.ascontiguousarray(demo.points[i], "<f4"),
                    visibility=np.ascontiguousarray(np.clip(demo.visibility[i], 0, 1), "<f4"),
                    pixels=np.ascontiguousarray(demo.pixels[i], "<f4"))
        out.append(HandLandmarks(seq=i, stamp_ns=int(stamp), frame_id="camera", hands=(hand,)))
    return out


def demonstration_recording(demo: Demonstration, rig: str = "default") -> list[RecordedMessage]:
    """The demonstration as recorded messages (log time = capture time)."""
    key = Keys(rig).hand_landmarks
    return [RecordedMessage(key=key, payload=m.to_msgpack(), log_time_ns=m.stamp_ns,
                            publish_time_ns=m.stamp_ns, schema=HandLandmarks.SCHEMA)
            for m in landmark_messages(demo)]


def synthetic_recording(object_name: str, participant: int = 3, seed: int = 0,
                        rig: str = "default") -> list[RecordedMessage]:
    """Generate a demonstration and return it as recorded messages for ``replay``."""
    return demonstration_recording(generate(object_name, participant, seed), rig)

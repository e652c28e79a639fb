"""Synthetic hand demonstrations with ground truth (objects, hand, motion, camera, generator).

Entry point: :func:`services.synthetic.generator.generate`; the splits, variants and conditions
it accepts are listed in :mod:`services.synthetic.splits` (docs/synthetic.md). Nothing is
computed or read at import beyond the object presets.
"""

from services.synthetic.demonstration import (
    ContactSegment,
    Detection,
    HandTrack,
    SecondHandTruth,
)
from services.synthetic.generator import (
    EVALUATION_SPLIT,
    OBJECTS,
    TUNING_SPLIT,
    Demonstration,
    GroundTruth,
    JointTruth,
    generate,
    load_npz,
    save_npz,
)

__all__ = [
    "EVALUATION_SPLIT",
    "OBJECTS",
    "TUNING_SPLIT",
    "ContactSegment",
    "Demonstration",
    "Detection",
    "GroundTruth",
    "HandTrack",
    "JointTruth",
    "SecondHandTruth",
    "generate",
    "load_npz",
    "save_npz",
]
